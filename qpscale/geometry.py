"""Base shapes, slanted prisms and rigid-body rotations.

Implements formulations/geometry.md (sections 1-3: the five base shapes at equal area
4 L^2, the oblique prism, finite rotations by a rotation vector in the xy-plane) and
formulations/contact.md section 2 (the tangent operator of the rotation).

All lengths are in units of L.  Base polygons are stored counter-clockwise with their
centroid at the origin; a scale's reference point is the centroid of its base face.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np
from numpy.typing import NDArray
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from .errors import InvalidDesign

BASE_AREA = 4.0
SHAPES: tuple[str, ...] = ("triangle", "square", "trapezoid", "dart", "hexagon")

# Dart (chevron) proportions: half-width W and vertical thickness S with W*S = 2, tip 90 deg.
DART_HALF_WIDTH = 2.0
DART_THICKNESS = BASE_AREA / (2.0 * DART_HALF_WIDTH)

Array = NDArray[np.float64]


def check_shape(shape: str) -> str:
    """Return ``shape`` if it is one of :data:`SHAPES`."""
    if shape not in SHAPES:
        raise InvalidDesign("shape", shape, "{" + ", ".join(SHAPES) + "}")
    return shape


def _centred(vertices: Array) -> Array:
    poly = orient(Polygon(vertices), sign=1.0)
    xy = np.asarray(poly.exterior.coords, dtype=float)[:-1]
    c = np.array(poly.centroid.coords[0])
    return xy - c


def _raw_shape(shape: str) -> tuple[Array, list[Array]]:
    """Vertices of the shape (any placement) and its convex pieces (same frame)."""
    if shape == "square":
        v = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
        return v, [v]
    if shape == "triangle":
        a = np.sqrt(4.0 * BASE_AREA / np.sqrt(3.0))
        h = a * np.sqrt(3.0) / 2.0
        v = np.array([[-a / 2, 0.0], [a / 2, 0.0], [0.0, h]])
        return v, [v]
    if shape == "hexagon":
        s = np.sqrt(2.0 * BASE_AREA / (3.0 * np.sqrt(3.0)))
        ang = np.deg2rad(30.0 + 60.0 * np.arange(6))
        v = s * np.column_stack([np.cos(ang), np.sin(ang)])
        return v, [v]
    if shape == "trapezoid":
        # Half a regular hexagon of side s: long base 2s, top s, legs s at 60 degrees.
        s = np.sqrt(4.0 * BASE_AREA / (3.0 * np.sqrt(3.0)))
        h = s * np.sqrt(3.0) / 2.0
        v = np.array([[-s, 0.0], [s, 0.0], [s / 2, h], [-s / 2, h]])
        return v, [v]
    if shape == "dart":
        w, t = DART_HALF_WIDTH, DART_THICKNESS
        v = np.array([[0.0, w], [-w, 0.0], [-w, -t], [0.0, w - t], [w, -t], [w, 0.0]])
        left = np.array([[0.0, w], [-w, 0.0], [-w, -t], [0.0, w - t]])
        right = np.array([[0.0, w], [0.0, w - t], [w, -t], [w, 0.0]])
        return v, [left, right]
    raise InvalidDesign("shape", shape, "{" + ", ".join(SHAPES) + "}")


@cache
def _shape_arrays(shape: str) -> tuple[Array, tuple[Array, ...]]:
    check_shape(shape)
    raw, pieces = _raw_shape(shape)
    poly = orient(Polygon(raw), sign=1.0)
    c = np.array(poly.centroid.coords[0])
    verts = _centred(raw)
    convex = tuple(np.asarray(orient(Polygon(p), sign=1.0).exterior.coords)[:-1] - c for p in pieces)
    for arr in (verts, *convex):
        arr.setflags(write=False)
    return verts, convex


def base_polygon(shape: str) -> Array:
    """Counter-clockwise vertices ``(n, 2)`` of the base shape, centroid at the origin.

    >>> bool(abs(Polygon(base_polygon("hexagon")).area - 4.0) < 1e-12)
    True
    """
    return _shape_arrays(shape)[0].copy()


def convex_pieces(shape: str) -> list[Array]:
    """The base shape as convex polygons ``(m_k, 2)`` in the frame of :func:`base_polygon`.

    Convex shapes return themselves; the dart returns its two parallelograms.
    """
    return [p.copy() for p in _shape_arrays(shape)[1]]


def rotate2d(xy: Array, angle: float) -> Array:
    """Rotate points ``(..., 2)`` by ``angle`` radians about the origin."""
    c, s = np.cos(angle), np.sin(angle)
    return np.asarray(xy) @ np.array([[c, s], [-s, c]])


def slant_offset(thickness: float, slant_deg: float, slant_dir_deg: float) -> Array:
    """In-plane offset ``(2,)`` of the top face: t tan(alpha) along the slant direction."""
    d = thickness * np.tan(np.deg2rad(slant_deg))
    phi = np.deg2rad(slant_dir_deg)
    return np.array([d * np.cos(phi), d * np.sin(phi)])


@dataclass(frozen=True)
class Prism:
    """An oblique prism: a convex base polygon extruded by ``thickness`` along a slant.

    Parameters
    ----------
    base : ndarray (n, 2)
        Counter-clockwise base vertices relative to the reference point, in L.
    thickness : float
        Height t of the prism, in L.
    top_offset : ndarray (2,)
        In-plane translation of the top face relative to the base, in L.

    Notes
    -----
    Vertex ``i`` is base vertex ``i`` (z = 0) and vertex ``n + i`` the top vertex above it.
    Faces are index lists ordered counter-clockwise seen from outside (formulations/geometry.md, sec. 2).
    """

    base: Array
    thickness: float
    top_offset: Array = field(default_factory=lambda: np.zeros(2))

    @property
    def n_base(self) -> int:
        return int(self.base.shape[0])

    @property
    def vertices(self) -> Array:
        """Vertices ``(2n, 3)`` in the body frame (reference point at the origin)."""
        n = self.n_base
        v = np.zeros((2 * n, 3))
        v[:n, :2] = self.base
        v[n:, :2] = self.base + self.top_offset
        v[n:, 2] = self.thickness
        return v

    @property
    def faces(self) -> list[list[int]]:
        """Vertex indices of every face: bottom, top, then the side faces."""
        n = self.n_base
        bottom = list(range(n - 1, -1, -1))
        top = list(range(n, 2 * n))
        sides = [[i, (i + 1) % n, n + (i + 1) % n, n + i] for i in range(n)]
        return [bottom, top, *sides]

    @property
    def face_normals(self) -> Array:
        """Outward unit normals ``(n_faces, 3)`` in the body frame."""
        v = self.vertices
        normals = []
        for f in self.faces:
            p = v[f]
            nrm = np.cross(p[1] - p[0], p[2] - p[0])
            normals.append(nrm / np.linalg.norm(nrm))
        return np.array(normals)

    @property
    def volume(self) -> float:
        """Base area times thickness (an oblique prism keeps the right prism's volume)."""
        return float(Polygon(self.base).area * self.thickness)

    @property
    def edges(self) -> list[tuple[int, int]]:
        """The 3n edges as vertex index pairs."""
        n = self.n_base
        out = [(i, (i + 1) % n) for i in range(n)]
        out += [(n + i, n + (i + 1) % n) for i in range(n)]
        out += [(i, n + i) for i in range(n)]
        return out


def cross(a: Array, b: Array) -> Array:
    """``np.cross(a, b)`` of 3-vectors on the last axis (broadcast), bit for bit: the same products
    and differences, without ``np.cross``'s axis handling and copies (60 us a call, most of it
    overhead on the contact detection's small arrays: 2,600 calls a default run)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    np.multiply(a1, b2, out=out[..., 0])
    out[..., 0] -= a2 * b1
    np.multiply(a2, b0, out=out[..., 1])
    out[..., 1] -= a0 * b2
    np.multiply(a0, b1, out=out[..., 2])
    out[..., 2] -= a1 * b0
    return out


def skew(w: Array) -> Array:
    """Cross-product matrix of a 3-vector: ``skew(w) @ x == cross(w, x)``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _skews(phi: Array) -> Array:
    """Cross-product matrices ``(n, 3, 3)`` of the rotation vectors ``(phi_x, phi_y, 0)``."""
    W = np.zeros((phi.shape[0], 3, 3))
    W[:, 0, 2], W[:, 2, 0] = phi[:, 1], -phi[:, 1]
    W[:, 1, 2], W[:, 2, 1] = -phi[:, 0], phi[:, 0]
    return W


def rotation_matrices(phi: Array) -> Array:
    """Rotation matrices ``(n, 3, 3)`` of rotation vectors ``phi`` ``(n, 2)``, Rodrigues' formula.

    Below 1e-8 rad the closed form loses digits, so the Taylor series is used there.
    """
    phi = np.asarray(phi, dtype=float).reshape(-1, 2)
    W = _skews(phi)
    a = np.hypot(phi[:, 0], phi[:, 1])
    small = a < 1e-8
    a_safe = np.where(small, 1.0, a)
    s1 = np.where(small, 1.0 - a * a / 6.0, np.sin(a_safe) / a_safe)
    s2 = np.where(small, 0.5 - a * a / 24.0, (1.0 - np.cos(a_safe)) / a_safe**2)
    return np.eye(3) + s1[:, None, None] * W + s2[:, None, None] * (W @ W)


def tangent_operators(phi: Array) -> Array:
    """Tangent operators ``(n, 3, 2)`` of rotation vectors ``phi`` ``(n, 2)``: omega = T dphi.

    With R = exp(skew(theta)), theta = (phi_x, phi_y, 0): dR = skew(T dtheta) R where T is the
    left Jacobian of SO(3) (formulations/contact.md, eq. (2)); the first two columns are kept
    because phi_z is held at zero.  Below 1e-6 rad its Taylor series is used.
    """
    phi = np.asarray(phi, dtype=float).reshape(-1, 2)
    W = _skews(phi)
    a = np.hypot(phi[:, 0], phi[:, 1])
    small = a < 1e-6
    a_safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5, (1.0 - np.cos(a_safe)) / a_safe**2)
    c2 = np.where(small, 1.0 / 6.0, (a_safe - np.sin(a_safe)) / a_safe**3)
    T = np.eye(3) + c1[:, None, None] * W + c2[:, None, None] * (W @ W)
    return T[:, :, :2]


def rotation_matrix(phi: Array) -> Array:
    """Rotation matrix of the rotation vector ``(phi_x, phi_y)`` (phi_z = 0), Rodrigues' formula.

    The tilt of the top face (angle between its normal and the vertical) is exactly
    ``hypot(phi_x, phi_y)``: the rotation axis lies in the plane.

    >>> R = rotation_matrix(np.array([0.0, np.pi / 2]))
    >>> np.allclose(R @ [0, 0, 1], [1, 0, 0])
    True
    """
    return rotation_matrices(phi)[0]


def tangent_operator(phi: Array) -> Array:
    """Map ``(3, 2)`` from rotation-vector increments to the spatial angular increment.

    One row of :func:`tangent_operators`.
    """
    return tangent_operators(phi)[0]


def tilt(phi: Array) -> float:
    """Tilt angle of the top face in radians for rotation vector ``(phi_x, phi_y)``."""
    return float(np.hypot(phi[0], phi[1]))
