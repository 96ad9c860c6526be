"""Closed-form integrals of the half-space surface kernels over polygons; Boussinesq influence.

Implements formulations/substrate.md, sec. 2 (eqs. (3)-(6)): the integral over a polygon of a
kernel ``g(e) / r`` (``e`` the unit vector from the field point, ``r`` the distance) is a sum over
the polygon's edges of one-dimensional integrals along each edge, which are elementary for
``g = 1, e_i, e_i e_j``.  The field point may lie inside the panel: the weak singularity of 1/r
is integrated exactly (the self-panel needs no special quadrature).

An edge shared by two panels contributes to both with opposite signs (its edge integral is odd
in the orientation), so each distinct edge is evaluated once per field point (eq. (6b)).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..geometry import Array

# Below this signed distance (in L) an edge passes through the field point and contributes nothing.
_H_TINY = 1e-13
KEYS = ("1", "x", "y", "xx", "xy", "yy")


def edge_incidence(tris: Array) -> tuple[Array, Array, sp.csr_matrix]:
    """Distinct edges of a set of panels and the signed incidence of edges in panels.

    Returns
    -------
    a, b : ndarray (E, 2)
        Start and end point of each distinct edge, in L.
    S : sparse (T, E)
        +1 where the panel runs along the edge a -> b, -1 where it runs b -> a.
    """
    T, nv = tris.shape[:2]
    starts, ends = tris.reshape(-1, 2), np.roll(tris, -1, axis=1).reshape(-1, 2)
    # vertices closer than 1e-12 L are one vertex (shared by neighbouring panels)
    _, vid = np.unique(np.round(starts * 1e12).astype(np.int64), axis=0, return_inverse=True)
    vid = vid.ravel()
    v0, v1 = vid, vid.reshape(T, nv)[:, np.r_[1:nv, 0]].ravel()
    sign = np.where(v0 < v1, 1.0, -1.0)
    pair = np.stack([np.minimum(v0, v1), np.maximum(v0, v1)], axis=1)
    _, first, eid = np.unique(pair, axis=0, return_index=True, return_inverse=True)
    # geometry of each distinct edge from its first occurrence, oriented from low to high vertex id
    fwd = (sign[first] > 0)[:, None]
    a = np.where(fwd, starts[first], ends[first])
    b = np.where(fwd, ends[first], starts[first])
    S = sp.csr_matrix((sign, (np.arange(T).repeat(nv), eid.ravel())), shape=(T, len(first)))
    return a, b, S


def _edge_terms(p: Array, a: Array, b: Array, keys: tuple[str, ...]) -> dict[str, Array]:
    """Primitive integrals ``(M, E)`` of the edges a -> b seen from the field points ``p (M, 2)``."""
    ab = b - a
    length = np.linalg.norm(ab, axis=1)
    t = ab / length[:, None]
    n = np.stack([t[:, 1], -t[:, 0]], axis=1)
    h = np.sum(a * n, axis=1) - p @ n.T
    s1 = np.sum(a * t, axis=1) - p @ t.T
    s2 = s1 + length
    h2 = h * h
    r1, r2 = np.sqrt(h2 + s1 * s1), np.sqrt(h2 + s2 * s2)
    live = np.abs(h) > _H_TINY
    h = np.where(live, h, 0.0)
    # asinh(s2/|h|) - asinh(s1/|h|) = log(f2 / f1), f = r + s, written h^2 / (r - s) when s < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        f1 = np.where(s1 >= 0.0, r1 + s1, h2 / (r1 - s1))
        f2 = np.where(s2 >= 0.0, r2 + s2, h2 / (r2 - s2))
        d_asinh = np.where(live, np.log(f2 / f1), 0.0)
    out = {"1": h * d_asinh}
    if "x" in keys:
        d_atan = np.arctan2(h * length, h2 + s1 * s2)
        d_log = 2.0 * np.log(r2 / r1)
        for key, c in (("x", 0), ("y", 1)):
            out[key] = h * (n[:, c] * d_atan + 0.5 * t[:, c] * d_log)
    if "xx" in keys:
        d_sr = s2 / r2 - s1 / r1
        d_ir = 1.0 / r2 - 1.0 / r1
        for ij, (i, j) in (("xx", (0, 0)), ("xy", (0, 1)), ("yy", (1, 1))):
            nn = n[:, i] * n[:, j]
            nt = n[:, i] * t[:, j] + t[:, i] * n[:, j]
            tt = t[:, i] * t[:, j]
            out[ij] = h * (nn * d_sr - h * nt * d_ir + tt * (d_asinh - d_sr))
    return out


def panel_integrals(
    points: Array, tris: Array, keys: tuple[str, ...] = KEYS, chunk: int = 512
) -> dict[str, Array]:
    """Integrals over every panel of 1/r, e_i/r and e_i e_j/r seen from every point.

    Parameters
    ----------
    points : ndarray (M, 2)
        Field points, in L.
    tris : ndarray (T, nv, 2)
        Counter-clockwise convex panels (triangles or quadrilaterals), in L.
    keys : tuple of str
        Which integrals to return (``"x"``/``"y"`` and ``"xx"``/``"xy"``/``"yy"`` come in groups).

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
    a, b, S = edge_incidence(np.asarray(tris, dtype=float))
    out = {k: np.empty((len(points), len(tris))) for k in keys}
    for lo in range(0, len(points), chunk):
        terms = _edge_terms(points[lo : lo + chunk], a, b, keys)
        for k in keys:
            out[k][lo : lo + chunk] = (S @ terms[k].T).T
    return out


def normal_influence(ints: dict[str, Array]) -> Array:
    """Normal surface displacement per unit normal traction on each panel, E* = 1 (eq. (1)).

    Boussinesq: a normal point force P gives ``u_z = P / (pi E* r)`` on the surface.
    """
    return ints["1"] / np.pi
