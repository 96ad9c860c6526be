"""Triangular panels on the footprints of rigid punches (formulations/substrate.md, sec. 3).

Each convex piece of a footprint is split into a fan of triangles from its centroid, one per
edge, and each fan triangle into ``N**2`` panels arranged in strips parallel to the edge.  The
strips are graded towards the footprint boundary, where the contact traction of a rigid punch
is singular, and the points along each strip are spaced by a cosine rule towards the corners.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from shapely.geometry import LineString, Polygon
from shapely.ops import unary_union

from ..errors import InvalidDesign
from ..geometry import Array

# Exponent of the strip grading 1 - rho_k = (1 - k/N)**GRADING (formulations/substrate.md, eq. (9)).
GRADING = 3.5
# Milder grading of the fan triangles on cuts inside a non-convex footprint (eq. (9b)).
INTERNAL_GRADING = 1.5
# Vertices closer than this (in L) are the same vertex when cuts between pieces are detected.
_SAME = 1e-9


@dataclass(frozen=True)
class Panels:
    """Constant-traction panels on several footprints.

    Attributes
    ----------
    tris : ndarray (P, 3, 2)
        Counter-clockwise panel vertices, world frame, in L.
    centroids : ndarray (P, 2)
        Collocation points (panel centroids), in L.
    areas : ndarray (P,)
        Panel areas, in L^2.
    owner : ndarray (P,) of int
        Index of the footprint each panel belongs to.
    """

    tris: Array
    centroids: Array
    areas: Array
    owner: np.ndarray

    @property
    def n(self) -> int:
        return int(self.areas.shape[0])


def _signed_areas(tris: Array) -> Array:
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


def _fan_triangle(c: Array, a: Array, b: Array, n: int, grading: float = GRADING) -> list[Array]:
    """Graded strip subdivision of the triangle (c, a, b) into n**2 panels; edge ab is the boundary."""
    rho = 1.0 - (1.0 - np.arange(n + 1) / n) ** grading
    levels = []
    for k in range(n + 1):
        tau = 0.5 * (1.0 - np.cos(np.pi * np.arange(k + 1) / max(k, 1)))
        levels.append(c + rho[k] * ((a - c) + tau[:, None] * (b - a)))
    out = []
    for k in range(1, n + 1):
        lo, up = levels[k - 1], levels[k]
        for j in range(k):
            out.append(np.array([lo[j], up[j], up[j + 1]]))
            if j < k - 1:
                out.append(np.array([lo[j], up[j + 1], lo[j + 1]]))
    return out


def piece_panels(
    piece: Array, n: int, internal: np.ndarray | None = None, far: np.ndarray | None = None
) -> Array:
    """Panels of one convex polygon ``(nv, 2)`` (counter-clockwise).

    A fan triangle on a boundary edge gets ``n**2`` graded panels; one on an ``internal`` edge (a
    cut between convex pieces of one footprint, where the traction is regular) gets
    ``max(1, n // 2)**2`` panels with a milder grading towards the cut's ends (eq. (9b)); one on a
    ``far`` edge (far from the footprint under study) gets ``max(1, n // 2)**2`` graded panels.
    """
    c = piece.mean(axis=0)
    inner = np.zeros(len(piece), bool) if internal is None else internal
    remote = np.zeros(len(piece), bool) if far is None else far
    tris: list[Array] = []
    for i in range(len(piece)):
        a, b = piece[i], piece[(i + 1) % len(piece)]
        if inner[i]:
            tris += _fan_triangle(c, a, b, max(1, n // 2), INTERNAL_GRADING)
        elif remote[i]:
            tris += _fan_triangle(c, a, b, max(1, n // 2))
        else:
            tris += _fan_triangle(c, a, b, n)
    arr = np.array(tris)
    flip = _signed_areas(arr) < 0.0
    arr[flip] = arr[flip][:, ::-1]
    return arr


def internal_edges(pieces: list[Array]) -> list[np.ndarray]:
    """For each piece, which edges (i -> i+1) are shared, reversed, with another piece."""
    edges = [(p, np.roll(p, -1, axis=0)) for p in pieces]
    out = []
    for k, (a, b) in enumerate(edges):
        inner = np.zeros(len(a), bool)
        for m, (a2, b2) in enumerate(edges):
            if m != k:
                same = (np.abs(a[:, None] - b2[None]).max(-1) < _SAME) & (
                    np.abs(b[:, None] - a2[None]).max(-1) < _SAME
                )
                inner |= same.any(axis=1)
        out.append(inner)
    return out


def far_edges(pieces: list[Array], focus: list[Array], reach: float) -> list[np.ndarray]:
    """For each piece, which edges lie farther than ``reach`` (in L) from the ``focus`` footprint."""
    target = unary_union([Polygon(p) for p in focus])
    return [
        np.array([LineString([p[i], p[(i + 1) % len(p)]]).distance(target) > reach for i in range(len(p))])
        for p in pieces
    ]


def mesh_footprints(
    footprints: list[list[Array]], density: list[int] | int, focus: int | None = None, reach: float = 0.5
) -> Panels:
    """Panels on every footprint; ``footprints[k]`` is a list of convex pieces (world frame).

    Parameters
    ----------
    footprints : list of list of ndarray (nv, 2)
        Convex pieces of each footprint, counter-clockwise, in L.
    density : int or list of int
        Strips per fan triangle N (>= 1), one value or one per footprint.
    focus : int, optional
        Footprint under study: edges of the other footprints farther than ``reach`` from it are
        meshed at half the density (eq. (9c)).
    """
    dens = [density] * len(footprints) if isinstance(density, int) else list(density)
    if any(int(d) != d or d < 1 for d in dens):
        raise InvalidDesign("refinement", density, "integers >= 1")
    tris, owner = [], []
    for k, (pieces, n) in enumerate(zip(footprints, dens)):
        pieces = [np.asarray(p, dtype=float) for p in pieces]
        far: Sequence[np.ndarray | None] = [None] * len(pieces)
        if focus is not None and k != focus:
            far = far_edges(pieces, footprints[focus], reach)
        for piece, inner, remote in zip(pieces, internal_edges(pieces), far):
            t = piece_panels(piece, int(n), inner, remote)
            tris.append(t)
            owner.append(np.full(len(t), k))
    all_tris = np.concatenate(tris)
    return Panels(all_tris, all_tris.mean(axis=1), _signed_areas(all_tris), np.concatenate(owner))
