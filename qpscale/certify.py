"""The exact solution of one increment QP by an active-set method, and the check of F_c.

Implements formulations/increment-qp.md sec. 8.  An interior-point answer passes the absolute
residual test (7)-(9) of that file, but on a degenerate QP a row 1e-8 apart may still carry a
force of 1e-5 and pass ``z * s <= tau``, so the answer may be off by more than ``tau``.  Here the
QP is solved again by a method that ends on an active set and solves its equality system directly:
DAQP (a dense dual active-set method) on small QPs, the sparse proximal active-set solve of
:mod:`qpscale.active_set` on large ones (DAQP is O(N^3) time and O(N^2) memory), each the other's
fallback where it fails and the other is affordable.  The answer is *certified* by our own
residuals at round-off level: feasible, balanced, and complementary exactly (a force only on a
row in contact).  With ``P`` positive definite such a point is the unique minimiser, whatever the
method.  Its multipliers need not be unique (dependent rows); the check reports the range the
loading row's multiplier, the force F, takes over all of them, by two sparse linear programs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from .active_set import solve_sparse
from .errors import InvalidDesign, QpscaleError
from .qp import IncrementQP

# Certification at round-off: row violation (L), balance (force units, F* = O(1)), and the
# largest force a row farther than FEASIBLE_TOL from contact may carry.
FEASIBLE_TOL = 1e-11
STATIONARY_TOL = 1e-9
# DAQP's own tolerances, below the certification's (its defaults stop at 1e-6 violation).
DAQP_TOL = 1e-13
# Iterations without progress before DAQP declares cycling (its default 10 stopped degenerate
# plane-formulation QPs that 154 iterations solve; the iteration limit still bounds the work).
CYCLE_TOL = 1000
# HiGHS for the multiplier range: its presolve declared the (feasible: the method's multipliers
# satisfy it) degenerate system infeasible, and its default feasibility tolerance 1e-7 would widen the range.
LP_OPTIONS = {"presolve": False, "primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}
# Balance slack of the multiplier range's LPs (force units): at 1e-11 HiGHS stopped with an
# unknown status on a feasible set; 1e-10 widens the range by ~3e-10 (measured), far below FORCE_RTOL.
RANGE_SLACK = 1e-10
# Methods by size (N unknowns), measured on the corner-loaded squares' final QPs, the whole check
# (solve, certificate and the range's LPs, one thread; sec. 8): DAQP below SPARSE_FROM, where it is
# as fast (0.005 s against 0.007 s at N = 105; then 0.096 s against 0.018 s at N = 341, 2.8 s
# against 0.056 s at N = 1221), the sparse solve from there on.  Either one's failure is retried
# by the other: the sparse solve always, DAQP only up to DENSE_UP_TO unknowns (it holds ~24 N^2
# bytes and takes up to 1e-8 N^3 s: 54 MB and 34 s at N = 1500).
SPARSE_FROM = 200
DENSE_UP_TO = 1500
METHODS = ("auto", "dense", "sparse")
# Outer steps of the sparse solve from PIQP's answer before it starts again from zero (sec. 8).
WARM_OUTER = 100
# The force of a converged state and the exact one agree when within this fraction of |F|
# (the path's F_c is located to 1e-6, formulations/puncture.md sec. 3).
FORCE_RTOL = 1e-6


@dataclass(frozen=True)
class ExactSolution:
    """The exact answer to an :class:`~qpscale.qp.IncrementQP` and its certificate (sec. 8).

    Attributes
    ----------
    certified : bool
        Feasible to ``FEASIBLE_TOL``, balanced to ``STATIONARY_TOL``, forces only on rows in
        contact.  False: ``status`` says why (DAQP's exit flag, the sparse solve's iteration
        limit, or the residual that failed; both methods' reasons when both were tried).
    x, z, y : ndarray
        The minimiser and the method's multipliers in our sign convention (formulations eq. (2)).
    active : ndarray of int
        The inequality rows in contact at ``x``.
    residuals : dict
        ``primal``, ``dual``, ``complementarity`` (:meth:`IncrementQP.residuals`) and
        ``off_contact_force``, the largest force on a row farther than ``FEASIBLE_TOL``.
    y_range : ndarray (p, 2)
        Smallest and largest value of each equality multiplier asked for (``ranged``) over all
        balancing non-negative multipliers on ``active`` (one value when the rows are
        independent); NaN for the others.
    seconds : float
        Wall time of the solves and the range's LPs.
    method : str
        ``"dense"`` (DAQP) or ``"sparse"`` (:func:`qpscale.active_set.solve_sparse`): the one
        whose answer this is.
    """

    certified: bool
    status: str
    x: np.ndarray
    z: np.ndarray
    y: np.ndarray
    active: np.ndarray
    residuals: dict[str, float]
    y_range: np.ndarray
    seconds: float
    method: str = "dense"


def _multiplier_range(
    qp: IncrementQP, x: np.ndarray, rows: np.ndarray, slack: float, ranged: np.ndarray
) -> np.ndarray:
    """Range of the equality multipliers ``ranged`` over ``{z >= 0, y : |G_W'z + A'y + Px + q| <=
    slack}`` (NaN for the others), written ``G_W'z + A'y + e = -(Px + q)``, ``|e| <= slack``: sparse
    columns, one equality row per unknown."""
    G, _, A, _ = qp.rows()
    k, p, n = len(rows), qp.m_eq, qp.n
    M = sp.hstack([G[rows].T, A.T, sp.identity(n)], format="csc")
    r = -(qp.P @ x + qp.q)
    bounds = [(0.0, None)] * k + [(None, None)] * p + [(-slack, slack)] * n
    out = np.full((p, 2), np.nan)
    for j in ranged:
        for col, sign in ((0, 1.0), (1, -1.0)):
            c = np.zeros(k + p + n)
            c[k + j] = sign
            res = linprog(c, A_eq=M, b_eq=r, bounds=bounds, method="highs", options=LP_OPTIONS)
            if res.status == 0:
                out[j, col] = res.x[k + j]
    return out


def _solve_dense(qp: IncrementQP) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """DAQP's ``(x, z, y)`` and its failure (``""`` when its exit flag is positive)."""
    import daqp  # imported here: only the check uses it

    p, m = qp.m_eq, qp.m_ineq
    G, _, A, _ = qp.rows()
    M = np.vstack([A.toarray(), G.toarray()])
    upper = np.r_[qp.b, qp.h]
    lower = np.r_[qp.b, np.full(m, -1e30)]
    sense = np.r_[np.full(p, 5), np.zeros(m)].astype(np.intc)  # 5: an equality row, 0: an inequality
    x, _, flag, info = daqp.solve(
        qp.P.toarray(),
        qp.q,
        M,
        upper,
        lower,
        sense,
        primal_tol=DAQP_TOL,
        dual_tol=DAQP_TOL,
        iter_limit=100 * (qp.n + p + m),
        cycle_tol=CYCLE_TOL,
    )
    lam = np.asarray(info["lam"], dtype=float)
    # 1 optimal; other positive flags are judged by our residuals alone
    return np.asarray(x, dtype=float), lam[p:], lam[:p], "" if flag >= 1 else f"daqp exit flag {flag}"


def _solve_sparse(qp: IncrementQP) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """The sparse active-set solve's ``(x, z, y)`` and its failure (``""`` when it converged).

    Started from PIQP's answer at "high" accuracy, at the final delta: on the 13x13 QP PIQP takes
    0.10 s and the solve from its answer 0.03 s (7 Newton steps), against 0.66 s (176) from zero.
    Where PIQP finds no answer, or the solve from it does not converge in ``WARM_OUTER`` outer
    steps (the 17x17 QP: a slow direction that 1000 steps from PIQP's multipliers did not
    resolve, 149 from zero did), it starts from zero, with the soft first steps that make any
    start converge (sec. 8).
    """
    from .active_set import DELTA
    from .solvers import solve_qp

    try:
        guess = solve_qp(qp, "piqp", "high", check=False)
    except QpscaleError:  # PIQP missing or broken: the start from zero needs no guess
        guess = None
    if (
        guess is not None
        and guess.found
        and guess.x is not None
        and guess.z is not None
        and guess.y is not None
    ):
        s = solve_sparse(qp, guess.x, guess.z, guess.y, delta0=DELTA, max_outer=WARM_OUTER)
        if s.converged:
            return s.x, s.z, s.y, ""
    s = solve_sparse(qp)
    return s.x, s.z, s.y, "" if s.converged else f"sparse active set: {s.status}"


def _certify(
    qp: IncrementQP, x: np.ndarray, z: np.ndarray, y: np.ndarray, failure: str
) -> tuple[str, dict, np.ndarray]:
    """``(status, residuals, active)`` of a candidate by our residuals (sec. 8)."""
    G, h, _, _ = qp.rows()
    active = np.flatnonzero(h - G @ x <= FEASIBLE_TOL)
    residuals = qp.residuals(x, z, y)
    far = np.ones(qp.m_ineq, dtype=bool)
    far[active] = False
    residuals["off_contact_force"] = float(np.abs(z[far]).max(initial=0.0))
    if failure:
        status = failure
    elif residuals["primal"] > FEASIBLE_TOL:
        status = f"primal residual {residuals['primal']:.3g}"
    elif residuals["dual"] > STATIONARY_TOL:
        status = f"dual residual {residuals['dual']:.3g}"
    elif residuals["off_contact_force"] > STATIONARY_TOL:
        status = f"force {residuals['off_contact_force']:.3g} on a row not in contact"
    else:
        status = "certified"
    return status, residuals, active


def _methods(qp: IncrementQP, method: str) -> tuple[str, ...]:
    """The methods to try, in order (``SPARSE_FROM``, ``DENSE_UP_TO``)."""
    if method not in METHODS:
        raise InvalidDesign("method", method, "one of " + ", ".join(METHODS))
    if method != "auto":
        return (method,)
    if qp.n < SPARSE_FROM:
        return ("dense", "sparse")
    return ("sparse", "dense") if qp.n <= DENSE_UP_TO else ("sparse",)


def solve_exact(qp: IncrementQP, ranged: Sequence[int] | None = None, method: str = "auto") -> ExactSolution:
    """``qp`` solved by an active-set method and certified by our residuals (sec. 8).

    ``ranged``: the equality rows whose multiplier range is computed (two LPs each; default all).
    The check of F_c needs only the loading row's, not those of a held path's ~170 symmetry rows.
    ``method``: ``"dense"`` (DAQP), ``"sparse"`` (:func:`qpscale.active_set.solve_sparse`) or
    ``"auto"``: DAQP below ``SPARSE_FROM`` unknowns, else the sparse solve, and the other method
    when the first is not certified (DAQP only up to ``DENSE_UP_TO`` unknowns).

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> qp = IncrementQP(P=sp.identity(2, format="csc"), q=np.array([-1.0, 0.0]),
    ...                  G=sp.csc_matrix([[1.0, 0.0]]), h=np.array([0.5]),
    ...                  A=sp.csc_matrix([[0.0, 1.0]]), b=np.array([2.0]))
    >>> ex = solve_exact(qp)
    >>> ex.certified, ex.x.round(12).tolist(), ex.z.round(12).tolist(), ex.y.round(12).tolist()
    (True, [0.5, 2.0], [0.5], [-2.0])
    >>> solve_exact(qp, method="sparse").x.round(12).tolist()
    [0.5, 2.0]
    """
    t0 = time.perf_counter()
    reasons: list[str] = []
    for name in _methods(qp, method):
        x, z, y, failure = (_solve_dense if name == "dense" else _solve_sparse)(qp)
        status, residuals, active = _certify(qp, x, z, y, failure)
        if status == "certified":
            break
        reasons.append(f"{name}: {status}" if method == "auto" else status)
    p = qp.m_eq
    y_range = np.full((p, 2), np.nan)
    if status == "certified":
        slack_y = max(10.0 * residuals["dual"], RANGE_SLACK)
        rows_y = np.arange(p) if ranged is None else np.asarray(ranged, dtype=int)
        y_range = _multiplier_range(qp, x, active, slack_y, rows_y)
    else:
        status = "; ".join(reasons)
    return ExactSolution(
        status == "certified", status, x, z, y, active, residuals, y_range, time.perf_counter() - t0, name
    )


@dataclass(frozen=True)
class ForceCheck:
    """A converged state's force against the exact solution of the QP linearised at it.

    ``status``: ``verified`` (the state's F lies within ``FORCE_RTOL |F|`` of the exact range),
    ``disagrees`` (certified, and outside it: the state's force is wrong), or ``unverified``
    (no certificate; ``detail`` says why).  ``dq_exact`` is the largest DOF increment of the exact
    solution: a converged state is the QP's fixed point, so it is below the step tolerance.
    """

    status: str
    F: float
    F_exact: tuple[float, float]
    dq_exact: float
    active_rows: int
    seconds: float
    detail: str = ""

    def to_dict(self) -> dict[str, Any]:
        """The JSON object ``Fc_check`` of ``qpscale puncture --json`` (docs/cli.md)."""
        return {
            "status": self.status,
            "F": self.F,
            "F_exact": list(self.F_exact),
            "dq_exact": self.dq_exact,
            "active_rows": self.active_rows,
            "seconds": self.seconds,
            "detail": self.detail,
        }


def check_force(qp: IncrementQP, F: float, n_dof: int, method: str = "auto") -> ForceCheck:
    """Check the force ``F`` of a converged state against the exact solution of ``qp``, the
    increment QP linearised at that state (its loading row first, ``n_dof`` DOF unknowns first);
    ``method`` as in :func:`solve_exact`.  Without a certificate no exact number is reported:
    ``F_exact`` and ``dq_exact`` are NaN."""
    ex = solve_exact(qp, ranged=[0], method=method)
    lo, hi = (float(v) for v in ex.y_range[0])
    if not ex.certified:
        nan = float("nan")
        return ForceCheck("unverified", F, (nan, nan), nan, len(ex.active), ex.seconds, ex.status)
    dq = float(np.abs(ex.x[:n_dof]).max(initial=0.0))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        why = "multiplier range LP failed"
        return ForceCheck("unverified", F, (lo, hi), dq, len(ex.active), ex.seconds, why)
    tol = FORCE_RTOL * max(abs(F), 1e-12)
    verdict = "verified" if lo - tol <= F <= hi + tol else "disagrees"
    detail = f"exact F in [{lo:.12g}, {hi:.12g}] ({ex.method} active set), state's F {F:.12g}"
    return ForceCheck(verdict, F, (lo, hi), dq, len(ex.active), ex.seconds, detail)
