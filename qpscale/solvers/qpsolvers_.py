"""Backends through qpsolvers.solve_problem: formulations/increment-qp.md section 3.3.

qpsolvers states the same Lagrangian as ours, ``1/2 x'Px + q'x + z'(Gx - h) + y'(Ax - b)``, so its
``Solution.z`` and ``Solution.y`` are used unchanged (eq. 13); the tests check the sign anyway.
qpsolvers has no status word of its own, so ``status`` is ``"found"`` or ``"not found"`` and the
solver's own extras (when any) are kept in ``extras``.
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np
import qpsolvers

from ..errors import SolverFailure
from ..qp import IncrementQP, IncrementResult, candidate_result


def installed() -> list[str]:
    """Names of the solvers qpsolvers reports installed."""
    return list(qpsolvers.available_solvers)


def build(qp: IncrementQP, name: str) -> qpsolvers.Problem:
    """The qpsolvers Problem; empty G or A are passed as None, matrices dense for dense-only solvers."""
    dense = name not in qpsolvers.sparse_solvers

    def mat(M: Any) -> Any:
        return M.toarray() if dense else M

    G, h = (mat(qp.G), qp.h) if qp.m_ineq else (None, None)
    A, b = (mat(qp.A), qp.b) if qp.m_eq else (None, None)
    return qpsolvers.Problem(mat(qp.P), qp.q, G, h, A, b)


def _vec(v: Any, size: int) -> np.ndarray | None:
    if size == 0:
        return np.zeros(0)
    return None if v is None else np.asarray(v, dtype=float).reshape(-1)


def solve(qp: IncrementQP, name: str, options: dict[str, Any], warm_start: Any = None) -> IncrementResult:
    """Solve ``qp`` with the qpsolvers solver ``name``; ``warm_start`` gives ``initvals``."""
    key = f"qpsolvers:{name}"
    x0 = getattr(warm_start, "x", warm_start)
    t0 = time.perf_counter()
    try:
        problem = build(qp, name)
        t1 = time.perf_counter()
        with warnings.catch_warnings():
            # dense-only solvers convert P, G, A and warn; that cost is part of what we time
            warnings.simplefilter("ignore")
            sol = qpsolvers.solve_problem(problem, solver=name, initvals=x0, verbose=False, **options)
    except Exception as exc:  # qpsolvers and the solvers under it raise many types
        raise SolverFailure(key, "exception", detail=f"{type(exc).__name__}: {exc}") from exc
    t2 = time.perf_counter()
    ok = bool(sol.found)
    extras = {"warm_start_used": x0 is not None, "solver_extras": dict(getattr(sol, "extras", {}) or {})}
    x = None if not ok or sol.x is None else np.asarray(sol.x, dtype=float)
    return candidate_result(
        qp,
        x,
        _vec(sol.z, qp.m_ineq),
        _vec(sol.y, qp.m_eq),
        status="found" if ok else "not found",
        ok=ok,
        build_s=t1 - t0,
        solve_s=t2 - t1,
        extras=extras,
    )
