"""Contact detection: the settings, the contact set of a configuration, and the overlap depth.

Implements formulations/contact.md as a caller sees it: the piece pairs closer than the margin
(the signed separation of section 2, eqs. (3)-(7), in :mod:`qpscale.contact.separation`) and the
rows they carry, gathered in a :class:`ContactSet`.  For the feature formulation these are the
contact points of section 3, eqs. (8)-(13) (in :mod:`qpscale.contact.clipping`), merged here where
they coincide (section 3.3), with the decisions of section 6 (the sticky axis choice, the face
plane of an empty clipping) taken here; for the plane formulation, the vertex rows of section 7
(in :mod:`qpscale.contact.planes`).  The linearised gap g + J dq and the contact forces J' lam of
a set (sections 4-5) are in :mod:`qpscale.contact.rows`.

Sign conventions: the normal n_k of contact point k points from scale a to scale b, the gap
g_k = n_k . (xb_k - xa_k) is positive when apart, and a multiplier lam_k >= 0 pushes b along
+n_k and a along -n_k.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from ..errors import InvalidDesign
from ..geometry import Array
from ..tiling import Patch
from .clipping import KIND_NAMES, VERTEX_PLANE, Points, edge_points, face_points, plane_points
from .placement import World, bodies_of, place
from .planes import SIDE_B, Planes, plane_rows
from .separation import separate
from .symmetry import Mirror

MODES = ("full", "vertex")
FORMULATIONS = ("plane", "feature")


@dataclass(frozen=True)
class ContactSettings:
    """Options of the contact detection.

    Parameters
    ----------
    margin : float
        Pairs and points whose separation is below this enter the contact set, in L, > 0.
    tie_tol : float
        Axes whose separation is within this of the best all contribute, in L, >= 0.
    edge_bias : float
        Hysteresis of the axis choice, in L, >= tie_tol: given the previous linearisation's set, a
        piece pair switches between face rows and an edge-edge row only when the other kind of
        axis is better by more than this (formulations/contact.md sec. 6).
    sampling : int
        Extra equally spaced points on every clipped edge (completeness checks), >= 0.
    mode : str
        ``"full"`` (vertex-face, edge crossings, edge-edge, face-face) or ``"vertex"`` (only
        polyhedron vertices against faces: an incomplete node-to-surface set).  Feature
        formulation only.
    formulation : str
        ``"plane"`` (default): every near piece pair carries a separating plane that the QP
        moves, vertices against it (formulations/contact.md sec. 7; path-independent).
        ``"feature"``: rows from the best separating axis and its clipped contact features
        (sections 3-6; the axis choice is kept sticky across linearisations).
    """

    margin: float = 0.1
    tie_tol: float = 1e-9
    edge_bias: float = 1e-3
    sampling: int = 0
    mode: str = "full"
    formulation: str = "plane"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.margin) and 0.0 < self.margin <= 10.0):
            raise InvalidDesign("margin", self.margin, "(0, 10] (in L)")
        if not (np.isfinite(self.tie_tol) and 0.0 <= self.tie_tol < self.margin):
            raise InvalidDesign("tie_tol", self.tie_tol, "[0, margin) (in L)")
        if not (np.isfinite(self.edge_bias) and self.tie_tol <= self.edge_bias < self.margin):
            raise InvalidDesign("edge_bias", self.edge_bias, "[tie_tol, margin) (in L)")
        if not (int(self.sampling) == self.sampling and 0 <= self.sampling <= 1000):
            raise InvalidDesign("sampling", self.sampling, "integers in [0, 1000]")
        if self.mode not in MODES:
            raise InvalidDesign("mode", self.mode, "{" + ", ".join(MODES) + "}")
        if self.formulation not in FORMULATIONS:
            raise InvalidDesign("formulation", self.formulation, "{" + ", ".join(FORMULATIONS) + "}")


@dataclass(frozen=True)
class ContactSet:
    """Contact points of a configuration; row k is one linearised constraint g_k + J_k dq >= 0.

    Attributes
    ----------
    a, b : ndarray (m,) of int
        Scale indices (a < b for the patch's candidate pairs).
    piece_a, piece_b : ndarray (m,) of int
        Convex piece indices (``patch.convex_prisms``).
    normal : ndarray (m, 3)
        Unit normal from a to b.
    xa, xb : ndarray (m, 3)
        Material points on a and on b, current world coordinates, in L.
    gap : ndarray (m,)
        g_k = n_k . (xb_k - xa_k), in L (negative: penetration).
    kind : ndarray (m,) of int
        Index into :data:`KIND_NAMES`.
    labels : tuple of str
        ``"a:pa-b:pb <feature>"`` naming the reference/incident faces or the edges of each row.
    q : ndarray (n, 5)
        Configuration the set was detected at.
    centre : ndarray (n, 3)
        Current reference points c_i at that configuration, in L.
    axis_kind : dict
        ``(a, piece_a, b, piece_b) -> ("face", side, f) | ("edge", ci, cj)``: the separating axis
        that gave the rows of each piece pair; passed back as ``previous`` to keep it sticky.
    planes : Planes or None
        Separating planes of the plane formulation (their unknowns follow the DOFs in the QP).
    side : ndarray (m,) of int
        Plane rows: +1 the row's vertex is xb (on scale b), -1 it is xa (on scale a); 0 for
        two-body rows of the feature formulation.
    plane : ndarray (m,) of int
        Plane index of each row (-1 for two-body rows).
    plane_memory : dict or None
        ``key -> (normal, point)``: the planes the next linearisation starts from (after the
        QP step, :meth:`Planes.advanced`).
    """

    a: np.ndarray
    b: np.ndarray
    piece_a: np.ndarray
    piece_b: np.ndarray
    normal: Array
    xa: Array
    xb: Array
    gap: Array
    kind: np.ndarray
    labels: tuple[str, ...]
    q: Array
    centre: Array
    axis_kind: dict = field(default_factory=dict)
    planes: Planes | None = None
    side: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    plane: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    plane_memory: dict | None = None

    def __post_init__(self) -> None:
        m = len(self.a)
        if self.planes is None and len(self.side) == 0:  # feature rows: two-body, no plane
            object.__setattr__(self, "side", np.zeros(m, dtype=int))
            object.__setattr__(self, "plane", -np.ones(m, dtype=int))
        names = ("b", "piece_a", "piece_b", "normal", "xa", "xb", "gap", "kind", "labels", "side", "plane")
        for name in names:
            if len(getattr(self, name)) != m:
                raise InvalidDesign(name, len(getattr(self, name)), f"length {m} (one row per contact point)")

    @property
    def m(self) -> int:
        return int(len(self.a))

    @property
    def n_scales(self) -> int:
        return int(self.q.shape[0])

    @property
    def n_extra(self) -> int:
        """Unknowns the set adds to the QP after the 5 n DOFs (3 per separating plane)."""
        return 3 * self.planes.count if self.planes is not None else 0

    @property
    def kind_names(self) -> tuple[str, ...]:
        return tuple(KIND_NAMES[k] for k in self.kind.tolist())


def _check_q(patch: Patch, q: Array) -> Array:
    q = np.asarray(q, dtype=float)
    if q.shape != (patch.n_scales, 5) or not np.all(np.isfinite(q)):
        raise InvalidDesign("q", q.shape, f"finite array of shape ({patch.n_scales}, 5)")
    return q


def _pairs(patch: Patch, pairs: np.ndarray | None) -> np.ndarray:
    out = patch.contact_pairs if pairs is None else np.asarray(pairs, dtype=int).reshape(-1, 2)
    if len(out) and (out.min() < 0 or out.max() >= patch.n_scales or np.any(out[:, 0] == out[:, 1])):
        raise InvalidDesign(
            "pairs", out.tolist(), f"pairs of distinct scale indices in [0, {patch.n_scales})"
        )
    return out


def penetration(patch: Patch, q: Array, pairs: np.ndarray | None = None) -> float:
    """Largest overlap depth between convex pieces of the candidate pairs, in L (>= 0).

    The depth is minus the signed separation of eq. (5), exact for overlapping convex pieces.

    >>> from qpscale import Design
    >>> p = Design(rings=1).patch()
    >>> penetration(p, np.zeros((p.n_scales, 5)))
    0.0
    """
    q = _check_q(patch, q)
    pairs = _pairs(patch, pairs)
    if len(pairs) == 0:
        return 0.0
    sat = separate(place(patch, q), pairs)
    return float(max(0.0, -sat.sep.min()))


def detect_contacts(
    patch: Patch,
    q: Array,
    settings: ContactSettings | None = None,
    pairs: np.ndarray | None = None,
    previous: ContactSet | None = None,
    refresh: float | None = None,
    mirror: Mirror | None = None,
    pressed: frozenset = frozenset(),
) -> ContactSet:
    """Contact points of every candidate pair closer than ``settings.margin`` (section 3).

    Parameters
    ----------
    patch : Patch
    q : ndarray (n, 5)
        DOFs [u_x, u_y, u_z, phi_x, phi_y] per scale (L, radians).
    settings : ContactSettings, optional
    pairs : ndarray (S, 2) of int, optional
        Candidate scale pairs; default ``patch.contact_pairs``.
    previous : ContactSet, optional
        The set of the previous linearisation: a piece pair keeps the kind of axis (face or
        edge-edge) it had unless the other kind beats it by more than ``settings.edge_bias``;
        for the plane formulation, it carries the planes to start from.
    refresh : float, optional
        Plane formulation: pairs overlapping by more than this (L) restart their plane from the
        best separating axis (sec. 7).
    mirror : Mirror, optional
        Plane formulation on a symmetric path: the planes are held mirror-symmetric (sec. 8).
    pressed : frozenset, optional
        Plane formulation: keys of the planes the last QP pressed; one of them restarts from its
        best axis where it parts its pieces by more than ``STALE_PLANE_TOL`` less than that axis
        (sec. 7, ``plane_rows``).

    Returns
    -------
    ContactSet

    >>> from qpscale import Design
    >>> p = Design(rings=1).patch()
    >>> cs = detect_contacts(p, np.zeros((p.n_scales, 5)))
    >>> bool(np.allclose(cs.gap, 0.0025))  # vertices to the half-way planes of the 0.005 L gaps
    True
    """
    settings = settings or ContactSettings()
    q = _check_q(patch, q)
    pairs = _pairs(patch, pairs)
    world = place(patch, q)
    if len(pairs) == 0:
        return _assemble(world, q, None, [], settings)
    bodies = bodies_of(patch)
    sat = separate(world, pairs)
    active = sat.sep < settings.margin
    if settings.formulation == "plane":
        memory = previous.plane_memory if previous is not None else None
        rows = plane_rows(world, sat, active, settings.margin, memory, refresh, mirror, pressed)
        return _plane_set(world, q, sat, rows)
    best_face = np.maximum(sat.face_a.max(axis=1), sat.face_b.max(axis=1))
    best_edge = sat.edge.reshape(len(sat.sep), -1).max(axis=1)
    use_edge = _choose_edge(sat, best_face, best_edge, previous, settings)
    face_memory, edge_memory = _axis_memory(sat, previous)
    faces = face_points(world, sat, bodies, active & ~use_edge, settings, face_memory)
    # A face axis whose clipping is empty (a corner facing a corner) would leave an active pair
    # without rows: its face plane then constrains the nearby vertices (formulations/contact.md sec. 6).
    empty = active & ~use_edge & ~np.isin(np.arange(len(sat.sep)), faces.pp) & (settings.mode != "vertex")
    parts = [
        faces,
        plane_points(world, sat, bodies, empty, settings, face_memory),
        edge_points(world, sat, bodies, active & use_edge, settings, edge_memory),
    ]
    return replace(_assemble(world, q, sat, parts, settings), axis_kind=_axis_kinds(sat, parts))


def _plane_set(world: World, q: Array, sat, rows) -> ContactSet:
    """ContactSet of the plane rows: the vertex and its projection on the plane as xb / xa."""
    planes: Planes = rows.planes
    keys = rows.keys[rows.plane]
    n = planes.normal[rows.plane]
    on_b = (rows.side == SIDE_B)[:, None]
    foot = rows.x - (rows.side * rows.gap)[:, None] * n
    xb, xa = np.where(on_b, rows.x, foot), np.where(on_b, foot, rows.x)
    # "a:pa-b:pb" per plane, then joined to the rows' own labels (one string operation per row).
    prefix = np.array([_pair_label(key) for key in planes.keys], dtype=object)
    labels = (
        tuple((prefix[rows.plane] + np.array(rows.labels, dtype=object)).tolist()) if len(rows.gap) else ()
    )
    return ContactSet(
        keys[:, 0],
        keys[:, 2],
        keys[:, 1],
        keys[:, 3],
        n,
        xa,
        xb,
        rows.gap,
        np.full(len(rows.gap), VERTEX_PLANE),
        labels,
        q.copy(),
        world.centre.copy(),
        planes=planes,
        side=rows.side,
        plane=rows.plane,
        plane_memory=planes.state(),
    )


@lru_cache(maxsize=1 << 16)
def _pair_label(key: tuple[int, int, int, int]) -> str:
    """``"a:pa-b:pb "``, the head of a plane's row labels (the same few hundred pairs every
    linearisation of a path: formatted once)."""
    return "{}:{}-{}:{} ".format(*key)


def _axis_kinds(sat, parts: list[Points]) -> dict:
    """Per active piece pair, the axis its rows came from: ("face", side, f) or ("edge", ci, cj)."""
    kinds: dict[tuple[int, int, int, int], tuple[str, int, int]] = {}
    for part in parts:
        for k, label in zip(part.pp.tolist(), part.label):
            key = (int(sat.a[k]), int(sat.pa[k]), int(sat.b[k]), int(sat.pb[k]))
            if key in kinds:
                continue
            head = label.split(":")[0]
            if head.startswith("F"):
                kinds[key] = ("face", 0 if head[1] == "a" else 1, int(head[2:].split("/")[0]))
            elif ":c" in label:
                ci, cj = label.split(":c")[1].split("/")
                kinds[key] = ("edge", int(ci), int(cj))
    return kinds


def _axis_memory(sat, previous: ContactSet | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(side, face) and (edge class, edge class) each piece pair used last time (-1 where none)."""
    if previous is None or not previous.axis_kind:
        return None, None
    faces = np.full((len(sat.sep), 2), -1, dtype=int)
    edges = np.full((len(sat.sep), 2), -1, dtype=int)
    for k in range(len(sat.sep)):
        kind = previous.axis_kind.get((int(sat.a[k]), int(sat.pa[k]), int(sat.b[k]), int(sat.pb[k])))
        if kind is not None:
            (faces if kind[0] == "face" else edges)[k] = kind[1:]
    return faces, edges


