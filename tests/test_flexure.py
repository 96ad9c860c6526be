"""Tests of the three-point bending path (formulations/membrane.md sections 6-9)."""

from __future__ import annotations

import numpy as np
import pytest

from qpscale.errors import InvalidDesign
from qpscale.experiments.flexure import FlexureSetup, run_flexure
from qpscale.membrane import MembraneModel, tie_rows
from qpscale.tiling import Design

COARSE = MembraneModel(h=1.0, nz=2)


def timoshenko_star(span: float, a: float, height: float, nu: float, k: float = 5.0 / 6.0) -> float:
    """C_f E I of a simply supported beam with two loads F/2 at +-a from the centre.

    Bending: deflection at the centre from each load P = F/2 at distance b = span/2 - a from a support,
    P b (3 S^2 - 4 b^2) / (48 EI), summed for both. Shear: F/2 over the length b, b / (2 k G A).
    """
    b = span / 2 - a
    bending = b * (3 * span**2 - 4 * b**2) / 48.0
    shear = b / 2.0 * 2.0 * (1.0 + nu) * (height**2 / 12.0) / k
    return bending + shear


def test_narrow_bare_beam_against_timoshenko():
    # Narrow strip (1 L along the load line, plane stress), nu = 0.3. The flat supports touch at their
    # inner edges (effective span 8 - w_s) and the plate at its edges (a = w_p/2). 5 %: where exactly the
    # strips carry the load and the local indentation under them are outside beam theory.
    mem = MembraneModel(length=1.0, h=0.25, nz=6, nu=0.3)
    r = run_flexure(FlexureSetup(mode="bare", membrane=mem, increments=1))
    ref = timoshenko_star(8.0 - 0.5, 0.25, 1.5, 0.3)
    assert r.Cf_star == pytest.approx(ref, rel=0.05)


def test_bare_curve_is_linear_and_refines():
    # Bare membrane: linear elasticity with supports that stay closed, so F is proportional to w (1e-4:
    # the QPs are solved to 1e-6 absolute KKT residuals and F is ~0.07); and the default mesh agrees with a
    # twice-finer in-plane mesh within 2 %.
    r1 = run_flexure(FlexureSetup(mode="bare", membrane=COARSE, increments=3))
    assert np.allclose(r1.force / r1.force[-1], r1.deflection / r1.deflection[-1], atol=1e-4)
    r2 = run_flexure(FlexureSetup(mode="bare", membrane=MembraneModel(h=0.5, nz=3), increments=1))
    assert r2.Cf_star == pytest.approx(r1.Cf_star, rel=0.02)


def test_no_volumetric_locking():
    # Selective reduced integration: C_f* changes by < 5 % from nu = 0.45 to 0.4999 (a real, small
    # physical change); the fully integrated element loses more than half its compliance (locks).
    def cf(nu, integ):
        mem = MembraneModel(h=1.0, nz=2, nu=nu, integration=integ)
        return run_flexure(FlexureSetup(mode="bare", membrane=mem, increments=1)).Cf_star

    assert cf(0.4999, "sri") == pytest.approx(cf(0.45, "sri"), rel=0.05)
    assert cf(0.4999, "full") < 0.5 * cf(0.45, "full")


def test_bare_response_is_symmetric_about_the_mid_line():
    # Square membrane, symmetric supports: u(x, s) mirrors u(x, -s) to solver accuracy.
    r = run_flexure(FlexureSetup(mode="bare", membrane=COARSE, increments=1))
    model = r.extras["model"]
    u = model.cond.displacement(r.z_final)
    xyz = model.mm.nodes
    mirror = {tuple(np.round(p, 9)): k for k, p in enumerate(xyz * [1, -1, 1])}
    idx = np.array([mirror[tuple(np.round(p, 9))] for p in xyz])
    assert np.allclose(u[:, 2], u[idx, 2], atol=1e-6 * np.abs(u[:, 2]).max())
    assert np.allclose(u[:, 1], -u[idx, 1], atol=1e-6 * np.abs(u).max())


def test_isolated_scale_moves_its_bonded_nodes_rigidly():
    r = run_flexure(FlexureSetup(mode="isolated", membrane=COARSE, increments=2))
    model = r.extras["model"]
    u = model.cond.displacement(r.z_final)
    top = model.mm.face_nodes(True)
    poly = model.patch.polygons()[0]
    inside = np.array(
        [poly.buffer(1e-9).contains(__import__("shapely").Point(p[:2])) for p in model.mm.nodes[top]]
    )
    nodes = top[inside]
    assert len(nodes) >= 4
    expect = (tie_rows(model.mm.nodes[nodes, :2], model.patch.centroids[0]) @ r.z_final[:5]).reshape(-1, 3)
    assert np.allclose(u[nodes], expect, atol=1e-14)


def test_scaled_membrane_is_stiffer_and_symmetric_in_load_line():
    # Square arrayed: the 5x5 array is symmetric under x <-> y, so both load lines give the same C_f*
    # (1e-4: QP residuals of 1e-6 on forces ~0.4); the array must be far less compliant than the isolated
    # scale.
    iso = run_flexure(FlexureSetup(mode="isolated", increments=3))
    rx = run_flexure(FlexureSetup(mode="scaled", load_line="x", increments=3))
    ry = run_flexure(FlexureSetup(mode="scaled", load_line="y", increments=3))
    assert rx.Cf_star == pytest.approx(ry.Cf_star, rel=1e-4)
    assert rx.n_scales == 25 and rx.max_penetration < 1e-9
    assert rx.Cf_star < 0.5 * iso.Cf_star
    assert rx.wall_s < 20.0


def test_contact_stiffens_the_scaled_membrane():
    # With scale-scale contact switched off the scales interact through the membrane only: more compliant.
    on = run_flexure(FlexureSetup(mode="scaled", increments=2))
    off = run_flexure(FlexureSetup(mode="scaled", increments=2, contact=False))
    assert on.Cf_star < off.Cf_star
    assert np.all(np.diff(on.force) > 0)


def test_setup_validation():
    with pytest.raises(InvalidDesign, match="load_line"):
        FlexureSetup(load_line="z")
    with pytest.raises(InvalidDesign, match="mode"):
        FlexureSetup(mode="half")
    with pytest.raises(InvalidDesign, match="span"):
        FlexureSetup(span=12.0)
    FlexureSetup(design=Design(shape="hexagon"))
