"""One load level: the sequential iteration shared by puncture, flexure and the penalty baseline.

Implements formulations/increment.md sec. 4-5 and 4c: linearise at the current iterate, solve the
linearised problem, update exactly, repeat until the step is below the step test (5), then accept
only if the exact penetration passes (6); stall detection and its ``stall_tighten`` rescue, the
Anderson acceleration of the DOFs and the separating planes together (the plain iteration's
relaxation and its extrapolation along a straight drift instead, sec. 4c), and the outcome of the
level as a value (``LevelOutcome``), never an exception.  What varies between the three uses is
a :class:`LevelProblem`: the puncture increment QP (``qpscale.increment``), the membrane QP of
three-point bending (``qpscale.experiments.flexure``, formulations/membrane.md eq. (13)) and the
penalised Newton system (``qpscale.penalty``, formulations/penalty.md).
"""

from __future__ import annotations

import time
from collections.abc import Hashable
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from . import active_set
from .contact import ContactSet
from .errors import SolverFailure
from .events import Rescue
from .qp import IncrementQP, IncrementResult, WarmStart, resolve_tolerance
from .solvers import solve_qp

# A load level whose step has not halved over STALL_WINDOW iterations while below STALL_BAND is
# stalled on solver noise (a plane hinge fixed only to the QP tolerance over PLANE_PROX,
# formulations/increment.md sec. 4, "Stall on noise"); the answers of its next STALL_WINDOW QPs
# are made exact by the sparse active-set solve, started from them, in at most EXACT_OUTER outer
# steps (a level they do not converge is not stalled on noise).  Above STALL_BAND a slow step is
# the path's geometry, not noise.
STALL_WINDOW = 8
STALL_BAND = 1e-5
EXACT_OUTER = 20
# A step this many times the last restarts Anderson's history (sec. 4, Acceleration): a mildly
# expanding mode is what the extrapolation cures, a leap out of the smooth region is not.
ANDERSON_GROWTH = 2.0
# Relaxation of the plain iteration's step (sec. 4c; the accelerated one keeps omega = 1: relaxed,
# it reached the far branch of a bistable level and each landing was located as a jump): a step
# of the plain iteration that turns back on the one before it, by its component
# along it ``rho = dx_k . dx_(k-1) / |dx_(k-1)|^2`` below REVERSAL, marks a mode of the iteration
# map with multiplier mu < 0 (an oscillation; below -1 it grows).  The step is then scaled by
# omega / (1 - rho), the secant estimate that puts that mode's multiplier at zero, never below
# MIN_RELAXATION, and stays so for the rest of the level.
REVERSAL = -0.5
MIN_RELAXATION = 1.0 / 16.0
# Extrapolation of the plain iteration along a straight drift (sec. 4c): after DRIFT_RUN steps in a
# row parallel to the one before (cosine above DRIFT_COS) and of the same size to a factor 2, the
# step is doubled at each further such step, up to DRIFT_MAX times; a step then shorter than half
# the last along it (the drift bent or the extrapolation overshot) ends it.  Near a fold the plain
# iteration's dominant multiplier is within 2e-3 of 1: a landing moved 2.1e-3 L in 2,800 parallel
# steps and ran out of its linearisations.
DRIFT_COS = 0.999
DRIFT_RUN = 3
DRIFT_MAX = 64.0
# A step within the test that swung no plane is accepted without the confirming linearisation
# when its DOF step is also below step_tol / CONFIRM_FREE (sec. 4, eq. (5b)): at the test itself
# the accepted states were one contraction short and the energy balance flagged kinks as jumps.
CONFIRM_FREE = 10.0

L = TypeVar("L")  # one linearisation of a level problem
S = TypeVar("S")  # the converged state of a level


class LevelStatus(str, Enum):
    """How one load level ended (formulations/increment.md sec. 5)."""

    CONVERGED = "converged"
    QP_FAILED = "qp failed"
    NOT_CONVERGED = "not converged"


