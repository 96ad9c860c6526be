"""Clarabel backend, called directly: formulations/increment-qp.md section 3.1.

The QP goes in as ``min 1/2 x'Px + q'x  s.t.  [A; G] x + s = [b; h],  s in {0}^p x R_+^m``.
Clarabel's Lagrangian ``... + z'([A; G]x - [b; h])`` has our sign, so its ``z`` splits into our
``y`` (first p entries) and ``z`` (the rest) unchanged (eq. 11).
"""

from __future__ import annotations

import time
from typing import Any

import clarabel
import numpy as np
import scipy.sparse as sp

from ..errors import SolverFailure
from ..qp import IncrementQP, IncrementResult, candidate_result

#: Clarabel status words we take as success; AlmostSolved is accepted only through our residual check.
OK_STATUS = ("Solved", "AlmostSolved")


def build(qp: IncrementQP, options: dict[str, Any]) -> clarabel.DefaultSolver:
    """Build the Clarabel solver object (upper triangle of P, Zero cone then Nonnegative cone)."""
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    for key, value in options.items():
        setattr(settings, key, value)
    M = sp.vstack([qp.A, qp.G], format="csc")
    rhs = np.concatenate([qp.b, qp.h])
    cones = []
    if qp.m_eq:
        cones.append(clarabel.ZeroConeT(qp.m_eq))
    if qp.m_ineq:
        cones.append(clarabel.NonnegativeConeT(qp.m_ineq))
    return clarabel.DefaultSolver(sp.triu(qp.P, format="csc"), qp.q, M, rhs, cones, settings)


def solve(qp: IncrementQP, options: dict[str, Any], warm_start: Any = None) -> IncrementResult:
    """Solve ``qp`` with Clarabel; ``warm_start`` is ignored (interior point, no warm start)."""
    t0 = time.perf_counter()
    try:
        solver = build(qp, options)
        t1 = time.perf_counter()
        sol = solver.solve()
    except Exception as exc:  # Clarabel raises plain exceptions on bad data or settings
        raise SolverFailure("clarabel", "exception", detail=str(exc)) from exc
    t2 = time.perf_counter()
    status = str(sol.status)
    zz = np.asarray(sol.z, dtype=float)
    ok = status in OK_STATUS
    x = np.asarray(sol.x, dtype=float) if ok else None
    extras = {"solve_time_internal": float(sol.solve_time), "warm_start_used": False}
    return candidate_result(
        qp,
        x,
        zz[qp.m_eq :],
        zz[: qp.m_eq],
        status=status,
        ok=ok,
        build_s=t1 - t0,
        solve_s=t2 - t1,
        iterations=int(sol.iterations),
        extras=extras,
    )
