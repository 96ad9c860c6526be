"""The separating-axis test between the placed convex pieces of the scales.

Implements formulations/contact.md section 2, eqs. (3)-(7): the signed separation of two convex
polyhedra as the largest separation over the face normals of both and the cross products of their
edge directions.  Everything is vectorised over all piece pairs of a patch at once; the placed
pieces come from :mod:`qpscale.contact.placement`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import Array, cross
from .placement import World

# Edge pairs whose unit directions have |d_a x d_b| below this (sine of their angle) give no axis.
PARALLEL_SIN = 1e-6


@dataclass(frozen=True)
class SAT:
    """Separations of every piece pair (a, pa) - (b, pb) along every candidate axis.

    Attributes
    ----------
    a, pa, b, pb : ndarray (P,) of int
        Scale and piece indices of each piece pair.
    face_a : ndarray (P, nf)
        Separation along the outward normals of a's faces (axis from a to b), eq. (3).
    face_b : ndarray (P, nf)
        Separation along the outward normals of b's faces (axis from a to b is minus that normal).
    edge : ndarray (P, nc, nc)
        Separation along the edge-pair axes (-inf for near-parallel edges), eq. (4).
    edge_axis : ndarray (P, nc, nc, 3)
        Those axes as unit vectors oriented from a to b.
    sep : ndarray (P,)
        Signed separation, eq. (5): positive apart, minus the overlap depth if overlapping.
    """

    a: np.ndarray
    pa: np.ndarray
    b: np.ndarray
    pb: np.ndarray
    face_a: Array
    face_b: Array
    edge: Array
    edge_axis: Array
    sep: Array


def piece_pairs(world: World, pairs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Expand scale pairs ``(S, 2)`` into every combination of their convex pieces."""
    n_p = world.verts.shape[1]
    pa, pb = np.meshgrid(np.arange(n_p), np.arange(n_p), indexing="ij")
    a = np.repeat(pairs[:, 0], n_p * n_p)
    b = np.repeat(pairs[:, 1], n_p * n_p)
    return a, np.tile(pa.ravel(), len(pairs)), b, np.tile(pb.ravel(), len(pairs))


def _projections(axes: Array, verts: Array) -> Array:
    """``axes (P, k, 3)`` dotted with ``verts (P, v, 3)``, vertex axis first: ``(v, P, k)``.

    One batched product, then laid out so that the min and max over a piece's vertices reduce
    over the leading axis: numpy reduces a short trailing axis (8 vertices) an order of magnitude
    slower, and on a 5x5 dart array the einsum and those reductions were the contact detection's
    largest cost (formulations/contact.md sec. 2 states what is computed; this is only how)."""
    return np.ascontiguousarray((axes @ verts.transpose(0, 2, 1)).transpose(2, 0, 1))


def separate(world: World, pairs: np.ndarray) -> SAT:
    """Separating-axis test over all piece pairs of the scale pairs ``(S, 2)``."""
    a, pa, b, pb = piece_pairs(world, pairs)
    VA, VB = world.verts[a, pa], world.verts[b, pb]
    NA, NB = world.normals[a, pa], world.normals[b, pb]
    pAA, pAB = _projections(NA, VA), _projections(NA, VB)
    face_a = pAB.min(axis=0) - pAA.max(axis=0)
    pBA, pBB = _projections(NB, VA), _projections(NB, VB)
    face_b = pBA.min(axis=0) - pBB.max(axis=0)
    U = cross(world.dirs[a, pa][:, :, None, :], world.dirs[b, pb][:, None, :, :])
    norm = np.linalg.norm(U, axis=-1)
    valid = norm > PARALLEL_SIN
    U = U / np.where(valid, norm, 1.0)[..., None]
    n, nc = len(a), U.shape[1]
    flat = U.reshape(n, nc * nc, 3)
    uA, uB = _projections(flat, VA), _projections(flat, VB)
    s_plus = (uB.min(axis=0) - uA.max(axis=0)).reshape(n, nc, nc)
    s_minus = (uA.min(axis=0) - uB.max(axis=0)).reshape(n, nc, nc)
    sign = np.where(s_plus >= s_minus, 1.0, -1.0)
    edge = np.where(valid, np.maximum(s_plus, s_minus), -np.inf)
    best = np.maximum(np.maximum(face_a.max(axis=1), face_b.max(axis=1)), edge.reshape(n, -1).max(axis=1))
    return SAT(a, pa, b, pb, face_a, face_b, edge, U * sign[..., None], best)
