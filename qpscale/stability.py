"""Stability of a converged state: the second variation of the energy on the active contact set.

Implements formulations/stability.md, eqs. (1)-(6).  Under displacement control the state is
stable when the stored energy is a strict local minimum over the configurations that keep the
load point at its depth and the scales apart.  To second order this is the Lagrangian Hessian

    H = K - sum_k lam_k grad^2 g_k + F grad^2 w

(the contact gaps g_k and the load point's height w are nonlinear in the finite rotations and in
the separating planes' unknowns) restricted to the directions that keep every strongly active
constraint at zero.  A negative eigenvalue of that restriction is a direction in which the
energy falls: the path branches there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as la

from .contact import ContactSet
from .contact_plane import tangent_basis
from .errors import SolverFailure
from .geometry import Array, rotation_matrices, tangent_operators
from .increment import Equilibrium, LoadPoint
from .tiling import Patch

# Rows whose multiplier exceeds this fraction of the largest (and ACTIVE_FLOOR, in F*) are strongly
# active (eq. (3)); the QP's multipliers of rows that carry nothing are of its tolerance's size.
ACTIVE_FRACTION = 1e-6
ACTIVE_FLOOR = 1e-8
# Finite-difference step of the Hessian of the constraint terms (eq. (5)), in L or rad.
FD_STEP = 1e-6
# Proximal weight on plane unknowns (as in the increment QP): a plane that nothing pins adds a
# zero-curvature direction that moves no scale; this keeps it out of the spectrum.
PLANE_WEIGHT = 1e-3


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

    def jacobian(self, z: Array, rows: np.ndarray | None = None) -> Array:
        """Gradients (m, size) of the active gaps at z, eqs. (1)-(2); ``rows`` picks a subset."""
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
        out = np.zeros((len(k), self.size))
        cols = 5 * s[:, None] + np.arange(5)
        dof = np.hstack([n, np.einsum("mji,mj->mi", T, np.cross(x - c, n))])
        np.put_along_axis(out, cols, sigma[:, None] * dof, axis=1)
        p = self.p0[j] + th[j, 2:3] * self.n0[j]
        proj = np.eye(3)[None] - np.einsum("mi,mj->mij", n, n)
        dn = np.einsum("mij,mjk->mik", proj, self.T0[j]) / length[:, None, None]
        dt = np.einsum("mk,mki->mi", x - p, dn)
        pc = 5 * self.n + 3 * j[:, None] + np.arange(3)
        extra = np.hstack([dt, -np.einsum("mk,mk->m", n, self.n0[j])[:, None]])
        np.put_along_axis(out, pc, sigma[:, None] * extra, axis=1)
        return out

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

    LAPACK's divide-and-conquer SVD (gesdd) occasionally fails to converge on these matrices
    (seen on the 5x5 dart); the QR-iteration driver (gesvd) is slower but robust.  Non-finite
    entries are a solver failure, reported as such.
    """
    if not np.all(np.isfinite(C)):
        raise SolverFailure("stability", "non-finite constraint gradients", detail="second variation")
    try:
        return la.null_space(C, rcond=1e-10)
    except la.LinAlgError:
        return la.null_space(C, rcond=1e-10, lapack_driver="gesvd")


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
    cs = eq.contacts
    n = patch.n_scales
    if cs is not None and cs.m and np.any(cs.side == 0):
        raise ValueError("second_variation needs the plane contact formulation")
    lifted = _Lifted(patch, cs, eq.lam, eq.q, load, eq.F)
    N = lifted.size
    H = np.zeros((N, N))
    H[: 5 * n, : 5 * n] = K.toarray()
    H[5 * n :, 5 * n :] = PLANE_WEIGHT * np.eye(N - 5 * n)
    # Unknown i enters only the gradients of its own scale's rows (or its plane's rows) and, on
    # the loaded scale, the load's: the other terms of column i are exactly zero.
    touched = np.unique(np.r_[lifted.scale, load.scale])
    columns = np.r_[(5 * touched[:, None] + np.arange(5)).ravel(), np.arange(5 * n, N)]
    for i in columns:
        e = np.zeros(N)
        e[i] = FD_STEP
        rows, loaded = lifted.rows_of(int(i))
        plus = lifted.force_gradient(lifted.z0 + e, rows, loaded)
        H[:, i] -= (plus - lifted.force_gradient(lifted.z0 - e, rows, loaded)) / (2 * FD_STEP)
    H = 0.5 * (H + H.T)
    C = np.vstack([lifted.jacobian(lifted.z0), np.r_[load.gradient(eq.q), np.zeros(N - 5 * n)]])
    Z = _null_space(C)
    scale = float(np.max(K.diagonal()))
    if Z.shape[1] == 0:
        return Stability(np.inf, True, np.zeros((n, 5)), len(lifted.rows))
    w, V = np.linalg.eigh(Z.T @ H @ Z)
    mode = (Z @ V[:, 0])[: 5 * n].reshape(n, 5)
    big = np.max(np.abs(mode))
    if big > 0:
        mode = mode / (big * np.sign(mode.ravel()[np.argmax(np.abs(mode))]))
    lo = float(w[0]) / scale
    return Stability(lo, lo > -tol, mode, len(lifted.rows))
