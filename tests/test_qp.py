"""Tests of qpscale.qp: the QP record, its validation, our KKT residuals and the acceptance rule."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from qpscale.errors import InvalidDesign, QpscaleWarning
from qpscale.qp import ACCURACY, IncrementQP, IncrementResult, accept, candidate_result, resolve_tolerance
from qpscale.solvers.timing import synthetic_qp


def _tiny() -> IncrementQP:
    # min 1/2 (x1^2 + x2^2) + x1 + x2  s.t.  x1 <= -0.2,  x1 + x2 = 1
    return IncrementQP(
        P=sp.identity(2, format="csc"),
        q=np.array([1.0, 1.0]),
        G=sp.csc_matrix([[1.0, 0.0]]),
        h=np.array([-0.2]),
        A=sp.csc_matrix([[1.0, 1.0]]),
        b=np.array([1.0]),
        row_labels_G=("contact",),
        row_labels_A=("load",),
    )


def test_named_accuracies_and_explicit_tolerance():
    assert [resolve_tolerance(k) for k in ("high", "mid", "low")] == [1e-9, 1e-6, 1e-3]
    assert resolve_tolerance(2e-7) == pytest.approx(2e-7, rel=1e-15)
    assert set(ACCURACY) == {"high", "mid", "low"}
    for bad in ("best", 0.0, -1e-3, 2.0):
        with pytest.raises(InvalidDesign) as info:
            resolve_tolerance(bad)
        assert info.value.parameter == "accuracy"


def test_empty_blocks_and_default_labels():
    qp = IncrementQP(P=sp.identity(3, format="csc"), q=np.ones(3))
    assert (qp.n, qp.m_ineq, qp.m_eq) == (3, 0, 0)
    assert qp.G.shape == (0, 3) and qp.A.shape == (0, 3)
    qp2 = IncrementQP(P=sp.identity(2, format="csc"), q=np.ones(2), G=sp.csc_matrix(np.eye(2)), h=np.ones(2))
    assert qp2.row_labels_G == ("g0", "g1") and qp2.row_labels_A == ()


def test_dense_input_is_converted_with_a_warning():
    with pytest.warns(QpscaleWarning, match="dense"):
        qp = IncrementQP(P=np.eye(2), q=np.zeros(2))
    assert sp.issparse(qp.P) and qp.P.format == "csc"


@pytest.mark.parametrize(
    "kwargs, parameter",
    [
        ({"q": np.zeros(3)}, "P.shape"),
        ({"G": sp.csc_matrix(np.ones((1, 2))), "h": np.zeros(2)}, "h.shape"),
        ({"G": sp.csc_matrix(np.ones((1, 3))), "h": np.zeros(1)}, "G.shape[1]"),
        (
            {"A": sp.csc_matrix(np.ones((1, 2))), "b": np.zeros(1), "row_labels_A": ("a", "b")},
            "len(row_labels_A)",
        ),
        ({"P": sp.csc_matrix([[1.0, 0.5], [0.0, 1.0]])}, "P"),
        ({"q": np.array([np.nan, 0.0])}, "q"),
    ],
)
def test_invalid_problems_name_the_parameter(kwargs, parameter):
    args = {"P": sp.identity(2, format="csc"), "q": np.zeros(2), **kwargs}
    with pytest.raises(InvalidDesign) as info:
        IncrementQP(**args)
    assert info.value.parameter == parameter


def test_residuals_by_hand():
    qp = _tiny()
    # exact KKT point, derived by hand: x = (-0.2, 1.2); stationarity x2 + 1 + y = 0 gives y = -2.2,
    # x1 + 1 + z + y = 0 gives z = 1.4
    res = qp.residuals(np.array([-0.2, 1.2]), np.array([1.4]), np.array([-2.2]))
    assert max(res.values()) < 1e-15  # exact arithmetic up to one rounding of 0.2
    # a hand-made wrong point: x = (0, 1) violates x1 <= -0.2 by 0.2; z = -1 gives stationarity
    # (0+1-1-2.2, 1+1-2.2) = (-2.2, -0.2) and a sign violation of 1; complementarity |(-1)(-0.2)| = 0.2
    res = qp.residuals(np.array([0.0, 1.0]), np.array([-1.0]), np.array([-2.2]))
    assert res["primal"] == pytest.approx(0.2, abs=1e-15)
    assert res["dual"] == pytest.approx(2.2, abs=1e-15)
    assert res["complementarity"] == pytest.approx(0.2, abs=1e-15)
    assert qp.objective(np.array([-0.2, 1.2])) == pytest.approx(0.5 * (0.04 + 1.44) + 1.0, abs=1e-15)


def test_synthetic_problem_meets_kkt_at_its_known_point():
    k = synthetic_qp(3, n_blocks=25, m=40, coupling=20)
    res = k.qp.residuals(k.x, k.z, k.y)
    # q and h were built from (x*, z*, y*), so only rounding of O(100)-term sums remains
    assert max(res.values()) < 1e-12
    assert np.all(k.z >= 0) and np.linalg.eigvalsh(k.qp.P.toarray()).min() > 0


def test_accept_rejects_large_residuals_and_clears_numbers():
    qp = _tiny()
    good = candidate_result(
        qp,
        np.array([-0.2, 1.2]),
        np.array([1.4]),
        np.array([-2.2]),
        status="Solved",
        ok=True,
        build_s=0.0,
        solve_s=0.0,
    )
    assert accept(good, 1e-12) is good
    bad = candidate_result(
        qp,
        np.array([-0.2, 1.2 + 1e-6]),
        np.array([1.4]),
        np.array([-2.2]),
        status="Solved",
        ok=True,
        build_s=0.0,
        solve_s=0.0,
    )
    out = accept(bad, 1e-9)
    assert not out.found and out.x is None and out.obj is None and out.status == "Solved"
    assert out.extras["rejected_by"] == "residuals" and out.residuals["dual"] == pytest.approx(1e-6, rel=1e-6)
    failed = candidate_result(
        qp, None, None, None, status="PrimalInfeasible", ok=False, build_s=0.0, solve_s=0.0
    )
    assert not accept(failed, 1.0).found and failed.residuals is None


def test_result_cannot_claim_found_without_numbers():
    with pytest.raises(InvalidDesign):
        IncrementResult(None, None, None, True, "Solved", None, None, 0.0, 0.0)