def _choose_edge(
    sat, best_face: Array, best_edge: Array, previous: ContactSet | None, settings: ContactSettings
) -> np.ndarray:
    """Which piece pairs take their rows from an edge-edge axis (formulations/contact.md sec. 6).

    Without memory the better axis wins, faces winning ties (their clipping already holds the
    edge crossings).  With memory the previous kind is kept unless the other kind is better by
    more than ``edge_bias``: near-parallel or touching edges make the two nearly equal, and a
    choice by the sign of a round-off-sized difference makes the sequential QP cycle.
    """
    use_edge = best_edge > best_face + settings.tie_tol
    if previous is None or not previous.axis_kind:
        return use_edge
    memory = previous.axis_kind
    for k in range(len(sat.sep)):
        kind = memory.get((int(sat.a[k]), int(sat.pa[k]), int(sat.b[k]), int(sat.pb[k])))
        if kind is None:
            continue
        if kind[0] == "edge":
            use_edge[k] = best_edge[k] >= best_face[k] - settings.edge_bias
        else:
            use_edge[k] = best_edge[k] > best_face[k] + settings.edge_bias
    return use_edge


def _assemble(world: World, q: Array, sat, parts: list[Points], settings: ContactSettings) -> ContactSet:
    if not parts or sum(len(p.pp) for p in parts) == 0:
        e, z3 = np.zeros(0, dtype=int), np.zeros((0, 3))
        return ContactSet(e, e, e, e, z3, z3, z3, np.zeros(0), e, (), q.copy(), world.centre.copy())
    pp = np.concatenate([p.pp for p in parts])
    normal, xa, xb = (np.concatenate([getattr(p, k) for p in parts]) for k in ("normal", "xa", "xb"))
    gap = np.concatenate([p.gap for p in parts])
    kind = np.concatenate([p.kind for p in parts])
    labels = [lab for p in parts for lab in p.label]
    keep = _unique_rows(pp, normal, xa, xb)
    a, b, pa, pb = sat.a[pp], sat.b[pp], sat.pa[pp], sat.pb[pp]
    names = tuple(f"{a[k]}:{pa[k]}-{b[k]}:{pb[k]} {labels[k]}" for k in keep.tolist())
    return ContactSet(
        a[keep],
        b[keep],
        pa[keep],
        pb[keep],
        normal[keep],
        xa[keep],
        xb[keep],
        gap[keep],
        kind[keep],
        names,
        q.copy(),
        world.centre.copy(),
    )


def _unique_rows(pp: np.ndarray, normal: Array, xa: Array, xb: Array, tol: float = 1e-9) -> np.ndarray:
    """Sorted indices of the first of every group of coincident rows (same pieces, points, normal)."""
    order = np.argsort(pp, kind="stable")
    key, feat = pp[order], np.hstack([normal, xa, xb])[order]
    start = np.r_[0, np.flatnonzero(np.diff(key)) + 1]
    width = int(np.diff(np.r_[start, len(key)]).max())
    dup = np.zeros(len(key), dtype=bool)
    for s in range(1, width):
        same = (key[s:] == key[:-s]) & (np.abs(feat[s:] - feat[:-s]).max(axis=1) < tol)
        dup[s:] |= same
    return np.sort(order[~dup])
