"""Refinement of the flexure compliance (formulations/membrane.md sec. 9; qpscale.studies.flexure_bench)."""

from __future__ import annotations

import math

import pytest

from qpscale.experiments.flexure import FlexureSetup
from qpscale.studies.flexure_bench import (
    DEFAULT_LEVEL,
    MeshLevel,
    converged_compliance,
    flexure_bench,
    richardson,
    run_level,
)

BARE = FlexureSetup(mode="bare", increments=1)


def test_richardson_recovers_a_known_limit_and_refuses_to_extrapolate_noise():
    # v(h) = 3 + 2 h^1.5 at h = 1, 1/2, 1/4: the limit 3 and the order 1.5 to round-off.
    limit, p, err = richardson([3 + 2 * h**1.5 for h in (1.0, 0.5, 0.25)])
    assert limit == pytest.approx(3.0, abs=1e-12) and p == pytest.approx(1.5, abs=1e-12)
    assert err == pytest.approx(2 * 0.25**1.5, rel=1e-9)
    # Differences that change sign: no order, the finest value, the larger difference as the bound.
    limit, p, err = richardson([9.80, 9.83, 9.82])
    assert math.isnan(p) and limit == 9.82 and err == pytest.approx(0.03)


def test_bare_compliance_converges_through_the_thickness():
    # nz = 2, 4, 8 at h = 1: the layers' error falls like nz^-2.6 (measured; the band [2, 3.5] would
    # catch a first-order or a stalled sequence) and the extrapolation's error estimate is below 0.5 %.
    levels = [MeshLevel(1.0, nz, 0.1) for nz in (2, 4, 8)]
    values = [run_level(BARE, lv)["Cf_star"] for lv in levels]
    limit, p, err = richardson(values)
    assert 2.0 < p < 3.5
    assert err < 0.005 * limit
    assert values[0] > values[1] > values[2] > limit  # refining the layers lowers C_f*


@pytest.mark.slow
def test_bare_compliance_converged_from_the_default_mesh():
    # From the default mesh (h 0.5, nz 3, contact_h 0.05), each direction refined twice by 2 (h down to
    # 0.125: ~2 min). Measured: h 9.802, 9.926, 9.976 (order 1.3), nz 9.802, 9.507, 9.456 (order 2.5),
    # contact_h 9.802, 9.829, 9.819 (not monotone: the contact width is a few elements; bounded by the
    # larger difference); limit 9.67 +- 0.07. Checked: the limit lies between the plane-strain (9.35) and
    # plane-stress (12.0) beams, the error estimate is below 1.5 %, and the default mesh is within 2 % of
    # the limit (it owes that to the cancelling h and nz errors, membrane.md sec. 9).
    c = converged_compliance(BARE, DEFAULT_LEVEL)
    assert 9.35 < c.Cf_star < 12.0
    assert c.error < 0.015 * c.Cf_star
    assert 1.0 < c.directions["h"]["order"] < 2.5 and 2.0 < c.directions["nz"]["order"] < 3.5
    assert c.base == pytest.approx(c.Cf_star, rel=0.02)
    rows = flexure_bench(BARE, [MeshLevel(1.0, 2, 0.1)], c)
    assert rows[0]["rel_error"] > abs(c.base - c.Cf_star) / c.Cf_star  # the coarse mesh is worse
