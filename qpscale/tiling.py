"""The eight designs, their lattices, and patches of N rings around the punctured scale.

Implements formulations/geometry.md sections 4-6: each design is a lattice (two vectors)
and a motif (one or two copies of the base shape, the second rotated by 180 degrees).  The
lattice is built from the base shape inflated by d/2 with mitred corners, so that every pair
of neighbouring scales is separated by exactly the gap d along their shared edges.  The
neighbour graph of a patch is derived from the neighbour offsets of the lattice (computed
once per design on one unit cell), never by testing every pair of the patch.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
from functools import cache, cached_property

import numpy as np
from shapely import STRtree
from shapely.geometry import LineString, MultiPoint, Polygon

from .errors import InvalidDesign
from .geometry import Array, Prism, base_polygon, check_shape, convex_pieces, rotate2d, slant_offset

TILINGS_OF: dict[str, tuple[str, ...]] = {
    "triangle": ("arrayed", "staggered"),
    "square": ("arrayed", "staggered"),
    "trapezoid": ("arrayed", "staggered"),
    "dart": ("chevron",),
    "hexagon": ("honeycomb",),
}
TILINGS: tuple[str, ...] = ("arrayed", "staggered", "chevron", "honeycomb")
DESIGNS: tuple[tuple[str, str], ...] = tuple((s, t) for s, ts in TILINGS_OF.items() for t in ts)

# Pairs whose plan hulls come within this distance (in L, times max(1, t)) are contact candidates.
CONTACT_MARGIN = 0.3
_TOUCH_TOL = 1e-7


@dataclass(frozen=True)
class Design:
    """A scaled-skin design: base shape, tiling, slant, gap, thickness and patch size.

    Parameters
    ----------
    shape : str
        One of ``triangle, square, trapezoid, dart, hexagon``.
    tiling : str or None
        ``arrayed`` or ``staggered`` for triangle, square, trapezoid; the dart and the
        hexagon have one tiling each (``chevron``, ``honeycomb``); None picks the first.
    slant_deg : float
        Slant angle alpha from the vertical, degrees, in [0, 90).
    slant_dir_deg : float
        Direction of the slant in the plane, degrees from +x, in [0, 360).
    gap : float
        Distance d between neighbouring base polygons, in L, >= 0.
    thickness : float
        Scale thickness t, in L, > 0.
    rings : int
        Rings of neighbours around the punctured scale (2 gives the paper's 5x5), >= 0.

    >>> Design().n_motif
    1
    """

    shape: str = "square"
    tiling: str | None = None
    slant_deg: float = 0.0
    slant_dir_deg: float = 0.0
    gap: float = 0.005
    thickness: float = 1.0
    rings: int = 2

    def __post_init__(self) -> None:
        check_shape(self.shape)
        allowed = TILINGS_OF[self.shape]
        if self.tiling is None:
            object.__setattr__(self, "tiling", allowed[0])
        elif self.tiling not in allowed:
            raise InvalidDesign(
                "tiling", self.tiling, "{" + ", ".join(allowed) + "}", f"not a tiling of shape={self.shape!r}"
            )
        checks = [
            ("slant_deg", self.slant_deg, 0.0 <= self.slant_deg < 90.0, "[0, 90)"),
            ("slant_dir_deg", self.slant_dir_deg, 0.0 <= self.slant_dir_deg < 360.0, "[0, 360)"),
            ("gap", self.gap, 0.0 <= self.gap < 1.0, "[0, 1) (in L)"),
            ("thickness", self.thickness, 0.0 < self.thickness <= 100.0, "(0, 100] (in L)"),
            ("rings", self.rings, 0 <= int(self.rings) == self.rings <= 50, "integers in [0, 50]"),
        ]
        for name, value, ok, allowed_range in checks:
            if not (np.isfinite(float(value)) and ok):
                raise InvalidDesign(name, value, allowed_range)

    @property
    def top_offset(self) -> Array:
        """In-plane offset ``(2,)`` of every top face relative to its base, in L."""
        return slant_offset(self.thickness, self.slant_deg, self.slant_dir_deg)

    @property
    def n_motif(self) -> int:
        return len(_lattice(self.shape, self.tiling or "", self.gap)[2])

    def with_(self, **changes: object) -> Design:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]

    def isolated(self) -> Design:
        """The same scale alone on the substrate (zero rings)."""
        return replace(self, rings=0)

    def patch(self) -> Patch:
        return build_patch(self)


def inflated_polygon(shape: str, gap: float) -> Polygon:
    """The base polygon offset outward by gap/2 with mitred corners (edge directions kept).

    Gaps below 1e-12 L are round-off: the base polygon itself is returned (GEOS mis-handles
    sub-normal buffer distances).
    """
    poly = Polygon(base_polygon(shape))
    if gap < 1e-12:
        return poly
    return poly.buffer(gap / 2.0, join_style="mitre", mitre_limit=1e3)


@cache
def _lattice(
    shape: str, tiling: str, gap: float
) -> tuple[Array, Array, tuple[tuple[float, float, float], ...]]:
    """Lattice vectors a1, a2 and motif ((angle, cx, cy), ...) of a design.

    Derived from the inflated prototile (formulations/geometry.md, sec. 4): the inflated
    tiles touch, so the real ones stand exactly ``gap`` apart along shared edges.
    """
    poly = inflated_polygon(shape, gap)
    minx, miny, maxx, maxy = poly.bounds
    width = maxx - minx
    motif: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)]
    if shape == "square":
        a1, a2 = np.array([width, 0.0]), np.array([0.0, maxy - miny])
        if tiling == "staggered":
            a2 = np.array([width / 2.0, maxy - miny])
    elif shape in ("triangle", "trapezoid"):
        h = maxy - miny
        top = np.asarray(poly.exterior.coords)[:-1]
        top_right = top[np.isclose(top[:, 1], maxy)][:, 0].max()
        # 180-degree copy: its lower-left vertex is the image of the upper-right one.
        motif.append((np.pi, maxx + top_right, miny + maxy))
        period = width + 2.0 * top_right
        a1 = np.array([period, 0.0])
        a2 = np.array([0.0, h]) if tiling == "arrayed" else np.array([period / 2.0, h])
    elif shape == "hexagon":
        a1 = np.array([width, 0.0])
        a2 = np.array([width / 2.0, 0.75 * (maxy - miny)])
    elif shape == "dart":
        through = LineString([(0.0, miny - 1.0), (0.0, maxy + 1.0)]).intersection(poly).length
        a1, a2 = np.array([width, 0.0]), np.array([0.0, through])
    else:  # pragma: no cover - check_shape rejects it first
        raise InvalidDesign("shape", shape, "")
    return a1, a2, tuple(motif)


def _site_polygon(shape: str, angle: float, centre: Array) -> Array:
    return rotate2d(base_polygon(shape), angle) + centre


@cache
def _neighbour_offsets(shape: str, tiling: str, gap: float) -> tuple[tuple[tuple[int, int, int], ...], ...]:
    """For each motif member k, the offsets (di, dj, m) of the scales adjacent to it."""
    a1, a2, motif = _lattice(shape, tiling, gap)
    # Adjacent = the inflated (gap-free) tiles touch, at an edge or at a vertex.
    inflated = np.asarray(inflated_polygon(shape, gap).exterior.coords)[:-1]
    polys = {}
    for i in range(-2, 3):
        for j in range(-2, 3):
            for m, (ang, cx, cy) in enumerate(motif):
                c = i * a1 + j * a2 + np.array([cx, cy])
                polys[(i, j, m)] = Polygon(rotate2d(inflated, ang) + c)
    return _near_offsets(polys, len(motif), _TOUCH_TOL)


@dataclass(frozen=True)
class Patch:
    """The punctured scale (index 0) and its rings of neighbours.

    Attributes
    ----------
    design : Design
    sites : ndarray (n, 3) of int
        Lattice indices (i, j) and motif member m of each scale.
    centroids : ndarray (n, 2)
        Reference points (base centroids), in L.
    angles : ndarray (n,)
        In-plane rotation of each scale's base shape, radians (0 or pi).
    ring : ndarray (n,) of int
        Graph distance from the punctured scale.
    neighbours : ndarray (E, 2) of int
        Pairs i < j of scales whose base polygons are adjacent in the tiling.
    """

    design: Design
    sites: np.ndarray
    centroids: Array
    angles: Array
    ring: np.ndarray
    neighbours: np.ndarray

    @property
    def n_scales(self) -> int:
        return int(self.centroids.shape[0])

    @cached_property
    def base(self) -> Array:
        """World base vertices ``(n, n_vertices, 2)``."""
        return np.array([_site_polygon(self.design.shape, a, c) for a, c in zip(self.angles, self.centroids)])

    def polygons(self) -> list[Polygon]:
        """The base polygons as shapely objects (world frame)."""
        return [Polygon(b) for b in self.base]

    def prism(self, i: int) -> Prism:
        """Scale ``i`` as one prism in its body frame (reference point at the origin)."""
        return Prism(
            rotate2d(base_polygon(self.design.shape), self.angles[i]),
            self.design.thickness,
            self.design.top_offset,
        )

    def convex_prisms(self, i: int) -> list[Prism]:
        """Scale ``i`` as convex prisms (the dart as two) in its body frame."""
        d = self.design
        return [Prism(rotate2d(p, self.angles[i]), d.thickness, d.top_offset) for p in convex_pieces(d.shape)]

    @cached_property
    def contact_pairs(self) -> np.ndarray:
        """Pairs i < j that may touch: neighbours, plus pairs whose slanted prisms overhang.

        Candidates come from the lattice offsets whose plan hulls (base and top face) come
        within ``CONTACT_MARGIN * max(1, t)`` of each other, restricted to the patch.
        """
        d = self.design
        offsets = _contact_offsets(d.shape, d.tiling or "", d.gap, d.thickness, d.slant_deg, d.slant_dir_deg)
        index = {tuple(s): n for n, s in enumerate(self.sites.tolist())}
        pairs = set(map(tuple, self.neighbours.tolist()))
        for n, (i, j, k) in enumerate(self.sites.tolist()):
            for di, dj, m in offsets[k]:
                other = index.get((i + di, j + dj, m))
                if other is not None and other != n:
                    pairs.add((min(n, other), max(n, other)))
        return np.array(sorted(pairs), dtype=int).reshape(-1, 2)


@cache
def _contact_offsets(
    shape: str, tiling: str, gap: float, thickness: float, slant_deg: float, slant_dir_deg: float
) -> tuple[tuple[tuple[int, int, int], ...], ...]:
    a1, a2, motif = _lattice(shape, tiling, gap)
    off = slant_offset(thickness, slant_deg, slant_dir_deg)
    reach = float(np.linalg.norm(off)) + 6.0 + CONTACT_MARGIN * max(1.0, thickness)
    span = int(np.ceil(reach / min(np.linalg.norm(a1), abs(a2[1])))) + 1
    hulls = {}
    for i in range(-span, span + 1):
        for j in range(-span, span + 1):
            for m, (ang, cx, cy) in enumerate(motif):
                b = _site_polygon(shape, ang, i * a1 + j * a2 + np.array([cx, cy]))
                hulls[(i, j, m)] = MultiPoint(np.vstack([b, b + off])).convex_hull
    return _near_offsets(hulls, len(motif), gap + CONTACT_MARGIN * max(1.0, thickness))


def _near_offsets(shapes: dict, n_motif: int, tol: float) -> tuple[tuple[tuple[int, int, int], ...], ...]:
    """For each motif member k, the sites (di, dj, m) whose shape is within ``tol`` of site (0, 0, k)."""
    out = []
    for k in range(n_motif):
        here = shapes[(0, 0, k)]
        near = [key for key, p in shapes.items() if key != (0, 0, k) and here.distance(p) <= tol]
        out.append(tuple(sorted(near)))
    return tuple(out)


def build_patch(design: Design) -> Patch:
    """Grow the patch ring by ring along the tiling's neighbour graph (breadth first)."""
    a1, a2, motif = _lattice(design.shape, design.tiling or "", design.gap)
    offsets = _neighbour_offsets(design.shape, design.tiling or "", design.gap)
    start = (0, 0, 0)
    ring = {start: 0}
    order = [start]
    queue = deque([start])
    while queue:
        site = queue.popleft()
        if ring[site] == design.rings:
            continue
        for di, dj, m in offsets[site[2]]:
            nxt = (site[0] + di, site[1] + dj, m)
            if nxt not in ring:
                ring[nxt] = ring[site] + 1
                order.append(nxt)
                queue.append(nxt)
    sites = np.array(order, dtype=int)
    centres = np.array([i * a1 + j * a2 + np.array(motif[m][1:]) for i, j, m in order])
    angles = np.array([motif[m][0] for _, _, m in order])
    index = {s: n for n, s in enumerate(order)}
    pairs = set()
    for n, (i, j, k) in enumerate(order):
        for di, dj, m in offsets[k]:
            other = index.get((i + di, j + dj, m))
            if other is not None:
                pairs.add((min(n, other), max(n, other)))
    neighbours = np.array(sorted(pairs), dtype=int).reshape(-1, 2)
    return Patch(design, sites, centres, angles, np.array([ring[s] for s in order]), neighbours)


def min_gap(patch: Patch) -> float:
    """Smallest distance between the base polygons of neighbouring scales, in L."""
    if len(patch.neighbours) == 0:
        return float("inf")
    polys = patch.polygons()
    return float(min(polys[i].distance(polys[j]) for i, j in patch.neighbours))


def max_overlap_area(patch: Patch) -> float:
    """Largest overlap area between any two base polygons of the patch, in L^2.

    Polygons are shrunk by 1e-10 L first: GEOS can mis-resolve two polygons that share an edge
    exactly (d = 0), and overlaps thinner than that are round-off, not design errors.
    """
    polys = [p.buffer(-1e-10, join_style="mitre") for p in patch.polygons()]
    tree = STRtree(polys)
    worst = 0.0
    for i, p in enumerate(polys):
        for j in tree.query(p):
            if j > i:
                worst = max(worst, p.intersection(polys[j]).area)
    return worst
