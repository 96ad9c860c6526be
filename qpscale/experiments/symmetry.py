"""Symmetries of a patch: which top-face vertices are equivalent, which paths can branch.

Implements formulations/puncture.md section 5: an isometry of the plane about the punctured
scale's reference point is a symmetry of the model when it maps the slant offset to itself and
every scale of the patch onto a scale of the patch (same base polygon as a point set).  Under a
symmetry M (2x2) the DOFs of scale i map to those of scale perm[i]: in-plane translations by M,
u_z unchanged, and the in-plane rotation vector (an axial vector) by det(M) M.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..tiling import Patch

_TOL = 1e-6


def _candidates() -> list[np.ndarray]:
    maps = []
    for k in range(12):
        a = np.deg2rad(30.0 * k)
        maps.append(np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]))
        b = np.deg2rad(15.0 * k)
        maps.append(np.array([[np.cos(2 * b), np.sin(2 * b)], [np.sin(2 * b), -np.cos(2 * b)]]))
    return maps


def patch_symmetries(patch: Patch) -> list[tuple[np.ndarray, np.ndarray]]:
    """The isometries ``(M, perm)`` of the model about scale 0's reference point.

    ``perm[i]`` is the scale that scale ``i`` maps onto.  The identity is always first.
    """
    c0 = patch.centroids[0]
    cents = patch.centroids - c0
    verts = patch.base - c0
    tree = cKDTree(cents)
    offset = patch.design.top_offset
    found = []
    for M in _candidates():
        if np.linalg.norm(M @ offset - offset) > _TOL:
            continue
        dist, perm = tree.query(cents @ M.T)
        if np.max(dist) > _TOL:
            continue
        ok = all(_same_set(verts[i] @ M.T, verts[j]) for i, j in enumerate(perm))
        if ok:
            found.append((M, perm))
    return found


def _same_set(a: np.ndarray, b: np.ndarray) -> bool:
    d, _ = cKDTree(b).query(a)
    return bool(np.max(d) < _TOL)


def vertex_orbits(patch: Patch, points: np.ndarray) -> list[list[int]]:
    """Group the points ``(k, 2)`` (relative to scale 0's reference point) into symmetry orbits."""
    syms = patch_symmetries(patch)
    seen: set[int] = set()
    orbits = []
    tree = cKDTree(points)
    for i in range(len(points)):
        if i in seen:
            continue
        orbit = {i}
        for M, _ in syms:
            d, j = tree.query(M @ points[i])
            if d < _TOL:
                orbit.add(int(j))
        seen |= orbit
        orbits.append(sorted(orbit))
    return orbits


def mirror_through(patch: Patch, point: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A reflection symmetry of the model whose mirror line passes through ``point``, if any."""
    for M, perm in patch_symmetries(patch):
        if np.linalg.det(M) < 0 and np.linalg.norm(M @ point - point) < _TOL:
            return M, perm
    return None
