"""Contact points of nearly touching convex pieces: face clipping and edge-edge closest points.

Implements formulations/contact.md section 3, eqs. (8)-(13): for a face axis, the incident face
of the other piece clipped against the side planes of the reference face (Sutherland-Hodgman,
vectorised over every reference/incident face couple), each clipped vertex projected onto the
reference plane; for an edge-edge axis, the closest points of the two supporting edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import Array
from .placement import Bodies, World
from .separation import SAT

# Point kinds (ContactSet.kind); formulations/contact.md, section 3.4.
VERTEX_FACE, CROSSING, EDGE_EDGE, FACE_FACE, SAMPLE, VERTEX_PLANE = range(6)
KIND_NAMES = ("vertex-face", "edge-crossing", "edge-edge", "face-face", "sample", "vertex-plane")
# A point this far outside a side plane still counts as inside (round-off of coplanar faces).
_CLIP_EPS = 1e-12
# Incident faces whose normals are this close (in cosine) to the most anti-parallel one tie.
_FACE_TIE = 1e-9


@dataclass(frozen=True)
class Points:
    """Raw contact points before de-duplication (one row per point, see ContactSet)."""

    pp: np.ndarray
    normal: Array
    xa: Array
    xb: Array
    gap: Array
    kind: np.ndarray
    label: list[str]


def empty_points() -> Points:
    z3 = np.zeros((0, 3))
    return Points(np.zeros(0, dtype=int), z3, z3, z3, np.zeros(0), np.zeros(0, dtype=int), [])


def clip(
    poly: Array, count: np.ndarray, normals: Array, offsets: Array
) -> tuple[Array, np.ndarray, np.ndarray]:
    """Clip convex polygons by half-spaces ``s . x <= o`` (Sutherland-Hodgman, eq. (10)).

    Parameters
    ----------
    poly : ndarray (T, M, 3)
        Polygon vertices in order; rows beyond ``count`` are ignored.
    count : ndarray (T,) of int
    normals : ndarray (T, K, 3)
        Outward unit normals of the clipping planes (a zero row is no plane).
    offsets : ndarray (T, K)

    Returns
    -------
    poly, count, code
        Clipped polygons, their vertex counts, and a code per vertex: the original vertex
        index (< 100), or ``100 + 10 k + e`` for the crossing of plane k (e = 0 leaving, 1 entering).
    """
    T, M = poly.shape[:2]
    code = np.broadcast_to(np.arange(M), (T, M)).copy()
    for k in range(normals.shape[1]):
        d = np.einsum("tmk,tk->tm", poly, normals[:, k]) - offsets[:, k][:, None] - _CLIP_EPS
        idx = np.arange(poly.shape[1])[None, :]
        valid = idx < count[:, None]
        nxt = np.where(idx + 1 < count[:, None], idx + 1, 0)
        dj = np.take_along_axis(d, nxt, axis=1)
        Pj = np.take_along_axis(poly, nxt[..., None], axis=1)
        inside, inside_j = d <= 0.0, dj <= 0.0
        cross = valid & (inside != inside_j)
        denom = np.where(cross, d - dj, 1.0)
        t = np.clip(np.where(cross, d / denom, 0.0), 0.0, 1.0)
        X = poly + t[..., None] * (Pj - poly)
        cand = np.stack([poly, X], axis=2).reshape(T, -1, 3)
        keep = np.stack([valid & inside, cross], axis=2).reshape(T, -1)
        codes = np.stack([code, 100 + 10 * k + (~inside).astype(int)], axis=2).reshape(T, -1)
        order = np.argsort(~keep, axis=1, kind="stable")
        count = keep.sum(axis=1)
        width = max(int(count.max(initial=0)), 1)
        order = order[:, :width]
        poly = np.take_along_axis(cand, order[..., None], axis=1)
        code = np.take_along_axis(codes, order, axis=1)
    return poly, count, code


def _face_tasks(
    sat: SAT, active: np.ndarray, tie_tol: float, memory: np.ndarray | None = None, bias: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(piece pair, reference side 0=a/1=b, reference face) of every tied best face axis, eq. (8).

    ``memory`` ``(pairs, 2)`` = (side, face) used in the previous linearisation (-1: none): it is
    kept alone while its separation is within ``bias`` of the best face axis (sec. 6).
    """
    best_face = np.maximum(sat.face_a.max(axis=1), sat.face_b.max(axis=1))
    best = best_face[:, None] - tie_tol
    sticky = np.zeros(len(best_face), dtype=bool)
    if memory is not None:
        rows = np.flatnonzero(memory[:, 0] >= 0)
        seps = np.where(
            memory[rows, 0] == 0, sat.face_a[rows, memory[rows, 1]], sat.face_b[rows, memory[rows, 1]]
        )
        sticky[rows[seps >= best_face[rows] - bias]] = True
    out = []
    for side, seps in enumerate((sat.face_a, sat.face_b)):
        p, f = np.nonzero((seps >= best) & (active & ~sticky)[:, None])
        out.append((p, np.full(len(p), side), f))
    keep = np.flatnonzero(sticky & active)
    if memory is not None and len(keep):
        out.append((keep, memory[keep, 0], memory[keep, 1]))
    return tuple(np.concatenate(x) for x in zip(*out))  # type: ignore[return-value]


