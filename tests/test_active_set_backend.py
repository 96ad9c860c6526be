"""The package's own exact QP method as a backend (``--solver active-set``) and its KKT solves in
the contact space (formulations/increment-qp.md sec. 3.5 and 8, "In the contact space")."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from qpscale import active_set
from qpscale.experiments.flexure import FlexureSetup, run_flexure
from qpscale.membrane import MembraneModel
from qpscale.qp import IncrementQP, WarmStart
from qpscale.solvers import available_solvers, solve_qp

# The coarse gap-graded membrane of tests/test_flexure.py.
GRADED = MembraneModel(h=1.0, nz=2, growth=2.0)


def _flexure_like(k: int = 220, planes: int = 30, seed: int = 0, negative: bool = False) -> IncrementQP:
    """A QP shaped like the flexure QP (13): a dense SPD block (the condensed membrane), a diagonal
    of plane weights down to 1e-6, bounds on part of the block's unknowns (roller rows), rows mixing
    block and plane unknowns (contact rows), and two copies of one row (a hinge's dependent rows)."""
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((k, k))
    B = M @ M.T / k + 0.05 * np.eye(k)
    if negative:
        B[0, 0] = -1.0
    w = np.geomspace(1e-6, 1.0, planes)
    P = sp.block_diag([B, sp.diags(w)], format="csc")
    n = k + planes
    bounds = sp.csr_matrix((-np.ones(120), (np.arange(120), np.arange(120))), shape=(120, n))
    mixed = sp.random(40, n, density=0.05, random_state=seed, format="csr")
    G = sp.vstack([bounds, mixed, mixed[:1]], format="csc")
    h = np.r_[np.full(120, 0.01), rng.uniform(0.0, 0.02, 40), 0.0]
    h[-1] = h[120]
    return IncrementQP(P, rng.standard_normal(n), G, h)


def test_contact_space_solve_equals_the_sparse_ldl_solve(monkeypatch):
    # Same method, two linear algebras: both end at the QP's solution up to rounding, so their x
    # agree to 1e-10 (rounding over lambda_min(P) = 1e-6: ~1e-10) and their residuals are <= 1e-12.
    qp = _flexure_like()
    assert active_set.dense_block(qp.P) == 220
    G, h, A, _ = qp.rows()
    assert isinstance(active_set._kkt(qp.P, sp.vstack([A, G], format="csr"), 1e-6), active_set._ContactKKT)
    contact = active_set.solve_sparse(qp)
    monkeypatch.setattr(active_set, "CONTACT_MIN_BLOCK", 10**9)
    assert isinstance(active_set._kkt(qp.P, sp.vstack([A, G], format="csr"), 1e-6), active_set._KKT)
    ldl = active_set.solve_sparse(qp)
    assert contact.converged and ldl.converged, (contact.status, ldl.status)
    assert np.abs(contact.x - ldl.x).max() <= 1e-10
    for s in (contact, ldl):
        assert max(qp.residuals(s.x, s.z, s.y).values()) <= 1e-12
    assert (contact.z > 0).sum() > 10  # the test has rows in contact, some of them bounds


def test_the_block_inverse_is_kept_only_for_the_same_block():
    rng = np.random.default_rng(1)
    B = np.eye(5) + 0.1 * rng.standard_normal((5, 5))
    B = B @ B.T
    first = active_set._block_inverse(B)
    assert active_set._block_inverse(B.copy()) is first
    other = B + np.eye(5)
    inv = active_set._block_inverse(other)
    assert inv is not first
    assert np.allclose(inv @ other, np.eye(5), atol=1e-12)


def test_a_block_that_is_not_positive_definite_is_reported_with_its_status():
    qp = _flexure_like(negative=True)
    s = active_set.solve_sparse(qp)
    assert not s.converged and s.status.startswith("factorisation")
    r = solve_qp(qp, "active-set", check=False)
    assert not r.found and r.x is None and r.status.startswith("factorisation")


def test_the_backend_is_listed_and_exact():
    assert "active-set" in available_solvers()
    qp = _flexure_like(seed=2)
    r = solve_qp(qp, "active-set")
    # it stops once no row is violated, nor a row carrying force open, by more than a tenth of
    # the target 1e-9 (qp.backend_options): every residual is then below that tenth
    assert r.found and r.max_residual() <= 1e-10
    # the same QP from its own answer: a warm start that is already the solution takes one outer
    # step to confirm and moves nothing
    again = solve_qp(qp, "active-set", warm_start=WarmStart(r.x, r.z, r.y))
    assert again.extras["warm_start_used"] and again.extras["outer"] <= 2
    assert np.abs(again.x - r.x).max() <= 1e-12


def test_a_warm_start_of_the_wrong_shape_is_not_used():
    qp = _flexure_like(seed=3)
    r = solve_qp(qp, "active-set", warm_start=WarmStart(np.zeros(3), np.zeros(2), np.zeros(0)))
    assert r.found and not r.extras["warm_start_used"]


@pytest.mark.parametrize("contact_space", [False, True])
def test_flexure_with_the_exact_backend_agrees_with_piqp(monkeypatch, contact_space):
    # The 5x5 square array on the coarse graded membrane (103 retained DOFs, so the contact-space
    # solve is forced for the second case).  PIQP stops at 1e-10 on the residuals; over the
    # stiffness ~1 that moves C_f* by ~1e-9: agreement to 1e-8 relative.
    if contact_space:
        monkeypatch.setattr(active_set, "CONTACT_MIN_BLOCK", 1)
    setup = FlexureSetup(mode="scaled", membrane=GRADED, increments=2)
    ref = run_flexure(setup)
    exact = run_flexure(FlexureSetup(mode="scaled", membrane=GRADED, increments=2, solver="active-set"))
    assert exact.Cf_star == pytest.approx(ref.Cf_star, rel=1e-8)
    assert exact.max_penetration <= 1e-9


def test_the_bare_membrane_curve_equals_the_dense_active_set_solvers():
    # The bare membrane's QPs are strictly convex with bounds only (plate and roller rows): one
    # solution per plate position.  DAQP (a dense primal active-set method, through qpsolvers) and
    # this backend both end at it up to rounding, so the curves agree to 1e-11 relative.  PIQP
    # and Clarabel stop 6e-8 off at the third position (formulations/increment-qp.md sec. 3.5).
    setup = FlexureSetup(mode="bare", increments=5)
    exact = run_flexure(replace(setup, solver="active-set"))
    dense = run_flexure(replace(setup, solver="qpsolvers:daqp"))
    assert np.allclose(exact.force, dense.force, rtol=1e-11, atol=0.0)
    assert exact.Cf_star == pytest.approx(dense.Cf_star, rel=1e-11)


@pytest.mark.parametrize("seed", range(4))
def test_the_kkt_matrix_is_scipys_block_assembly_entry_for_entry(seed):
    # ``_KKT.matrix`` builds [[P, C_S'], [C_S, -delta I]] from triplets in ``sp.bmat``'s order
    # instead of calling it; ``_upper`` is ``sp.triu`` without its checks.  The factorisation sees
    # the same arrays either way, so the answers are the same to the bit: compared exactly here
    # (indptr, indices and data), on random sparse P and C with rows in any order, one row repeated.
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(5, 200)), int(rng.integers(1, 300))
    R = sp.random(n, n, density=0.05, random_state=seed, format="csc")
    P = sp.csc_matrix(R + R.T + sp.identity(n))
    C = sp.random(m, n, density=0.04, random_state=seed + 10, format="csr")
    S = rng.permutation(m)[: int(rng.integers(1, m + 1))]
    S = np.r_[S, S[:1]]
    kkt = active_set._KKT(P, C, 1e-3)
    ours = kkt.matrix(S)
    CS = C[S]
    ref = sp.bmat([[P, CS.T], [CS, -1e-3 * sp.identity(len(S))]], format="csc")
    for a, b in ((ours, ref), (active_set._upper(ours), sp.triu(ref, format="csc"))):
        assert np.array_equal(a.indptr, b.indptr)
        assert np.array_equal(a.indices, b.indices)
        assert np.array_equal(a.data, b.data)
