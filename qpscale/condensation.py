"""The increment QP on the rows that can act and the DOFs they touch: screened and condensed.

Implements formulations/increment.md sec. 2c.  The substrate's stiffness block of the increment
QP is the same along a path (``K``, or ``Zq' K Zq`` on a held path), so it is factored once
(:class:`ConstantBlock`) and every QP is solved in the unknowns that a row touches:

- **screening**: the contact rows of pairs whose gaps are all at least ``SCREEN_GAP`` stay out of
  the QP (their plane unknowns at zero, their multipliers zero) unless the answer brings one of
  them within ``SCREEN_GAP / 2`` of contact; then its pair joins and the QP is solved again, so the
  answer is the full QP's (every excluded row strictly inactive);
- **condensation**: the DOFs that no remaining row touches are eliminated exactly (a Schur
  complement through the columns of ``K^-1`` at the touched DOFs, ``S = (K^-1)_BB^-1``) and
  recovered from the answer (eq. (4c)).

The multipliers are those of the same rows; the residuals of the answer are measured on the full
QP, like every backend's.
"""

from __future__ import annotations

import time
import weakref
from dataclasses import replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from .level import Step, qp_step
from .qp import IncrementQP, IncrementResult, block_diagonal

# Contact rows whose gap is at least this (L) at the linearisation are screened out of the QP.
# The design gaps are 0.005 L by default: a pair enters once its gap has closed to a fifth of that.
SCREEN_GAP = 1e-3
# An excluded row whose slack after the step is below SCREEN_GAP * JOIN brings its pair into the QP.
JOIN = 0.5
# The touched DOFs are condensed only while they are at most this fraction of the block and at
# most CONDENSE_MAX: the condensed block is dense, and PIQP's sparse factorisation of a dense block
# grows fast with it (one solve with 300 rows: 15 ms at 100 DOFs, 30 ms at 200, 0.2 s at 400,
# 0.9 s at 800); past either the block stays whole and sparse (sec. 2c).
CONDENSE_FRACTION = 0.25
CONDENSE_MAX = 250
# Patches of at least this many scales are solved screened and condensed when the settings leave
# it to the size (``condense=None``): on the 5x5 patch the contact region is the whole patch at
# failure and the default path took 2.19 s against 2.11 s; from the 7x7 on it pays (sec. 2c).
AUTO_FROM = 49
# Kept condensations (one per touched DOF set) of one block: the sets of a level repeat.
KEEP = 4


