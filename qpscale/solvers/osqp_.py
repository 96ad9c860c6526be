"""OSQP backend, called directly: formulations/increment-qp.md section 3.2.

The QP goes in as ``l <= [A; G] x <= u`` with ``l = [b; -inf]``, ``u = [b; h]``.  OSQP's
multiplier ``y`` satisfies ``Px + q + M'y = 0`` and is positive on an active upper bound, which is
our sign: its first p entries are our ``y``, the rest our ``z`` (eq. 12).  ADMM answers are only
approximately complementary; polishing (on by default) solves the guessed active set exactly and
our residual check decides whether the answer is accurate enough.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp

from ..errors import SolverFailure
from ..qp import IncrementQP, IncrementResult, candidate_result

#: OSQP status words taken as success; "solved inaccurate" passes only through our residual check.
OK_STATUS = ("solved", "solved inaccurate")


def build(qp: IncrementQP, options: dict[str, Any]) -> osqp.OSQP:
    """Set up the OSQP solver object with the upper triangle of P and the stacked rows."""
    M = sp.vstack([qp.A, qp.G], format="csc")
    lower = np.concatenate([qp.b, np.full(qp.m_ineq, -np.inf)])
    upper = np.concatenate([qp.b, qp.h])
    solver = osqp.OSQP()
    solver.setup(sp.triu(qp.P, format="csc"), qp.q, M, lower, upper, verbose=False, **options)
    return solver


def _warm(solver: osqp.OSQP, qp: IncrementQP, warm_start: Any) -> bool:
    """Warm-start from an IncrementResult (x and multipliers) or a bare x array."""
    if warm_start is None:
        return False
    x = getattr(warm_start, "x", warm_start)
    if x is None:
        return False
    z, y = getattr(warm_start, "z", None), getattr(warm_start, "y", None)
    if z is not None and y is not None and z.size == qp.m_ineq and y.size == qp.m_eq:
        solver.warm_start(x=np.asarray(x, dtype=float), y=np.concatenate([y, z]))
    else:
        solver.warm_start(x=np.asarray(x, dtype=float))
    return True


def solve(qp: IncrementQP, options: dict[str, Any], warm_start: Any = None) -> IncrementResult:
    """Solve ``qp`` with OSQP (``options["polishing"]=False`` turns polishing off)."""
    t0 = time.perf_counter()
    try:
        solver = build(qp, options)
        used = _warm(solver, qp, warm_start)
        t1 = time.perf_counter()
        res = solver.solve(raise_error=False)
    except Exception as exc:  # OSQP raises ValueError on bad data or settings
        raise SolverFailure("osqp", "exception", detail=str(exc)) from exc
    t2 = time.perf_counter()
    info = res.info
    status = str(info.status)
    ok = status in OK_STATUS
    yy = np.asarray(res.y, dtype=float) if ok else None
    extras = {
        "status_polish": int(info.status_polish),
        "warm_start_used": used,
        "solve_time_internal": float(info.solve_time),
        "setup_time_internal": float(info.setup_time),
    }
    return candidate_result(
        qp,
        np.asarray(res.x, dtype=float) if ok else None,
        None if yy is None else yy[qp.m_eq :],
        None if yy is None else yy[: qp.m_eq],
        status=status,
        ok=ok,
        build_s=t1 - t0,
        solve_s=t2 - t1,
        iterations=int(info.iter),
        extras=extras,
    )
