"""The package's own exact QP method as a backend: formulations/increment-qp.md sec. 3.5 and 8.

``active_set.solve_sparse``: the proximal method of multipliers whose inner problems are minimised
exactly by semismooth Newton steps, asked to stop at a point stationary, feasible and
complementary to a tenth of the target (``stationary=True``), with no interior-point tolerance
left in the unknowns.  Its KKT systems are solved in the contact space when ``P`` is a large dense
block beside a diagonal (the flexure QP), else by a sparse LDL'.  A start of the QP's shape (an
earlier answer, or a ``qp.WarmStart`` carried to the QP's rows by their labels) is used at the
final delta from its multipliers, its rows carrying force the first working set; one that does
not converge in ``WARM_OUTER`` outer steps is dropped for the start from zero, whose soft first
steps converge from anywhere (sec. 8, "Start").
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .. import active_set
from ..qp import IncrementQP, IncrementResult, candidate_result

#: Outer steps allowed from a warm start before the start from zero.  From a good start 2-9 do
#: (flexure QPs, carried by row key); a start that needs more is poor, and its failed attempt cost
#: more than the start from zero (at 100, 0.5-0.9 s per QP on a slanted triangle array).
WARM_OUTER = 20


def _warm(qp: IncrementQP, warm_start: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(x, z, y)`` of a start (an ``IncrementResult`` or a ``WarmStart``) that fits ``qp``'s
    shape, else None."""
    x, z, y = (getattr(warm_start, name, None) for name in ("x", "z", "y"))
    if x is None or z is None or y is None:
        return None
    if x.shape != (qp.n,) or z.shape != (qp.m_ineq,) or y.shape != (qp.m_eq,):
        return None
    return x, z, y


def solve(qp: IncrementQP, options: dict[str, Any], warm_start: Any = None) -> IncrementResult:
    """Solve ``qp`` by ``active_set.solve_sparse``, stopping only at a point stationary to
    ``options["tol"]`` (its stopping tolerance, also on violation and open contact); ``warm_start``
    a previous answer or a ``WarmStart`` (used when its shape fits)."""
    tol = float(options.get("tol", active_set.STOP_TOL))
    t0 = time.perf_counter()
    start = _warm(qp, warm_start)
    s = None
    if start is not None:
        x, z, y = start
        s = active_set.solve_sparse(
            qp,
            x,
            z,
            y,
            working=np.flatnonzero(z > 0),
            delta0=active_set.DELTA,
            tol=tol,
            max_outer=WARM_OUTER,
            stationary=True,
        )
        if not s.converged:
            s = None
    warm_used = s is not None
    if s is None:
        s = active_set.solve_sparse(qp, tol=tol, stationary=True)
    t1 = time.perf_counter()
    return candidate_result(
        qp,
        s.x,
        s.z,
        s.y,
        status=s.status,
        ok=s.converged,
        build_s=0.0,
        solve_s=t1 - t0,
        iterations=s.newton,
        extras={"warm_start_used": warm_used, "outer": s.outer, "factorisations": s.factorisations},
    )
