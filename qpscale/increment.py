"""The increment QP of a loading path and the sequential-QP equilibrium at one load level.

Implements formulations/increment.md: the prescribed displacement of a material point (1)-(3),
the increment QP (4), the sequential QP at fixed load (5)-(6) and the acceptance checks (7).
The generic QP record and the backends live in ``qp.py`` and ``solvers/``; the contact geometry
in ``contact.py``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np
import scipy.sparse as sp

from .contact import ContactSet, ContactSettings, detect_contacts, gap_jacobian, penetration
from .contact.symmetry import Mirror
from .errors import InvalidDesign, SolverFailure
from .events import Rescue
from .geometry import rotation_matrix, tangent_operator
from .qp import IncrementQP, IncrementResult, resolve_tolerance
from .solvers import solve_qp
from .tiling import Patch

NDOF = 5
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
# A load level whose step |dq| has not halved over STALL_WINDOW iterations while below STALL_BAND
# is stalled on solver noise (a plane hinge fixed only to the QP tolerance over PLANE_PROX,
# formulations/increment.md sec. 4, "Stall on noise"); its remaining QPs are solved at
# STALL_TIGHTEN x the tolerance.  Above STALL_BAND a slow step is the path's geometry, not noise.
STALL_WINDOW = 8
STALL_BAND = 1e-5
STALL_TIGHTEN = 1e-2
# A step this many times the last restarts Anderson's history (sec. 4, Acceleration): a mildly
# expanding mode is what the extrapolation cures, a leap out of the smooth region is not.
ANDERSON_GROWTH = 2.0


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
        a[base + 3 : base + 5] = tangent_operator(u[3:5]).T @ np.cross(r, [0.0, 0.0, 1.0])
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
        Weight each pressed separating plane's rotation by the force it carries and let planes
        with violated rows move (``PlaneDamping``, sec. 4b): cures the hinge 2-cycle of nearly
        parallel edges, but creeps where a plane has far to travel.  Converged states are the
        same either way; off by default, and the puncture path solves a level that fails with
        one setting again with the other (puncture.md sec. 2).
    """

    solver: str = "clarabel"
    accuracy: str | float = "high"
    step_tol: float = 0.0
    penetration_tol: float = 0.0
    max_iter: int = 60
    anderson_depth: int = 5
    plane_damping: bool = False

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


def _stalled(steps: list[float]) -> bool:
    """True when the last ``STALL_WINDOW`` steps, all below ``STALL_BAND``, did not halve the
    smallest step before them (sec. 4, "Stall on noise")."""
    if len(steps) <= STALL_WINDOW or steps[-1] > STALL_BAND:
        return False
    return min(steps[-STALL_WINDOW:]) > 0.5 * min(steps[:-STALL_WINDOW])


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
    P = sp.block_diag([K, sp.diags(w)], format="csc") if extra else K
    A = sp.csc_matrix(np.r_[a, np.zeros(extra)].reshape(1, -1))
    return IncrementQP(
        P=P,
        q=np.r_[K @ x, np.zeros(extra)],
        G=sp.csc_matrix(-J),
        h=np.asarray(contacts.gap, dtype=float),
        A=A,
        b=b,
        row_labels_A=("load",),
    )


def _with_mirror(qp: IncrementQP, mirror: Mirror, q: np.ndarray, cs: ContactSet | None) -> IncrementQP:
    """Append the equalities that hold the path on its symmetric branch (sec. 2, Held symmetry).

    ``mirror.dof_rows @ (q + dq) = 0`` keeps the configuration symmetric; with separating planes
    (symmetric at the linearisation, contact.md sec. 8) the rows of ``Mirror.plane_rows`` map
    each plane's increment onto its partner's.
    """
    D = mirror.dof_rows
    blocks = [sp.hstack([sp.csc_matrix(D), sp.csc_matrix((D.shape[0], qp.n - D.shape[1]))], format="csc")]
    rhs = [-D @ q.reshape(-1)]
    labels = [f"sym{i}" for i in range(D.shape[0])]
    if cs is not None and cs.planes is not None and cs.planes.count:
        planes = cs.planes
        rows = mirror.plane_rows(planes.keys, planes.normal, planes.point, planes.basis)
        if len(rows):
            pad = sp.csc_matrix((len(rows), D.shape[1]))
            blocks.append(sp.hstack([pad, sp.csc_matrix(rows)], format="csc"))
            rhs.append(np.zeros(len(rows)))
            labels += [f"symplane{i}" for i in range(len(rows))]
    A = sp.vstack([qp.A, *blocks], format="csc")
    return IncrementQP(
        P=qp.P,
        q=qp.q,
        G=qp.G,
        h=qp.h,
        A=A,
        b=np.concatenate([qp.b, *rhs]),
        row_labels_G=qp.row_labels_G,
        row_labels_A=tuple(qp.row_labels_A or ("load",)) + tuple(labels),
    )


