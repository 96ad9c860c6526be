"""Convex pieces of the scales: their body-frame geometry and their placement in a configuration.

Implements formulations/contact.md section 1, eq. (1): the exact rigid placement x = c + R(phi) X
of every convex piece of every scale (``patch.convex_prisms``), vectorised over the whole patch.
The separating-axis test between placed pieces is in :mod:`qpscale.contact.separation`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from ..geometry import Array
from ..geometry import rotation_matrices as rotations
from ..tiling import Patch

_CACHE: dict[int, tuple[weakref.ref, Bodies]] = {}


@dataclass(frozen=True)
class Bodies:
    """Body-frame geometry of every convex piece of every scale (shared topology).

    Attributes
    ----------
    verts : ndarray (n, P, nv, 3)
        Vertices of piece p of scale i relative to its reference point, in L.
    normals : ndarray (n, P, nf, 3)
        Outward unit face normals.
    dirs : ndarray (n, P, nc, 3)
        One unit direction per class of parallel edges.
    faces : ndarray (nf, fmax) of int
        Vertex indices of each face, counter-clockwise from outside, padded with -1.
    face_size : ndarray (nf,) of int
    edges : ndarray (ne, 2) of int
    edge_class : ndarray (ne,) of int
    internal : ndarray (P, nf) of bool
        Side faces on the cut between two pieces of one scale (the dart's symmetry plane): inside
        the scale, so never a contact certificate.
    """

    verts: Array
    normals: Array
    dirs: Array
    faces: np.ndarray
    face_size: np.ndarray
    edges: np.ndarray
    edge_class: np.ndarray
    internal: np.ndarray


def _edge_classes(verts: Array, edges: np.ndarray) -> tuple[np.ndarray, list[int]]:
    d = verts[edges[:, 1]] - verts[edges[:, 0]]
    d /= np.linalg.norm(d, axis=1)[:, None]
    cls = -np.ones(len(edges), dtype=int)
    reps: list[int] = []
    for e in range(len(edges)):
        for c, r in enumerate(reps):
            if np.linalg.norm(np.cross(d[e], d[r])) < 1e-9:
                cls[e] = c
                break
        else:
            cls[e] = len(reps)
            reps.append(e)
    return cls, reps


def _edge_key(a: np.ndarray, b: np.ndarray) -> tuple[float, ...]:
    """A directed base edge ``a -> b`` as a hashable key (coordinates rounded to 1e-9 L)."""
    return tuple(float(round(float(v), 9)) for v in np.r_[a, b])


def _internal_faces(pieces: list) -> np.ndarray:
    """(P, nf) mask of side faces whose base edge another piece of the same scale shares."""
    n_faces = len(pieces[0].faces)
    out = np.zeros((len(pieces), n_faces), dtype=bool)
    edges = [{_edge_key(p.base[i], p.base[(i + 1) % p.n_base]) for i in range(p.n_base)} for p in pieces]
    for k, p in enumerate(pieces):
        for i in range(p.n_base):
            a, b = p.base[i], p.base[(i + 1) % p.n_base]
            reverse = _edge_key(b, a)
            if any(reverse in e for j, e in enumerate(edges) if j != k):
                out[k, 2 + i] = True  # faces: bottom, top, then side i
    return out


def bodies_of(patch: Patch) -> Bodies:
    """Body-frame piece geometry of a patch (cached per patch object)."""
    hit = _CACHE.get(id(patch))
    if hit is not None and hit[0]() is patch:
        return hit[1]
    prisms = [patch.convex_prisms(i) for i in range(patch.n_scales)]
    first = prisms[0][0]
    faces_list = first.faces
    fmax = max(len(f) for f in faces_list)
    faces = -np.ones((len(faces_list), fmax), dtype=int)
    for k, f in enumerate(faces_list):
        faces[k, : len(f)] = f
    edges = np.array(first.edges, dtype=int)
    cls, reps = _edge_classes(first.vertices, edges)
    verts = np.array([[p.vertices for p in ps] for ps in prisms])
    normals = np.array([[p.face_normals for p in ps] for ps in prisms])
    d = verts[:, :, edges[reps, 1]] - verts[:, :, edges[reps, 0]]
    dirs = d / np.linalg.norm(d, axis=-1, keepdims=True)
    out = Bodies(
        verts,
        normals,
        dirs,
        faces,
        np.array([len(f) for f in faces_list]),
        edges,
        cls,
        _internal_faces(prisms[0]),
    )
    _CACHE[id(patch)] = (weakref.ref(patch), out)
    return out


@dataclass(frozen=True)
class World:
    """Current placement of every piece: eq. (1) applied to :class:`Bodies`.

    Attributes
    ----------
    centre : ndarray (n, 3)
        Current reference points c_i = (C_i, 0) + u_i, in L.
    R : ndarray (n, 3, 3)
    verts, normals, dirs : ndarray (n, P, ., 3)
        World vertices, outward normals and edge-class directions.
    """

    centre: Array
    R: Array
    verts: Array
    normals: Array
    dirs: Array


def place(patch: Patch, q: Array) -> World:
    """Place every convex piece of the patch in configuration ``q`` (n, 5)."""
    b = bodies_of(patch)
    centre = np.zeros((patch.n_scales, 3))
    centre[:, :2] = patch.centroids
    centre += q[:, :3]
    R = rotations(q[:, 3:5])
    verts = np.einsum("ijk,ipvk->ipvj", R, b.verts) + centre[:, None, None, :]
    normals = np.einsum("ijk,ipvk->ipvj", R, b.normals)
    dirs = np.einsum("ijk,ipvk->ipvj", R, b.dirs)
    return World(centre, R, verts, normals, dirs)