@dataclass(frozen=True)
class LevelOutcome(Generic[S]):
    """The outcome of one load level: a status, the state if it converged, never an exception.

    Attributes
    ----------
    status : LevelStatus
    state : S or None
        The converged state (``increment.Equilibrium``, ``flexure.FlexureState``); None unless
        ``status`` is ``CONVERGED``.
    failure : SolverFailure or None
        What to report when the level failed: the backend's status, the increment, the detail.
    rescues : tuple of Rescue
        The declared rescues that fired on the way (``events.LEVEL_RESCUES``), in order.
    solves : int
        Linearisations solved on the way, converged or not (QPs; for the penalty baseline its
        Newton systems), a retried QP counted twice.
    """

    status: LevelStatus
    state: S | None
    failure: SolverFailure | None = None
    rescues: tuple[Rescue, ...] = ()
    solves: int = 0

    @property
    def converged(self) -> bool:
        return self.status is LevelStatus.CONVERGED

    def unwrap(self) -> S:
        """The converged state; for a failed level, raise its failure (the error a user sees)."""
        if self.state is not None:
            return self.state
        assert self.failure is not None
        raise self.failure


@dataclass(frozen=True)
class LevelControls:
    """The numbers that steer one level's iteration.

    Parameters
    ----------
    solver : str
        Who solves each linearisation (a QP backend, ``penalty``), named in the failures.
    delta : float
        The load level (puncture depth or plate displacement, L), recorded with each rescue.
    increment : int or None
        Index of the level in its path, recorded with each rescue and failure.
    step_tol, penetration_tol : float
        Converged when ``max |dx| <= step_tol``, eq. (5), and the exact overlap after the step
        is at most ``penetration_tol``, eq. (6); ``inf``: reported unchecked (the penalty
        baseline, whose overlap is O(F / k) by design).
    max_iter : int
        Linearisations before the level is ``not converged``.
    anderson_depth : int
        Depth of the acceleration; 0 is the plain fixed-point iteration.
    tighten : bool
        Whether the solve has a tolerance to tighten (``stall_tighten``); False (a direct Newton
        solve) turns the stall rule off.
    unconverged : str
        The status of a level that did not converge.
    """

    solver: str
    delta: float
    increment: int | None
    step_tol: float
    penetration_tol: float
    max_iter: int
    anderson_depth: int = 5
    tighten: bool = True
    unconverged: str = "sequential QP did not converge"


@dataclass(frozen=True)
class Step(Generic[S]):
    """One linearisation solved: the step it takes, or why there is none.

    Attributes
    ----------
    answer : S or None
        The state the level ends in if this is its last step (its DOFs, counts and times are
        filled in then, by ``LevelProblem.state``); None when the solve failed.
    failure : SolverFailure or None
        Why the solve failed: the solver's status, the increment, the detail.
    dx : ndarray
        The step of the DOFs (shape of the iterate); the exact update is ``x + dx``.
    rows : ContactSet or None
        The contact set to linearise at next, its separating planes moved by the step.
    labels : Hashable
        What identifies the linearised map (with separating planes, the planes' keys,
        ``increment.map_labels``; otherwise the rows): a change restarts Anderson's history.
    seconds : float
        Time spent in the solve.
    work : int
        Iterations the step counts for (1 for a QP, the Newton steps of the penalty system).
    retried : str or None
        The first status of a QP answered only on its retry (``qp_retry``).
    swing : float
        The largest step of the unknowns beside the DOFs that the next linearisation sees (the
        separating planes' rotations and shifts, in rad and L); 0 when there are none; inf (the
        default) when the problem does not report it, and then every converged step is confirmed.
    exact : bool or None
        Whether an answer asked to be exact (``tightened``) was made the QP's exact solution;
        None when it was not asked.
    """

    answer: S | None = None
    failure: SolverFailure | None = None
    dx: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rows: ContactSet | None = None
    labels: Hashable = ()
    seconds: float = 0.0
    work: int = 1
    retried: str | None = None
    swing: float = float("inf")
    exact: bool | None = None


@dataclass(frozen=True)
class Progress:
    """What the iteration measured on its way to a converged state (the fields of
    ``increment.Equilibrium`` of those names)."""

    iterations: int
    penetration: float
    build_s: float
    solve_s: float
    tightened: bool


class LevelProblem(Protocol[L, S]):
    """What varies between the levels of puncture, flexure and the penalty baseline.

    How to linearise at an iterate with the rows carried from the last step (``refresh``:
    restart the overlapping pairs' planes, contact.md sec. 7), how to solve one linearisation
    (``tightened``: the answer made exact, ``qp_step``) into a step, the exact overlap
    at a configuration, and the converged state from the last step's answer.  A problem object
    serves one attempt at one level: it may keep that attempt's memory.
    """

    @property
    def controls(self) -> LevelControls: ...

    def linearise(self, x: np.ndarray, rows: ContactSet | None, refresh: float | None) -> L: ...

    def solve(self, lin: L, tightened: bool) -> Step[S]: ...

    def penetration(self, x: np.ndarray) -> float: ...

    def state(self, x: np.ndarray, answer: S, progress: Progress) -> S: ...


