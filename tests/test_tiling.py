"""The eight designs and their patches: formulations/geometry.md sections 4-6."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely import unary_union
from shapely.geometry import Polygon

from qpscale import DESIGNS, TILINGS_OF, Design, InvalidDesign
from qpscale.tiling import inflated_polygon, max_overlap_area, min_gap

from .cases import ALL_DESIGNS, GAPS, SLANTS


def _check_patch(design: Design) -> None:
    patch = design.patch()
    polys = patch.polygons()
    areas = np.array([p.area for p in polys])
    assert np.all(np.abs(areas - 4.0) <= 4.0 * 1e-12)
    assert max_overlap_area(patch) == 0.0 or max_overlap_area(patch) < 1e-12
    if patch.n_scales > 1:
        # Shared edges are exactly d apart (tolerance: shapely's double arithmetic on O(10) coordinates).
        assert min_gap(patch) == pytest.approx(design.gap, abs=1e-9)

    # The gap-free tiles (bases inflated by d/2) cover the patch without holes or overlaps.
    # GEOS mis-resolves exactly shared edges, so overlaps are measured on tiles shrunk by 1e-9 L and
    # holes on tiles grown by 1e-9 L; a real overlap or a missing tile is O(1) L^2.
    def tiles(eps: float) -> list[Polygon]:
        return [
            Polygon(p).buffer(design.gap / 2 + eps, join_style="mitre", mitre_limit=1e3) for p in patch.base
        ]

    shrunk = tiles(-1e-9)
    assert unary_union(shrunk).area == pytest.approx(sum(p.area for p in shrunk), rel=1e-7)
    union = unary_union(tiles(1e-9))
    assert union.geom_type == "Polygon"
    assert all(Polygon(hole).area < 1e-12 for hole in union.interiors)
    offset = design.top_offset
    assert np.hypot(*offset) == pytest.approx(
        design.thickness * np.tan(np.deg2rad(design.slant_deg)), abs=1e-12
    )
    assert patch.prism(0).volume == pytest.approx(4.0 * design.thickness, rel=1e-12)


@pytest.mark.parametrize("design", ALL_DESIGNS, ids=lambda d: f"{d.shape}-{d.tiling}")
@pytest.mark.parametrize("gap", GAPS)
def test_every_design_tiles_at_every_gap(design, gap):
    _check_patch(design.with_(gap=gap))


@pytest.mark.parametrize("design", ALL_DESIGNS, ids=lambda d: f"{d.shape}-{d.tiling}")
@pytest.mark.parametrize("slant", SLANTS, ids=str)
def test_slanted_designs(design, slant):
    _check_patch(design.with_(slant_deg=slant[0], slant_dir_deg=slant[1]))


@given(
    design=st.sampled_from(DESIGNS),
    gap=st.floats(0.0, 0.3),
    alpha=st.floats(0.0, 75.0),
    direction=st.sampled_from([0.0, 45.0, 90.0]),
    thickness=st.floats(0.1, 3.0),
    rings=st.integers(0, 3),
)
@settings(max_examples=40, deadline=None)
def test_property_valid_designs_tile(design, gap, alpha, direction, thickness, rings):
    _check_patch(Design(design[0], design[1], alpha, direction, gap, thickness, rings))


def test_square_patch_is_five_by_five():
    patch = Design().patch()
    assert patch.n_scales == 25
    xs = np.unique(np.round(patch.centroids[:, 0], 9))
    assert len(xs) == 5
    assert np.allclose(np.diff(xs), 2.005)
    # Arrayed squares: each interior scale has 8 neighbours (4 edge, 4 corner).
    counts = np.bincount(patch.neighbours.ravel(), minlength=25)
    assert counts[0] == 8


@pytest.mark.parametrize(
    "shape,tiling,expected",
    [
        ("square", "arrayed", [1, 9, 25, 49]),
        ("hexagon", "honeycomb", [1, 7, 19, 37]),
        ("square", "staggered", [1, 7, 19, 37]),
    ],
)
def test_ring_counts(shape, tiling, expected):
    # Counts of a lattice with 8 (resp. 6) neighbours: (2N+1)^2 and 3N(N+1)+1.
    got = [Design(shape, tiling, rings=r).patch().n_scales for r in range(4)]
    assert got == expected


def test_slant_adds_overhanging_contact_candidates():
    flat = Design().patch()
    slanted = Design(slant_deg=63.4).patch()
    assert set(map(tuple, flat.neighbours.tolist())) <= set(map(tuple, slanted.contact_pairs.tolist()))
    assert len(slanted.contact_pairs) > len(flat.contact_pairs)


def test_inflated_square_is_similar():
    poly = inflated_polygon("square", 0.1)
    assert poly.area == pytest.approx(2.1**2, rel=1e-12)


@pytest.mark.parametrize(
    "field,value,allowed",
    [
        ("shape", "circle", "triangle"),
        ("tiling", "spiral", "arrayed"),
        ("slant_deg", 90.0, "[0, 90)"),
        ("slant_deg", -1.0, "[0, 90)"),
        ("gap", -0.001, "[0, 1)"),
        ("thickness", 0.0, "(0, 100]"),
        ("rings", -1, "[0, 50]"),
        ("rings", 1.5, "[0, 50]"),
    ],
)
def test_bad_input_names_parameter(field, value, allowed):
    with pytest.raises(InvalidDesign) as info:
        Design(**{field: value})
    assert info.value.parameter == field
    assert allowed in str(info.value)


def test_tiling_a_shape_does_not_have():
    with pytest.raises(InvalidDesign, match="not a tiling of shape='hexagon'"):
        Design(shape="hexagon", tiling="arrayed")
    for shape, tilings in TILINGS_OF.items():
        assert Design(shape).tiling == tilings[0]