def _gather_faces(V: Array, bodies: Bodies, f: np.ndarray) -> tuple[Array, np.ndarray]:
    idx = bodies.faces[f]
    poly = np.take_along_axis(V, np.where(idx < 0, 0, idx)[..., None], axis=1)
    return poly, bodies.face_size[f]


def face_points(
    world: World, sat: SAT, bodies: Bodies, active: np.ndarray, settings, memory: np.ndarray | None = None
) -> Points:
    """Contact points of every face axis within ``settings.tie_tol`` of the best one (eqs. (8)-(12)).

    ``memory``: the (side, face) of each piece pair's previous reference face, see ``_face_tasks``.
    """
    p, side, f = _face_tasks(sat, active, settings.tie_tol, memory, settings.edge_bias)
    VA, VB = world.verts[sat.a[p], sat.pa[p]], world.verts[sat.b[p], sat.pb[p]]
    NA, NB = world.normals[sat.a[p], sat.pa[p]], world.normals[sat.b[p], sat.pb[p]]
    on_a = (side == 0)[:, None, None]
    Vref, Vinc = np.where(on_a, VA, VB), np.where(on_a, VB, VA)
    Nref, Ninc = np.where(on_a, NA, NB), np.where(on_a, NB, NA)
    n_ref = Nref[np.arange(len(p)), f]
    dots = np.einsum("tfk,tk->tf", Ninc, n_ref)
    t, g = np.nonzero(dots <= dots.min(axis=1, initial=1.0)[:, None] + _FACE_TIE)
    if len(t) == 0:
        return empty_points()
    ref_poly, ref_n = _gather_faces(Vref[t], bodies, f[t])
    inc_poly, inc_n = _gather_faces(Vinc[t], bodies, g)
    n_ref = n_ref[t]
    nxt = np.roll(ref_poly, -1, axis=1)
    nxt[np.arange(len(t)), ref_n - 1] = ref_poly[:, 0]
    s = np.cross(nxt - ref_poly, n_ref[:, None, :])
    s_norm = np.linalg.norm(s, axis=-1, keepdims=True)
    s = np.where(
        np.arange(s.shape[1])[None, :, None] < ref_n[:, None, None], s / np.maximum(s_norm, 1e-300), 0.0
    )
    pts, cnt, code = clip(inc_poly, inc_n, s, np.einsum("tkj,tkj->tk", s, ref_poly))
    if settings.sampling > 0:
        pts, cnt, code = _sample(pts, cnt, code, settings.sampling)
    sep = np.einsum("tmk,tk->tm", pts - ref_poly[:, :1], n_ref)
    parallel = dots[t, g] < -1.0 + 1e-9
    kind = np.where(code < 100, np.where(parallel[:, None], FACE_FACE, VERTEX_FACE), CROSSING)
    kind = np.where(code < 0, SAMPLE, kind)
    keep = (np.arange(pts.shape[1])[None, :] < cnt[:, None]) & (sep < settings.margin)
    if settings.mode == "vertex":
        keep &= (code >= 0) & (code < 100)
    ti, mi = np.nonzero(keep)
    clipped = _face_records(p[t], side[t], f[t], g, n_ref, pts, sep, kind, code, ti, mi)
    if settings.mode == "vertex":
        return clipped
    near = _plane_vertices(
        Vinc[t], Vref[t], Nref[t], bodies, ref_poly, n_ref, p[t], side[t], f[t], g, settings
    )
    return _merge(clipped, near)


def _plane_vertices(
    V: Array, Vref: Array, Nref: Array, bodies: Bodies, ref_poly: Array, n_ref: Array, p, side, f, g, settings
) -> Points:
    """Vertices of the incident piece near the reference piece, against the reference plane (sec. 6).

    The separating-axis depth along a face is the minimum over all vertices of the other piece;
    next to an obtuse edge of the reference piece (slanted prisms, the dart's 45-degree sides) the
    deepest vertex can lie beyond the reference face's edge yet inside the piece, and the clipped
    incident face misses it: the overlap then survives the sequential QP.  Rows are added for the
    vertices within ``edge_bias`` of the reference piece (signed distance to its face planes), so
    vertices far beyond the face, which could pass it without touching, stay free.
    """
    corner = Vref[np.arange(len(Vref))[:, None], bodies.faces[:, 0][None, :]]
    inside = np.einsum("tvk,tfk->tvf", V, Nref) - np.einsum("tfk,tfk->tf", corner, Nref)[:, None, :]
    near = inside.max(axis=2) <= settings.edge_bias
    sep = np.einsum("tvk,tk->tv", V - ref_poly[:, :1], n_ref)
    ti, mi = np.nonzero(near & (sep < settings.margin))
    code = np.broadcast_to(np.arange(V.shape[1]), sep.shape)
    kind = np.full(sep.shape, VERTEX_FACE)
    return _face_records(p, side, f, g, n_ref, V, sep, kind, code, ti, mi)


