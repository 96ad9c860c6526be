"""The sparse exact solve of an increment QP (qpscale/active_set.py) against DAQP's dense one, and
its use by the check of F_c (formulations/increment-qp.md sec. 8)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from qpscale import active_set, certify
from qpscale.certify import check_force, solve_exact
from qpscale.errors import InvalidDesign
from qpscale.qp import IncrementQP

from .test_solvers import _stored_qp


@pytest.fixture(scope="module")
def default_final():
    """The increment QP linearised at the default scene's failure state (5x5 square, 341 unknowns,
    492 contact rows; ``python -m qpscale puncture``), its state's force and DOF count."""
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / "default_final_qp.npz")
    return _stored_qp("default_final_qp.npz"), float(d["F"][0]), int(d["n_dof"][0])


def _certified(qp: IncrementQP, s: active_set.SparseSolution) -> str:
    return certify._certify(qp, s.x, s.z, s.y, "" if s.converged else s.status)[0]


def test_sparse_and_dense_agree_on_the_default_scene(default_final):
    # Both certified at round-off.  x ~ 1e-10 L (the state is its QP's fixed point) and is pinned
    # by round-off residuals only to ~ residual / lambda_min(P) = 1e-16 / 1e-6 (the planes'
    # regularisation): 1e-10 L absolute.  The load multiplier's range, by the same LPs from each
    # answer's rows in contact, agrees to 1e-9, and the state's F lies in both.
    qp, F, n_dof = default_final
    dense = solve_exact(qp, ranged=[0], method="dense")
    sparse = solve_exact(qp, ranged=[0], method="sparse")
    assert dense.certified and sparse.certified, (dense.status, sparse.status)
    assert np.abs(sparse.x - dense.x).max() <= 1e-10
    assert np.abs(sparse.y_range[0] - dense.y_range[0]).max() <= 1e-9
    assert np.array_equal(sparse.active, dense.active)
    for method in ("dense", "sparse"):
        check = check_force(qp, F, n_dof, method)
        assert check.status == "verified", check.detail
        assert check.dq_exact <= 1e-7


def test_sparse_and_dense_agree_on_a_held_qp():
    # A QP of a path held mirror-symmetric (tests/data/held_square_qp.npz: 341 unknowns, 448
    # contact rows and 173 equality rows, the loading row and the symmetry's): the equality rows
    # sit in every KKT system, dependent or not.  Same tolerances as on the default scene.
    qp = _stored_qp("held_square_qp.npz")
    dense = solve_exact(qp, ranged=[0], method="dense")
    sparse = solve_exact(qp, ranged=[0], method="sparse")
    assert dense.certified and sparse.certified, (dense.status, sparse.status)
    assert np.abs(sparse.x - dense.x).max() <= 1e-10
    assert np.abs(sparse.y_range[0] - dense.y_range[0]).max() <= 1e-9


@pytest.mark.parametrize("guess", ["empty", "all"])
def test_a_wrong_guess_of_the_contact_rows_ends_at_the_same_certified_answer(default_final, guess):
    # The first Newton step solves the KKT system of the guessed rows (none: the load row alone
    # pushes the scales through their neighbours; all 492: an inconsistent system, solvable only
    # because it is regularised); the iteration still ends on the answer of a cold start.
    qp, _, _ = default_final
    cold = active_set.solve_sparse(qp)
    rows = np.arange(qp.m_ineq) if guess == "all" else np.zeros(0, dtype=int)
    s = active_set.solve_sparse(qp, working=rows)
    assert _certified(qp, s) == "certified" and _certified(qp, cold) == "certified"
    assert np.abs(s.x - cold.x).max() <= 1e-10
    assert s.y[0] == pytest.approx(cold.y[0], abs=1e-9)


def test_a_warm_start_from_the_interior_point_answer_takes_few_steps(default_final):
    # From PIQP's answer the multipliers are close: the first outer steps keep the rows in contact.
    from qpscale.solvers import solve_qp

    qp, _, _ = default_final
    r = solve_qp(qp, "piqp", "high")
    warm = active_set.solve_sparse(qp, r.x, r.z, r.y)
    cold = active_set.solve_sparse(qp)
    assert _certified(qp, warm) == "certified"
    assert np.abs(warm.x - cold.x).max() <= 1e-10
    assert warm.newton < cold.newton