class ConstantBlock:
    """The constant DOF block ``Kc`` of a path's increment QPs: its factor, the columns of its
    inverse computed so far, and the condensed blocks ``S_B = ((Kc^-1)_BB)^-1`` of the last sets.

    Built once per block object (:func:`constant_block`); every quantity is a function of ``Kc``
    and the DOF set alone, so the order in which a path asks for them changes no number.
    """

    def __init__(self, Kc: sp.csc_matrix) -> None:
        self.n = Kc.shape[0]
        self.K = sp.csc_matrix(Kc, copy=True)  # a copy: the block must not keep its key alive
        self._lu = splu(
            sp.csc_matrix(Kc),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        self._cols = np.zeros((self.n, 0))
        self._used = 0
        self._slot = np.full(self.n, -1, dtype=np.int64)
        self._condensed: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``Kc^-1 rhs``."""
        return self._lu.solve(np.asarray(rhs, dtype=float))

    def inverse_columns(self, dofs: np.ndarray) -> np.ndarray:
        """Columns ``Kc^-1 e_j`` for ``j`` in ``dofs``, ``(n, len(dofs))``; each is solved once."""
        new = dofs[self._slot[dofs] < 0]
        if new.size:
            E = np.zeros((self.n, new.size))
            E[new, np.arange(new.size)] = 1.0
            start = self._used
            if start + new.size > self._cols.shape[1]:  # room doubles: each column copied O(1) times
                grown = np.empty((self.n, max(2 * self._cols.shape[1], start + new.size)))
                grown[:, :start] = self._cols[:, :start]
                self._cols = grown
            self._cols[:, start : start + new.size] = self._lu.solve(E)
            self._slot[new] = start + np.arange(new.size)
            self._used = start + new.size
        return self._cols[:, self._slot[dofs]]

    def condensed(self, dofs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(S_B, H_B)``: the Schur complement of ``Kc`` on ``dofs`` (dense, symmetric positive
        definite) and the inverse's columns ``H_B = Kc^-1 E_B`` that lift a condensed answer."""
        key = dofs.tobytes()
        hit = self._condensed.get(key)
        if hit is not None:
            return hit
        H = self.inverse_columns(dofs)
        HBB = H[dofs]
        S = sla.cho_solve(sla.cho_factor(0.5 * (HBB + HBB.T)), np.eye(dofs.size))
        out = (0.5 * (S + S.T), H)
        if len(self._condensed) >= KEEP:
            self._condensed.pop(next(iter(self._condensed)))
        self._condensed[key] = out
        return out


# id(Kc) -> (a weak reference to Kc, its block): an entry goes with its matrix (sparse matrices
# are not hashable, so a WeakKeyDictionary cannot hold them).
_BLOCKS: dict[int, tuple[weakref.ref, ConstantBlock]] = {}


def constant_block(Kc: sp.csc_matrix) -> ConstantBlock:
    """The :class:`ConstantBlock` of ``Kc`` (the same object along a path), built on first use."""
    hit = _BLOCKS.get(id(Kc))
    if hit is not None and hit[0]() is Kc:
        return hit[1]
    block = ConstantBlock(Kc)
    key = id(Kc)
    _BLOCKS[key] = (weakref.ref(Kc), block)
    weakref.finalize(Kc, _BLOCKS.pop, key, None)
    return block


def screened_step(
    qp: IncrementQP,
    block: ConstantBlock,
    groups: np.ndarray,
    joined: set[int],
    solver: str,
    accuracy: str | float,
    tightened: bool,
    increment: int | None,
) -> tuple[IncrementResult | None, Step]:
    """``level.qp_step`` of the screened, condensed QP, its answer lifted to the full QP's.

    ``qp.P`` is ``blockdiag(Kc, P_e)``, ``Kc`` the block of ``block`` (the DOFs) and ``P_e`` the
    extra unknowns' (the separating planes), which only the rows touch.  ``groups`` gives each
    inequality row its pair: a pair's rows enter together.  ``joined`` holds the pairs that a
    step brought into the QP (the attempt's memory, updated here): they stay for its next QPs.
    The step counts one QP per round (``Step.work``): a round whose answer brought rows in is a
    QP solved like any other.
    """
    t0 = time.perf_counter()
    G, h, A, b = qp.rows()
    Gr = G.tocsr()
    Ar = A.tocsr()
    rounds, seconds = 0, 0.0
    near = np.unique(groups[h < SCREEN_GAP])
    while True:
        rows = np.isin(groups, np.union1d(near, np.fromiter(joined, dtype=groups.dtype, count=len(joined))))
        reduced, lift = _condensed_qp(qp, block, Gr, Ar, rows)
        build = time.perf_counter() - t0
        res, step = qp_step(reduced, solver, accuracy, tightened, increment)
        seconds += build + step.seconds
        rounds += 1
        if res is None:
            return None, replace(step, seconds=seconds, work=rounds)
        t0 = time.perf_counter()
        x = lift(np.asarray(res.x))
        slack = h - Gr @ x
        join = ~rows & (slack < JOIN * SCREEN_GAP)
        if not join.any():
            break
        joined.update(np.unique(groups[join]).tolist())
    z = np.zeros(h.size)
    z[rows] = np.asarray(res.z)
    y = np.asarray(res.y)
    full = IncrementResult(
        x,
        z,
        y,
        True,
        res.status,
        qp.objective(x),
        qp.residuals(x, z, y),
        res.build_s + time.perf_counter() - t0,
        res.solve_s,
        res.iterations,
        {**res.extras, "condensed": (int(lift.dofs), int(rows.sum()), rounds)},
    )
    return full, replace(step, seconds=seconds + time.perf_counter() - t0, work=rounds)


class _Lift:
    """The full unknowns of a condensed answer (eq. (4c)): ``x = x* + H_B S_B (x_B - x*_B)`` on
    the DOFs, the kept extra unknowns as solved, the others zero."""

    def __init__(
        self,
        n: int,
        xstar: np.ndarray | None,
        B: np.ndarray,
        extra: np.ndarray,
        S: np.ndarray | None = None,
        H: np.ndarray | None = None,
    ):
        self.n, self.xstar, self.B, self.S, self.H, self.extra = n, xstar, B, S, H, extra
        self.dofs = B.size

    def __call__(self, xr: np.ndarray) -> np.ndarray:
        x = np.zeros(self.n)
        nb = self.B.size
        if self.S is None or self.H is None or self.xstar is None:  # every DOF kept
            x[:nb] = xr[:nb]
        else:
            x[: self.xstar.size] = self.xstar + self.H @ (self.S @ (xr[:nb] - self.xstar[self.B]))
        x[self.extra] = xr[nb:]
        return x


def _condensed_qp(
    qp: IncrementQP,
    block: ConstantBlock,
    Gr: sp.csr_matrix,
    Ar: sp.csr_matrix,
    rows: np.ndarray,
) -> tuple[IncrementQP, _Lift]:
    """The QP on the inequality ``rows`` in the DOFs they (or the equalities) touch and the extra
    unknowns they touch (with those coupled to them through ``P_e``), eqs. (4c)."""
    nq = block.n
    GR = Gr[rows]
    touched = np.union1d(GR.indices, Ar.indices)
    B = touched[touched < nq]
    extra = _closure(qp.P, touched[touched >= nq], nq)
    Pe = qp.P[extra][:, extra]
    if B.size > min(CONDENSE_FRACTION * nq, CONDENSE_MAX):
        B = np.arange(nq)
        S = H = xstar = None
        P = block_diagonal(block.K, Pe)
        q = np.concatenate([qp.q[:nq], qp.q[extra]])
    else:
        # the unconstrained minimiser x* = -Kc^-1 c: only a condensed QP needs it
        xstar = -block.solve(qp.q[:nq])
        S, H = block.condensed(B)
        P = block_diagonal(sp.csc_matrix(S), Pe)
        q = np.concatenate([-S @ xstar[B], qp.q[extra]])
    keep = np.concatenate([B, extra])
    reduced = IncrementQP.assembled(
        P,
        q,
        GR[:, keep].tocsc(),
        qp.rows()[1][rows],
        Ar[:, keep].tocsc(),
        qp.rows()[3],
        tuple(qp.row_labels_A or ("load",)),
    )
    return reduced, _Lift(qp.n, xstar, B, extra, S, H)


def _closure(P: sp.csc_matrix, extra: np.ndarray, nq: int) -> np.ndarray:
    """The extra unknowns ``extra`` with every one coupled to them through ``P`` (a held path's
    plane orbits couple their unknowns; a free path's plane block is diagonal)."""
    keep = np.zeros(P.shape[0], dtype=bool)
    keep[extra] = True
    while True:
        cols = np.flatnonzero(keep)
        coupled = np.unique(P[:, cols].indices)
        coupled = coupled[coupled >= nq]
        if keep[coupled].all():
            return cols
        keep[coupled] = True
