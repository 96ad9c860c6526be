"""Synthetic increment QPs and backend timing for the benchmark: formulations/increment-qp.md section 6.

Random strictly convex QPs with a known KKT point, shaped like the puncture increment QP.

The solution is chosen first (x*, an active set, z* > 0 on it, y*), then q and h are set so that
the KKT conditions of formulations/increment-qp.md eqs. (3)-(6) hold exactly; with P positive
definite and linearly independent active rows, (x*, z*, y*) is the unique KKT point.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..qp import IncrementQP


@dataclass(frozen=True)
class KnownQP:
    """A QP and its exact primal-dual solution."""

    qp: IncrementQP
    x: np.ndarray
    z: np.ndarray
    y: np.ndarray


def block_stiffness(
    n_blocks: int, rng: np.random.Generator, coupling: int = 0, block: int = 5
) -> sp.csc_matrix:
    """SPD matrix of 5x5 diagonal blocks (``block`` x ``block``) plus ``coupling`` PSD coupling blocks."""
    diag = []
    for _ in range(n_blocks):
        B = rng.standard_normal((block, block))
        diag.append(B @ B.T + block * np.eye(block))
    K = sp.block_diag(diag, format="lil")
    for _ in range(coupling):
        i, j = rng.choice(n_blocks, size=2, replace=False)
        C = 0.3 * rng.standard_normal((block, block))
        # add [[C C'],[C' C]]-like PSD-preserving coupling: B'B with B = [C, -C]
        Bc = np.hstack([C, -C])
        M = Bc.T @ Bc
        idx = np.r_[block * i : block * (i + 1), block * j : block * (j + 1)]
        K[np.ix_(idx, idx)] = K[np.ix_(idx, idx)].toarray() + M
    K = sp.csc_matrix(K)
    return sp.csc_matrix(0.5 * (K + K.T))


def synthetic_qp(
    seed: int,
    n_blocks: int = 5,
    m: int = 12,
    p: int = 1,
    coupling: int = 2,
    active_fraction: float = 0.5,
    density: float = 0.3,
) -> KnownQP:
    """A QP with ``5 n_blocks`` variables, ``m`` inequality rows, ``p`` equality rows and known solution."""
    rng = np.random.default_rng(seed)
    P = block_stiffness(n_blocks, rng, coupling)
    n = P.shape[0]
    G = sp.random(m, n, density=density, random_state=rng, data_rvs=rng.standard_normal, format="csc")
    A = sp.csc_matrix(rng.standard_normal((p, n)))
    x = rng.standard_normal(n)
    active = rng.random(m) < active_fraction
    z = np.where(active, rng.uniform(0.5, 2.0, m), 0.0)
    slack = np.where(active, 0.0, rng.uniform(0.5, 2.0, m))
    y = rng.standard_normal(p)
    q = -(P @ x + G.T @ z + A.T @ y)
    h = G @ x + slack
    b = A @ x
    qp = IncrementQP(P=P, q=q, G=G, h=h, A=A, b=b)
    return KnownQP(qp, x, z, y)


@dataclass(frozen=True)
class Timing:
    """Timing of one backend on one QP: medians over repeats, in seconds."""

    solver: str
    build_s: float
    solve_s: float
    wall_s: float
    found: bool
    max_residual: float


#: The three routes the benchmark compares: direct interface, qpsolvers, CVXPY (all Clarabel inside).
ROUTES = ("clarabel", "qpsolvers:clarabel", "cvxpy")


def time_qp(
    qp: IncrementQP, solvers: tuple[str, ...] = ROUTES, accuracy: str | float = "high", repeats: int = 5
) -> list[Timing]:
    """Time ``qp`` through each backend in ``solvers`` (median of ``repeats`` solves each).

    ``wall_s`` includes our residual check, so ``wall_s - build_s - solve_s`` is qpscale's own
    overhead; a backend that fails is reported with ``found=False``, not skipped.

    >>> rows = time_qp(synthetic_qp(0, n_blocks=2, m=3).qp, ("clarabel",), repeats=1)
    >>> rows[0].found
    True
    """
    from . import solve_qp

    rows = []
    for name in solvers:
        samples = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = solve_qp(qp, name, accuracy, check=False)
            samples.append((r.build_s, r.solve_s, time.perf_counter() - t0, r.found, r.max_residual()))
        med = np.median(np.array([s[:3] for s in samples]), axis=0)
        rows.append(
            Timing(
                name,
                float(med[0]),
                float(med[1]),
                float(med[2]),
                all(s[3] for s in samples),
                max(s[4] for s in samples),
            )
        )
    return rows
