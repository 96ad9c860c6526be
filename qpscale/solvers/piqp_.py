"""PIQP backend, called directly: formulations/increment-qp.md section 3.2a.

PIQP (a proximal interior-point method) takes ``min 1/2 x'Px + c'x  s.t.  Ax = b,
h_l <= Gx <= h_u``; our rows have no lower bound.  Its Lagrangian adds ``y'(Ax - b)`` and
``z_u'(Gx - h_u) - z_l'(Gx - h_l)``, so our ``y`` is its ``y`` and our ``z`` its ``z_u - z_l``
(``z_l`` is zero without lower bounds), eq. (11a).  The proximal terms regularise the KKT system
without changing the problem, which is what the plane formulation's dependent active rows need.

A QP whose ``P`` is at least ``DENSE_FROM`` full (flexure's condensed membrane) goes to PIQP's
dense solver, with its rows on a single unknown given as bounds on that unknown
(formulations/increment-qp.md sec. 3.2a, "Dense QPs").
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import numpy as np
import piqp
import scipy.sparse as sp

from ..errors import SolverFailure
from ..qp import IncrementQP, IncrementResult, candidate_result

#: Fill of P (nonzeros / n^2) from which PIQP's dense solver is used.  Measured on captured flexure
#: QPs (one BLAS thread, same settings and iterations): the square staggered array along y (fill
#: 0.71, 965 unknowns) 3.0x faster, the trapezoid array along x (0.66) 2.1x, the slanted triangle
#: array (0.28) 2.4x slower; puncture QPs are at most 0.04 full.
DENSE_FROM = 0.5

#: PIQP's status of a solved problem.
OK_STATUS = ("Status.PIQP_SOLVED", "PIQP_SOLVED")
#: PIQP stopped at its iteration limit: its last point is handed to our residual check, which
#: decides (formulations/increment-qp.md table 1).  On the hinged planes of slanted arrays PIQP
#: stagnates just above its own target (a tenth of ours): 59 of 72 such points of a 5x5 dart
#: path passed our check at 1e-9, and rejecting them by status failed whole levels.
LIMIT_STATUS = ("Status.PIQP_MAX_ITER_REACHED", "PIQP_MAX_ITER_REACHED")


def _bounds(G: sp.csr_matrix, h: np.ndarray, n: int) -> tuple[np.ndarray, ...]:
    """The rows of ``G x <= h`` on a single unknown, as bounds: ``(rows, unknowns, v, x_l, x_u)``.

    Row ``i`` with its one entry ``v`` on unknown ``j`` is ``x_j <= h_i / v`` (v > 0) or
    ``x_j >= h_i / v`` (v < 0); only the first such row of each unknown and side becomes a bound,
    the others stay rows.
    """
    one = np.flatnonzero(np.diff(G.indptr) == 1)
    col, v = G.indices[G.indptr[one]], G.data[G.indptr[one]]
    one, col, v = one[v != 0], col[v != 0], v[v != 0]
    _, first = np.unique(col * 2 + (v > 0), return_index=True)
    rows, col, v = one[first], col[first], v[first]
    x_l, x_u = np.full(n, -np.inf), np.full(n, np.inf)
    up = v > 0
    x_u[col[up]] = h[rows[up]] / v[up]
    x_l[col[~up]] = h[rows[~up]] / v[~up]
    return rows, col, v, x_l, x_u


class _Layout(NamedTuple):
    """Where our rows went: ``keep`` to PIQP's G, ``rows`` to bounds on the unknowns ``col`` with
    their entries ``v`` (eq. (11b))."""

    keep: np.ndarray
    rows: np.ndarray
    col: np.ndarray
    v: np.ndarray


def build(qp: IncrementQP, options: dict[str, Any]) -> tuple[Any, _Layout]:
    """Set up PIQP on ``qp``: its sparse solver (full P, A and G in CSC, no lower bounds), or its
    dense solver when ``P`` is at least ``DENSE_FROM`` full, with single-unknown rows as bounds.

    Returns the solver and where the rows went.
    """
    G, h, A, b = qp.rows()
    dense = qp.n > 0 and qp.P.nnz >= DENSE_FROM * qp.n**2
    solver = piqp.DenseSolver() if dense else piqp.SparseSolver()
    solver.settings.verbose = False
    for key, value in options.items():
        setattr(solver.settings, key, value)
    if not dense:
        solver.setup(
            qp.P,
            qp.q,
            A if qp.m_eq else None,
            b if qp.m_eq else None,
            G if qp.m_ineq else None,
            None,
            h if qp.m_ineq else None,
        )
        no_bounds = np.zeros(0, dtype=int)
        return solver, _Layout(np.arange(qp.m_ineq), no_bounds, no_bounds, np.zeros(0))
    Gr = sp.csr_matrix(G)
    rows, col, v, x_l, x_u = _bounds(Gr, h, qp.n)
    keep = np.setdiff1d(np.arange(qp.m_ineq), rows)
    solver.setup(
        qp.P.toarray(),
        qp.q,
        A.toarray() if qp.m_eq else None,
        b if qp.m_eq else None,
        Gr[keep].toarray() if len(keep) else None,
        None,
        h[keep] if len(keep) else None,
        x_l if len(rows) else None,
        x_u if len(rows) else None,
    )
    return solver, _Layout(keep, rows, col, v)


def solve(qp: IncrementQP, options: dict[str, Any], warm_start: Any = None) -> IncrementResult:
    """Solve ``qp`` with PIQP; ``warm_start`` is ignored (interior point, no warm start)."""
    t0 = time.perf_counter()
    try:
        solver, layout = build(qp, options)
        t1 = time.perf_counter()
        status = str(solver.solve())
    except Exception as exc:  # PIQP raises plain exceptions on bad data or settings
        raise SolverFailure("piqp", "exception", detail=str(exc)) from exc
    t2 = time.perf_counter()
    res = solver.result
    limit = status in LIMIT_STATUS
    ok = status in OK_STATUS or limit
    x = np.asarray(res.x, dtype=float) if ok else None
    z = np.zeros(qp.m_ineq)
    if len(layout.keep):
        z[layout.keep] = np.asarray(res.z_u, dtype=float) - np.asarray(res.z_l, dtype=float)
    if len(layout.rows):
        # a bound's multiplier is the row's times |v|: x_j <= h/v is the row v x_j <= h over v > 0
        z_u, z_l = (np.asarray(w, dtype=float)[layout.col] for w in (res.z_bu, res.z_bl))
        z[layout.rows] = np.where(layout.v > 0, z_u, z_l) / np.abs(layout.v)
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
