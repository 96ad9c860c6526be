"""Closed-form integrals of the half-space surface kernels over triangles; Boussinesq influence.

Implements formulations/substrate.md, sec. 2 (eqs. (3)-(6)): the integral over a polygon of a
kernel ``g(e) / r`` (``e`` the unit vector from the field point, ``r`` the distance) is a sum over
the polygon's edges of one-dimensional integrals along each edge, which are elementary for
``g = 1, e_i, e_i e_j``.  The field point may lie inside the panel: the weak singularity of 1/r
is integrated exactly (the self-panel needs no special quadrature).
"""

from __future__ import annotations

import numpy as np

from ..geometry import Array

# Below this signed distance (in L) an edge passes through the field point and contributes nothing.
_H_TINY = 1e-13


def _edge_terms(p: Array, a: Array, b: Array) -> dict[str, Array]:
    """Primitive integrals of one edge a->b seen from field points p; shapes broadcast to (M, T)."""
    ab = b - a
    t = ab / np.linalg.norm(ab, axis=-1, keepdims=True)
    n = np.stack([t[..., 1], -t[..., 0]], axis=-1)
    ap, bp = a - p, b - p
    h = np.einsum("...i,...i->...", ap, n)
    s1, s2 = np.einsum("...i,...i->...", ap, t), np.einsum("...i,...i->...", bp, t)
    r1, r2 = np.linalg.norm(ap, axis=-1), np.linalg.norm(bp, axis=-1)
    live = np.abs(h) > _H_TINY
    hs = np.where(live, h, 1.0)
    ah = np.abs(hs)
    d_asinh = np.where(live, np.arcsinh(s2 / ah) - np.arcsinh(s1 / ah), 0.0)
    d_atan = np.where(live, np.arctan(s2 / hs) - np.arctan(s1 / hs), 0.0)
    d_log = np.where(live, np.log(r2 * r2) - np.log(r1 * r1), 0.0)
    d_sr = s2 / r2 - s1 / r1
    d_ir = 1.0 / r2 - 1.0 / r1
    h = np.where(live, h, 0.0)
    out = {"1": h * d_asinh}
    for i, c in (("x", 0), ("y", 1)):
        out[i] = h * n[..., c] * d_atan + 0.5 * h * t[..., c] * d_log
    for ij, (i, j) in (("xx", (0, 0)), ("xy", (0, 1)), ("yy", (1, 1))):
        nn = n[..., i] * n[..., j]
        nt = n[..., i] * t[..., j] + t[..., i] * n[..., j]
        tt = t[..., i] * t[..., j]
        out[ij] = h * (nn * d_sr - h * nt * d_ir + tt * (d_asinh - d_sr))
    return out


def panel_integrals(points: Array, tris: Array, chunk: int = 256) -> dict[str, Array]:
    """Integrals over every triangle of 1/r, e_i/r and e_i e_j/r seen from every point.

    Parameters
    ----------
    points : ndarray (M, 2)
        Field points, in L.
    tris : ndarray (T, 3, 2)
        Counter-clockwise triangles, in L.

    Returns
    -------
    dict of ndarray (M, T)
        Keys ``"1", "x", "y", "xx", "xy", "yy"``: the integrals of ``1/r``, ``e_x/r``, ``e_y/r``,
        ``e_x e_x/r``, ``e_x e_y/r``, ``e_y e_y/r`` with ``e = (source - point)/r``, in L or
        dimensionless times L (formulations/substrate.md, eqs. (4)-(6)).

    >>> sq = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float)
    >>> bool(abs(panel_integrals(np.array([[0.5, 0.5]]), sq)["1"].sum() - 4 * np.arcsinh(1)) < 1e-12)
    True
    """
    keys = ("1", "x", "y", "xx", "xy", "yy")
    out = {k: np.zeros((len(points), len(tris))) for k in keys}
    for lo in range(0, len(points), chunk):
        p = points[lo : lo + chunk, None, :]
        for e in range(3):
            terms = _edge_terms(p, tris[None, :, e, :], tris[None, :, (e + 1) % 3, :])
            for k in keys:
                out[k][lo : lo + chunk] += terms[k]
    return out


def normal_influence(ints: dict[str, Array]) -> Array:
    """Normal surface displacement per unit normal traction on each panel, E* = 1 (eq. (1)).

    Boussinesq: a normal point force P gives ``u_z = P / (pi E* r)`` on the surface.
    """
    return ints["1"] / np.pi
