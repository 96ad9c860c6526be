"""Shapes, prisms and rotations: formulations/geometry.md."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Polygon

from qpscale import SHAPES, InvalidDesign, Prism, base_polygon, convex_pieces, rotation_matrix
from qpscale.geometry import slant_offset, tangent_operator, tilt


@pytest.mark.parametrize("shape", SHAPES)
def test_base_area_is_four_and_centroid_at_origin(shape):
    poly = Polygon(base_polygon(shape))
    # Closed-form side lengths: area is exact to round-off.
    assert abs(poly.area - 4.0) <= 4.0 * 1e-12
    assert np.allclose(poly.centroid.coords[0], 0.0, atol=1e-12)
    assert poly.exterior.is_ccw


@pytest.mark.parametrize("shape", SHAPES)
def test_convex_pieces_partition_the_shape(shape):
    poly = Polygon(base_polygon(shape))
    pieces = [Polygon(p) for p in convex_pieces(shape)]
    assert all(abs(p.area - p.convex_hull.area) < 1e-12 for p in pieces)
    assert abs(sum(p.area for p in pieces) - poly.area) < 1e-12
    union = pieces[0]
    for p in pieces[1:]:
        union = union.union(p)
    assert union.symmetric_difference(poly).area < 1e-12


def test_dart_is_non_convex_and_others_convex():
    for shape in SHAPES:
        poly = Polygon(base_polygon(shape))
        convex = abs(poly.convex_hull.area - poly.area) < 1e-12
        assert convex == (shape != "dart")


@given(
    shape=st.sampled_from(SHAPES),
    t=st.floats(0.05, 5.0),
    alpha=st.floats(0.0, 80.0),
    direction=st.floats(0.0, 359.0),
)
@settings(max_examples=60, deadline=None)
def test_prism_volume_normals_and_offset(shape, t, alpha, direction):
    off = slant_offset(t, alpha, direction)
    assert np.hypot(*off) == pytest.approx(t * np.tan(np.deg2rad(alpha)), rel=1e-12, abs=1e-15)
    for piece in convex_pieces(shape):
        prism = Prism(piece, t, off)
        # Cavalieri: an oblique prism keeps base area x height.
        assert prism.volume == pytest.approx(Polygon(piece).area * t, rel=1e-12)
        v = prism.vertices
        centre = v.mean(axis=0)
        for face, n in zip(prism.faces, prism.face_normals):
            # Outward: the centroid of a convex body is behind every face plane.
            assert np.dot(n, v[face[0]] - centre) > 0
            # Planar faces: every vertex of a face lies on its plane.
            assert np.allclose((v[face] - v[face[0]]) @ n, 0.0, atol=1e-10)
        top_normal = prism.face_normals[1]
        assert np.allclose(top_normal, [0, 0, 1])


@given(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5))
@settings(max_examples=60, deadline=None)
def test_rotation_is_orthonormal_and_tilt_is_norm(px, py):
    phi = np.array([px, py])
    R = rotation_matrix(phi)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-13)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-13)
    # The axis lies in the plane, so the top normal tilts by exactly |phi|.
    angle = np.arccos(np.clip((R @ [0, 0, 1.0])[2], -1, 1))
    assert angle == pytest.approx(tilt(phi), abs=1e-7)


@given(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1, 1), st.floats(-1, 1))
@settings(max_examples=40, deadline=None)
def test_tangent_operator_matches_finite_differences(px, py, dx, dy):
    phi, d = np.array([px, py]), np.array([dx, dy])
    h = 1e-6
    dR = (rotation_matrix(phi + h * d) - rotation_matrix(phi - h * d)) / (2 * h)
    omega = tangent_operator(phi) @ d
    W = dR @ rotation_matrix(phi).T
    # dR R' is skew with axial vector omega; central differences err by O(h^2).
    assert np.allclose(W, -W.T, atol=1e-8)
    assert np.allclose([W[2, 1], W[0, 2], W[1, 0]], omega, atol=1e-8)


def test_unknown_shape_rejected():
    with pytest.raises(InvalidDesign, match="shape='circle'"):
        base_polygon("circle")
