"""PIQP backend, called directly: formulations/increment-qp.md section 3.2a.

PIQP (a proximal interior-point method) takes ``min 1/2 x'Px + c'x  s.t.  Ax = b,
h_l <= Gx <= h_u``; our rows have no lower bound.  Its Lagrangian adds ``y'(Ax - b)`` and
``z_u'(Gx - h_u) - z_l'(Gx - h_l)``, so our ``y`` is its ``y`` and our ``z`` its ``z_u - z_l``
(``z_l`` is zero without lower bounds), eq. (11a).  The proximal terms regularise the KKT system
without changing the problem, which is what the plane formulation's dependent active rows need.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import piqp

from ..errors import SolverFailure
from ..qp import IncrementQP, IncrementResult, candidate_result

#: PIQP's status of a solved problem.
OK_STATUS = ("Status.PIQP_SOLVED", "PIQP_SOLVED")
#: PIQP stopped at its iteration limit: its last point is handed to our residual check, which
#: decides (formulations/increment-qp.md table 1).  On the hinged planes of slanted arrays PIQP
#: stagnates just above its own target (a tenth of ours): 59 of 72 such points of a 5x5 dart
#: path passed our check at 1e-9, and rejecting them by status failed whole levels.
LIMIT_STATUS = ("Status.PIQP_MAX_ITER_REACHED", "PIQP_MAX_ITER_REACHED")


def build(qp: IncrementQP, options: dict[str, Any]) -> Any:
    """Set up PIQP's sparse solver on ``qp`` (full P, A and G in CSC, no lower bounds)."""
    G, h, A, b = qp.rows()
    solver = piqp.SparseSolver()
    solver.settings.verbose = False
    for key, value in options.items():
        setattr(solver.settings, key, value)
    solver.setup(
        qp.P,
        qp.q,
        A if qp.m_eq else None,
        b if qp.m_eq else None,
        G if qp.m_ineq else None,
        None,
        h if qp.m_ineq else None,
    )
    return solver


def solve(qp: IncrementQP, options: dict[str, Any], warm_start: Any = None) -> IncrementResult:
    """Solve ``qp`` with PIQP; ``warm_start`` is ignored (interior point, no warm start)."""
    t0 = time.perf_counter()
    try:
        solver = build(qp, options)
        t1 = time.perf_counter()
        status = str(solver.solve())
    except Exception as exc:  # PIQP raises plain exceptions on bad data or settings
        raise SolverFailure("piqp", "exception", detail=str(exc)) from exc
    t2 = time.perf_counter()
    res = solver.result
    limit = status in LIMIT_STATUS
    ok = status in OK_STATUS or limit
    x = np.asarray(res.x, dtype=float) if ok else None
    z = np.asarray(res.z_u, dtype=float) - np.asarray(res.z_l, dtype=float) if qp.m_ineq else np.zeros(0)
    y = np.asarray(res.y, dtype=float) if qp.m_eq else np.zeros(0)
    return candidate_result(
        qp,
        x,
        z,
        y,
        status=status.removeprefix("Status."),
        ok=ok,
        build_s=t1 - t0,
        solve_s=t2 - t1,
        iterations=int(res.info.iter),
        extras={"warm_start_used": False, "stopped_at_limit": limit},
    )
