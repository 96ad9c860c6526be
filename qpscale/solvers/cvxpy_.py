"""The same QP written in CVXPY, the readable reference: formulations/increment-qp.md section 3.4.

``minimize 1/2 x'Px + q'x  s.t.  G x <= h,  A x == b`` with CLARABEL underneath by default.
The dual value of ``G x <= h`` is our ``z`` (non-negative); the dual value of ``A x == b`` is our
``y`` (eq. 14; both checked by the tests).  ``build_s`` covers building the expression tree,
``solve_s`` the whole ``Problem.solve`` call (canonicalisation + solver), so CVXPY's overhead
against the direct backends is visible; the solver's own time is in ``extras``.
"""

from __future__ import annotations

import time
from typing import Any

import cvxpy as cp
import numpy as np

from ..errors import SolverFailure
from ..qp import IncrementQP, IncrementResult, candidate_result

#: CVXPY status words taken as success; optimal_inaccurate passes only through our residual check.
OK_STATUS = (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)


def build(qp: IncrementQP) -> tuple[cp.Problem, cp.Variable, list[cp.Constraint]]:
    """The CVXPY problem, its variable and its constraints ``[G x <= h, A x == b]`` (each if present)."""
    x = cp.Variable(qp.n)
    objective = 0.5 * cp.quad_form(x, cp.psd_wrap(qp.P)) + qp.q @ x
    cons = []
    if qp.m_ineq:
        cons.append(qp.G @ x <= qp.h)
    if qp.m_eq:
        cons.append(qp.A @ x == qp.b)
    return cp.Problem(cp.Minimize(objective), cons), x, cons


def _duals(qp: IncrementQP, cons: list[cp.Constraint]) -> tuple[Any, Any]:
    it = iter(cons)
    z = next(it).dual_value if qp.m_ineq else np.zeros(0)
    y = next(it).dual_value if qp.m_eq else np.zeros(0)
    return z, y


def solve(
    qp: IncrementQP, options: dict[str, Any], warm_start: Any = None, cvxpy_solver: str = "CLARABEL"
) -> IncrementResult:
    """Solve ``qp`` through CVXPY with ``cvxpy_solver``; ``options`` go to that solver."""
    t0 = time.perf_counter()
    try:
        problem, x, cons = build(qp)
        t1 = time.perf_counter()
        problem.solve(solver=cvxpy_solver, **options)
    except cp.error.SolverError as exc:
        raise SolverFailure("cvxpy", "SolverError", detail=str(exc)) from exc
    except Exception as exc:  # CVXPY wraps most errors, but not all
        raise SolverFailure("cvxpy", "exception", detail=f"{type(exc).__name__}: {exc}") from exc
    t2 = time.perf_counter()
    status = str(problem.status)
    ok = status in OK_STATUS
    z, y = _duals(qp, cons) if ok else (None, None)
    stats = problem.solver_stats
    extras = {
        "cvxpy_solver": cvxpy_solver,
        "warm_start_used": False,
        "solve_time_internal": getattr(stats, "solve_time", None),
    }
    return candidate_result(
        qp,
        x.value if ok else None,
        z,
        y,
        status=status,
        ok=ok,
        build_s=t1 - t0,
        solve_s=t2 - t1,
        iterations=getattr(stats, "num_iters", None),
        extras=extras,
    )
