"""A sparse exact solve of an increment QP: proximal multipliers and semismooth Newton steps.

Implements formulations/increment-qp.md sec. 8 ("The sparse exact solve").  The QP
``min 1/2 x'Px + q'x  s.t.  Gx <= h,  Ax = b`` with ``P`` positive definite is solved by the
proximal method of multipliers: for fixed multipliers ``(y_, z_)`` the piecewise quadratic

    phi(x) = 1/2 x'Px + q'x + |Ax - b + delta y_|^2 / (2 delta) + |[Gx - h + delta z_]_+|^2 / (2 delta)

is minimised exactly (semismooth Newton steps: full where they lower phi, else with an exact line
search; each step is the KKT system of the rows where the bracket is positive, quasi-definite, so
a sparse LDL' factorisation without pivoting exists whatever the rows' rank; for a large dense
block of ``P`` beside a diagonal, the flexure QP's, it is solved in the contact space through
``H = C P^-1 C'``, sec. 8 "In the contact space"), then
``y_ += (Ax - b)/delta`` and ``z_ = [z_ + (Gx - h)/delta]_+`` (read from the KKT solve).  delta
starts soft and falls to DELTA; the loop stops where the certificate will pass with a margin.
With the active set fixed, an outer step is one step of iterative refinement of the regularised
KKT system towards the unregularised one, so the answer is exact up to rounding once the set
settles, like a primal active-set method's, but dependent rows (a hinged plane) only leave the
multipliers non-unique, never the factorisation singular.
The caller certifies the answer with its own residuals (``certify.solve_exact``), or, as the
``active-set`` backend (``stationary=True``), the solve stops only at a stationary point.
"""

from __future__ import annotations

import hashlib
import threading
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from .qp import IncrementQP

#: Proximal (dual) regularisation, force^-1 L: the violation a unit multiplier error makes.  A
#: fixed active set's error contracts by delta / (delta + sigma) per outer step (sigma an eigenvalue
#: of C P^-1 C' on the rows' range), so a small delta converges in few steps; but a row at contact
#: with no force gets a multiplier of (its rounding) / delta, clipped at zero, which the balance
#: then shows: 1e-8 left 1.2e-8 on the default scene (the certificate allows 1e-9), 1e-6 ~1e-10.
DELTA = 1e-6
#: A row whose bracket is within NOISE x (|C_i|_1 |x|_inf + |d_i| + delta |lam_i|) of zero is at
#: rounding (the solve's error is relative to the whole of x, not to the row's entries): the
#: Newton step's point is accepted whichever side it falls on (else the set can flip forever).
NOISE = 8 * np.finfo(float).eps
#: Outer steps stop when no row is violated, and no row carrying force is open, by more than this
#: (L): a tenth of the certificate's FEASIBLE_TOL.
STOP_TOL = 1e-12
#: The first outer steps use a softer delta, from DELTA0 down by DELTA_RATE per step: far from the
#: answer (a wrong guess of the rows in contact) the exact inner minimisation of phi at DELTA took
#: over 100 Newton steps; a soft phi is minimised in a few and brings the multipliers close.
DELTA0 = 1e-1
DELTA_RATE = 0.1
#: Refinement steps of each KKT solve against its own (regularised) matrix.
REFINE = 3
#: Iteration limits: outer (multiplier) updates and Newton steps per inner minimisation; with
#: ``stationary`` (the backend) STATIONARY_NEWTON (a slanted dart array's flexure QP, 757 unknowns
#: and 1,302 rows, needed 120 in one inner loop).
MAX_OUTER = 1000
MAX_NEWTON = 100
STATIONARY_NEWTON = 300
#: The KKT systems (17) are solved in the contact space (``_ContactKKT``) when ``P`` is a dense
#: leading block of at least CONTACT_MIN_BLOCK unknowns, at least CONTACT_MIN_DENSITY full, beside a
#: diagonal (the flexure QP: the condensed membrane S and the planes' weights, membrane.md eq. (13));
#: a sparse LDL' of such a block costs O(k^3) per active set, the contact space O(|S|^3).
CONTACT_MIN_BLOCK = 200
CONTACT_MIN_DENSITY = 0.25


@dataclass(frozen=True)
class SparseSolution:
    """The answer of :func:`solve_sparse` before certification.

    ``converged``: the rows carrying force held over the last outer step, at the final delta, and
    no row is violated, nor a row carrying force open, by more than the stopping tolerance
    (``status`` says which iteration limit, or the factorisation's failure, stopped it otherwise).
    ``outer``, ``newton``: the steps taken; ``factorisations``: sparse LDL' factorisations made
    (one per distinct set of rows and delta met in a row).  ``z >= 0``, zero off the rows that
    carry force.
    """

    x: np.ndarray
    z: np.ndarray
    y: np.ndarray
    converged: bool
    status: str
    outer: int
    newton: int
    factorisations: int


