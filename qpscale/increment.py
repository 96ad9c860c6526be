"""The increment QP of a loading path and the sequential-QP equilibrium at one load level.

Implements formulations/increment.md: the prescribed displacement of a material point (1)-(3),
the increment QP (4), the planes' trust region (sec. 4b) and the puncture level (``PunctureLevel``)
that the level driver of ``level.py`` iterates, eqs. (5)-(7), with its ``other_plane_update``
rescue (sec. 5).  The generic QP record and the backends live in ``qp.py`` and ``solvers/``; the
contact geometry in ``contact.py``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from . import condensation, level
from .contact import ContactSet, ContactSettings, detect_contacts, gap_jacobian, penetration
from .contact.symmetry import Mirror
from .errors import InvalidDesign
from .events import Rescue
from .geometry import cross, rotation_matrix, tangent_operator
from .level import LevelOutcome
from .level import LevelStatus as LevelStatus  # re-exported: a level's outcome is read with it
from .qp import IncrementQP, block_diagonal, resolve_tolerance, transpose_times
from .solvers import DEFAULT_SOLVER
from .tiling import Patch

NDOF = 5
_E_Z = np.array([0.0, 0.0, 1.0])
# Proximal weight on the separating planes' unknowns (formulations/increment.md sec. 2): makes the
# QP strictly convex in a plane no row pins; zero at a converged state, so it moves no answer.
PLANE_PROX = 1e-6
# Trust region of a pressed plane's normal (``PlaneDamping``): weight on its two rotation unknowns
# per unit of the normal force it transmits, in L (formulations/increment.md sec. 4b).
PLANE_DAMPING = 1.0
# Convergence of the sequential QP at the high accuracy (sec. 4, eqs. (5)-(6)); looser QP
# tolerances loosen both (SQPSettings).
STEP_TOL = 1e-8
PENETRATION_TOL = 1e-9


@dataclass(frozen=True)
class LoadPoint:
    """A material point of one scale, driven vertically (the paper's rigid connector).

    Parameters
    ----------
    scale : int
        Index of the loaded scale in the patch.
    X : ndarray (3,)
        The point in the scale's body frame (reference point at the origin), in L.
    """

    scale: int
    X: np.ndarray

    def height_change(self, q: np.ndarray) -> float:
        """Vertical displacement w(q) of the point, eq. (1); negative when pushed down."""
        u = q[self.scale]
        return float(u[2] + rotation_matrix(u[3:5])[2] @ self.X - self.X[2])

    def gradient(self, q: np.ndarray) -> np.ndarray:
        """dw/dq ``(5n,)``, eq. (2): e_z on u_z and T(phi)' (r x e_z) on the rotations."""
        u = q[self.scale]
        r = rotation_matrix(u[3:5]) @ self.X
        a = np.zeros(q.size)
        base = NDOF * self.scale
        a[base + 2] = 1.0
        a[base + 3 : base + 5] = tangent_operator(u[3:5]).T @ cross(r, _E_Z)
        return a

    def world(self, patch: Patch, q: np.ndarray) -> np.ndarray:
        """Current world position ``(3,)`` of the point."""
        u = q[self.scale]
        c = np.append(patch.centroids[self.scale], 0.0)
        return c + u[:3] + rotation_matrix(u[3:5]) @ self.X


@dataclass(frozen=True)
class SQPSettings:
    """Tolerances of the sequential QP at one load level (formulations/increment.md, sec. 4).

    Parameters
    ----------
    solver : str
        Backend key (``qpscale.solvers.available_solvers()``).
    accuracy : str or float
        KKT tolerance of each QP: ``high`` 1e-9, ``mid`` 1e-6, ``low`` 1e-3, or a float.
    step_tol : float
        Converged when the largest DOF increment is below this (L or rad); 0 (default): ten
        times the QP tolerance, at least 1e-8 (sec. 4: a QP solved to tol moves dq by ~tol).
    penetration_tol : float
        Largest exact overlap accepted after the rigid-body update, in L; 0 (default): the QP
        tolerance, at least 1e-9 (a QP solved to tol meets its rows to tol, no better).
    max_iter : int
        Sequential QP iterations at one load level before giving up.
    anderson_depth : int
        Depth of the Anderson acceleration (sec. 4, Acceleration); 0 is the plain fixed-point iteration, a
        descent of the energy in the K metric (the landing of a snap, puncture.md sec. 4).
    plane_damping : bool
        Weight each pressed separating plane's rotation by the force it carries
        (``PlaneDamping``, sec. 4b; planes with violated rows move either way): cures the hinge
        2-cycle of nearly parallel edges, but creeps where a plane has far to travel.  Converged
        states are the same either way; off by default, and the puncture path solves a level
        that fails with one setting again with the other (puncture.md sec. 2).
    condense : bool or None
        Solve each QP on the rows that can act and the DOFs they touch, the rest eliminated
        through the path's factored stiffness (``qpscale.condensation``, sec. 2c): the same
        answer, in QPs the size of the contact region instead of the patch.  None (default):
        from ``condensation.AUTO_FROM`` scales on.
    """

    solver: str = DEFAULT_SOLVER
    accuracy: str | float = "high"
    step_tol: float = 0.0
    penetration_tol: float = 0.0
    max_iter: int = 60
    anderson_depth: int = 5
    plane_damping: bool = False
    condense: bool | None = None

    def __post_init__(self) -> None:
        tol = resolve_tolerance(self.accuracy)
        if not self.step_tol >= 0.0 or not self.penetration_tol >= 0.0:
            raise InvalidDesign("step_tol/penetration_tol", (self.step_tol, self.penetration_tol), "[0, inf)")
        if self.step_tol == 0.0:
            object.__setattr__(self, "step_tol", max(STEP_TOL, 10.0 * tol))
        if self.penetration_tol == 0.0:
            object.__setattr__(self, "penetration_tol", max(PENETRATION_TOL, tol))


@dataclass
class Equilibrium:
    """A converged state at one load level.

    Attributes
    ----------
    q : ndarray (n, 5)
        DOFs of every scale.
    delta : float
        Prescribed downward displacement of the load point, in L.
    F : float
        Force pushing the load point down, F* (the loading constraint's multiplier).
    contacts : ContactSet or None
        The contact points of the last QP; ``lam`` their forces (F*), >= 0.
    """

    q: np.ndarray
    delta: float
    F: float
    contacts: ContactSet | None
    lam: np.ndarray
    iterations: int
    penetration: float
    residuals: dict[str, float] = field(default_factory=dict)
    build_s: float = 0.0
    solve_s: float = 0.0
    tightened: bool = False


def assemble_increment(
    K: sp.csc_matrix,
    q: np.ndarray,
    load: LoadPoint,
    delta: float,
    contacts: ContactSet | None,
    J: sp.csr_matrix | None,
    plane_weight: np.ndarray | None = None,
) -> IncrementQP:
    """The QP (4): min 1/2 dq'K dq + (K q)'dq s.t. -J dq <= g, a'dq = -delta - w(q).

    With separating planes (``contacts.n_extra`` > 0) their unknowns follow dq, with the proximal
    weights ``plane_weight`` (3 per plane, default ``PLANE_PROX``) on the diagonal.
    """
    x = q.reshape(-1)
    a = load.gradient(q)
    b = np.array([-delta - load.height_change(q)])
    if contacts is None or J is None or J.shape[0] == 0:
        A = sp.csc_matrix(a.reshape(1, -1))
        return IncrementQP(P=K, q=K @ x, A=A, b=b, row_labels_A=("load",))
    extra = contacts.n_extra
    w = np.full(extra, PLANE_PROX) if plane_weight is None else np.asarray(plane_weight, dtype=float)
    n = x.size + extra
    on = np.flatnonzero(a)
    # one entry per nonzero column, in CSC arrays directly (the triplet constructor took 0.2 ms)
    indptr = np.zeros(n + 1, dtype=np.int32)
    indptr[on + 1] = 1
    np.cumsum(indptr, out=indptr)
    A = sp.csc_matrix((a[on], np.zeros(on.size, dtype=np.int32), indptr), shape=(1, n))
    G = J.tocsc(copy=True)  # a new matrix, negated in place (``-J`` copied it again: 60 us a call)
    np.negative(G.data, out=G.data)
    return IncrementQP.assembled(
        _with_diagonal(K, w),
        np.concatenate([K @ x, np.zeros(extra)]),
        G,
        np.asarray(contacts.gap, dtype=float),
        A,
        b,
        ("load",),
    )


def _with_diagonal(K: sp.csc_matrix, w: np.ndarray) -> sp.csc_matrix:
    """``blockdiag(K, diag(w))`` in CSC, by appending to K's arrays (scipy's ``block_diag`` took
    1.6 ms a call, a tenth of a default run's assembly)."""
    if not w.size:
        return K
    n, e = K.shape[0], w.size
    indptr = np.concatenate([K.indptr, K.indptr[-1] + np.arange(1, e + 1, dtype=K.indptr.dtype)])
    indices = np.concatenate([K.indices, n + np.arange(e, dtype=K.indices.dtype)])
    return sp.csc_matrix((np.concatenate([K.data, w]), indices, indptr), shape=(n + e, n + e))


def _with_mirror(qp: IncrementQP, mirror: Mirror, q: np.ndarray, cs: ContactSet | None) -> IncrementQP:
    """Append the equalities that hold the path on its symmetric branch (sec. 2, Held symmetry).

    ``mirror.dof_rows @ (q + dq) = 0`` keeps the configuration symmetric; with separating planes
    (symmetric at the linearisation, contact.md sec. 8) the rows of ``Mirror.plane_rows`` map
    each plane's increment onto its partner's.
    """
    D = mirror.dof_rows
    r, nq = D.shape
    rows = sp.csr_matrix((0, qp.n - nq))
    if cs is not None and cs.planes is not None and cs.planes.count:
        planes = cs.planes
        rows = mirror.plane_rows(planes.keys, planes.normal, planes.point, planes.basis)
    G, h, A, b = qp.rows()
    # Both sets of rows are sparse (at most ten entries a row): stacked as triplets, so the
    # equality block grows linearly with the patch.
    Ac, Dc, Rc = sp.coo_matrix(A), sp.coo_matrix(D), sp.coo_matrix(rows)
    top = A.shape[0]
    M = sp.csc_matrix(
        (
            np.r_[Ac.data, Dc.data, Rc.data],
            (np.r_[Ac.row, top + Dc.row, top + r + Rc.row], np.r_[Ac.col, Dc.col, nq + Rc.col]),
        ),
        shape=(top + r + Rc.shape[0], qp.n),
    )
    labels = [f"sym{i}" for i in range(r)] + [f"symplane{i}" for i in range(Rc.shape[0])]
    rhs = np.concatenate([b, -D @ q.reshape(-1), np.zeros(Rc.shape[0])])
    return IncrementQP.assembled(
        qp.P, qp.q, G, h, M, rhs, tuple(qp.row_labels_A or ("load",)) + tuple(labels)
    )


@dataclass(frozen=True)
class HeldBasis:
    """The unknowns of a held QP: ``x = x0 + Z xi`` (formulations/increment.md sec. 2, "Held symmetry").

    ``Z`` (CSC, orthonormal columns) spans the increments that keep the configuration and the
    separating planes symmetric; ``x0`` takes the configuration back onto the symmetric subspace
    (the least-norm solution of ``mirror.dof_rows (q + dq) = 0``, round-off in practice).
    """

    Z: sp.csc_matrix
    x0: np.ndarray

    def lift(self, xi: np.ndarray) -> np.ndarray:
        """The full unknowns of the reduced answer ``xi``."""
        return self.x0 + self.Z @ xi


def _held(
    qp: IncrementQP, mirror: Mirror, q: np.ndarray, cs: ContactSet | None, K: sp.csc_matrix
) -> tuple[IncrementQP, HeldBasis]:
    """The held QP in the reduced unknowns xi of :class:`HeldBasis` (sec. 2, Held symmetry).

    The same problem as ``_with_mirror``'s, with its equalities solved instead of appended: the
    DOF columns ``mirror.dof_basis``, each plane orbit's null space (``Mirror.plane_block``),
    ``P_r = Z' P Z`` and the rows ``G Z``, ``A Z``.  About half the unknowns and only the load's
    equality (the default path's held QPs: 169 of 341 unknowns and 1 of 174 equalities); a
    mirror pair of contact rows becomes one row written twice.

    ``qp.P`` is ``blockdiag(K, diag(w))`` as :func:`assemble_increment` lays it out, and so is
    ``Z = blockdiag(Zq, Zp)``: ``P_r`` is block diagonal too.  Its DOF block ``Zq' K Zq`` is the
    same along a path (``Mirror.reduced_stiffness`` keeps it); only the small plane block
    ``Zp' diag(w) Zp`` is formed here, by the same sparse products as the whole one, so that
    every entry is the same sum, bit for bit.
    """
    Zq = mirror.dof_basis
    nq = Zq.shape[0]
    D = mirror.dof_rows
    S = mirror.reduced_stiffness(K)
    Z = Zq
    if qp.n > nq:
        planes = cs.planes if cs is not None else None
        if planes is None or 3 * planes.count != qp.n - nq:
            raise ValueError("held QP: extra unknowns that are not plane unknowns")
        if qp.P.indptr[nq] != K.nnz or qp.P.nnz != K.nnz + qp.n - nq:
            raise ValueError("held QP: P is not blockdiag(K, diag(w))")
        Zp, Sp = mirror.plane_block(planes.keys, planes.point, planes.basis, qp.P.data[K.nnz :])
        Z, S = block_diagonal(Zq, Zp), block_diagonal(S, Sp)
    x0 = np.zeros(qp.n)
    x0[:nq] = -transpose_times(D, D @ q.reshape(-1))
    G, h, A, b = qp.rows()
    reduced = IncrementQP.assembled(
        S,
        transpose_times(Z, qp.P @ x0 + qp.q),
        G @ Z,
        h - G @ x0,
        A @ Z,
        b - A @ x0,
        tuple(qp.row_labels_A or ("load",)),
    )
    return reduced, HeldBasis(Z, x0)


class PlaneDamping:
    """Trust region of the separating planes' normals: a proximal weight per pressed plane.

    Formulations/increment.md sec. 4b.  A pressed plane whose active rows lie on one line (two
    parallel edges, a corner on an edge) can hinge about that line; in the QP nothing but
    ``PLANE_PROX`` resists the hinge, so the QP swings the plane across the whole wedge its other
    rows allow (the dropped product of the plane's rotation and the scales' motion is then as
    large as the step), the contact force turns with it, and the next linearisation swings it
    back: the sequential QP cycles.  Short of a cycle, the hinge is fixed only to the solver's
    tolerance divided by ``PLANE_PROX``, and that noise stalls the iteration above ``step_tol``.

    The weight on a plane's two rotation unknowns is ``scale * PLANE_DAMPING * F``, F the normal
    force the plane transmitted in the last QP, and never below ``PLANE_PROX``: a plane is then
    turned only as far as its force's work pays for.  ``scale`` starts at 1 and is quartered each
    time the plane's normal increment keeps its direction without contracting fourfold (a plane
    that must travel far, a corner sliding off an edge, is not held back).  At a converged state
    the plane unknowns vanish, so the weight moves no answer.
    """

    def __init__(self) -> None:
        self.force: dict[tuple[int, int, int, int], float] = {}
        self.scale: dict[tuple[int, int, int, int], float] = {}
        self.last: dict[tuple[int, int, int, int], np.ndarray] = {}

    def weights(self, cs: ContactSet) -> np.ndarray:
        """Diagonal ``(3 P,)`` of the proximal term on the plane unknowns of ``cs``."""
        count = cs.planes.count if cs.planes is not None else 0
        w = np.full((count, 3), PLANE_PROX)
        for j, k in enumerate(cs.planes.keys if cs.planes is not None else ()):
            w[j, :2] = max(PLANE_PROX, PLANE_DAMPING * self.scale.get(k, 1.0) * self.force.get(k, 0.0))
        return w.ravel()

    def update(self, cs: ContactSet, theta: np.ndarray, lam: np.ndarray) -> None:
        """Record the forces of the last QP and its plane step ``theta`` (3 P,)."""
        if cs.planes is None or not cs.planes.count:
            return
        t = np.asarray(theta, dtype=float).reshape(-1, 3)
        dn = np.einsum("pij,pj->pi", cs.planes.basis, t[:, :2])
        on_b = cs.side > 0
        force = np.bincount(cs.plane[on_b], weights=np.asarray(lam)[on_b], minlength=cs.planes.count)
        self.force = {k: float(force[j]) for j, k in enumerate(cs.planes.keys)}
        last, self.last = self.last, {}
        for j, k in enumerate(cs.planes.keys):
            if not np.any(dn[j]):
                continue
            self.last[k] = dn[j]
            scale = self.scale.get(k, 1.0)
            if k in last and scale > 0.0 and float(dn[j] @ last[k]) > 0.25 * float(last[k] @ last[k]):
                self.scale[k] = 0.25 * scale if scale > 1e-3 else 0.0


def map_labels(cs: ContactSet | None) -> tuple:
    """What identifies the linearised map of a level for Anderson's history (sec. 4, Acceleration).

    With separating planes, the planes' keys: they are the unknowns beside the DOFs, so a new or
    dropped plane changes the map.  A vertex that enters or leaves a plane's margin band does not:
    its row is slack, and the QP's answer is that of the rows it had.  Restarting on every such
    change threw away the history exactly where it was needed (a hinged plane whose swing takes a
    far vertex in and out of the band every step, growing into a two-cycle that Anderson's secant
    step cures).  Feature rows have no unknowns of their own: their labels.
    """
    if cs is None:
        return ()
    if cs.planes is not None:
        return cs.planes.keys
    return tuple(cs.labels)


def pressed_rows(lam: np.ndarray) -> np.ndarray:
    """The rows whose multiplier counts as a force: above 1e-6 of the largest and 1e-12 (what a
    QP leaves on rows that carry nothing is of its tolerance's size)."""
    lam = np.asarray(lam, dtype=float)
    return lam > max(1e-6 * float(np.max(lam, initial=0.0)), 1e-12)


def pressed_planes(cs: ContactSet, lam: np.ndarray) -> frozenset:
    """Keys of the planes with a row that carries force (``pressed_rows``, the floor of
    ``_pinned_only``): the planes the QP's step keeps."""
    assert cs.planes is not None
    on = np.unique(cs.plane[pressed_rows(lam) & (cs.plane >= 0)])
    return frozenset(cs.planes.keys[j] for j in on.tolist())


def _pinned_only(
    theta: np.ndarray,
    cs: ContactSet,
    lam: np.ndarray | None,
    violated: bool = False,
    mirror: Mirror | None = None,
) -> np.ndarray:
    """Plane unknowns with those of free planes set to zero (their QP optimum).

    A plane is free when no row presses on it and none of its rows is violated before the step:
    nothing but the proximal weight fixes it, so the solver returns it only to its tolerance
    divided by that weight, noise that would move a certificate for no reason.  A plane with a
    violated row (the pieces have moved through where it was) must move to separate them, and
    keeps its step: zeroed, it stayed where it was, violated by up to 0.5 L after many increments,
    and every QP moved it again at the price of multipliers ``PLANE_PROX`` times its travel.
    With ``mirror`` a plane is free only if its partner is too (a symmetric step stays symmetric).
    """
    if lam is None:
        return theta
    carried = np.zeros(cs.planes.count, dtype=bool) if cs.planes is not None else np.zeros(0, dtype=bool)
    pressed = pressed_rows(lam) | (np.asarray(cs.gap) < 0.0) if violated else pressed_rows(lam)
    on = pressed & (cs.plane >= 0)
    carried[np.unique(cs.plane[on])] = True
    if mirror is not None and cs.planes is not None:
        carried = mirror.orbit_any(cs.planes.keys, carried)
    return np.where(np.repeat(carried, 3), theta, 0.0)


@dataclass(frozen=True)
class PunctureLevel:
    """One load level of a puncture path: everything the sequential QP at that level needs.

    Parameters
    ----------
    patch : Patch
    K : sparse (5n, 5n)
        The substrate stiffness.
    q0 : ndarray (n, 5)
        The starting configuration (the last converged state, or a pushed one).
    load : LoadPoint
    delta : float
        The prescribed depth, eq. (3), in L.
    contact : ContactSettings or None
        The contact rows; None: no contact.
    settings : SQPSettings
    increment : int or None
        Index of the level in its path, for the failures and rescues it reports.
    previous : ContactSet or None
        The contact set of the starting state: it carries the separating planes (or, for the
        feature formulation, keeps each pair's axis sticky, formulations/contact.md sec. 6).
    mirror : Mirror or None
        Holds the path on the symmetric branch of that reflection: the antisymmetric DOF modes
        stay zero and the separating planes mirror-symmetric (sec. 2, Held symmetry).
    """

    patch: Patch
    K: sp.csc_matrix
    q0: np.ndarray
    load: LoadPoint
    delta: float
    contact: ContactSettings | None
    settings: SQPSettings
    increment: int | None = None
    previous: ContactSet | None = None
    mirror: Mirror | None = None

    def iterate(self) -> LevelOutcome[Equilibrium]:
        """One attempt: the sequential QP, eqs. (5)-(7), by the level driver (:func:`level.solve`).

        Linearise the loading constraint and the contact gaps at the current configuration, solve
        the QP, update the configuration exactly (finite rotations), repeat until the update is
        below ``step_tol``; then the exact penetration must be below ``penetration_tol``.  The
        first two rescues of the level's policy act inside (``qp_retry`` in
        :func:`qpscale.solvers.solve_qp`, ``stall_tighten`` in :func:`qpscale.level.solve`); each
        firing is recorded in the outcome.  ``.iterate().unwrap()`` is the state, or the failure
        raised as :class:`~qpscale.errors.SolverFailure`.
        """
        return level.solve(_SequentialQP(self), self.q0, self.previous)

    def increment_qp(self) -> tuple[IncrementQP, ContactSet | None]:
        """The increment QP (4) linearised at ``q0`` with the rows of ``previous``, and its contact
        set (its planes as they are, the memory the second variation reads).  At a converged
        state the QP's solution is dq ~ 0: its exact solution checks the state (``certify``) and
        its multiplier set decides the state's stability (``multipliers``)."""
        _, qp, cs, _ = _SequentialQP(self, reduced=False).linearise(self.q0, self.previous, None)
        if cs is not None and cs.planes is not None:
            cs = replace(cs, plane_memory=cs.planes.advanced(np.zeros(3 * cs.planes.count)))
        return qp, cs

    def solve(self) -> LevelOutcome[Equilibrium]:
        """The level under the declared rescue policy (sec. 5, ``events.LEVEL_RESCUES``).

        One attempt (:meth:`iterate`); if it fails with separating planes, the level is solved
        again from the same start with the other plane update (sec. 4b): the undamped iteration
        can cycle on a hinged plane, the damped one creep where a plane travels far, and a
        converged state is a fixed point of both.  A level that fails both ways reports the first
        attempt's failure (the update the caller asked for).
        """
        first = self.iterate()
        if first.converged or self.contact is None or self.contact.formulation != "plane":
            return first
        other = replace(self.settings, plane_damping=not self.settings.plane_damping)
        second = replace(self, settings=other).iterate()
        solves = first.solves + second.solves
        if not second.converged:
            return replace(first, rescues=first.rescues + second.rescues, solves=solves)
        how = "damped" if other.plane_damping else "undamped"
        fired = Rescue("other_plane_update", self.delta, self.increment, how)
        return replace(second, rescues=first.rescues + (fired,) + second.rescues, solves=solves)


# The increment QP linearised at a configuration q, its contact set (None without contact) and,
# on a held path, the basis its reduced unknowns lift through (None: the QP's unknowns are x).
_Linearised = tuple[np.ndarray, IncrementQP, ContactSet | None, HeldBasis | None]


class _SequentialQP:
    """One attempt at a puncture level as a :class:`level.LevelProblem` (sec. 4).

    Linearise the loading constraint and the contact gaps at the configuration (and hold the
    symmetric branch with ``mirror``) into the increment QP (4), solve it, keep the unknowns of
    the planes some row presses (``_pinned_only``) and, with ``plane_damping``, the trust region
    of the pressed planes (``PlaneDamping``, the attempt's memory).
    """

    def __init__(self, at: PunctureLevel, reduced: bool = True) -> None:
        s = at.settings
        self.at, self.damping, self.reduced = at, PlaneDamping(), reduced
        self.joined: set[int] = set()  # pairs a step brought into the screened QP (sec. 2c)
        self.pressed: frozenset = frozenset()  # keys of the planes the last QP's rows pressed
        auto = at.patch.n_scales >= condensation.AUTO_FROM
        self.condense = s.condense if s.condense is not None else auto
        self.controls = level.LevelControls(
            s.solver, at.delta, at.increment, s.step_tol, s.penetration_tol, s.max_iter, s.anderson_depth
        )

    def linearise(self, q: np.ndarray, rows: ContactSet | None, refresh: float | None) -> _Linearised:
        at, damped = self.at, self.at.settings.plane_damping
        cs = None
        # A pressed plane left edge-on behind its pieces restarts from their best axis (sec. 4,
        # "Stale pressed planes"): its linearised turn is a constant step that Anderson's
        # extrapolation cannot converge.  The plain iteration (a landing's descent) converges
        # through it and keeps its linearisations.
        pressed = self.pressed if at.settings.anderson_depth > 0 else frozenset()
        if at.contact is not None:
            cs = detect_contacts(
                at.patch, q, at.contact, previous=rows, refresh=refresh, mirror=at.mirror, pressed=pressed
            )
        J = gap_jacobian(cs, at.patch, q) if cs is not None and len(cs.gap) else None
        weight = self.damping.weights(cs) if damped and cs is not None and cs.n_extra else None
        qp = assemble_increment(at.K, q, at.load, at.delta, cs, J, weight)
        if at.mirror is None:
            return (q, qp, cs, None)
        if not self.reduced:
            return (q, _with_mirror(qp, at.mirror, q, cs), cs, None)
        reduced, held = _held(qp, at.mirror, q, cs, at.K)
        return (q, reduced, cs, held)

    def solve(self, lin: _Linearised, tightened: bool) -> level.Step[Equilibrium]:
        q, qp, cs, held = lin
        at, s = self.at, self.at.settings
        if self.condense:
            Kc = at.K if held is None or at.mirror is None else at.mirror.reduced_stiffness(at.K)
            groups = cs.a * at.patch.n_scales + cs.b if cs is not None else np.zeros(0, dtype=int)
            block = condensation.constant_block(Kc)
            res, step = condensation.screened_step(
                qp, block, groups, self.joined, s.solver, s.accuracy, tightened, at.increment
            )
        else:
            res, step = level.qp_step(qp, s.solver, s.accuracy, tightened, at.increment)
        if res is None:
            return step
        x = np.asarray(res.x) if held is None else held.lift(np.asarray(res.x))
        lam = np.asarray(res.z)
        theta = x[q.size :]
        if cs is not None and cs.planes is not None and len(theta):
            theta = _pinned_only(theta, cs, lam, violated=True, mirror=at.mirror)
            self.pressed = pressed_planes(cs, lam)
            cs = replace(cs, plane_memory=cs.planes.advanced(theta))
            if s.plane_damping:
                self.damping.update(cs, theta, lam)
        F, residuals = float(np.asarray(res.y)[0]), dict(res.residuals or {})
        answer = Equilibrium(q, at.delta, F, cs, lam if cs is not None else np.zeros(0), 0, 0.0, residuals)
        swing = float(np.max(np.abs(theta), initial=0.0))
        return replace(
            step, answer=answer, dx=x[: q.size].reshape(q.shape), rows=cs, labels=map_labels(cs), swing=swing
        )

    def penetration(self, q: np.ndarray) -> float:
        return penetration(self.at.patch, q) if self.at.contact is not None else 0.0

    def state(self, q: np.ndarray, answer: Equilibrium, progress: level.Progress) -> Equilibrium:
        return replace(answer, q=q, **asdict(progress))