class Anderson:
    """Anderson acceleration (type II, depth m) of the fixed-point map q -> q + dq(q) (sec. 4).

    The sequential QP with P = K contracts linearly at the ratio of geometric to elastic stiffness;
    near a stability limit that ratio approaches 1 (0.985 was seen on slanted darts).  With the
    contact rows unchanged the map is smooth and Anderson's secant extrapolation restores fast
    convergence; any change of the row set resets the history.
    """

    def __init__(self, depth: int = 5) -> None:
        self.depth = depth
        self.x: list[np.ndarray] = []
        self.f: list[np.ndarray] = []

    def reset(self) -> None:
        self.x.clear()
        self.f.clear()

    def step(self, x: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Next iterate from the current one and its QP step.

        Safeguards: a step more than ``ANDERSON_GROWTH`` times the last restarts the history with a
        plain step (the extrapolation had left the region where the map is smooth), and the least-squares
        problem is regularised by 1e-4 |f|^2 so that differences of round-off size (a stagnating
        residual) give small coefficients instead of cancelling the plain step.
        """
        if self.f and np.linalg.norm(f) > ANDERSON_GROWTH * np.linalg.norm(self.f[-1]):
            self.reset()
        self.x.append(x.copy())
        self.f.append(f.copy())
        if len(self.f) > self.depth + 1:
            self.x.pop(0)
            self.f.pop(0)
        if len(self.f) < 2:
            return x + f
        dF = np.diff(np.array(self.f), axis=0).T
        dG = np.diff(np.array(self.x) + np.array(self.f), axis=0).T
        mu = 1e-4 * float(f @ f)
        gamma = np.linalg.solve(dF.T @ dF + mu * np.eye(dF.shape[1]), dF.T @ f)
        return x + f - dG @ gamma


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
    floor = max(1e-6 * float(np.max(lam, initial=0.0)), 1e-12)
    pressed = (lam > floor) | (np.asarray(cs.gap) < 0.0) if violated else lam > floor
    on = pressed & (cs.plane >= 0)
    carried[np.unique(cs.plane[on])] = True
    if mirror is not None and cs.planes is not None:
        carried = mirror.orbit_any(cs.planes.keys, carried)
    return np.where(np.repeat(carried, 3), theta, 0.0)


def _accelerated(
    accel: Anderson, q: np.ndarray, dq: np.ndarray, cs: ContactSet | None
) -> tuple[np.ndarray, ContactSet | None]:
    """Anderson step of the joint fixed-point map of the DOFs and the separating planes (sec. 4).

    The planes enter as their normal and point (6 numbers each, normal re-normalised after the
    step): they converge together with the scales, so extrapolating one without the other would
    pair an extrapolated configuration with a lagging certificate.
    """
    if cs is None or cs.planes is None or not cs.planes.count:
        return accel.step(q.reshape(-1), dq.reshape(-1)).reshape(q.shape), cs
    keys = cs.planes.keys
    x_pl = np.hstack([cs.planes.normal, cs.planes.point]).ravel()
    new = cs.plane_memory
    f_pl = np.zeros_like(x_pl)
    if new:
        f_pl = np.array([np.r_[new[k][0], new[k][1]] for k in keys]).ravel() - x_pl
    z = accel.step(np.r_[q.reshape(-1), x_pl], np.r_[dq.reshape(-1), f_pl])
    planes = z[q.size :].reshape(-1, 6)
    normals = planes[:, :3] / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    memory = {k: (normals[j], planes[j, 3:]) for j, k in enumerate(keys)}
    return z[: q.size].reshape(q.shape), replace(cs, plane_memory=memory)


class LevelStatus(str, Enum):
    """How one load level ended (formulations/increment.md sec. 5)."""

    CONVERGED = "converged"
    QP_FAILED = "qp failed"
    NOT_CONVERGED = "not converged"


@dataclass(frozen=True)
class LevelOutcome:
    """The outcome of one load level: a status, the state if it converged, never an exception.

    Attributes
    ----------
    status : LevelStatus
    state : Equilibrium or None
        The converged state; None unless ``status`` is ``CONVERGED``.
    failure : SolverFailure or None
        What to report when the level failed: the backend's status, the increment, the detail.
    rescues : tuple of Rescue
        The declared rescues that fired on the way (``events.LEVEL_RESCUES``), in order.
    """

    status: LevelStatus
    state: Equilibrium | None
    failure: SolverFailure | None = None
    rescues: tuple[Rescue, ...] = ()

    @property
    def converged(self) -> bool:
        return self.status is LevelStatus.CONVERGED

    def unwrap(self) -> Equilibrium:
        """The converged state; for a failed level, raise its failure (the error a user sees)."""
        if self.state is not None:
            return self.state
        assert self.failure is not None
        raise self.failure


def _failed(status: LevelStatus, failure: SolverFailure, rescues: list[Rescue]) -> LevelOutcome:
    return LevelOutcome(status, None, failure, tuple(rescues))


def iterate_level(
    patch: Patch,
    K: sp.csc_matrix,
    q0: np.ndarray,
    load: LoadPoint,
    delta: float,
    contact: ContactSettings | None,
    settings: SQPSettings,
    increment: int | None = None,
    previous: ContactSet | None = None,
    mirror: Mirror | None = None,
) -> LevelOutcome:
    """One attempt at a load level: the sequential QP, eqs. (5)-(7), with one plane update.

    Linearise the loading constraint and the contact gaps at the current configuration, solve
    the QP, update the configuration exactly (finite rotations), repeat until the update is
    below ``step_tol``; then the exact penetration must be below ``penetration_tol``.
    ``previous`` (the contact set of the starting state) carries the separating planes (or,
    for the feature formulation, keeps each pair's axis sticky, formulations/contact.md sec. 6).
    ``mirror`` holds the path on the symmetric branch of that reflection: the antisymmetric DOF
    modes stay zero and the separating planes mirror-symmetric (sec. 2, Held symmetry).  While the
    contact rows stay the same, the iterates are Anderson-accelerated (sec. 4).  The first two
    rescues of the level's policy act inside (``qp_retry`` in :func:`qpscale.solvers.solve_qp`,
    ``stall_tighten`` here); each firing is recorded in the outcome.
    """
    q = np.array(q0, dtype=float, copy=True)
    build_s = solve_s = 0.0
    cs = previous
    accel = Anderson(settings.anderson_depth)
    rows: tuple[str, ...] | None = None
    dq = np.zeros_like(q)
    refresh: float | None = None
    damping = PlaneDamping()
    accuracy: str | float = settings.accuracy
    steps: list[float] = []
    tighten_tried = False
    rescues: list[Rescue] = []
    for it in range(1, settings.max_iter + 1):
        t0 = time.perf_counter()
        cs = (
            detect_contacts(patch, q, contact, previous=cs, refresh=refresh, mirror=mirror)
            if contact is not None
            else None
        )
        refresh = None
        J = gap_jacobian(cs, patch, q) if cs is not None and len(cs.gap) else None
        weight = damping.weights(cs) if settings.plane_damping and cs is not None and cs.n_extra else None
        qp = assemble_increment(K, q, load, delta, cs, J, weight)
        if mirror is not None:
            qp = _with_mirror(qp, mirror, q, cs)
        build_s += time.perf_counter() - t0
        res = _solve(qp, settings.solver, accuracy)
        if not res.found and accuracy != settings.accuracy:
            # The backend cannot reach the tightened tolerance: back to the one asked for.
            accuracy = settings.accuracy
            rescues.append(Rescue("stall_tighten", delta, increment, "tightened tolerance not reached"))
            res = _solve(qp, settings.solver, accuracy)
        if res.extras.get("retried"):
            rescues.append(
                Rescue("qp_retry", delta, increment, f"first status {res.extras.get('first_status')}")
            )
        x, y, residuals = res.x, res.y, res.residuals
        if not res.found or x is None or y is None or residuals is None:
            failure = SolverFailure(settings.solver, res.status, increment, res.extras.get("detail", ""))
            return _failed(LevelStatus.QP_FAILED, failure, rescues)
        solve_s += res.build_s + res.solve_s
        dq = x[: q.size].reshape(q.shape)
        theta = x[q.size :]
        if cs is not None and cs.planes is not None and len(theta):
            theta = _pinned_only(theta, cs, res.z, violated=settings.plane_damping, mirror=mirror)
            cs = replace(cs, plane_memory=cs.planes.advanced(theta))
            if settings.plane_damping:
                damping.update(cs, theta, np.asarray(res.z))
        if np.max(np.abs(dq)) <= settings.step_tol:
            q = q + dq
            pen = penetration(patch, q) if contact is not None else 0.0
            if pen > settings.penetration_tol:
                refresh = settings.penetration_tol
                continue
            lam = res.z if res.z is not None and cs is not None else np.zeros(0)
            state = Equilibrium(
                q=q,
                delta=delta,
                F=float(y[0]),
                contacts=cs,
                lam=np.asarray(lam),
                iterations=it,
                penetration=pen,
                residuals=dict(residuals),
                build_s=build_s,
                solve_s=solve_s,
                tightened=accuracy != settings.accuracy,
            )
            return LevelOutcome(LevelStatus.CONVERGED, state, None, tuple(rescues))
        steps.append(float(np.max(np.abs(dq))))
        if not tighten_tried and _stalled(steps):
            accuracy, tighten_tried = STALL_TIGHTEN * resolve_tolerance(settings.accuracy), True
            rescues.append(Rescue("stall_tighten", delta, increment, f"|dq| {steps[-1]:.3g} stalled"))
        labels = cs.labels if cs is not None else ()
        if labels != rows:
            accel.reset()
            rows = labels
        q, cs = _accelerated(accel, q, dq, cs)
    failure = SolverFailure(
        settings.solver,
        "sequential QP did not converge",
        increment,
        f"last |dq| = {np.max(np.abs(dq)):.3g} after {settings.max_iter} iterations",
    )
    return _failed(LevelStatus.NOT_CONVERGED, failure, rescues)


def _solve(qp: IncrementQP, solver: str, accuracy: str | float) -> IncrementResult:
    """``solve_qp`` without raising on a rejected answer (``found`` says, the reason is in
    ``extras["detail"]``); a backend that raises (bad data, an exception inside it) is a rejected
    answer too."""
    try:
        return solve_qp(qp, solver=solver, accuracy=accuracy, check=False)
    except SolverFailure as exc:
        return IncrementResult(
            None, None, None, False, exc.status, None, None, 0.0, 0.0, extras={"detail": exc.detail}
        )


def solve_level(
    patch: Patch,
    K: sp.csc_matrix,
    q0: np.ndarray,
    load: LoadPoint,
    delta: float,
    contact: ContactSettings | None,
    settings: SQPSettings,
    increment: int | None = None,
    previous: ContactSet | None = None,
    mirror: Mirror | None = None,
) -> LevelOutcome:
    """A load level under the declared rescue policy (sec. 5, ``events.LEVEL_RESCUES``).

    One attempt (:func:`iterate_level`); if it fails with separating planes, the level is solved
    again from the same start with the other plane update (sec. 4b): the undamped iteration can
    cycle on a hinged plane, the damped one creep where a plane travels far, and a converged
    state is a fixed point of both.  A level that fails both ways reports the first attempt's
    failure (the update the caller asked for).
    """
    first = iterate_level(patch, K, q0, load, delta, contact, settings, increment, previous, mirror)
    if first.converged or contact is None or contact.formulation != "plane":
        return first
    other = replace(settings, plane_damping=not settings.plane_damping)
    second = iterate_level(patch, K, q0, load, delta, contact, other, increment, previous, mirror)
    if not second.converged:
        return replace(first, rescues=first.rescues + second.rescues)
    fired = Rescue("other_plane_update", delta, increment, "damped" if other.plane_damping else "undamped")
    return replace(second, rescues=first.rescues + (fired,) + second.rescues)


def solve_equilibrium(
    patch: Patch,
    K: sp.csc_matrix,
    q0: np.ndarray,
    load: LoadPoint,
    delta: float,
    contact: ContactSettings | None,
    settings: SQPSettings,
    increment: int | None = None,
    previous: ContactSet | None = None,
    mirror: Mirror | None = None,
) -> Equilibrium:
    """One attempt at a load level (:func:`iterate_level`), its state or its failure raised.

    Raises
    ------
    SolverFailure
        When a QP fails its checks, or the iteration does not converge.
    """
    return iterate_level(patch, K, q0, load, delta, contact, settings, increment, previous, mirror).unwrap()