class _KKT:
    """The quasi-definite KKT matrix ``[[P, C_S'], [C_S, -delta I]]`` of an active set ``S``, its
    LDL' factors (qdldl, AMD ordering) kept for the last set met."""

    def __init__(self, P: sp.csc_matrix, C: sp.csr_matrix, delta: float) -> None:
        self.P, self.C, self.delta = P, sp.csr_matrix(C), delta
        self.key: bytes | None = None
        self.count = 0
        Pc = sp.coo_matrix(P)
        self._P = (Pc.row, Pc.col, Pc.data)

    def matrix(self, S: np.ndarray) -> sp.csc_matrix:
        """``[[P, C_S'], [C_S, -delta I]]`` in CSC, from triplets in ``sp.bmat``'s order: the same
        arrays without its per-block checks, which with ``triu`` took nearly half of the stalled
        levels' exact solves (formulations/increment-qp.md sec. 8)."""
        C, n, k = self.C, self.P.shape[0], len(S)
        counts = np.diff(C.indptr)[S]
        starts = C.indptr[S]
        take = np.repeat(starts - np.r_[0, np.cumsum(counts)[:-1]], counts) + np.arange(counts.sum())
        i, j, v = np.repeat(np.arange(k), counts), C.indices[take], C.data[take]
        Pr, Pj, Pv = self._P
        d = np.arange(n, n + k)
        rows = np.concatenate([Pr, j, n + i, d])
        cols = np.concatenate([Pj, n + i, j, d])
        data = np.concatenate([Pv, v, v, np.full(k, -self.delta)])
        return sp.csc_matrix((data, (rows, cols)), shape=(n + k, n + k))

    def solve(self, S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        import qdldl

        key = S.tobytes()
        if key != self.key:
            self.K = self.matrix(S)
            self.solver = qdldl.Solver(_upper(self.K), upper=True)
            self.key = key
            self.count += 1
        sol = self.solver.solve(rhs)
        for _ in range(REFINE):
            sol = sol + self.solver.solve(rhs - self.K @ sol)
        return sol


def _upper(M: sp.csc_matrix) -> sp.csc_matrix:
    """The upper triangle of ``M`` (CSC), entries in their order: what qdldl takes with
    ``upper=True`` (given the whole matrix, it calls ``scipy.sparse.triu``: the same arrays,
    slower)."""
    col = np.repeat(np.arange(M.shape[1]), np.diff(M.indptr))
    keep = M.indices <= col
    indptr = np.r_[0, np.cumsum(np.bincount(col[keep], minlength=M.shape[1]))]
    return sp.csc_matrix((M.data[keep], M.indices[keep], indptr), shape=M.shape)


def dense_block(P: sp.spmatrix) -> int:
    """The size ``k`` of the leading block of ``P`` that holds every off-diagonal entry: ``P`` is
    ``blockdiag(P[:k, :k], diagonal)``.

    >>> P = sp.block_diag([np.array([[2.0, 1.0], [1.0, 2.0]]), sp.identity(3)])
    >>> dense_block(P)
    2
    """
    C = sp.coo_matrix(P)
    off = C.row != C.col
    return int(max(C.row[off].max(initial=-1), C.col[off].max(initial=-1)) + 1)


# The inverse of the last dense block met, by the hash of its entries: the flexure QPs of one
# curve share the condensed membrane S (membrane.md sec. 5), so it is inverted once per curve.
_INVERSE: dict[str, np.ndarray] = {}
_INVERSE_LOCK = threading.Lock()


def _block_inverse(B: np.ndarray) -> np.ndarray:
    """``B^-1`` of the symmetric positive definite ``B`` (Cholesky), the last one kept for reuse.

    Raises RuntimeError (as the sparse factorisation does) when ``B`` is not positive definite."""
    key = hashlib.blake2b(np.ascontiguousarray(B).tobytes(), digest_size=16).hexdigest()
    with _INVERSE_LOCK:
        if key in _INVERSE:
            return _INVERSE[key]
    try:
        factor = sla.cho_factor(B, lower=True, check_finite=False)
    except np.linalg.LinAlgError as exc:
        raise RuntimeError(f"dense block not positive definite: {exc}") from exc
    inv = sla.cho_solve(factor, np.eye(len(B)), check_finite=False)
    inv = 0.5 * (inv + inv.T)
    with _INVERSE_LOCK:
        _INVERSE.clear()
        _INVERSE[key] = inv
    return inv


class _ContactKKT:
    """The KKT matrix (17) of an active set ``S`` solved in the contact space (formulations/
    increment-qp.md sec. 8, "In the contact space"), for ``P = blockdiag(B, D)`` with ``B`` dense
    and ``D`` diagonal: ``(C_S P^-1 C_S' + delta I) mu = C_S P^-1 r1 - r2``, then
    ``x = P^-1 (r1 - C_S' mu)``.  ``P^-1`` (``B^-1`` kept across QPs that share ``B``) and
    ``H = C P^-1 C'`` are formed once per QP, so an active set costs one dense Cholesky of
    ``|S|`` rows; refinement against (17) itself, until its residual is at rounding."""

    def __init__(self, P: sp.csc_matrix, C: sp.csr_matrix, delta: float, B: np.ndarray) -> None:
        k = len(B)
        self.P, self.C, self.delta, self.k = P, C, delta, k
        self.key: tuple[bytes, float] | None = None
        self.count = 0
        self.B_inv = _block_inverse(B)
        diag = P.diagonal()[k:]
        if np.any(diag <= 0.0):
            raise RuntimeError("diagonal of P not positive")
        self.d_inv = 1.0 / diag
        Ct = sp.csc_matrix(C.T)
        W = np.empty((P.shape[0], C.shape[0]))
        W[:k] = np.asarray(sp.csr_matrix(Ct[:k].T) @ self.B_inv).T
        W[k:] = Ct[k:].multiply(self.d_inv[:, None]).toarray()
        self.H = np.asarray(C @ W)

    def _p_inv(self, v: np.ndarray) -> np.ndarray:
        return np.r_[self.B_inv @ v[: self.k], self.d_inv * v[self.k :]]

    def solve(self, S: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        n = self.P.shape[0]
        key = (S.tobytes(), self.delta)
        if key != self.key:
            M = self.H[np.ix_(S, S)]
            M[np.diag_indices_from(M)] += self.delta
            try:
                self.factor = sla.cho_factor(M, lower=True, check_finite=False)
            except np.linalg.LinAlgError as exc:
                raise RuntimeError(f"contact-space matrix not positive definite: {exc}") from exc
            self.CS = self.C[S]
            self.key = key
            self.count += 1

        def once(r: np.ndarray) -> np.ndarray:
            mu = sla.cho_solve(self.factor, self.CS @ self._p_inv(r[:n]) - r[n:], check_finite=False)
            return np.r_[self._p_inv(r[:n] - self.CS.T @ mu), mu]

        sol = once(rhs)
        floor = NOISE * max(float(np.abs(rhs).max(initial=0.0)), 1.0)
        for _ in range(REFINE):
            x, mu = sol[:n], sol[n:]
            res = rhs - np.r_[self.P @ x + self.CS.T @ mu, self.CS @ x - self.delta * mu]
            if np.abs(res).max(initial=0.0) <= floor:
                break
            sol = sol + once(res)
        return sol


def _kkt(P: sp.csc_matrix, C: sp.csr_matrix, delta: float) -> _KKT | _ContactKKT:
    """The solver of the KKT systems (17): in the contact space for a large dense block beside a
    diagonal (``CONTACT_MIN_BLOCK``, ``CONTACT_MIN_DENSITY``), else sparse LDL'."""
    k = dense_block(P)
    if k >= CONTACT_MIN_BLOCK:
        B = sp.csc_matrix(P[:k, :k])
        if B.nnz >= CONTACT_MIN_DENSITY * k * k:
            return _ContactKKT(sp.csc_matrix(P), C, delta, B.toarray())
    return _KKT(P, C, delta)


def _line_search(alpha: float, beta: float, r: np.ndarray, a: np.ndarray, eq: int, delta: float) -> float:
    """The minimiser ``t > 0`` of the piecewise quadratic ``phi(x + t dx)``, whose derivative is
    ``alpha t + beta + (1/delta) sum_i a_i [r_i + t a_i]`` over the equality rows (the first ``eq``)
    and the inequality rows with ``r_i + t a_i > 0`` (``r = Cx - d + delta lam_``, ``a = C dx``)."""
    re, ae = r[:eq], a[:eq]
    s0 = alpha + float(ae @ ae) / delta
    c0 = beta + float(ae @ re) / delta
    ri, ai = r[eq:], a[eq:]
    on = (ri > 0) | ((ri == 0) & (ai > 0))
    s0 += float(ai[on] @ ai[on]) / delta
    c0 += float(ai[on] @ ri[on]) / delta
    moving = ai != 0
    t_break = np.full(ri.size, np.inf)
    t_break[moving] = -ri[moving] / ai[moving]
    # rows that switch at t_break > 0: entering ones (a > 0, off now) and leaving ones (a < 0, on now)
    cross = np.flatnonzero(moving & (t_break > 0) & (((ai > 0) & ~on) | ((ai < 0) & on)))
    order = cross[np.argsort(t_break[cross])]
    sign = np.where(ai[order] > 0, 1.0, -1.0)
    ds = np.concatenate([[0.0], np.cumsum(sign * ai[order] ** 2) / delta])
    dc = np.concatenate([[0.0], np.cumsum(sign * ai[order] * ri[order]) / delta])
    slope, intercept = s0 + ds, c0 + dc
    ends = np.concatenate([t_break[order], [np.inf]])
    starts = np.concatenate([[0.0], t_break[order]])
    for k in range(len(ends)):
        if slope[k] > 0:
            t = -intercept[k] / slope[k]
            if t <= ends[k]:
                return max(t, starts[k])
        elif intercept[k] >= 0:
            return starts[k]
    return float(starts[-1])


def solve_sparse(
    qp: IncrementQP,
    x0: np.ndarray | None = None,
    z0: np.ndarray | None = None,
    y0: np.ndarray | None = None,
    working: np.ndarray | None = None,
    delta: float = DELTA,
    delta0: float = DELTA0,
    tol: float = STOP_TOL,
    max_outer: int | None = None,
    stationary: bool = False,
) -> SparseSolution:
    """``qp`` solved by the proximal method of multipliers with exact semismooth Newton inner
    minimisations (module docstring), from ``(x0, z0, y0)`` (default zero).

    ``max_outer``: the outer steps allowed (default ``MAX_OUTER``).
    ``stationary``: the backend's stop (its answer must pass the residual check): at a point
    stationary to ``tol`` (``|Px + q + C'lam| <= tol``) whether or not the rows carrying force
    repeat, and at the inner cap (``STATIONARY_NEWTON``) only if the Newton point of the piece
    reached fails that test.  Without it (the exact check, which certifies its answer itself, and
    the stall window's exact answers): when the rows carrying force repeat, and at the inner cap
    ``MAX_NEWTON``.
    ``working``: a guess of the inequality rows in contact; the first Newton step solves the KKT
    system of these rows (and the equality rows) instead of those the start point selects.
    Stops when an outer step leaves the rows carrying force unchanged, moves no coordinate of
    ``x`` by more than ``tol`` (L) and leaves no row violated by more than ``tol``; the
    certificate is the caller's.

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> qp = IncrementQP(P=sp.identity(2, format="csc"), q=np.array([-1.0, 0.0]),
    ...                  G=sp.csc_matrix([[1.0, 0.0]]), h=np.array([0.5]),
    ...                  A=sp.csc_matrix([[0.0, 1.0]]), b=np.array([2.0]))
    >>> s = solve_sparse(qp)
    >>> s.converged, s.x.round(12).tolist(), s.z.round(12).tolist(), s.y.round(12).tolist()
    (True, [0.5, 2.0], [0.5], [-2.0])
    """
    G, h, A, b = qp.rows()
    P, q = qp.P, qp.q
    n, p, m = qp.n, len(b), len(h)
    C = sp.vstack([A, G], format="csr")
    row_norm = np.asarray(abs(C).sum(axis=1)).ravel()
    d = np.r_[b, h]
    eq = np.arange(p)
    x = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float).copy()
    lam = np.zeros(p + m)
    if y0 is not None:
        lam[:p] = y0
    if z0 is not None:
        lam[p:] = np.maximum(z0, 0.0)
    final_delta = delta
    delta = max(delta0, final_delta)
    try:
        kkt = _kkt(P, C, delta)
    except RuntimeError as exc:
        return SparseSolution(x, lam[p:], lam[:p], False, f"factorisation: {exc}", 0, 0, 0)
    newton = 0
    prev_set: bytes | None = None
    converged = False
    outer = 0

    def bracket(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``r = Cx - d + delta lam``, the rows where it is positive, and its rounding bound."""
        r = C @ x - d + delta * lam
        noise = NOISE * (row_norm * np.abs(x).max(initial=0.0) + np.abs(d) + delta * np.abs(lam))
        return r, np.r_[eq, p + np.flatnonzero(r[p:] > 0)], noise

    def merit(x: np.ndarray, r: np.ndarray) -> float:
        """``phi(x)`` with ``r = Cx - d + delta lam``."""
        pos = np.r_[r[:p], np.maximum(r[p:], 0.0)]
        return float(0.5 * x @ (P @ x) + q @ x + pos @ pos / (2.0 * delta))

    S = None if working is None else np.r_[eq, p + np.unique(np.asarray(working, dtype=int))]
    limit = MAX_OUTER if max_outer is None else max_outer
    status = f"outer iteration limit {limit}"
    for outer in range(1, limit + 1):
        # inner: minimise phi(x) for the fixed multipliers lam.  A Newton step's point is the
        # minimiser of phi when the bracket is positive on the same rows there (phi is convex and
        # its gradient agrees with the piece's) up to rows whose bracket is rounding; else an
        # exact line search along the step (a descent direction unless the gradient is zero, so a
        # search that stays at t = 0 means that x is already the minimiser up to rounding).
        if S is None:
            S = bracket(x)[1]
        forced = outer == 1 and working is not None
        capped = False
        # the backend's loop has one more solve: at its cap, the Newton point of the piece that x
        # is on, whose multipliers the stop test reads (pieces whose brackets differ by rounding
        # can be visited in turn with x already at the answer); the cap ends the solve only if
        # that point fails the test
        cap = STATIONARY_NEWTON if stationary else MAX_NEWTON
        for it in range(cap + stationary):
            try:
                sol = kkt.solve(S, np.r_[-q, d[S] - delta * lam[S]])
            except RuntimeError as exc:  # qdldl: a pivot of the wrong sign (rounding)
                return SparseSolution(
                    x, lam[p:], lam[:p], False, f"factorisation: {exc}", outer, newton, kkt.count
                )
            newton += 1
            if it == cap:
                capped, x = True, sol[:n]
                break
            r_full, S_full, noise = bracket(sol[:n])
            differ = np.setxor1d(S, S_full)
            if np.all(np.abs(r_full[differ]) <= noise[differ]):
                x = sol[:n]
                break
            if forced or merit(sol[:n], r_full) < merit(x, C @ x - d + delta * lam):
                # a full step that lowers phi (a primal-dual active-set step), or the first step
                # from guessed rows (no descent direction to search along)
                x, forced = sol[:n], False
            else:
                dx = sol[:n] - x
                r = C @ x - d + delta * lam
                t = _line_search(float(dx @ (P @ dx)), float(dx @ (P @ x + q)), r, C @ dx, p, delta)
                if t <= 0.0:  # no descent along a Newton step: the gradient at x is rounding
                    x = sol[:n]
                    break
                x = x + t * dx
            S = bracket(x)[1]
        else:
            status = f"Newton iteration limit {MAX_NEWTON}"
            break
        # the multipliers of the minimiser: the KKT solve's (accurate), not (Cx - d)/delta + lam,
        # which multiplies the rounding of x by 1/delta
        lam = np.zeros(p + m)
        lam[S] = sol[n:]
        lam[p:] = np.maximum(lam[p:], 0.0)
        S = None
        # stop where the certificate will pass with a margin: rows violated by at most tol, and
        # force only on rows within tol of contact (a row carrying force at the prox iterate may
        # still be up to delta * lam_ from contact)
        slack = h - G @ x
        carrying = np.flatnonzero(lam[p:] > 0)
        viol = max(np.abs(A @ x - b).max(initial=0.0), np.maximum(-slack, 0.0).max(initial=0.0))
        gap = np.maximum(slack[carrying], 0.0).max(initial=0.0)
        key = carrying.tobytes()
        # settled: for the backend the point is stationary to tol (a row at zero force that
        # enters and leaves the set by rounding never lets the set repeat); for the exact check
        # and the stall window the set repeats
        if stationary:
            settled = bool(np.abs(P @ x + q + C.T @ lam).max(initial=0.0) <= tol)
        else:
            settled = key == prev_set
        if delta == final_delta and settled and viol <= tol and gap <= tol:
            status, converged = "converged", True
            break
        if capped:
            status = f"Newton iteration limit {STATIONARY_NEWTON}"
            break
        prev_set = key
        if delta > final_delta:  # the next inner problem is stiffer: new KKT matrices
            delta = max(final_delta, DELTA_RATE * delta)
            kkt.delta, kkt.key = delta, None
    return SparseSolution(x, lam[p:], lam[:p], converged, status, outer, newton, kkt.count)