def test_dependent_rows_in_contact():
    # Three copies of the row x1 + x2 <= 0 (one scaled by 2) and the equality x1 - x2 = 0: the
    # working set is rank deficient, its KKT matrix singular without the regularisation.  The
    # minimiser of 1/2 |x - (1, 1)|^2 is x = 0; balance: (z1 + 2 z2 + z3 - 1)(1, 1) + y (1, -1) = 0,
    # so z1 + 2 z2 + z3 = 1 (any split) and y = 0 exactly.
    qp = IncrementQP(
        P=sp.identity(2, format="csc"),
        q=np.array([-1.0, -1.0]),
        G=sp.csc_matrix([[1.0, 1.0], [2.0, 2.0], [1.0, 1.0]]),
        h=np.zeros(3),
        A=sp.csc_matrix([[1.0, -1.0]]),
        b=np.zeros(1),
    )
    ex = solve_exact(qp, method="sparse")
    assert ex.certified, ex.status
    assert np.abs(ex.x).max() <= 1e-15
    assert ex.z[0] + 2 * ex.z[1] + ex.z[2] == pytest.approx(1.0, abs=1e-12)
    assert ex.y_range[0] == pytest.approx([0.0, 0.0], abs=1e-9)


@pytest.mark.parametrize(
    "G, h, A, b",
    [
        ([[1.0, 0.0], [-1.0, 0.0]], [-1.0, -1.0], [[0.0, 1.0]], [0.0]),  # x1 <= -1 and x1 >= 1
        ([[1.0, 0.0]], [1.0], [[0.0, 1.0], [0.0, 1.0]], [0.0, 1.0]),  # x2 = 0 and x2 = 1
    ],
)
def test_an_infeasible_qp_is_not_certified(G, h, A, b):
    # No minimiser: the multipliers grow without bound and the solve stops at its iteration limit;
    # neither method may report a force.
    qp = IncrementQP(
        P=sp.identity(2, format="csc"),
        q=np.zeros(2),
        G=sp.csc_matrix(G),
        h=np.array(h),
        A=sp.csc_matrix(A),
        b=np.array(b),
    )
    ex = solve_exact(qp, method="sparse")
    assert not ex.certified and ex.status.startswith("sparse active set")
    assert np.isnan(ex.y_range).all()
    check = check_force(qp, 1.0, 2)  # auto: both methods tried, both reasons kept
    assert check.status == "unverified"
    assert "dense: " in check.detail and "sparse: " in check.detail
    assert np.isnan(check.F_exact).all() and np.isnan(check.dq_exact)


def test_a_solve_stopped_early_is_not_certified(default_final, monkeypatch):
    # One outer step cannot see the rows settle: the solve stops at its iteration limit (from
    # PIQP's answer, then from zero), and the check says unverified, with no exact number.
    qp, F, n_dof = default_final
    monkeypatch.setattr(active_set, "MAX_OUTER", 1)
    monkeypatch.setattr(certify, "WARM_OUTER", 1)  # the start from PIQP's answer too
    check = check_force(qp, F, n_dof, "sparse")
    assert check.status == "unverified" and check.detail == "sparse active set: outer iteration limit 1"
    assert np.isnan(check.F_exact).all()


def test_the_method_is_picked_by_size(default_final):
    qp, _, _ = default_final  # 341 unknowns: the sparse solve first, DAQP after its failure
    assert certify._methods(qp, "auto") == ("sparse", "dense")
    n = certify.SPARSE_FROM - 1
    below = IncrementQP(P=sp.identity(n, format="csc"), q=np.zeros(n))
    assert certify._methods(below, "auto") == ("dense", "sparse")
    n = certify.DENSE_UP_TO + 1
    big = IncrementQP(P=sp.identity(n, format="csc"), q=np.zeros(n))
    assert certify._methods(big, "auto") == ("sparse",)
    assert certify._methods(big, "dense") == ("dense",)
    with pytest.raises(InvalidDesign, match="method"):
        certify._methods(qp, "exact")


