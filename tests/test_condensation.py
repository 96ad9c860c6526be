"""The screened, condensed increment QP (qpscale/condensation.py, formulations/increment.md sec. 2c)
against the full QP it stands for."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from qpscale import condensation
from qpscale.certify import solve_exact
from qpscale.condensation import SCREEN_GAP, ConstantBlock, constant_block, screened_step
from qpscale.qp import IncrementQP

from .test_solvers import _stored_qp


@pytest.fixture(scope="module")
def default_final():
    """The increment QP at the default scene's failure state (5x5 squares: 125 DOFs, 72 planes,
    492 contact rows) and its DOF block K, the object a path would factor."""
    from pathlib import Path

    d = np.load(Path(__file__).parent / "data" / "default_final_qp.npz")
    qp = _stored_qp("default_final_qp.npz")
    n_dof = int(d["n_dof"][0])
    return qp, sp.csc_matrix(qp.P[:n_dof, :n_dof])


def _pushed(qp: IncrementQP, depth: float) -> IncrementQP:
    """The same QP with the load point pushed ``depth`` further: a step that closes gaps which
    the screened QP leaves out at first."""
    G, h, A, b = qp.rows()
    return IncrementQP.assembled(qp.P, qp.q, G, h, A, b - depth, ("load",))


def test_the_condensed_block_is_the_schur_complement():
    # S_B = ((K^-1)_BB)^-1 against K_BB - K_BI K_II^-1 K_IB formed densely: two formulas of the
    # same matrix (cond(K) ~ 10 here, so 1e-12 relative is round-off).
    rng = np.random.default_rng(3)
    M = rng.standard_normal((30, 30))
    K = sp.csc_matrix(M @ M.T + 30 * np.eye(30))
    B = np.array([2, 5, 6, 17, 29])
    I = np.setdiff1d(np.arange(30), B)
    Kd = K.toarray()
    schur = Kd[np.ix_(B, B)] - Kd[np.ix_(B, I)] @ np.linalg.solve(Kd[np.ix_(I, I)], Kd[np.ix_(I, B)])
    S, H = ConstantBlock(K).condensed(B)
    assert np.allclose(S, schur, rtol=0, atol=1e-12 * np.abs(schur).max())
    assert np.allclose(Kd @ H, np.eye(30)[:, B], atol=1e-12)


def test_a_block_is_built_once_per_matrix_and_goes_with_it():
    K = sp.identity(4, format="csc")
    assert constant_block(K) is constant_block(K)
    key = id(K)
    del K
    assert key not in condensation._BLOCKS


@pytest.mark.parametrize("depth", [0.0, 0.2])
def test_the_screened_answer_is_the_full_qps(default_final, depth):
    # The same QP solved whole and screened (each row its own group).  At depth 0 (the state's
    # own QP, x ~ 1e-10) every row farther than SCREEN_GAP stays out; pushed 0.2 L deeper, the
    # step closes gaps and rows must join.  x is unique (P > 0); the reference is the exact
    # active-set solution (certified at round-off, increment-qp.md sec. 8).  PIQP's answers to the
    # default path's QPs lie within 1.1e-8 of exact ones in dq (sec. 3.2a: the planes' weight of
    # 1e-6 turns a 1e-9 residual into 1e-8 in dq), so both answers must be within 5e-8 of it, and
    # the load's multiplier (F, a range 3e-10 wide at this state) within 1e-7 relative.
    qp, K = default_final
    qp = _pushed(qp, depth)
    full = solve_exact(qp, ranged=[0])
    assert full.certified
    G, h, _, _ = qp.rows()
    joined: set[int] = set()
    res, step = screened_step(qp, ConstantBlock(K), np.arange(h.size), joined, "piqp", "high", False, None)
    assert res is not None and res.found
    assert max(res.residuals.values()) <= 1e-9, res.residuals
    dofs, rows, rounds = res.extras["condensed"]
    assert rows < h.size
    assert np.max(np.abs(res.x[: K.shape[0]] - full.x[: K.shape[0]])) <= 5e-8
    assert abs(res.y[0] - full.y[0]) <= 1e-7 * abs(full.y[0])
    if depth:
        assert rounds >= 2 and joined, "the deeper step must bring rows into the QP"
        assert np.all(h[list(joined)] >= SCREEN_GAP)
    else:
        assert rounds == 1 and not joined


def test_a_small_contact_region_is_condensed(default_final):
    # Only the rows of one scale's pairs: the DOFs they touch are a fraction of the patch, and
    # the condensed QP (dense S_B on those DOFs) gives the full QP's answer on those rows.
    qp, K = default_final
    G, h, A, b = qp.rows()
    loaded = np.unique(A.tocsr().indices)
    Gr = G.tocsr()
    near = np.unique(Gr[:, loaded].tocoo().row)
    sub = IncrementQP.assembled(
        qp.P, qp.q, Gr[near].tocsc(), np.minimum(h[near], 0.0), A, b - 0.02, ("load",)
    )
    full = solve_exact(sub, ranged=[0])
    assert full.certified
    res, _ = screened_step(sub, ConstantBlock(K), np.arange(near.size), set(), "piqp", "high", False, None)
    dofs = res.extras["condensed"][0]
    assert dofs <= condensation.CONDENSE_FRACTION * K.shape[0]
    assert np.max(np.abs(res.x[: K.shape[0]] - full.x[: K.shape[0]])) <= 5e-8
    assert abs(res.y[0] - full.y[0]) <= 1e-7 * abs(full.y[0])
    assert max(res.residuals.values()) <= 1e-9


@pytest.mark.parametrize("shape, fraction", [("square", 1.0), ("hexagon", condensation.CONDENSE_FRACTION)])
def test_a_condensed_path_ends_at_the_same_Fc(shape, fraction, monkeypatch):
    # The corner-loaded 3x3 path (a held symmetric branch, then the free one) solved with every QP
    # whole and every QP screened and condensed: the same QPs, so the same F_c* up to the
    # accuracy F_c is located to (1e-6 relative, puncture.md sec. 3), and both verified by the
    # exact check.  On the square every touched DOF set is condensed (fraction 1: the dense S_B
    # and the lift, on held and free QPs); the hexagon's honeycomb, at the default fraction,
    # condenses only its first QPs (the load row alone) and then keeps its DOFs whole.
    from qpscale.experiments.puncture import PunctureSetup, run_puncture
    from qpscale.increment import SQPSettings
    from qpscale.tiling import Design

    monkeypatch.setattr(condensation, "CONDENSE_FRACTION", fraction)
    built = []
    condensed_block = ConstantBlock.condensed
    monkeypatch.setattr(
        ConstantBlock, "condensed", lambda self, B: built.append(B.size) or condensed_block(self, B)
    )
    runs = [
        run_puncture(PunctureSetup(design=Design(shape=shape, rings=1), sqp=SQPSettings(condense=c)))
        for c in (False, True)
    ]
    whole, condensed = (r.Fc_star for r in runs)
    assert abs(condensed - whole) <= 1e-6 * whole
    assert all(r.Fc_check is not None and r.Fc_check.status == "verified" for r in runs)
    assert built and (fraction < 1.0 or max(built) > 20), sorted(set(built))


def test_condense_is_refused_with_the_penalty_baseline_and_checked():
    from qpscale.api import puncture
    from qpscale.errors import InvalidDesign

    with pytest.raises(InvalidDesign, match="condense"):
        puncture(rings=1, solver="penalty", condense="on")
    with pytest.raises(InvalidDesign, match="auto, on, off"):
        puncture(rings=1, condense="yes")
