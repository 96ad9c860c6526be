"""The exact active-set solution of an increment QP and the check of F_c (formulations/
increment-qp.md sec. 8)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from qpscale.certify import check_force, solve_exact
from qpscale.experiments.puncture import PunctureSetup, run_puncture
from qpscale.qp import IncrementQP
from qpscale.solvers import solve_qp
from qpscale.solvers.timing import synthetic_qp
from qpscale.tiling import Design

from .test_solvers import _dart_hinge_qp


@pytest.mark.parametrize("method", ["dense", "sparse"])
@pytest.mark.parametrize("seed", range(5))
def test_exact_solution_is_the_known_one(seed, method):
    # The synthetic QPs have a unique KKT point chosen first (strict complementarity, P > 0);
    # an active-set solve is exact up to rounding: 1e-10 on O(1) data, by either method.
    k = synthetic_qp(seed, n_blocks=6, m=20, p=2)
    ex = solve_exact(k.qp, method=method)
    assert ex.certified, ex.status
    assert ex.method == method
    assert np.abs(ex.x - k.x).max() <= 1e-10
    assert np.abs(ex.y_range[:, 0] - k.y).max() <= 1e-9 and np.abs(ex.y_range[:, 1] - k.y).max() <= 1e-9


@pytest.mark.parametrize("method", ["dense", "sparse"])
def test_multiplier_range_of_a_degenerate_qp(method):
    # min 1/2 |x|^2 - x2  s.t.  x1 = 0 (y),  x2 <= 0,  x2 - x1 <= 0.  At x = 0 both rows are in
    # contact and balance x2 together: z1 + z2 = 1, y = z2, so y takes every value in [0, 1].
    qp = IncrementQP(
        P=sp.identity(2, format="csc"),
        q=np.array([0.0, -1.0]),
        G=sp.csc_matrix([[0.0, 1.0], [-1.0, 1.0]]),
        h=np.zeros(2),
        A=sp.csc_matrix([[1.0, 0.0]]),
        b=np.zeros(1),
    )
    ex = solve_exact(qp, method=method)
    assert ex.certified and np.abs(ex.x).max() <= 1e-14
    assert ex.y_range[0] == pytest.approx([0.0, 1.0], abs=1e-9)
    assert check_force(qp, 0.3, 2, method).status == "verified"
    assert check_force(qp, 1.1, 2, method).status == "disagrees"


def test_a_hinge_qp_that_daqp_cannot_certify_says_so_and_the_sparse_solve_certifies():
    # The degenerate QP of the 5x5 dart on which Clarabel's default settings stall: dependent
    # rows of a hinged plane.  DAQP cycles on it at every tolerance tried (1e-9 to 1e-13, with or
    # without proximal terms; with its default 1e-6 it stops 5e-7 infeasible), so DAQP's check
    # must report "unverified" with DAQP's own flag, and no exact number.  The sparse solve's
    # factorisations are quasi-definite whatever the rows' rank: it is certified, and the force
    # Clarabel's retry found (1e-9 residuals) lies in its range.
    qp = _dart_hinge_qp()
    ex = solve_exact(qp, method="dense")
    assert not ex.certified and ex.status.startswith("daqp exit flag")
    r = solve_qp(qp, "clarabel", "high")
    check = check_force(qp, float(r.y[0]), 125, method="dense")
    assert check.status == "unverified" and check.detail == ex.status
    assert np.isnan(check.F_exact).all() and np.isnan(check.dq_exact)
    sparse = solve_exact(qp)  # 521 unknowns: the sparse solve first
    assert sparse.certified and sparse.method == "sparse", sparse.status
    assert check_force(qp, float(r.y[0]), 125).status == "verified"


@pytest.fixture(scope="module")
def corner_3x3():
    return run_puncture(PunctureSetup(design=Design(rings=1), load_point=(0.5, 0.5), probe=False))


def test_path_Fc_is_verified_by_the_exact_solution(corner_3x3):
    # The corner-loaded 3x3 square: F_c lies in the exact range to 1e-6 (puncture.md sec. 3),
    # and the failure state is the fixed point of its own QP (dq below the step tolerance).
    check = corner_3x3.Fc_check
    assert check is not None and check.status == "verified", check.detail
    lo, hi = check.F_exact
    assert lo - 1e-6 * hi <= corner_3x3.Fc_star <= hi + 1e-6 * hi
    assert check.dq_exact <= 1e-7
    assert check.active_rows > 0


@pytest.mark.parametrize("method", ["dense", "sparse"])
def test_a_wrong_force_is_caught(corner_3x3, method):
    from qpscale.continuation import SQPLevels
    from qpscale.experiments.puncture import _load_point, build_model

    setup, final = corner_3x3.setup, corner_3x3.states[-1]
    patch, K = build_model(setup)
    level = SQPLevels(patch, K, _load_point(patch, (0.5, 0.5)), setup.contact, setup.sqp)
    qp = level.increment_qp(final)[0]
    assert check_force(qp, final.F, patch.n_scales * 5, method).status == "verified"
    assert check_force(qp, final.F * (1 + 1e-5), patch.n_scales * 5, method).status == "disagrees"