def solve(problem: LevelProblem[L, S], start: np.ndarray, rows: ContactSet | None = None) -> LevelOutcome[S]:
    """One attempt at a load level from ``start`` (formulations/increment.md sec. 4-5).

    Linearise, solve, step; converged when ``max |dx| <= step_tol``, eq. (5), twice in a row (the
    second linearisation with the rows as the first step left them: a plane's swing about its
    hinge moves no DOF in the step that makes it) or once by eq. (5b), a step that swung no plane
    (``Step.swing``) and moved the DOFs by at most a tenth of the test, and then only if
    the exact penetration at ``x + dx`` is at most ``penetration_tol``, eq. (6), otherwise the
    iteration goes on with the overlapping pairs' planes refreshed.  While the steps keep their
    labels (``Step.labels``) the iterates are Anderson-accelerated (DOFs and planes together,
    ``_accelerated``); the plain iteration's steps (``anderson_depth = 0``) are relaxed
    (``relaxation``) and extrapolated along a straight drift (``drift``) instead.
    A level whose steps stall on solver noise (``_stalled``) is solved on with exact answers,
    once, for at most ``STALL_WINDOW`` QPs, and back at the backend's own answers if the exact
    solve does not converge (``stall_tighten``); a QP answered only on its retry is recorded
    (``qp_retry``).  ``rows`` is the contact set carried in from the starting state.
    """
    c = problem.controls
    x = np.array(start, dtype=float, copy=True)
    accel = Anderson(c.anderson_depth)
    labels: Hashable = None
    dx = np.zeros_like(x)
    refresh: float | None = None
    tightened = tighten_tried = confirmed = False
    exact_left = 0
    steps: list[float] = []
    omega, last = 1.0, np.zeros(0)
    beta, run = 1.0, 0
    rescues: list[Rescue] = []
    build_s = solve_s = 0.0
    work = solves = 0
    for _ in range(c.max_iter):
        t0 = time.perf_counter()
        lin = problem.linearise(x, rows, refresh)
        refresh = None
        build_s += time.perf_counter() - t0
        step = problem.solve(lin, tightened)
        solves += step.work + (step.retried is not None)
        if tightened and step.exact is False:
            # The answer could not be made exact: the level goes on with the backend's answers.
            tightened = False
            rescues.append(Rescue("stall_tighten", c.delta, c.increment, "exact solve not reached"))
        elif tightened:
            exact_left -= 1
        if step.retried is not None:
            rescues.append(Rescue("qp_retry", c.delta, c.increment, f"first status {step.retried}"))
        if step.answer is None:
            return LevelOutcome(LevelStatus.QP_FAILED, None, step.failure, tuple(rescues), solves)
        solve_s += step.seconds
        work += step.work
        dx, rows = step.dx, step.rows
        size = float(np.max(np.abs(dx), initial=0.0))
        if size <= c.step_tol:
            x = x + dx
            pen = problem.penetration(x)
            if pen > c.penetration_tol:
                refresh, confirmed = c.penetration_tol, False
                continue
            if not confirmed and max(step.swing, CONFIRM_FREE * size) > c.step_tol:
                # One more linearisation, with the rows as the step left them: a separating plane
                # may swing about its hinge in a step that moves x by nothing, and the state is a
                # fixed point only if the next step, with the plane where it swung, is small too.
                # A step that swung nothing and is well inside the test needs no second look (5b).
                confirmed = True
                continue
            state = problem.state(x, step.answer, Progress(work, pen, build_s, solve_s, tightened))
            return LevelOutcome(LevelStatus.CONVERGED, state, None, tuple(rescues), solves)
        if confirmed:
            # Not a fixed point after all: the unaccelerated step breaks Anderson's history.
            accel.reset()
            confirmed = False
        steps.append(size)
        if tightened and not exact_left:
            # Exact answers have not converged the level: its stall is not the backend's noise (a
            # cycle of the iteration, a slow mode), which exact answers repeat at their cost.
            tightened = False
            rescues.append(Rescue("stall_tighten", c.delta, c.increment, "not noise: exact answers ended"))
        if c.tighten and not tighten_tried and _stalled(steps):
            tightened = tighten_tried = True
            exact_left = STALL_WINDOW
            rescues.append(Rescue("stall_tighten", c.delta, c.increment, f"|dx| {size:.3g} stalled"))
        if step.labels != labels:
            accel.reset()
            labels = step.labels
        if not c.anderson_depth:  # the plain iteration (the landings' descent): relaxed, extrapolated
            beta, run, ended = drift(beta, run, dx, last)
            if not ended:
                omega = relaxation(omega, dx, last)
            last = dx
        x, rows = _accelerated(accel, x, dx, rows, omega * beta)
    detail = f"last |dx| = {np.max(np.abs(dx), initial=0.0):.3g} after {c.max_iter} linearisations"
    failure = SolverFailure(c.solver, c.unconverged, c.increment, detail)
    return LevelOutcome(LevelStatus.NOT_CONVERGED, None, failure, tuple(rescues), solves)