@pytest.mark.parametrize("seed", range(4))
def test_the_line_search_is_the_minimiser_along_the_line(seed):
    # phi(t) = alpha t^2 / 2 + beta t + (|r_eq + t a_eq|^2 + |[r + t a]_+|^2) / (2 delta): the
    # exact minimiser against a dense grid refined twice around its best point.
    rng = np.random.default_rng(seed)
    p, m, delta = 2, 30, 1e-2
    r, a = rng.normal(size=p + m), rng.normal(size=p + m)
    alpha, beta = 0.5, -5.0 - rng.random()

    def phi(t):
        pos = np.r_[r[:p] + t * a[:p], np.maximum(r[p:] + t * a[p:], 0.0)]
        return 0.5 * alpha * t * t + beta * t + pos @ pos / (2 * delta)

    t = active_set._line_search(alpha, beta, r, a, p, delta)
    lo, hi = 0.0, 20.0
    for _ in range(3):
        grid = np.linspace(lo, hi, 4001)
        best = grid[np.argmin([phi(g) for g in grid])]
        step = grid[1] - grid[0]
        lo, hi = max(0.0, best - step), best + step
    assert t == pytest.approx(best, abs=1e-6)
    assert phi(t) <= phi(best) + 1e-12


def test_the_cost_estimate_counts_the_dense_solve_where_the_check_may_run_it():
    # validation.py keeps its own copy of DENSE_UP_TO (the CLI validates before importing scipy);
    # the copies must agree, or a patch the check runs densely would be estimated sparse.
    from qpscale import validation

    assert validation.DENSE_CHECK_UP_TO == certify.DENSE_UP_TO


def test_a_failed_factorisation_is_a_status_not_an_exception(default_final, monkeypatch):
    # qdldl refuses a matrix whose pivots come out of the wrong sign; the check reports it.
    qp, F, n_dof = default_final

    def refuse(self, S, rhs):
        raise RuntimeError("Input matrix is not quasi-definite")

    monkeypatch.setattr(active_set._KKT, "solve", refuse)
    check = check_force(qp, F, n_dof, "sparse")
    assert check.status == "unverified" and "factorisation" in check.detail
    assert np.isnan(check.F_exact).all()


def test_rows_at_contact_with_no_force_stop_the_backend_at_a_stationary_point():
    # 30 rows through the unconstrained minimiser of a strictly convex QP: at the answer every row
    # is at contact and carries no force (degenerate complementarity), so rounding moves rows in
    # and out of the set that carries force, which then never repeats.  With ``stationary`` (the
    # backend's stop) the solve stops because its point is stationary to the tolerance; with the
    # exact check's stop (the set must repeat) it runs to its limit with residuals at 1e-14, as
    # it did on a flexure QP of a slanted square array.  The answer is the minimiser itself, to
    # rounding over lambda_min(P) >= 0.1.
    rng = np.random.default_rng(0)
    n = 40
    M = rng.standard_normal((n, n))
    P = M @ M.T / n + 0.1 * np.eye(n)
    q = rng.standard_normal(n)
    x_free = np.linalg.solve(P, -q)
    G = rng.standard_normal((30, n))
    qp = IncrementQP(P=sp.csc_matrix(P), q=q, G=sp.csc_matrix(G), h=G @ x_free)
    s = active_set.solve_sparse(qp, stationary=True)
    assert s.converged and s.outer < 20, (s.status, s.outer)
    assert max(qp.residuals(s.x, s.z, s.y).values()) <= 1e-12
    assert np.abs(s.x - x_free).max() <= 1e-12
    repeated = active_set.solve_sparse(qp, max_outer=50)
    assert not repeated.converged and repeated.status == "outer iteration limit 50"
    assert max(qp.residuals(repeated.x, repeated.z, repeated.y).values()) <= 1e-12
