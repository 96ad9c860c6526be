"""Stability of a converged state: the second variation of the energy on the active contact set.

Implements formulations/stability.md, eqs. (1)-(7).  Under displacement control the state is
stable when the stored energy is a strict local minimum over the configurations that keep the
load point at its depth and the scales apart.  To second order this is the Lagrangian Hessian

    H = K - sum_k lam_k grad^2 g_k + F grad^2 w

(the contact gaps g_k and the load point's height w are nonlinear in the finite rotations and in
the separating planes' unknowns) restricted to the directions that keep every strongly active
constraint at zero.  A negative eigenvalue of that restriction is a direction in which the
energy falls: the path branches there.

H is exact (sec. 4): each strongly active row depends on eight unknowns (its scale's five DOFs,
its plane's three), so its 8x8 Hessian is formed in closed form for all rows at once, with the
rotation's second derivatives from Rodrigues' formula as series in |theta|^2 (eq. (7)), and
scattered into H.  The finite-difference Hessian it replaced (one unknown at a time, ten times
slower on the 5x5 patch) is kept as ``_hessian_fd``, the tests' reference.

Above ``SPARSE_FROM`` unknowns the test runs without dense matrices (sec. 8): H and the
constraint gradients as sparse matrices, and the smallest eigenvalue on the null space by
shift-invert Lanczos on the KKT pencil, so memory stays linear in the patch.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import factorial

import numpy as np
import numpy.polynomial.polynomial as P
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .contact import ContactSet
from .contact.planes import tangent_basis
from .errors import SolverFailure
from .geometry import Array, rotation_matrices, tangent_operators
from .increment import Equilibrium, LoadPoint
from .tiling import Patch

# Rows whose multiplier exceeds this fraction of the largest (and ACTIVE_FLOOR, in F*) are strongly
# active (eq. (3)); the QP's multipliers of rows that carry nothing are of its tolerance's size.
ACTIVE_FRACTION = 1e-6
ACTIVE_FLOOR = 1e-8
# Finite-difference step of the reference Hessian ``_hessian_fd`` (tests only), in L or rad.
FD_STEP = 1e-6
# Proximal weight on plane unknowns (as in the increment QP): a plane that nothing pins adds a
# zero-curvature direction that moves no scale; this keeps it out of the spectrum.
PLANE_WEIGHT = 1e-3

# Above this many unknowns N (5 per scale, 3 per plane with an active row) the test is sparse
# (sec. 8); below it the dense null space and eigensolver of sec. 3 (exact, and faster there: on
# the default scene's paths 7x7 N <= 416, dense 5.6 ms a state, sparse 7.1 ms; 9x9 N <= 633, 22
# and 13 ms; 11x11 N <= 830, 153 and 55 ms).  The 3x3 and 5x5 patches stay dense.
SPARSE_FROM = 450
# The sparse test's KKT regularisation (in units of max K_ii, rows of C of unit length), the margin
# of its first shift below the Gershgorin bound, the fraction of the way from there up to the
# first estimate of mu_min that the second shift goes, and the Lanczos tolerances of the two runs.
KKT_REGULARISATION = 1e-14
SHIFT_MARGIN = 1e-3
SHIFT_STEP = 0.9
LANCZOS_ROUGH = 1e-3
LANCZOS_TIGHT = 1e-12
# Shifts tried for the tight run, each SHIFT_STEP of the way from the last up to the latest loose
# estimate (sec. 8): the first converges on every path measured but one, the 9x9 staggered triangle
# slanted 60 deg towards 45 deg, where the third did (the distance shrinks tenfold a shift).
SHIFT_RUNS = 8
# Restarts (ARPACK's maxiter) of a tight run before the shift moves on: a run that converges takes
# a few (sec. 8); ARPACK's default, 10 N, let the one that could not spend 150 s on a 9x9 state.
TIGHT_RESTARTS = 20

# Taylor coefficients, in b = |theta|^2, of cos|theta|, sin|theta|/|theta| and (1 - cos|theta|)/|theta|^2
# (the three scalars of Rodrigues' formula, eq. (7)): all three are entire in b, so the series and
# its b-derivatives need no small-angle branch.  24 terms reach round-off for |theta| <= 2 pi (the
# first omitted term is below 1e-20 there; tilts stay below pi/2).
_TERMS = np.arange(24)
_SERIES = np.array(
    [(-1.0) ** _TERMS / np.array([float(factorial(2 * k + j)) for k in _TERMS]) for j in range(3)]
).T
_SERIES_D1 = P.polyder(_SERIES)
_SERIES_D2 = P.polyder(_SERIES, 2)


def rotated_point_derivatives(phi: Array, X: Array) -> tuple[Array, Array, Array]:
    """r = R(theta) X and its exact first and second derivatives in phi, eq. (7).

    Parameters
    ----------
    phi : ndarray (m, 2)
        Rotation vectors (phi_x, phi_y) (theta = (phi_x, phi_y, 0)), in rad.
    X : ndarray (m, 3)
        Body-frame points, in L.

    Returns
    -------
    r : ndarray (m, 3)
    dr : ndarray (m, 2, 3)
        dr[:, i] = d r / d phi_i (equals T[:, i] x r, contact.md eq. 2).
    ddr : ndarray (m, 2, 2, 3)
        ddr[:, i, j] = d^2 r / d phi_i d phi_j.

    Examples
    --------
    e_x turned about e_y by phi is (cos phi, 0, -sin phi): at phi = 0 its second derivative is -e_x.

    >>> r, dr, ddr = rotated_point_derivatives(np.zeros((1, 2)), np.array([[1.0, 0.0, 0.0]]))
    >>> bool(np.allclose(dr[0, 1], [0, 0, -1]) and np.allclose(ddr[0, 1, 1], [-1, 0, 0]))
    True
    """
    m = len(phi)
    th = np.zeros((m, 3))
    th[:, :2] = phi
    b = np.einsum("mi,mi->m", th, th)
    (c, s1, s2), (c1, s11, s21), (c2, s12, s22) = (P.polyval(b, S) for S in (_SERIES, _SERIES_D1, _SERIES_D2))
    E = np.eye(3)[:2]
    t2 = th[:, :2]
    tx = np.cross(th, X)
    ex = np.cross(E[None], X[:, None])  # e_i x X
    tX = np.einsum("mi,mi->m", th, X)
    h = tX[:, None] * th  # (theta.X) theta and its derivatives
    dh = X[:, :2, None] * th[:, None] + tX[:, None, None] * E[None]
    ddh = X[:, :2, None, None] * E[None, None] + X[:, None, :2, None] * E[None, :, None]
    r = c[:, None] * X + s1[:, None] * tx + s2[:, None] * h
    dr = 2 * t2[:, :, None] * (c1[:, None, None] * X[:, None] + s11[:, None, None] * tx[:, None])
    dr += (
        2 * s21[:, None, None] * t2[:, :, None] * h[:, None] + s1[:, None, None] * ex + s2[:, None, None] * dh
    )
    tt = t2[:, :, None] * t2[:, None, :]
    delta = np.eye(2)[None]

    def curv(f1: Array, f2: Array, v: Array) -> Array:
        # d^2 f(b) / d phi_i d phi_j times a fixed vector v: (2 f' delta_ij + 4 f'' th_i th_j) v
        return (2 * f1[:, None, None] * delta + 4 * f2[:, None, None] * tt)[..., None] * v[:, None, None]

    def cross_terms(f1: Array, dv: Array) -> Array:
        # 2 f'(b) (th_i dv_j + th_j dv_i), dv (m, 2, 3) the derivatives of the vector f multiplies
        one = t2[:, :, None, None] * dv[:, None, :, :]
        return 2 * f1[:, None, None, None] * (one + one.transpose(0, 2, 1, 3))

    ddr = curv(c1, c2, X) + curv(s11, s12, tx) + cross_terms(s11, ex)
    ddr += curv(s21, s22, h) + cross_terms(s21, dh) + s2[:, None, None, None] * ddh
    return r, dr, ddr


@dataclass(frozen=True)
class Stability:
    """Result of the second-variation test of one converged state.

    Attributes
    ----------
    min_eigenvalue : float
        Smallest eigenvalue of the reduced Hessian, divided by the largest diagonal entry of K.
    stable : bool
        ``min_eigenvalue > -tol``.
    mode : ndarray (n, 5)
        DOF part of the eigenvector (max-norm 1, sign fixed so its largest entry is positive).
    active : int
        Number of strongly active contact rows.
    """

    min_eigenvalue: float
    stable: bool
    mode: Array
    active: int


def _no_contact(q: Array) -> ContactSet:
    e, z3 = np.zeros(0, dtype=int), np.zeros((0, 3))
    return ContactSet(e, e, e, e, z3, z3, z3, np.zeros(0), e, (), q, q[:, :3])


class _Lifted:
    """Gaps of fixed contact rows and the load height as functions of z = (q, plane unknowns)."""

    def __init__(self, patch: Patch, cs: ContactSet | None, lam: Array, q: Array, load: LoadPoint, F: float):
        self.load, self.F, self.n = load, F, patch.n_scales
        self.ref = np.zeros((patch.n_scales, 3))
        self.ref[:, :2] = patch.centroids
        if cs is None:
            cs = _no_contact(q)
            lam = np.zeros(0)
        on = lam > max(ACTIVE_FRACTION * float(np.max(lam, initial=0.0)), ACTIVE_FLOOR)
        self.rows = np.flatnonzero(on & (cs.side != 0))
        self.lam = lam[self.rows]
        side = cs.side[self.rows]
        self.sigma = side.astype(float)
        self.scale = np.where(side > 0, cs.b[self.rows], cs.a[self.rows])
        x = np.where((side > 0)[:, None], cs.xb[self.rows], cs.xa[self.rows])
        R0 = rotation_matrices(cs.q[:, 3:5])
        self.X = np.einsum("mji,mj->mi", R0[self.scale], x - cs.centre[self.scale])
        used, self.plane = np.unique(cs.plane[self.rows], return_inverse=True)
        memory = cs.plane_memory or {}
        keys = [cs.planes.keys[j] for j in used] if cs.planes is not None else []
        self.n0 = np.array([memory[k][0] for k in keys]).reshape(-1, 3)
        self.p0 = np.array([memory[k][1] for k in keys]).reshape(-1, 3)
        self.T0 = tangent_basis(self.n0) if len(keys) else np.zeros((0, 3, 2))
        self.size = 5 * self.n + 3 * len(keys)
        self.z0 = np.r_[q.ravel(), np.zeros(3 * len(keys))]

    def gradient_entries(self, z: Array, rows: np.ndarray | None = None) -> tuple[Array, np.ndarray]:
        """Non-zero entries ``(m, 8)`` of the active gaps' gradients at z (eqs. (1)-(2)) and their
        columns ``(m, 8)``: each row's scale DOFs (5) and plane unknowns (3)."""
        k = np.arange(len(self.rows)) if rows is None else rows
        q = z[: 5 * self.n].reshape(self.n, 5)
        th = z[5 * self.n :].reshape(-1, 3)
        s, j, sigma = self.scale[k], self.plane[k], self.sigma[k]
        R, T = rotation_matrices(q[s, 3:5]), tangent_operators(q[s, 3:5])
        c = self.ref[s] + q[s, :3]
        x = c + np.einsum("mij,mj->mi", R, self.X[k])
        v = self.n0[j] + np.einsum("mij,mj->mi", self.T0[j], th[j, :2])
        length = np.linalg.norm(v, axis=1)
        n = v / length[:, None]
        dof = np.hstack([n, np.einsum("mji,mj->mi", T, np.cross(x - c, n))])
        p = self.p0[j] + th[j, 2:3] * self.n0[j]
        proj = np.eye(3)[None] - np.einsum("mi,mj->mij", n, n)
        dn = np.einsum("mij,mjk->mik", proj, self.T0[j]) / length[:, None, None]
        dt = np.einsum("mk,mki->mi", x - p, dn)
        extra = np.hstack([dt, -np.einsum("mk,mk->m", n, self.n0[j])[:, None]])
        cols = np.hstack([5 * s[:, None] + np.arange(5), 5 * self.n + 3 * j[:, None] + np.arange(3)])
        return sigma[:, None] * np.hstack([dof, extra]), cols

    def jacobian(self, z: Array, rows: np.ndarray | None = None) -> Array:
        """Gradients (m, size) of the active gaps at z, eqs. (1)-(2); ``rows`` picks a subset."""
        vals, cols = self.gradient_entries(z, rows)
        out = np.zeros((len(vals), self.size))
        np.put_along_axis(out, cols, vals, axis=1)
        return out

    def sparse_jacobian(self, z: Array) -> sp.csr_matrix:
        """:meth:`jacobian` of every active row, sparse: eight entries a row."""
        vals, cols = self.gradient_entries(z)
        m = len(vals)
        indptr = 8 * np.arange(m + 1)
        return sp.csr_matrix((vals.ravel(), cols.ravel(), indptr), shape=(m, self.size))

    def force_gradient(self, z: Array, rows: np.ndarray | None = None, load: bool = True) -> Array:
        """sum_k lam_k grad g_k - F grad w at z: the constraint part of the Lagrangian's gradient
        (only the rows ``rows`` of the contact sum, and the load term if ``load``)."""
        k = np.arange(len(self.rows)) if rows is None else rows
        grad = np.asarray(self.lam[k] @ self.jacobian(z, k)) if len(k) else np.zeros(self.size)
        if load:
            grad[: 5 * self.n] -= self.F * self.load.gradient(z[: 5 * self.n].reshape(self.n, 5))
        return grad

    def rows_of(self, column: int) -> tuple[np.ndarray, bool]:
        """The rows whose gradient depends on unknown ``column``, and whether the load's does."""
        if column >= 5 * self.n:
            return np.flatnonzero(self.plane == (column - 5 * self.n) // 3), False
        owner = column // 5
        return np.flatnonzero(self.scale == owner), owner == self.load.scale


def _null_space(C: Array) -> Array:
    """Orthonormal basis of the null space of ``C`` (singular values below 1e-10 of the largest).

    The right singular vectors only: for a tall ``C`` (the multiplier set's ``B``: one row per
    unknown, one column per row in contact) the thin SVD holds all of them, where
    ``scipy.linalg.null_space`` forms the full square ``U`` as well (3.2 GB and minutes per call
    for the 20,000 unknowns of a 41x41 patch).  LAPACK's divide-and-conquer SVD (gesdd)
    occasionally fails to converge on these matrices (seen on the 5x5 dart); the QR-iteration
    driver (gesvd) is slower but robust.  Non-finite entries are a solver failure, reported as such.
    """
    if not np.all(np.isfinite(C)):
        raise SolverFailure("stability", "non-finite constraint gradients", detail="second variation")
    m, n = C.shape
    if n == 0:
        return np.zeros((0, 0))
    full = m < n  # then Vh must be square to hold the null space
    try:
        _, s, vh = la.svd(C, full_matrices=full)
    except la.LinAlgError:
        _, s, vh = la.svd(C, full_matrices=full, lapack_driver="gesvd")
    rank = int(np.sum(s > 1e-10 * s.max(initial=0.0))) if len(s) else 0
    return vh[rank:].T.copy()


def _base_hessian(lifted: _Lifted, K) -> Array:
    """K on the DOFs and the proximal weight on the plane unknowns (eq. (4))."""
    N, nq = lifted.size, 5 * lifted.n
    H = np.zeros((N, N))
    H[:nq, :nq] = K.toarray()
    H[nq:, nq:] = PLANE_WEIGHT * np.eye(N - nq)
    return H


def _row_hessians(lifted: _Lifted, z: Array, r: Array, dr: Array, ddr: Array) -> tuple[Array, np.ndarray]:
    """Exact Hessians (m, 8, 8) of the active gaps (contact.md eq. 20) in each row's local unknowns
    (u, phi of its scale; t, sigma of its plane) at z, and their global indices (m, 8); eq. (5).
    ``r, dr, ddr``: each row's rotated body point and its phi-derivatives at z (eq. (7))."""
    nq = 5 * lifted.n
    q, th = z[:nq].reshape(lifted.n, 5), z[nq:].reshape(-1, 3)
    s, j = lifted.scale, lifted.plane
    x = lifted.ref[s] + q[s, :3] + r
    E, n0 = lifted.T0[j], lifted.n0[j]
    v = n0 + np.einsum("mij,mj->mi", E, th[j, :2])
    length = np.linalg.norm(v, axis=1)
    nu = v / length[:, None]
    d = x - (lifted.p0[j] + th[j, 2:3] * n0)
    proj = np.eye(3)[None] - np.einsum("mi,mj->mij", nu, nu)
    dnu = np.einsum("mij,mjk->mik", proj, E) / length[:, None, None]  # (m, 3, 2)
    # d^2 nu / dt_a dt_b = -[(nu.e_a) P e_b + (nu.e_b) P e_a + (e_a' P e_b) nu] / |v|^2
    ne = np.einsum("mk,mka->ma", nu, E)
    ePd = np.einsum("mka,mkl,ml->ma", E, proj, d)
    ePe = np.einsum("mka,mkl,mlb->mab", E, proj, E)
    nd = np.einsum("mk,mk->m", nu, d)
    ne_ePd = ne[:, :, None] * ePd[:, None, :]
    tt = -(ne_ePd + ne_ePd.transpose(0, 2, 1) + ePe * nd[:, None, None]) / length[:, None, None] ** 2
    h = np.zeros((len(s), 8, 8))
    h[:, 0:3, 5:7] = dnu
    h[:, 3:5, 3:5] = np.einsum("mijk,mk->mij", ddr, nu)
    h[:, 3:5, 5:7] = np.einsum("mik,mkb->mib", dr, dnu)
    h[:, 5:7, 7] = -np.einsum("mk,mkb->mb", n0, dnu)
    h[:, 5:7, 5:7] = tt
    upper = np.triu(np.ones((8, 8), dtype=bool), 1)
    h.transpose(0, 2, 1)[:, upper] = h[:, upper]
    h *= lifted.sigma[:, None, None]
    idx = np.hstack([5 * s[:, None] + np.arange(5), nq + 3 * j[:, None] + np.arange(3)])
    return h, idx


def _hessian(lifted: _Lifted, K, z: Array | None = None) -> Array:
    """H of eq. (3) plus the plane weight of eq. (4), exact (eqs. (5)-(7)), at z (default: the state)."""
    z = lifted.z0 if z is None else z
    q = z[: 5 * lifted.n].reshape(lifted.n, 5)
    load = lifted.load
    # The load point is one more rotated body point: one batched evaluation for all of them.
    s = np.r_[lifted.scale, load.scale]
    r, dr, ddr = rotated_point_derivatives(q[s, 3:5], np.vstack([lifted.X, np.reshape(load.X, (1, 3))]))
    H = _base_hessian(lifted, K)
    if len(lifted.rows):
        h, idx = _row_hessians(lifted, z, r[:-1], dr[:-1], ddr[:-1])
        np.add.at(H, (idx[:, :, None], idx[:, None, :]), -lifted.lam[:, None, None] * h)
    ij = 5 * load.scale + np.arange(3, 5)
    H[np.ix_(ij, ij)] += lifted.F * ddr[-1, :, :, 2]
    return 0.5 * (H + H.T)


def geometric_terms(lifted: _Lifted, z: Array | None = None) -> tuple[Array, np.ndarray, Array, np.ndarray]:
    """The pieces of H that depend on the forces (eqs. (5)-(6)) at z (default: the state): every
    active row's 8 x 8 gap Hessian ``h (m, 8, 8)`` and its unknowns ``idx (m, 8)``, and the load
    point's ``hw (2, 2)`` on the loaded scale's rotations ``ij (2,)``;
    H = K + PLANE_WEIGHT I_theta - sum_v lam_v h_v + F hw."""
    z = lifted.z0 if z is None else z
    load = lifted.load
    q = z[: 5 * lifted.n].reshape(lifted.n, 5)
    s = np.r_[lifted.scale, load.scale]
    r, dr, ddr = rotated_point_derivatives(q[s, 3:5], np.vstack([lifted.X, np.reshape(load.X, (1, 3))]))
    if len(lifted.rows):
        h, idx = _row_hessians(lifted, z, r[:-1], dr[:-1], ddr[:-1])
    else:
        h, idx = np.zeros((0, 8, 8)), np.zeros((0, 8), dtype=int)
    return h, idx, ddr[-1, :, :, 2], 5 * load.scale + np.arange(3, 5)


def geometric_matrix(
    N: int, nq: int, terms: tuple[Array, np.ndarray, Array, np.ndarray], lam: Array, F: float
) -> sp.csc_matrix:
    """H - K (sparse, N x N, symmetric) for the forces ``lam`` (one per row of ``terms``) and ``F``:
    the plane weight and the geometric terms of :func:`geometric_terms`."""
    h, idx, hw, ij = terms
    planes = np.arange(nq, N)
    i = np.concatenate([planes, np.repeat(ij, 2), np.broadcast_to(idx[:, :, None], h.shape).ravel()])
    j = np.concatenate([planes, np.tile(ij, 2), np.broadcast_to(idx[:, None, :], h.shape).ravel()])
    v = np.concatenate([np.full(N - nq, PLANE_WEIGHT), (F * hw).ravel(), (-lam[:, None, None] * h).ravel()])
    G = sp.csc_matrix((v, (i, j)), shape=(N, N))
    return (0.5 * (G + G.T)).tocsc()


def padded(K, N: int) -> sp.csc_matrix:
    """K (5n x 5n) as the N x N matrix of every unknown (zero on the plane unknowns)."""
    Kc = sp.coo_matrix(K)
    return sp.csc_matrix((Kc.data, (Kc.row, Kc.col)), shape=(N, N))


def _sparse_hessian(lifted: _Lifted, K, z: Array | None = None) -> sp.csc_matrix:
    """:func:`_hessian`, sparse: the same terms summed as triplets, never an N x N array."""
    G = geometric_matrix(lifted.size, 5 * lifted.n, geometric_terms(lifted, z), lifted.lam, lifted.F)
    return (padded(K, lifted.size) + G).tocsc()


def _hessian_fd(lifted: _Lifted, K) -> Array:
    """Reference H at the state: central differences (step FD_STEP) of the exact constraint
    gradients, one unknown at a time.  Kept to test :func:`_hessian` against (the loop costs one
    gradient pair per unknown a row touches: ~30 ms per state on the 5x5 patch)."""
    n, N = lifted.n, lifted.size
    H = _base_hessian(lifted, K)
    # Unknown i enters only the gradients of its own scale's rows (or its plane's rows) and, on
    # the loaded scale, the load's: the other terms of column i are exactly zero.
    touched = np.unique(np.r_[lifted.scale, lifted.load.scale])
    columns = np.r_[(5 * touched[:, None] + np.arange(5)).ravel(), np.arange(5 * n, N)]
    for i in columns:
        e = np.zeros(N)
        e[i] = FD_STEP
        rows, loaded = lifted.rows_of(int(i))
        plus = lifted.force_gradient(lifted.z0 + e, rows, loaded)
        H[:, i] -= (plus - lifted.force_gradient(lifted.z0 - e, rows, loaded)) / (2 * FD_STEP)
    return 0.5 * (H + H.T)


def _reduced_minimum(
    patch: Patch, K, eq: Equilibrium, load: LoadPoint, tol: float, H: Array, lifted: _Lifted
) -> Stability:
    """Smallest eigenvalue of Z'HZ, eq. (4), and its mode."""
    n, N = patch.n_scales, lifted.size
    C = np.vstack([lifted.jacobian(lifted.z0), np.r_[load.gradient(eq.q), np.zeros(N - 5 * n)]])
    Z = _null_space(C)
    scale = float(np.max(K.diagonal()))
    if Z.shape[1] == 0:
        return Stability(np.inf, True, np.zeros((n, 5)), len(lifted.rows))
    # Only the smallest eigenpair is needed: LAPACK's MRRR driver (evr) stops there.
    w, V = la.eigh(Z.T @ H @ Z, subset_by_index=[0, 0])
    lo = float(w[0]) / scale
    return Stability(lo, lo > -tol, dof_mode(Z @ V[:, 0], n), len(lifted.rows))


def constraints(lifted: _Lifted, load: LoadPoint, q: Array) -> sp.csr_matrix:
    """C of eq. (4), sparse: the strongly active gaps' gradients and the load's, each row scaled to
    unit length (a row's scale does not change the null space)."""
    a = load.gradient(q)
    nz = np.flatnonzero(a)
    w = sp.csr_matrix((a[nz], nz, [0, len(nz)]), shape=(1, lifted.size))
    C = sp.vstack([lifted.sparse_jacobian(lifted.z0), w]).tocsr()
    norms = np.sqrt(np.asarray(C.multiply(C).sum(axis=1)).ravel())
    return sp.diags(1.0 / np.maximum(norms, np.finfo(float).tiny)) @ C


def _shift_inverse(H: sp.csc_matrix, C: sp.csr_matrix, sigma: float) -> spla.LinearOperator:
    """x = Z (Z'(H - sigma I)Z)^-1 Z' b by one sparse LU of the KKT matrix of the pencil (eq. (9)),
    [H - sigma I, C'; C, -eps I] [x; y] = [b; 0].  ``eps`` (KKT_REGULARISATION) lets dependent
    rows of C through; it softens a constraint only along singular values of C below about its
    square root (1e-7)."""
    N, m = H.shape[0], C.shape[0]
    kkt = sp.bmat(
        [[H - sigma * sp.identity(N, format="csc"), C.T], [C, -KKT_REGULARISATION * sp.identity(m)]],
        format="csc",
    )
    try:
        lu = spla.splu(kkt, permc_spec="MMD_AT_PLUS_A")
    except RuntimeError as exc:  # an exactly singular pencil: sigma is an eigenvalue
        failure = f"KKT factorisation failed ({exc})"
        raise SolverFailure("stability", failure, detail="second variation") from exc
    rhs = np.zeros(N + m)

    def apply(b: Array) -> Array:
        rhs[:N] = np.ravel(b)
        return lu.solve(rhs)[:N]

    return spla.LinearOperator((N, N), matvec=apply, dtype=float)


def _gershgorin_floor(G: sp.spmatrix) -> float:
    """A lower bound of the smallest eigenvalue of the symmetric ``G`` (Gershgorin's discs)."""
    G = sp.csr_matrix(G)
    d = G.diagonal()
    off = np.asarray(abs(G).sum(axis=1)).ravel() - np.abs(d)
    return float(np.min(d - off, initial=0.0))


def smallest_on_null_space(Ks: sp.csc_matrix, G: sp.csc_matrix, C: sp.csr_matrix) -> tuple[float, Array]:
    """Smallest eigenvalue of Z'(Ks + G)Z, Z an orthonormal basis of ker C, and its eigenvector
    (unit length, in the unknowns), without forming Z or any dense N x N array (sec. 8).

    ``Ks`` is positive semidefinite (the scaled stiffness), so Gershgorin's bound of ``G`` is
    below every eigenvalue of Ks + G and hence of Z'(Ks + G)Z (interlacing): the first shift,
    SHIFT_MARGIN below it, is below mu_min, and shift-invert Lanczos there (every solve one
    sparse LU of the KKT matrix) converges to mu_min.  A loose run estimates it; the next shift,
    SHIFT_STEP of the way up to the estimate, makes mu_min dominant and a tight run converges in a
    few steps.  Where it does not (mu_min in a cluster too tight to resolve from that distance:
    the separating planes' own modes, sec. 8), a loose run from that shift estimates mu_min
    again and the shift moves on, each time SHIFT_STEP of the remaining way, at most SHIFT_RUNS
    times.  The start vector is fixed: one state, one answer.
    """
    H = (Ks + G).tocsc()
    N = H.shape[0]
    floor = min(_gershgorin_floor(G), 0.0) - SHIFT_MARGIN
    start = np.random.default_rng(0).standard_normal(N)

    factored: dict[float, spla.LinearOperator] = {}  # one LU per shift (a shift's two runs share it)

    def top(sigma: float, v0: Array, tolerance: float, restarts: int | None = None) -> tuple[float, Array]:
        if sigma not in factored:
            factored[sigma] = _shift_inverse(H, C, sigma)
        theta, V = spla.eigsh(factored[sigma], k=1, which="LA", v0=v0, tol=tolerance, maxiter=restarts)
        if not theta[0] > 0:  # the operator is positive semidefinite: round-off only
            raise SolverFailure("stability", "shift above the spectrum", detail="second variation")
        return sigma + 1.0 / float(theta[0]), V[:, 0]

    def failed() -> SolverFailure:
        return SolverFailure("stability", "Lanczos did not converge", detail="second variation")

    def converged(sigma: float, v0: Array, tolerance: float) -> tuple[float, Array]:
        """``top`` with ARPACK's default restarts: not converging there fails the test."""
        try:
            return top(sigma, v0, tolerance)
        except spla.ArpackNoConvergence as exc:
            raise failed() from exc

    rough, v = converged(floor, start, LANCZOS_ROUGH)
    sigma = floor
    for _ in range(SHIFT_RUNS):
        sigma += SHIFT_STEP * (rough - sigma)
        try:
            mu, x = top(sigma, v, LANCZOS_TIGHT, TIGHT_RESTARTS)
            break
        except spla.ArpackNoConvergence:
            rough, v = converged(sigma, v, LANCZOS_ROUGH)
    else:
        raise failed()
    # A Ritz value of a loose run bounds mu_min from above; a larger answer means the last shift
    # passed mu_min (the loose run had not found the top): then the tight run from the safe shift.
    if mu > rough + 1e-9 * (rough - floor):
        mu, x = converged(floor, start, LANCZOS_TIGHT)
    return mu, x / np.linalg.norm(x)


def _sparse_reduced_minimum(
    patch: Patch, K, eq: Equilibrium, load: LoadPoint, tol: float, lifted: _Lifted
) -> Stability:
    """:func:`_reduced_minimum` without dense matrices (sec. 8)."""
    n, N = patch.n_scales, lifted.size
    scale = float(np.max(K.diagonal()))
    G = geometric_matrix(N, 5 * n, geometric_terms(lifted), lifted.lam, lifted.F)
    mu, x = smallest_on_null_space(padded(K, N) / scale, G / scale, constraints(lifted, load, eq.q))
    return Stability(mu, mu > -tol, dof_mode(x, n), len(lifted.rows))


def dof_mode(v: Array, n: int) -> Array:
    """The DOF part ``(n, 5)`` of an eigenvector ``v`` of the reduced Hessian (sec. 5): max-norm
    one, its largest entry positive."""
    mode = v[: 5 * n].reshape(n, 5)
    big = np.max(np.abs(mode))
    if big > 0:
        mode = mode / (big * np.sign(mode.ravel()[np.argmax(np.abs(mode))]))
    return mode


def _lifted(patch: Patch, eq: Equilibrium, load: LoadPoint) -> _Lifted:
    cs = eq.contacts
    if cs is not None and cs.m and np.any(cs.side == 0):
        raise ValueError("second_variation needs the plane contact formulation")
    return _Lifted(patch, cs, eq.lam, eq.q, load, eq.F)


def second_variation(patch: Patch, K, eq: Equilibrium, load: LoadPoint, tol: float = 1e-4) -> Stability:
    """Second-variation test of the converged state ``eq`` (formulations/stability.md).

    Parameters
    ----------
    patch, K : the model (K sparse 5n x 5n, E* = L = 1)
    eq : Equilibrium
        A converged state of the plane formulation (or without contact).
    load : LoadPoint
    tol : float
        Eigenvalues above ``-tol`` (relative to the largest diagonal of K) count as stable.
    """
    lifted = _lifted(patch, eq, load)
    if lifted.size > SPARSE_FROM:
        return _sparse_reduced_minimum(patch, K, eq, load, tol, lifted)
    return _reduced_minimum(patch, K, eq, load, tol, _hessian(lifted, K), lifted)


def _second_variation_fd(patch: Patch, K, eq: Equilibrium, load: LoadPoint, tol: float = 1e-4) -> Stability:
    """:func:`second_variation` with the reference finite-difference Hessian (tests only)."""
    lifted = _lifted(patch, eq, load)
    return _reduced_minimum(patch, K, eq, load, tol, _hessian_fd(lifted, K), lifted)
