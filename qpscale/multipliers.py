"""The multiplier set of a degenerate converged state, and the stability verdict over all of it.

Implements formulations/stability.md sec. 7.  Where the rows in contact are dependent (a face
on a face, hinged planes, mirror images), the contact forces that balance a state form a
polytope, and the second variation (stability.md eq. (4)) read with one point of it depends on
which point the backend returned: an interior point's and an active-set method's verdicts on
the same configuration differ.  The verdict used here does not depend on that choice:

    mu* = max over (lam, F) in the multiplier set of lambda_min(Z' H(lam, F) Z) / max K_ii,

with Z the directions that keep every row that can carry force (for some point of the set) and
the load at zero.  H is affine in (lam, F), so mu* is a concave maximisation, solved by cutting
planes over the set (a semidefinite program by Clarabel's PSD cone gave the same value 200 times
slower).  A state is stable when mu* > -tol (the
second-order sufficient condition with a multiplier set), and mu* is at least the value any one
point of the set gives, so a state the backend's multipliers call stable is stable here too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog, nnls

from .certify import LP_OPTIONS
from .errors import SolverFailure
from .increment import Equilibrium, LoadPoint
from .qp import IncrementQP
from .stability import (
    SPARSE_FROM,
    Stability,
    _hessian,
    _Lifted,
    _lifted,
    _null_space,
    _row_hessians,
    constraints,
    dof_mode,
    geometric_matrix,
    geometric_terms,
    padded,
    rotated_point_derivatives,
    smallest_on_null_space,
)
from .tiling import Patch

# The rows that may carry force are those within a reach (L) of contact at the state, the first
# of NEAR_LADDER that balances the state to BALANCED times its force scale.  A converged state's gaps are
# its QP's answer's: Clarabel's leave forces on rows up to ~7e-6 L apart (its plane unknowns carry
# its residual over their 1e-6 weight), PIQP's within 1e-7.  A fixed 1e-5 let two rows 6.4e-7 L
# apart in or out of the support by the states' imbalance noise (1.6e-8 or 7.1e-9: the support
# threshold falls on either side of the 8e-7 they can carry), and the verdict at one depth flipped
# between mu* = -2.1e-3 and +0.145 (3x3 square, mid-edge fold; with 1e-7 both read -2.1e-3).
NEAR_LADDER = (1e-7, 1e-6, 1e-5)
BALANCED = 1e-7
# A row is in the support when some member gives it this fraction of the force scale, and NOISE
# times the state's imbalance (rows 6 and 19 of the 3x3 corner path's last held state reach only
# 1e-8..3e-8 against an imbalance of 1.2e-8: noise, and they came and went with the scale).
SUPPORT = 1e-8
NOISE = 100.0
# The forces of the set's members are bounded by BOX times the force scale (a self-stress is a
# ray of the set); the cutting planes stop at MAX_CUTS or when their bounds are GAP apart.
BOX = 10.0
SUPPORT_LP_SETTINGS = {"tol_gap_abs": 1e-8, "tol_gap_rel": 1e-8, "tol_feas": 1e-8}
# A support LP's answer may leave the set by SUPPORT (force-scale units), the force below which a
# row is not in the support: at the settings above the interior point answers' rows at zero sit
# within 6e-9 of it (5x5 dart; at 1e-9 Clarabel ends AlmostSolved 2.8e-8 outside).  An answer
# farther out is brought back along the segment from the members' mean (``_into_set``).
SUPPORT_FEASIBLE = SUPPORT
MAX_CUTS = 200
GAP = 1e-10
# The dense reduced pieces (a d x d matrix per row and per kernel direction, d <= N) are used while
# they fit in this many bytes (the 5x5 default path needs at most 24 MB; products and their
# symmetrisation hold three to four times as much at once) and N <= SPARSE_FROM;
# above, the sparse evaluation of ``_sparse_uniform`` (memory linear in N).
DENSE_BYTES = 3e7


@dataclass(frozen=True)
class MultiplierSet:
    """The forces that balance a converged state as well as any can (stability.md sec. 7):
    ``{(lam, F) = (lam0, F0) + kernel u : lam >= 0}`` on ``rows``.

    ``rows`` are the QP's inequality rows (the contact set's rows) that carry force in some
    member (the support of the set's relative interior); ``B = [G_rows', a]`` (``a`` the loading
    row), ``kernel`` a basis of its null space, ``(lam0, F0)`` a member positive on every row,
    ``residual`` the largest entry of ``B [lam; F] + P 0 + q``, the same for every member.
    """

    rows: np.ndarray
    B: np.ndarray
    kernel: np.ndarray
    lam: np.ndarray
    F: float
    residual: float


def _clarabel_settings():
    """Clarabel's settings for the multiplier set's small programs (``SUPPORT_LP_SETTINGS``), quiet."""
    import clarabel  # only the stability test's degenerate states and the reported forces need it

    settings = clarabel.DefaultSettings()
    settings.verbose = False
    for key, value in SUPPORT_LP_SETTINGS.items():
        setattr(settings, key, value)
    return settings


def force_scale_of(eq: Equilibrium) -> float:
    """The force scale of a state's multiplier set (``multiplier_set``'s ``force_scale``): its largest
    contact force or its load."""
    return max(float(np.max(eq.lam, initial=0.0)), abs(eq.F))


def _support_lp(w0: np.ndarray, ker: np.ndarray, k: int, rows: np.ndarray, cap: float, bound: float):
    """``max sum_{i in rows} min(lam_i, cap)`` over ``lam = (w0 + ker u)[:k] >= 0``, ``lam <= bound``:
    unknowns (u, t); returns its answer ``w0 + ker u`` (brought into the set by :func:`_into_set`),
    or None when the LP is not solved.

    Solved in units of the force scale (``bound / BOX``) by Clarabel's interior point method.
    The set is a degenerate polytope: ``w0`` is a vertex with dozens of rows at zero, and the
    largest value a row reaches over the set spans 1e-11..1e-1 of the force scale (5x5 dart).
    On such LPs HiGHS at the 1e-9 tolerances this needs stopped with an unknown status (with
    presolve and without, dual or primal simplex, interior point with or without crossover), and where
    it did stop "optimal" its objectives differed by 25 %.  An interior point method is not
    troubled by degeneracy and ends inside the optimal face, so it loads at once every row the
    optimum can load (formulations/stability.md sec. 7)."""
    import clarabel  # only the stability test's degenerate states need it

    unit = bound / BOX
    nu, m = ker.shape[1], len(rows)
    K_lam = ker[:k]
    # [u; t] with A [u; t] + s = b, s >= 0: -lam <= 0, lam <= bound, t_i - lam_i <= 0, t <= cap, -t <= 0
    eye, zeros = sp.identity(m, format="csc"), sp.csc_matrix((2 * k, m))
    A = sp.vstack(
        [
            sp.hstack([sp.csc_matrix(np.vstack([-K_lam, K_lam, -ker[rows]])), sp.vstack([zeros, eye])]),
            sp.hstack([sp.csc_matrix((2 * m, nu)), sp.vstack([eye, -eye])]),
        ],
        format="csc",
    )
    b = np.r_[w0[:k], bound - w0[:k], w0[rows], np.full(m, cap), np.zeros(m)] / unit
    settings = _clarabel_settings()
    c = np.r_[np.zeros(nu), -np.ones(m)]
    cones = [clarabel.NonnegativeConeT(len(b))]
    sol = clarabel.DefaultSolver(sp.csc_matrix((nu + m, nu + m)), c, A, b, cones, settings).solve()
    if str(sol.status) not in ("Solved", "AlmostSolved"):
        return None
    return w0 + unit * (ker @ np.asarray(sol.x)[:nu])


def _into_set(w: np.ndarray, anchor: np.ndarray, k: int, bound: float) -> np.ndarray:
    """The point of the segment from ``anchor`` (a member) towards ``w`` (a support LP's answer,
    which balances like every member but may leave ``0 <= lam <= bound``) farthest along it that
    stays in the set to ``SUPPORT_FEASIBLE`` (force-scale units): ``w`` itself when it is in.

    The set is convex, so every such point is a member.  An interior point's answer on a
    degenerate LP can end just outside an optimal face that a row's bound cuts (the 5x5 dart
    slanted towards 90 deg: AlmostSolved with a row at -1.9e-6 where the anchor gives it
    1.8e-3); the step back to the set keeps 99.8 % of the answer's move from the anchor there
    (formulations/stability.md sec. 7)."""
    slack = SUPPORT_FEASIBLE * bound / BOX
    d = w[:k] - anchor[:k]
    theta = 1.0
    low = w[:k] < -slack  # rows the answer takes below zero: anchor + theta d >= -slack
    if low.any():
        theta = min(theta, float(np.min((anchor[:k][low] + slack) / -d[low])))
    high = w[:k] > bound + slack
    if high.any():
        theta = min(theta, float(np.min((bound + slack - anchor[:k][high]) / d[high])))
    return w if theta == 1.0 else anchor + max(theta, 0.0) * (w - anchor)


def multiplier_set(qp: IncrementQP, force_scale: float) -> MultiplierSet:
    """The multiplier set of the converged state ``qp`` is linearised at, and the rows it can load.

    It is read at the state itself (``x = 0``: a converged state is its QP's fixed point), not
    at a backend's answer: the hinged planes' unknowns of two answers differ by up to 1e-3 (only
    their proximal weight fixes them), which moves rows in and out of contact; the state does not
    depend on the backend.  A state balances only to its step tolerance: the best balance is a
    non-negative least-squares fit ``w0`` (``lam >= 0``), and the set is ``w0`` plus the null space of
    ``B``, whose members all balance exactly as well.  The loading row is the QP's first
    equality; the other equalities (rows that hold a symmetric path) get no multiplier: at a
    converged held state theirs vanish (contact.md eq. (28)), and a free one would balance what
    the contact must.  The support (rows positive in some member) is found by linear programs
    that maximise ``sum min(lam_i, cap)`` over the rows not yet found, until none is found: it
    is unique, whatever the cap.
    """
    G, h, A, _ = qp.rows()
    a = A[0].toarray().ravel()
    r = -np.asarray(qp.q)
    for reach in NEAR_LADDER:
        near = np.flatnonzero(h <= reach)
        B = np.hstack([G[near].T.toarray(), a[:, None]])
        k = len(near)
        # Lawson-Hanson with the free load multiplier split in two (45x faster than BVLS here)
        x, _ = nnls(np.hstack([B, -a[:, None]]), r, maxiter=50 * (k + 2))
        w0 = np.r_[x[:k], x[k] - x[k + 1]]
        residual = float(np.abs(B @ w0 - r).max(initial=0.0))
        scale = max(force_scale, float(np.max(w0[:k], initial=0.0)), 1e-12)  # sets the LPs' box too
        # balanced relative to the state's own forces, not the caller's scale: the rows near
        # enough to be read must not depend on the scale (a state with a loaded row 2e-7 L from
        # contact balanced "within 1e-7 of 3" without it, "within 1e-7 of 1" only with it)
        if residual <= BALANCED * max(float(np.abs(w0).max(initial=0.0)), 1e-12):
            break
    # a force no larger than the state's own imbalance is noise, not support
    tol, cap, bound = max(SUPPORT * scale, NOISE * residual), 1e-3 * scale, BOX * scale
    ker = _null_space(B)
    members = [w0]
    found = w0[:k] > tol
    while ker.shape[1] and not found.all():
        rest = np.flatnonzero(~found)
        answer = _support_lp(w0, ker, k, rest, cap, bound)
        if answer is None:
            raise SolverFailure("stability", "multiplier set LP failed", detail="uniform second variation")
        w = _into_set(answer, np.mean(members, axis=0), k, bound)
        new = rest[w[rest] > tol]
        if not len(new):
            if (answer[rest] > tol).any():  # the LP loads rows that no member reached: no support
                raise SolverFailure(
                    "stability", "multiplier set LP left the set", detail="uniform second variation"
                )
            break
        members.append(w)
        found[new] = True
    lam0 = np.mean(members, axis=0)
    keep = np.flatnonzero(found)
    cols = np.r_[keep, k]
    B_w = B[:, cols]
    return MultiplierSet(near[keep], B_w, _null_space(B_w), lam0[keep], float(lam0[k]), residual)


def least_norm_member(ms: MultiplierSet) -> tuple[np.ndarray, float]:
    """The member of ``ms`` whose contact forces have the least Euclidean norm: ``(lam, F)`` on
    ``ms.rows`` (formulations/stability.md sec. 7, "The reported forces").

    The set is a closed convex polyhedron and the norm strictly convex in ``lam``, so this member
    is unique; ``F`` follows from ``lam`` (a kernel direction that moved ``F`` alone would
    balance the load row by nothing).  It is the projection of zero onto the set: in the kernel
    coordinates ``u``, ``min |lam0 + N u|^2 s.t. lam0 + N u >= 0``, a small QP (Clarabel).
    Where the set is one point (unique multipliers) it is that point.
    """
    import clarabel  # only the reported forces of degenerate states need it

    k = len(ms.rows)
    w0 = np.r_[ms.lam, ms.F]
    N = ms.kernel[:k]
    if N.shape[1] == 0:
        return ms.lam.copy(), ms.F
    unit = max(float(np.max(np.abs(ms.lam), initial=0.0)), 1e-12)
    P = sp.csc_matrix(np.triu(N.T @ N))
    cones = [clarabel.NonnegativeConeT(k)]
    solver = clarabel.DefaultSolver(
        P, N.T @ ms.lam / unit, sp.csc_matrix(-N), ms.lam / unit, cones, _clarabel_settings()
    )
    sol = solver.solve()
    if str(sol.status) not in ("Solved", "AlmostSolved"):
        raise SolverFailure("multipliers", f"least-norm member: {sol.status}", detail="reported forces")
    w = w0 + unit * (ms.kernel @ np.asarray(sol.x))
    return np.maximum(w[:k], 0.0), float(w[k])


def _maximise_smallest_eigenvalue(
    base: np.ndarray, dirs: np.ndarray, lam0: np.ndarray, N: np.ndarray, bound: float, tol: float
) -> np.ndarray:
    """``u`` maximising ``mu(u) = lambda_min(base + sum_j u_j dirs_j)`` over ``lam0 + N u >= 0``,
    ``|lam0 + N u| <= bound``, by Kelley's cutting planes: ``mu(u) <= mu(u_i) + g_i'(u - u_i)``
    with the subgradient ``g_ij = v_i' dirs_j v_i`` (``v_i`` the eigenvector).  Stops when the
    best value exceeds ``-tol`` (stable) or when the model's bound and the best value are within
    ``GAP``: an unstable state's mode is then the maximiser's (the direction the path pushes
    along), not that of wherever the bound first fell below ``-tol``; the best ``u`` found is
    returned."""

    def value(u: np.ndarray) -> tuple[float, np.ndarray]:
        vals, vecs = np.linalg.eigh(base + np.tensordot(u, dirs, axes=1))
        v = vecs[:, 0]
        return float(vals[0]), (dirs @ v) @ v

    return _cutting_planes(value, len(dirs), lam0, N, bound, tol)


def _cutting_planes(
    value: Callable[[np.ndarray], tuple[float, np.ndarray]],
    nu: int,
    lam0: np.ndarray,
    N: np.ndarray,
    bound: float,
    tol: float,
) -> np.ndarray:
    """Kelley's cutting planes of :func:`_maximise_smallest_eigenvalue` for any concave ``value``
    returning ``(mu(u), subgradient)``."""
    if nu == 0:  # one member: nothing to choose
        return np.zeros(0)
    u = np.zeros(nu)
    best, g = value(u)
    if best > -tol:
        return u
    best_u, cuts = u, [(best, g, u)]
    # LP in (u, theta): max theta, theta - g_i'u <= f_i - g_i'u_i, -N u <= lam0, N u <= bound - lam0
    for _ in range(MAX_CUTS):
        model = np.array([np.r_[-gi, 1.0] for fi, gi, ui in cuts])
        levels = [fi - gi @ ui for fi, gi, ui in cuts]
        box = np.zeros((len(N), 1))
        A_ub = np.vstack([model, np.hstack([-N, box]), np.hstack([N, box])])
        b_ub = np.r_[levels, lam0, bound - lam0]
        res = linprog(
            np.r_[np.zeros(nu), -1.0],
            A_ub=A_ub,
            b_ub=b_ub,
            bounds=[(None, None)] * (nu + 1),
            method="highs",
            options=LP_OPTIONS,
        )
        if res.status != 0:  # the best value is below -tol: unstable is not shown, so no verdict
            raise SolverFailure(
                "stability", f"cutting-plane LP: {res.message}", detail="uniform second variation"
            )
        u, upper = res.x[:nu], float(res.x[nu])
        f, g = value(u)
        if f > best:
            best, best_u = f, u
        if best > -tol or upper - best <= GAP:
            break
        cuts.append((f, g, u))
    else:
        if upper > -tol:  # out of cuts with the bound above -tol: neither verdict is shown
            raise SolverFailure(
                "stability",
                f"cutting planes: bound {upper:.3g}, best {best:.3g}",
                detail="uniform second variation",
            )
    return best_u


def uniform_second_variation(
    patch: Patch, K, eq: Equilibrium, load: LoadPoint, qp: IncrementQP, tol: float
) -> Stability:
    """The stability verdict over the whole multiplier set (stability.md sec. 7).

    ``qp`` is the increment QP linearised at ``eq`` and ``eq.contacts`` its contact set
    (``SQPLevels.increment_qp``); no backend's answer is read.
    """
    forces = force_scale_of(eq)
    ms = multiplier_set(qp, forces)
    indicator = np.zeros(qp.m_ineq)
    indicator[ms.rows] = 1.0
    lifted = _lifted(patch, replace(eq, lam=indicator, F=0.0), load)
    if not np.array_equal(lifted.rows, ms.rows):
        raise SolverFailure(
            "stability", "multiplier rows are not plane rows", detail="uniform second variation"
        )
    n, N = patch.n_scales, lifted.size
    bound = BOX * max(forces, float(np.max(ms.lam, initial=0.0)))  # the support LPs' box
    if N > SPARSE_FROM or 8.0 * N * N * (len(ms.rows) + ms.kernel.shape[1] + 4) > DENSE_BYTES:
        return _sparse_uniform(patch, K, eq, load, lifted, ms, bound, tol)
    C = np.vstack([lifted.jacobian(lifted.z0), np.r_[load.gradient(eq.q), np.zeros(N - 5 * n)]])
    Z = _null_space(C)
    scale = float(np.max(K.diagonal()))
    d = Z.shape[1]
    if d == 0:
        return Stability(np.inf, True, np.zeros((n, 5)), len(ms.rows))
    lifted.lam = np.zeros(len(ms.rows))
    H0 = _hessian(lifted, K)  # K, the plane weight; no contact or load term (lam = F = 0)
    q = lifted.z0[: 5 * n].reshape(n, 5)
    s = np.r_[lifted.scale, load.scale]
    rr, dr, ddr = rotated_point_derivatives(q[s, 3:5], np.vstack([lifted.X, np.reshape(load.X, (1, 3))]))
    h, idx = _row_hessians(lifted, lifted.z0, rr[:-1], dr[:-1], ddr[:-1])
    ij = 5 * load.scale + np.arange(3, 5)
    # Reduced pieces: H(lam, F) = H0 - sum lam_i h_i + F h_w, each as Z'(.)Z / scale.
    M0 = Z.T @ H0 @ Z / scale
    Zr = Z[idx]  # (rows, 8, d): each row's eight unknowns in the reduced basis
    Mi = np.matmul(Zr.transpose(0, 2, 1), np.matmul(h, Zr)) / scale
    Mw = Z[ij].T @ ddr[-1, :, :, 2] @ Z[ij] / scale
    Mw = 0.5 * (Mw + Mw.T)
    Mi = 0.5 * (Mi + Mi.transpose(0, 2, 1))
    # The members: (lam, F) = (lam0, F0) + ker u (every member balances the state as well as the
    # base does).  mu(u), the smallest eigenvalue of M(lam, F), is concave in u; it is maximised
    # over lam0 + ker_lam u >= 0 (and a box of BOX times the force scale on every force, since a
    # self-stress is a ray of the set) by cutting planes, which bound mu* from above as well as
    # from below: they stop once the state is shown stable, else when the bounds meet.
    k = len(ms.rows)
    ker = ms.kernel
    base = M0 - np.tensordot(ms.lam, Mi, axes=1) + ms.F * Mw
    dirs = -np.tensordot(ker[:k].T, Mi, axes=1) + ker[k][:, None, None] * Mw
    u = _maximise_smallest_eigenvalue(base, dirs, ms.lam, ker[:k], bound, tol)
    w = np.r_[ms.lam, ms.F] + ker @ u
    lam, F = w[:k], w[k]
    Mstar = M0 - np.tensordot(lam, Mi, axes=1) + F * Mw
    vals, vecs = np.linalg.eigh(0.5 * (Mstar + Mstar.T))
    mu = float(vals[0])
    return Stability(mu, mu > -tol, dof_mode(Z @ vecs[:, 0], n), k)


def _sparse_uniform(
    patch: Patch,
    K,
    eq: Equilibrium,
    load: LoadPoint,
    lifted: _Lifted,
    ms: MultiplierSet,
    bound: float,
    tol: float,
) -> Stability:
    """:func:`uniform_second_variation` without dense matrices: each member's mu(u) by the sparse
    test (``stability.smallest_on_null_space``) and its subgradient from the eigenvector x in the
    unknowns, ``-sum_i ker_ij x_i' h_i x_i + ker_kj x_w' h_w x_w`` (row i's eight unknowns x_i)."""
    n, N = patch.n_scales, lifted.size
    scale = float(np.max(K.diagonal()))
    terms = geometric_terms(lifted)
    h, idx, hw, ij = terms
    Ks = padded(K, N) / scale
    C = constraints(lifted, load, eq.q)
    k, ker = len(ms.rows), ms.kernel

    def evaluate(u: np.ndarray) -> tuple[float, np.ndarray]:
        w = np.r_[ms.lam, ms.F] + ker @ u
        return smallest_on_null_space(Ks, geometric_matrix(N, 5 * n, terms, w[:k], float(w[k])) / scale, C)

    def value(u: np.ndarray) -> tuple[float, np.ndarray]:
        mu, x = evaluate(u)
        xr = x[idx]
        rows = np.einsum("ma,mab,mb->m", xr, h, xr) / scale
        return mu, -ker[:k].T @ rows + ker[k] * float(x[ij] @ hw @ x[ij]) / scale

    u = _cutting_planes(value, ker.shape[1], ms.lam, ker[:k], bound, tol)
    mu, x = evaluate(u)
    return Stability(mu, mu > -tol, dof_mode(x, n), k)