def _merge(a: Points, b: Points) -> Points:
    return Points(
        np.concatenate([a.pp, b.pp]),
        np.concatenate([a.normal, b.normal]),
        np.concatenate([a.xa, b.xa]),
        np.concatenate([a.xb, b.xb]),
        np.concatenate([a.gap, b.gap]),
        np.concatenate([a.kind, b.kind]),
        a.label + b.label,
    )


def plane_points(
    world: World, sat: SAT, bodies: Bodies, active: np.ndarray, settings, memory: np.ndarray | None = None
) -> Points:
    """Vertex rows against the best face plane, unclipped, for pairs whose clipping is empty (sec. 6).

    The best face plane separates the pieces, so every vertex of the other piece within the
    margin of it is constrained to stay outside: a valid certificate when the nearest features are
    off the face (a corner facing a corner), and symmetric because tied faces all contribute.
    """
    if not active.any():
        return empty_points()
    p, side, f = _face_tasks(sat, active, settings.tie_tol, memory, settings.edge_bias)
    outer = ~bodies.internal[np.where(side == 0, sat.pa[p], sat.pb[p]), f]
    p, side, f = p[outer], side[outer], f[outer]
    VA, VB = world.verts[sat.a[p], sat.pa[p]], world.verts[sat.b[p], sat.pb[p]]
    NA, NB = world.normals[sat.a[p], sat.pa[p]], world.normals[sat.b[p], sat.pb[p]]
    on_a = (side == 0)[:, None, None]
    Vref, Vinc = np.where(on_a, VA, VB), np.where(on_a, VB, VA)
    n_ref = np.where(on_a[:, :, 0], NA[np.arange(len(p)), f], NB[np.arange(len(p)), f])
    ref_point = Vref[np.arange(len(p)), bodies.faces[f, 0]]
    sep = np.einsum("tvk,tk->tv", Vinc - ref_point[:, None, :], n_ref)
    code = np.broadcast_to(np.arange(Vinc.shape[1]), sep.shape)
    ti, mi = np.nonzero(sep < settings.margin)
    kind = np.full(sep.shape, VERTEX_FACE)
    return _face_records(p, side, f, np.full(len(p), -1), n_ref, Vinc, sep, kind, code, ti, mi)


def _face_records(p, side, f, g, n_ref, pts, sep, kind, code, ti, mi) -> Points:
    x, s = pts[ti, mi], sep[ti, mi]
    ref_a = side[ti] == 0
    n = np.where(ref_a[:, None], n_ref[ti], -n_ref[ti])
    proj = x - s[:, None] * n_ref[ti]
    xa = np.where(ref_a[:, None], proj, x)
    xb = np.where(ref_a[:, None], x, proj)
    labels = [
        f"F{'ab'[sd]}{ff}/{gg}:{'v' if c < 100 else 'x'}{c}"
        for sd, ff, gg, c in zip(side[ti].tolist(), f[ti].tolist(), g[ti].tolist(), code[ti, mi].tolist())
    ]
    return Points(p[ti], n, xa, xb, s, kind[ti, mi], labels)


def _sample(pts: Array, cnt: np.ndarray, code: np.ndarray, s: int) -> tuple[Array, np.ndarray, np.ndarray]:
    """Add ``s`` equally spaced points on every edge of each clipped polygon (code -1)."""
    T, M = code.shape
    idx = np.arange(M)[None, :]
    nxt = np.where(idx + 1 < cnt[:, None], idx + 1, 0)
    Pj = np.take_along_axis(pts, nxt[..., None], axis=1)
    frac = np.arange(1, s + 1) / (s + 1.0)
    extra = pts[:, :, None, :] + frac[None, None, :, None] * (Pj - pts)[:, :, None, :]
    # A two-point polygon is a segment: its closing edge repeats the first one.
    ok = (idx < cnt[:, None]) & ((cnt[:, None] > 2) | (idx == 0)) & (cnt[:, None] > 1)
    ok = np.repeat(ok, s, axis=1)
    extra = extra.reshape(T, M * s, 3)
    all_pts = np.concatenate([pts, extra], axis=1)
    valid = np.concatenate([idx < cnt[:, None], ok], axis=1)
    codes = np.concatenate([code, -np.ones((T, M * s), dtype=int)], axis=1)
    order = np.argsort(~valid, axis=1, kind="stable")
    return (
        np.take_along_axis(all_pts, order[..., None], axis=1),
        valid.sum(axis=1),
        np.take_along_axis(codes, order, axis=1),
    )