def qp_step(
    qp: IncrementQP,
    solver: str,
    accuracy: str | float,
    tightened: bool,
    increment: int | None,
    warm_start: IncrementResult | WarmStart | None = None,
) -> tuple[IncrementResult | None, Step[Any]]:
    """``solve_qp`` as a level's solve: the answer if it passed its check, and the step so far.

    ``tightened``: the answer made the QP's exact solution (``_exact``).  ``warm_start``: a start
    for a backend that can use one (``solve_qp``).  The step carries
    the solve's time and, when the answer came only on ``solve_qp``'s own retry, its first
    status; without an answer (None), the failure to report.  ``solve_qp`` runs without raising
    (``check=False``, the reason of a rejection in ``extras["detail"]``); a backend that raises
    (bad data, an exception inside it) is a rejected answer too.
    """
    try:
        res = solve_qp(qp, solver=solver, accuracy=accuracy, check=False, warm_start=warm_start)
    except SolverFailure as exc:
        return None, Step(failure=SolverFailure(solver, exc.status, increment, exc.detail))
    retried = str(res.extras.get("first_status")) if res.extras.get("retried") else None
    if not res.found or res.x is None or res.y is None or res.z is None or res.residuals is None:
        failure = SolverFailure(solver, res.status, increment, res.extras.get("detail", ""))
        return None, Step(failure=failure, retried=retried)
    if tightened:
        return _exact(qp, res, accuracy, retried)
    return res, Step(seconds=res.build_s + res.solve_s, retried=retried)


def _exact(
    qp: IncrementQP, res: IncrementResult, accuracy: str | float, retried: str | None
) -> tuple[IncrementResult, Step[Any]]:
    """The backend's answer ``res`` made the QP's exact solution: the sparse active-set solve of
    the exact check (``active_set.solve_sparse``, formulations/increment-qp.md sec. 8) started from
    it, at most ``EXACT_OUTER`` outer steps, accepted when its residuals are within the tolerance
    of ``accuracy`` (they are at rounding).  The remedy of ``stall_tighten`` (formulations/
    increment.md sec. 4, "Stall on noise"); the backend's own answer, with the step's ``exact``
    False, when the solve does not converge."""
    assert res.x is not None and res.z is not None and res.y is not None
    t0 = time.perf_counter()
    s = active_set.solve_sparse(qp, res.x, res.z, res.y, delta0=active_set.DELTA, max_outer=EXACT_OUTER)
    seconds = res.build_s + res.solve_s + time.perf_counter() - t0
    residuals = qp.residuals(s.x, s.z, s.y)
    if not s.converged or max(residuals.values()) > resolve_tolerance(accuracy):
        return res, Step(seconds=seconds, retried=retried, exact=False)
    exact = replace(res, x=s.x, z=s.z, y=s.y, residuals=residuals, solve_s=seconds - res.build_s)
    return exact, Step(seconds=seconds, retried=retried, exact=True)


def relaxation(omega: float, dx: np.ndarray, last: np.ndarray) -> float:
    """The step's relaxation after the step ``dx`` that followed ``last`` (sec. 4c).

    With ``rho`` the component of ``dx`` along ``last`` (``dx . last / |last|^2``), a reversal
    (``rho < REVERSAL``) lowers ``omega`` to ``omega / (1 - rho)``: for a linear map whose mode
    along ``last`` has multiplier ``mu``, the relaxed iteration multiplies it by
    ``rho = 1 - omega (1 - mu)``, and ``omega / (1 - rho) = 1 / (1 - mu)`` sends it to zero.
    Never below ``MIN_RELAXATION``; never raised within a level.

    >>> relaxation(1.0, np.array([-1.5]), np.array([1.0]))  # mu = -1.5: the optimal 1/2.5
    0.4
    >>> relaxation(1.0, np.array([0.9]), np.array([1.0]))  # a slow contraction: kept
    1.0
    """
    if last.shape != dx.shape:
        return omega
    norm = float(np.vdot(last, last))
    rho = float(np.vdot(dx, last)) / norm if norm > 0.0 else 0.0
    if rho >= REVERSAL:
        return omega
    return max(MIN_RELAXATION, min(omega, omega / (1.0 - rho)))


