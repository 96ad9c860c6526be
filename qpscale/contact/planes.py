"""Separating-plane contact: every near piece pair carries a plane that the QP moves with the scales.

Implements formulations/contact.md section 7, eqs. (19)-(24).  Two convex pieces do not overlap
if and only if some plane has every vertex of one on one side and every vertex of the other on
the other side.  Instead of choosing the features that touch (a separating axis, then clipping,
which needs a rule for ties), each near piece pair gets such a plane as three extra unknowns of
the increment QP: two rotations of its normal and a shift along it.  Each vertex within the
margin of the plane gives one linear row; the QP then places the plane where equilibrium wants
it, so vertex-face, edge-edge and face-face contact all come out of the same rows and the
converged state does not depend on which axis the plane started from.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from ..geometry import Array, cross
from .placement import World
from .separation import SAT
from .symmetry import Mirror

# Vertex of the piece facing the plane's positive side (b) and of the one behind it (a).
SIDE_B, SIDE_A = 1, -1


@dataclass(frozen=True)
class Planes:
    """The separating planes of one linearisation (one per near piece pair).

    Attributes
    ----------
    keys : tuple of (a, piece_a, b, piece_b)
    normal : ndarray (P, 3)
        Unit normal pointing from piece a towards piece b.
    point : ndarray (P, 3)
        A point of the plane near the contact (the centroid of the rows' vertices, projected), in L.
    basis : ndarray (P, 3, 2)
        Two unit vectors orthogonal to the normal: the directions its increment may take, eq. (21).
    """

    keys: tuple[tuple[int, int, int, int], ...]
    normal: Array
    point: Array
    basis: Array

    @property
    def count(self) -> int:
        return len(self.keys)

    def state(self) -> dict[tuple[int, int, int, int], tuple[Array, Array]]:
        """key -> (normal, point): what the next linearisation starts from."""
        return dict(zip(self.keys, zip(self.normal, self.point)))  # rows as views, as normal[j] gives

    def advanced(self, theta: Array) -> dict[tuple[int, int, int, int], tuple[Array, Array]]:
        """The planes moved by the QP's plane unknowns ``theta`` (3 P,): eq. (22), exact on the sphere."""
        t = np.asarray(theta, dtype=float).reshape(-1, 3)
        n = self.normal + np.einsum("pij,pj->pi", self.basis, t[:, :2])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        p = self.point + t[:, 2:3] * self.normal
        return dict(zip(self.keys, zip(n, p)))


def tangent_basis(n: Array) -> Array:
    """(P, 3, 2) orthonormal pairs spanning the plane orthogonal to each unit row of ``n``."""
    helper = np.where(np.abs(n[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = cross(helper, n)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = cross(n, e1)
    return np.stack([e1, e2], axis=2)


def best_axes(sat: SAT, world: World, rows: np.ndarray) -> Array:
    """Unit normal (from a to b) of the best separating axis of each piece pair in ``rows`` (eq. (5))."""
    fa, fb = sat.face_a[rows], sat.face_b[rows]
    ed = sat.edge[rows].reshape(len(rows), -1)
    cand = np.stack([fa.max(axis=1), fb.max(axis=1), ed.max(axis=1)], axis=1)
    which = np.argmax(cand, axis=1)
    NA = world.normals[sat.a[rows], sat.pa[rows]]
    NB = world.normals[sat.b[rows], sat.pb[rows]]
    k = np.arange(len(rows))
    u_a = NA[k, fa.argmax(axis=1)]
    u_b = -NB[k, fb.argmax(axis=1)]
    ij = ed.argmax(axis=1)
    nc = sat.edge.shape[1]
    u_e = sat.edge_axis[rows, ij // nc, ij % nc]
    return np.where((which == 0)[:, None], u_a, np.where((which == 1)[:, None], u_b, u_e))


#: A pressed plane that parts its pieces by more than this (L) less than their best separating axis
#: is stale (``plane_rows``, ``pressed``): 1000 times the penetration tolerance, so a plane of a
#: converged contact (both separations within ~1e-9 of zero) never is.
STALE_PLANE_TOL = 1e-6


@dataclass(frozen=True)
class PlaneRows:
    """Vertex rows against the planes, eq. (20): gap_k = side_k n_j . (x_k - p_j)."""

    planes: Planes
    plane: np.ndarray  # (m,) plane index of each row
    side: np.ndarray  # (m,) SIDE_B or SIDE_A
    vertex: np.ndarray  # (m,) vertex index within its piece
    x: Array  # (m, 3) the vertex, current world position
    gap: Array  # (m,)
    labels: list[str]
    keys: np.ndarray  # (P, 4) ``planes.keys`` as an array


@cache
def _vertex_names(n_verts: int) -> np.ndarray:
    """``(2, V)`` row labels ``P{a,b}v{k}`` of the vertices of the piece behind / in front of a plane."""
    return np.array([[f"P{c}v{v}" for v in range(n_verts)] for c in "ab"], dtype=object)


def plane_rows(
    world: World,
    sat: SAT,
    active: np.ndarray,
    margin: float,
    memory: dict[tuple[int, int, int, int], tuple[Array, Array]] | None,
    refresh: float | None = None,
    mirror: Mirror | None = None,
    pressed: frozenset = frozenset(),
) -> PlaneRows:
    """Planes of the active piece pairs and the vertex rows within ``margin`` of them.

    A pair keeps the plane of ``memory`` (the previous linearisation, moved by its QP step); a
    pair that has just come within the margin starts from its best separating axis, the plane
    half-way between the pieces along it.  The plane's point is re-centred on the rows'
    vertices (the plane itself is unchanged), which keeps the lever arms of eq. (21) short.
    With ``refresh``, pairs that overlap by more than it restart from their best axis too: the
    linearised rotation of a plane can keep satisfying its rows while the pieces overlap (the
    sequential QP then stalls with the overlap), and the best axis is the shortest way out.  So
    does a remembered plane that separates the pieces worse than their best axis by more than
    ``margin`` (stale: the increment QP cannot rotate it far enough and becomes infeasible).
    A remembered plane among the keys ``pressed`` (the planes the last QP pressed) is held to a
    much tighter test: it restarts where it parts its pieces by more than ``STALE_PLANE_TOL`` less
    than their best axis.  Its separation is ``min n.x_b - max n.x_a`` over the pieces' vertices
    (its shift is free), the best axis's the separating-axis test's ``sep`` (the pieces' distance
    when they are apart).  Such a plane can press pieces that do not touch, and its linearised
    rotation, whose lever is the rows' spread across the hinge, turns it back only by
    ``lambda * lever / rho`` per QP (membrane.md sec. 8, increment.md sec. 4).
    With ``mirror`` (a symmetric path, sec. 8) a plane restarts together with its image, and every
    plane is replaced by the mean of itself and its partner's image before the rows are taken.
    """
    rows = np.flatnonzero(active)
    key_array = np.stack([sat.a[rows], sat.pa[rows], sat.b[rows], sat.pb[rows]], axis=1)
    keys = list(map(tuple, key_array.tolist()))  # Python ints: a fifth of the per-item int()s' time
    VA = world.verts[sat.a[rows], sat.pa[rows]]
    VB = world.verts[sat.b[rows], sat.pb[rows]]
    n = best_axes(sat, world, rows) if len(rows) else np.zeros((0, 3))
    h = 0.5 * (np.einsum("pvk,pk->pv", VA, n).max(axis=1) + np.einsum("pvk,pk->pv", VB, n).min(axis=1))
    # The new plane's point: the foot of the pieces' mid-point on it, near the pair.  (The foot of
    # the origin, h n, lies up to the patch's size away along the plane; on a held path the mean
    # of such a point and its partner's image, eq. (26), left the mean plane there, and a corner
    # pair of the 9x9 square on the mirror line started 4.96 L on the wrong side of it.)
    mid = 0.5 * (VA.mean(axis=1) + VB.mean(axis=1))
    p = mid + (h - np.einsum("pk,pk->p", n, mid))[:, None] * n
    memory = memory or {}
    overlapping = sat.sep[rows] < -refresh if refresh is not None else np.zeros(len(rows), dtype=bool)
    kept = np.zeros(len(rows), dtype=bool)
    known = np.flatnonzero(np.array([key in memory for key in keys], dtype=bool) & ~overlapping)
    nm = np.array([memory[keys[j]][0] for j in known])
    pm = np.array([memory[keys[j]][1] for j in known])
    if len(known):
        # A remembered plane that separates the pieces worse than their best axis by more than
        # the margin is stale (it was left behind while the pieces moved on): no step of its
        # linearised rotation reaches a separating position, and the QP would be infeasible.
        # It restarts from the best axis (contact.md sec. 7).
        below_a = np.einsum("pvk,pk->pv", pm[:, None, :] - VA[known], nm).min(axis=1)
        above_b = np.einsum("pvk,pk->pv", VB[known] - pm[:, None, :], nm).min(axis=1)
        kept[known] = np.minimum(below_a, above_b) >= sat.sep[rows[known]] - margin
        if pressed:
            tight = np.array([keys[j] in pressed for j in known.tolist()], dtype=bool)
            stale = sat.sep[rows[known]] > below_a + above_b + STALE_PLANE_TOL
            kept[known] &= ~(tight & stale)
    if mirror is not None:
        kept = ~mirror.orbit_any(keys, ~kept)
    if kept.any():
        use = np.flatnonzero(kept)  # remembered planes only (the mirror only clears more)
        at = np.searchsorted(known, use)
        n[use] = nm[at]
        p[use] = pm[at]
    if mirror is not None:
        n, p = mirror.symmetrise(keys, n, p)
    ga = np.einsum("pk,pvk->pv", n, p[:, None, :] - VA)
    gb = np.einsum("pk,pvk->pv", n, VB - p[:, None, :])
    near_a, near_b = ga < margin, gb < margin
    # Re-centre the plane point on its rows' vertices (projected): same plane, short lever arms.
    w = near_a.sum(axis=1) + near_b.sum(axis=1)
    c = (np.einsum("pv,pvk->pk", near_a, VA) + np.einsum("pv,pvk->pk", near_b, VB)) / np.maximum(w, 1)[
        :, None
    ]
    c = np.where((w > 0)[:, None], c, p)
    p = c - np.einsum("pk,pk->p", c - p, n)[:, None] * n
    planes = Planes(tuple(keys), n, p, tangent_basis(n) if len(rows) else np.zeros((0, 3, 2)))
    ja, va = np.nonzero(near_a)
    jb, vb = np.nonzero(near_b)
    plane = np.concatenate([ja, jb])
    side = np.concatenate([np.full(len(ja), SIDE_A), np.full(len(jb), SIDE_B)])
    vertex = np.concatenate([va, vb])
    x = np.concatenate([VA[ja, va], VB[jb, vb]])
    gap = np.concatenate([ga[ja, va], gb[jb, vb]])
    order = np.lexsort((vertex, -side, plane))
    # Row labels from a table of the (side, vertex) names: no string formatting per row.
    names = _vertex_names(VA.shape[1] if len(rows) else 0)
    labels = names[(side[order] > 0).astype(int), vertex[order]].tolist() if len(order) else []
    order_of = (plane[order], side[order], vertex[order], x[order], gap[order])
    return PlaneRows(planes, *order_of, labels, key_array)