def segment_closest(p1: Array, q1: Array, p2: Array, q2: Array) -> tuple[Array, Array]:
    """Closest points of segments [p1, q1] and [p2, q2], rows ``(T, 3)`` (eq. (13))."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = (np.einsum("tk,tk->t", x, y) for x, y in ((d1, d1), (d2, d2), (d2, r)))
    c, b = np.einsum("tk,tk->t", d1, r), np.einsum("tk,tk->t", d1, d2)
    den = a * e - b * b
    ok = den > 1e-14 * a * e
    s = np.where(ok, np.clip((b * f - c * e) / np.where(ok, den, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    low, high = t < 0.0, t > 1.0
    s = np.where(low, np.clip(-c / a, 0.0, 1.0), np.where(high, np.clip((b - c) / a, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return p1 + s[:, None] * d1, p2 + t[:, None] * d2


def edge_points(
    world: World, sat: SAT, bodies: Bodies, active: np.ndarray, settings, memory: np.ndarray | None = None
) -> Points:
    """Closest points of the supporting edges for every tied best edge axis (eq. (13)).

    ``memory`` ``(pairs, 2)`` holds the edge classes each piece pair used in the previous
    linearisation (-1: none); a remembered axis is kept while it is within ``settings.edge_bias``
    of the best, so a corner touching a corner does not flip between edge pairs (sec. 6).
    """
    if settings.mode == "vertex" or not active.any():
        return empty_points()
    flat = sat.edge.reshape(len(sat.sep), -1)
    best = flat.max(axis=1)[:, None, None] - settings.tie_tol
    chosen = sat.edge >= best
    if memory is not None:
        rows = np.flatnonzero(memory[:, 0] >= 0)
        kept = sat.edge[rows, memory[rows, 0], memory[rows, 1]] >= flat[rows].max(axis=1) - settings.edge_bias
        rows = rows[kept]
        chosen[rows] = False
        chosen[rows, memory[rows, 0], memory[rows, 1]] = True
    p, ci, cj = np.nonzero(chosen & active[:, None, None])
    u = sat.edge_axis[p, ci, cj]
    VA, VB = world.verts[sat.a[p], sat.pa[p]], world.verts[sat.b[p], sat.pb[p]]
    ea = _support_edge(VA, bodies, ci, u)
    eb = _support_edge(VB, bodies, cj, -u)
    rows = np.arange(len(p))
    EA, EB = bodies.edges[ea], bodies.edges[eb]
    xa, xb = segment_closest(VA[rows, EA[:, 0]], VA[rows, EA[:, 1]], VB[rows, EB[:, 0]], VB[rows, EB[:, 1]])
    n = _edge_normal(u, xb - xa)
    gap = np.einsum("tk,tk->t", n, xb - xa)
    keep = gap < settings.margin
    labels = [
        f"E{i}/{j}:c{k}/{m}"
        for i, j, k, m in zip(ea[keep].tolist(), eb[keep].tolist(), ci[keep].tolist(), cj[keep].tolist())
    ]
    kind = np.full(int(keep.sum()), EDGE_EDGE)
    return Points(p[keep], n[keep], xa[keep], xb[keep], gap[keep], kind, labels)


def _edge_normal(u: Array, r: Array) -> Array:
    """Normals of edge-edge points, eq. (13): the axis u, or the direction of r = xb - xa when the
    closest points are clamped to an edge end (then r is not along u) and the edges are apart."""
    dist = np.linalg.norm(r, axis=1)
    use_r = (dist > 1e-9) & (np.einsum("tk,tk->t", u, r) > 0.5 * dist)
    return np.where(use_r[:, None], r / np.maximum(dist, 1e-300)[:, None], u)


def _support_edge(V: Array, bodies: Bodies, cls: np.ndarray, u: Array) -> np.ndarray:
    """Per row, the edge of class ``cls`` highest along u (both end points counted).

    Two parallel edges tie only when a face holds both; that face's axis then ties with the edge
    axis and wins, so one edge per row suffices.
    """
    h = np.einsum("tvk,tk->tv", V, u)
    lowest = np.minimum(h[:, bodies.edges[:, 0]], h[:, bodies.edges[:, 1]])
    lowest = np.where(bodies.edge_class[None, :] == cls[:, None], lowest, -np.inf)
    return np.argmax(lowest, axis=1)