def drift(beta: float, run: int, dx: np.ndarray, last: np.ndarray) -> tuple[float, int, bool]:
    """The plain iteration's extrapolation factor after the step ``dx`` that followed ``last``
    (sec. 4c): ``(beta, run, ended)``, ``run`` the parallel steps so far, ``ended`` when a step
    shorter than half the last along it ends an extrapolation (its reversal is the
    extrapolation's, not a mode of the map: the relaxation does not read it).

    >>> drift(1.0, 2, np.array([1.0, 0.0]), np.array([1.0, 1e-4]))  # the third parallel step
    (2.0, 3, False)
    >>> drift(8.0, 5, np.array([-0.5, 0.0]), np.array([1.0, 0.0]))  # overshot: back to 1
    (1.0, 0, True)
    """
    norm = float(np.vdot(last, last))
    if last.shape != dx.shape or norm == 0.0:
        return beta, run, False
    along = float(np.vdot(dx, last))
    rho = along / norm
    if beta > 1.0 and rho < 0.5:
        return 1.0, 0, True
    if along > DRIFT_COS * np.sqrt(norm * float(np.vdot(dx, dx))) and 0.5 < rho < 2.0:
        run += 1
        return (min(2.0 * beta, DRIFT_MAX) if run >= DRIFT_RUN else beta), run, False
    return 1.0, 0, False


def _stalled(steps: list[float]) -> bool:
    """True when the last ``STALL_WINDOW`` steps, all below ``STALL_BAND``, did not halve the
    smallest step before them (sec. 4, "Stall on noise")."""
    if len(steps) <= STALL_WINDOW or steps[-1] > STALL_BAND:
        return False
    return min(steps[-STALL_WINDOW:]) > 0.5 * min(steps[:-STALL_WINDOW])


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

    def step(self, x: np.ndarray, f: np.ndarray, beta: float = 1.0) -> np.ndarray:
        """Next iterate from the current one and its QP step, relaxed by ``beta`` (sec. 4c: the
        mixing parameter of Anderson's method, ``x + beta f - (dX + beta dF) gamma``).

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
            return x + beta * f
        dF = np.diff(np.array(self.f), axis=0).T
        dG = np.diff(np.array(self.x) + beta * np.array(self.f), axis=0).T
        mu = 1e-4 * float(f @ f)
        gamma = np.linalg.solve(dF.T @ dF + mu * np.eye(dF.shape[1]), dF.T @ f)
        return x + beta * f - dG @ gamma


def _accelerated(
    accel: Anderson, q: np.ndarray, dq: np.ndarray, cs: ContactSet | None, omega: float = 1.0
) -> tuple[np.ndarray, ContactSet | None]:
    """Anderson step of the joint fixed-point map of the DOFs and the separating planes (sec. 4).

    The planes enter as their normal and point (6 numbers each, normal re-normalised after the
    step): they converge together with the scales, so extrapolating one without the other would
    pair an extrapolated configuration with a lagging certificate.
    """
    if cs is None or cs.planes is None or not cs.planes.count:
        return accel.step(q.reshape(-1), dq.reshape(-1), omega).reshape(q.shape), cs
    keys = cs.planes.keys
    x_pl = np.hstack([cs.planes.normal, cs.planes.point]).ravel()
    new = cs.plane_memory
    f_pl = np.zeros_like(x_pl)
    if new:
        moved = [new[k] for k in keys]
        f_pl = np.hstack([[m[0] for m in moved], [m[1] for m in moved]]).ravel() - x_pl
    z = accel.step(np.r_[q.reshape(-1), x_pl], np.r_[dq.reshape(-1), f_pl], omega)
    planes = z[q.size :].reshape(-1, 6)
    normals = planes[:, :3] / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    memory = {k: (normals[j], planes[j, 3:]) for j, k in enumerate(keys)}
    return z[: q.size].reshape(q.shape), replace(cs, plane_memory=memory)
