"""Continuation of the equilibria of one loading, from the unloaded state to failure.

Implements formulations/puncture.md sec. 2 (the path: first step from the linear response, the
secant predictor, the step rule (S), the energy balance (R) that locates jumps, the curvature cap,
the landing by the plain iteration), sec. 3 (the failure state: tilt = phi_c located by Illinois
regula falsi, or failure by a snap) and sec. 4 (the second-variation test of every state with
qpscale/stability.py, the location of a loss of stability, branch switching along the unstable
mode, and the held-symmetric branch left at a bifurcation or where the free problem no longer
balances its states).

A :class:`Path` is given

(a) a level solver (:class:`LevelSolver`): the converged state at a depth from a start state, or
    why there is none (``increment.PunctureLevel.solve`` through :class:`SQPLevels`, or the penalty
    baseline through :class:`PenaltyLevels`);
(b) the functions of a state it reads (:class:`StateFunctions`): stored energy, how much the
    energy moves per unit of error in q, tilt, stability;
(c) what it is asked for (:class:`PathSettings`): the failure tilt, the target number of
    increments, whether states are tested and jumps located;

and records what happens on it as the typed events of :mod:`qpscale.events` in ``Path.events``:
``Rescue`` (the level's own and the path's ``halve_step`` / ``plain_iteration``),
``ContactChange``, ``Snap``, ``Branch`` and ``Failure``; what its stability probe found over the
whole path is a :class:`BranchRecord`.  Which loading it is (the load point, the model, the
symmetry held) is the caller's: ``qpscale.experiments.puncture`` builds the puncture test's paths.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp

from .contact import ContactSet, ContactSettings
from .contact.symmetry import Mirror
from .errors import SolverFailure
from .events import Branch, ContactChange, Event, Failure, Rescue, Snap
from .geometry import tilt
from .increment import STEP_TOL, Equilibrium, LevelOutcome, LoadPoint, PunctureLevel, SQPSettings
from .level import qp_step
from .multipliers import uniform_second_variation
from .penalty import PenaltySettings, penalty_level
from .qp import IncrementQP
from .stability import Stability, second_variation
from .tiling import Patch

# Size of the push along an unstable mode before the path is continued on the branch, in L.
BRANCH_PUSH = 1e-4
# A step releasing more than this fraction of its work is bisected as a possible jump between
# equilibria, and a jump surviving down to SNAP_RESOLUTION * delta is a snap (sec. 2).
SNAP_WORK = 1e-3
# Smallest eigenvalue of the second variation (relative to K's largest diagonal) still counted as
# stable: the Hessian is exact (the state's accuracy moves mu by ~1e-7), and a pitchfork's eigenvalue falls
# through zero at a slope of order 1e-3 per L of depth, so the branch point moves by ~1e-3 L.
STABILITY_TOL = 1e-6
# The ceiling of a located loss of stability, re-solved from the last stable state once its bracket
# is below the resolution, dismisses the instability only if it is stable by at least this margin
# (mu + STABILITY_TOL, relative like mu): the state's accuracy moves mu by ~1e-7, so a smaller
# margin is the ceiling's verdict within noise.  Dismissed on such a margin, a path whose
# eigenvalue falls slowly through the tolerance re-found the instability one step on, every step
# (a held 3x3 dart path: margins of 1e-9; it advanced 1e-4 L in 640 increments; puncture.md sec. 4).
VERDICT_NOISE = 1e-7
# Iterations allowed to the landing of a jump: the plain iteration leaves an unstable state at the
# rate of its negative eigenvalue, slowly near the branch point.
LANDING_MAX_ITER = 3000
SNAP_RESOLUTION = 1e-7
# A jump whose landing stays below phi_c is located to this fraction of its depth only: where it
# lies within the bracket changes only the start of the landing (the state 1e-5 instead of 1e-7
# of the depth below it), not the branch it lands on (5x5 triangle 60/45: F_c* the same to 1e-9),
# so the last 7 halvings bought nothing but levels.  A landing past phi_c is the failure, and its
# bracket is refined to ``SNAP_RESOLUTION`` before it is reported.  (A path of twenty snaps can
# land otherwise: fuzz design 78, puncture.md sec. 2.)  So is a loss of stability off a held path
# (puncture.md sec. 4): on hinged planes its eigenvalue can jump between two values with the
# state the level converged to, and regula falsi crept (the dart slanted towards 45 deg: 132
# levels while its kept states advanced by 1.9e-6 L).
JUMP_RESOLUTION = 1e-5
# A converged state lies within this many step tolerances of the exact one (the sequential QP
# stops at |dq| <= step_tol and contracts at a rate of 0.5-0.9): the energy balance's noise floor.
STATE_ERROR = 10.0
# Target error of the secant predictor, in L or rad (``_growth``): the step is sized by it.
PREDICTOR_ERROR = 1e-3
# States kept inside brackets (locating events) allowed per step of the path's budget: the budget
# counts steps only (``run``), and this bound keeps a cycle of brackets that never lets a step
# through finite (fuzz design 78, 22 located snaps, kept 562 states on its way to phi_c).
LOCATED_PER_STEP = 3
# The secant predictor extrapolates over at most this many times its base (``predict``): the step
# rule (S) grows the step by at most 2.
PREDICTOR_REACH = 2.0
# A held state is an equilibrium of the free problem when the free increment QP linearised at it
# moves the DOFs by at most this (L): the held states of the corner-loaded 5x5 square, hexagon and
# triangle move by at most 6e-9; fuzz design 866's held branch left the free problem's at 3e-5,
# growing to 0.06 L (puncture.md sec. 4, "a held branch that stops being an equilibrium").
HELD_FREE_TOL = 1e-6
# The failure state's tilt must lie within this fraction of phi_c (issue #5: F_c at phi_c to 1e-6).
TILT_LOCATED = 1e-6
# The failure search stops at a state whose tilt is within this fraction of phi_c: states solved at
# one depth from different starts differ by ~2e-9 phi_c in tilt (default scene), so a tighter
# target only re-solves the noise (13 more levels there), and F_c moves by ~1e-9 across it.
TILT_TARGET = 1e-8
# A failure search's cut whose level fails is halved towards the bracket's lower end up to this many
# times (``Path._cut``), as the path halves a step whose level fails.
FAILURE_SEARCH_HALVINGS = 8


class LevelSolver(Protocol):
    """One load level: the converged state at depth ``delta`` started from ``start``.

    ``index`` is the increment (for the records; -1 for a push off a branch); ``descent`` asks
    for the plain fixed-point iteration, an energy descent in the K metric (the landing of a jump,
    formulations/puncture.md sec. 2).  The outcome carries the state or the failure, and the
    rescues that fired on the way.
    """

    def __call__(
        self, start: Equilibrium, delta: float, index: int, descent: bool = False
    ) -> LevelOutcome: ...


@dataclass(frozen=True)
class SQPLevels:
    """The sequential-QP level (``increment.PunctureLevel.solve``) under the path's settings.

    ``mirror`` holds the level on the symmetric branch of that reflection (configuration and
    separating planes, formulations/puncture.md sec. 4).
    """

    patch: Patch
    K: sp.csc_matrix
    load: LoadPoint
    contact: ContactSettings | None
    settings: SQPSettings
    mirror: Mirror | None = None

    def __call__(self, start: Equilibrium, delta: float, index: int, descent: bool = False) -> LevelOutcome:
        return self.at(start, delta, index, descent).solve()

    def increment_qp(self, state: Equilibrium) -> tuple[IncrementQP, ContactSet | None]:
        """The increment QP linearised at a converged ``state`` and its contact set
        (``PunctureLevel.increment_qp``)."""
        return self.at(state, state.delta).increment_qp()

    def at(
        self, start: Equilibrium, delta: float, index: int | None = None, descent: bool = False
    ) -> PunctureLevel:
        """The level at depth ``delta`` from ``start`` (its contact rows and planes)."""
        return PunctureLevel(
            self.patch,
            self.K,
            start.q,
            self.load,
            delta,
            self.contact,
            self.sqp(descent),
            index,
            start.contacts,
            self.mirror,
        )

    def sqp(self, descent: bool = False) -> SQPSettings:
        """The SQP settings of a level: the plain iteration for a landing (``descent``), and no
        plane damping on a held-symmetry path: it moves no converged state, but a fold located
        with it depended on the step (1.4e-5 over 6-30 increments against 4e-7 without,
        formulations/puncture.md sec. 4).  Off a held path a landing damps the planes first: the
        undamped plain iteration cycles on a hinged plane for all its ``LANDING_MAX_ITER``
        iterations before the other update is tried (puncture.md sec. 2, Landing)."""
        settings = self.settings
        if self.mirror is not None:
            settings = replace(settings, plane_damping=False)
        if descent:
            settings = replace(settings, anderson_depth=0, max_iter=LANDING_MAX_ITER)
            if self.mirror is None:
                settings = replace(settings, plane_damping=True)
        return settings


@dataclass(frozen=True)
class PenaltyLevels:
    """The penalty baseline's level (``penalty.penalty_level``, formulations/penalty.md); it has
    no plain iteration of its own, so a landing is solved like any level."""

    patch: Patch
    K: sp.csc_matrix
    load: LoadPoint
    contact: ContactSettings | None
    settings: PenaltySettings

    def __call__(self, start: Equilibrium, delta: float, index: int, descent: bool = False) -> LevelOutcome:
        return penalty_level(
            self.patch,
            self.K,
            start.q,
            self.load,
            delta,
            self.contact,
            self.settings,
            increment=index,
            previous=start.contacts,
        )


@dataclass(frozen=True)
class StateFunctions:
    """The functions of a converged state that the path reads.

    Attributes
    ----------
    energy : callable
        Stored energy of a state (F* L): the energy balance (R) and the branch of lower energy.
    force_norm : callable
        |dE/dq|_1, how much the stored energy moves per unit of error in q: the noise floor of (R).
    tilt : callable
        Tilt of the loaded face (rad): the failure criterion, tilt = phi_c (sec. 3).
    stability : callable
        The second-variation test of a state (sec. 4).
    """

    energy: Callable[[Equilibrium], float]
    force_norm: Callable[[Equilibrium], float]
    tilt: Callable[[Equilibrium], float]
    stability: Callable[[Equilibrium], Stability]

    @classmethod
    def of_point_load(
        cls, patch: Patch, K: sp.csc_matrix, load: LoadPoint, levels: SQPLevels | None = None
    ) -> StateFunctions:
        """The quadratic substrate energy 1/2 q'Kq, the tilt of the loaded scale's top face
        (geometry.md eq. 3) and the second variation of ``stability.second_variation`` with the
        path's tolerance ``STABILITY_TOL``.

        With ``levels`` (the path's sequential-QP levels, whose contact forces need not be
        unique) a state that the state's own multipliers call unstable is decided over the whole
        multiplier set (``multipliers.uniform_second_variation``, stability.md sec. 7): the
        verdict then does not depend on which point of the set the backend returned.  A state
        they call stable is stable over the set too (its value is at least theirs).
        """

        def energy(eq: Equilibrium) -> float:
            x = eq.q.ravel()
            return 0.5 * float(x @ (K @ x))

        def force_norm(eq: Equilibrium) -> float:
            return float(np.abs(K @ eq.q.ravel()).sum())

        def tilt_of(eq: Equilibrium) -> float:
            return tilt(eq.q[load.scale, 3:5])

        def stability(eq: Equilibrium) -> Stability:
            own = second_variation(patch, K, eq, load, tol=STABILITY_TOL)
            if own.stable or levels is None or eq.contacts is None or not len(eq.lam):
                return own
            qp, rows = levels.increment_qp(eq)
            return uniform_second_variation(patch, K, replace(eq, contacts=rows), load, qp, STABILITY_TOL)

        return cls(energy, force_norm, tilt_of, stability)


@dataclass(frozen=True)
class PathSettings:
    """What one path is asked for.

    Parameters
    ----------
    phi_c_deg : float
        Failure tilt, degrees (sec. 3).
    increments : int
        Target number of increments up to failure: the first step and the step's upper bound
        are sized by it (sec. 2).
    max_increments : int
        States allowed before the path gives up (``failure tilt not reached``).
    solver : str
        Name of the level's backend, for the failures the path reports.
    check : bool
        Test every converged state by the second variation, locate and leave instabilities (sec. 4).
    conservative : bool
        The energy balance (R) holds (exact frictionless contact: the plane rows, or none), so
        jumps are located; the feature rows' sticky axis and the penalty dissipate ~1e-3 of the
        work (sec. 2).
    """

    phi_c_deg: float
    increments: int
    max_increments: int
    solver: str
    check: bool = False
    conservative: bool = True


@dataclass(frozen=True)
class BranchRecord:
    """What the stability probe found on the path of one load point (sec. 4).

    Attributes
    ----------
    check : str
        ``second variation`` or ``off``.
    mirror : bool or None
        True when the load point lies on a mirror line and the path was first held symmetric.
    branched : bool
        A confirmed loss of stability was left along its mode.
    delta_branch : float, tuple of two floats, or None
        Depth of the first branch point; on a held path the bracket of its located bifurcation.
    min_eigenvalue : float or None
        Smallest eigenvalue of the second variation at a held path's bifurcation.
    followed : str or None
        The branch the path took: ``lower-energy side`` or ``asymmetric``.
    asymmetry_at_failure : float or None
        Largest DOF difference between the failure state and its mirror image (held paths).
    """

    check: str
    mirror: bool | None = None
    branched: bool = False
    delta_branch: float | tuple[float, float] | None = None
    min_eigenvalue: float | None = None
    followed: str | None = None
    asymmetry_at_failure: float | None = None

    @classmethod
    def of_events(cls, events: list[Event], check: bool) -> BranchRecord:
        """The record of a path held by no symmetry: its first confirmed ``Branch`` event."""
        branches = [e for e in events if isinstance(e, Branch) and e.confirmed]
        record = cls(check="second variation" if check else "off", branched=bool(branches))
        if branches:
            record = replace(record, delta_branch=branches[0].delta, followed="lower-energy side")
        return record

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of the command line's ``branch`` (docs/cli.md): the fields that are
        set, in the order above, a bracket as a list."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None:
                out[f.name] = list(value) if isinstance(value, tuple) else value
        return out


class Bifurcation(Exception):
    """A held-symmetric path reached a located state whose unstable mode breaks the symmetry.

    Attributes
    ----------
    before : list of Equilibrium
        The held path's states up to the last stable one.
    state : Equilibrium
        The first unstable state, within ``SNAP_RESOLUTION`` of the last stable one.
    stability : Stability
        Its second variation (the mode the path leaves along).
    step : float
        The step the path had before the bisection, to resume with.
    """

    def __init__(
        self, before: list[Equilibrium], state: Equilibrium, stability: Stability, step: float
    ) -> None:
        super().__init__("symmetric path lost stability")
        self.before, self.state, self.stability, self.step = before, state, stability, step


class HeldBranchEnds(Exception):
    """A held-symmetric path reached a state that is no equilibrium without the mirror constraints.

    Attributes
    ----------
    before : list of Equilibrium
        The held path's states up to the last one the free problem balances.
    state : Equilibrium
        The first held state it does not.
    step : float
        The step the path had, to resume with.
    """

    def __init__(self, before: list[Equilibrium], state: Equilibrium, step: float) -> None:
        super().__init__("the held branch is no equilibrium of the free problem")
        self.before, self.state, self.step = before, state, step


class Path:
    """The continuation of one loading: the level solver, the functions of a state, the events.

    Parameters
    ----------
    level : LevelSolver
        Solves a load level from a start state.
    functions : StateFunctions
        Energy, its sensitivity, tilt and stability of a state.
    settings : PathSettings
        Failure tilt, increments, whether states are tested and jumps located.
    origin : Equilibrium
        The unloaded state the path starts from.
    mirror : Mirror or None
        The reflection the level holds the path symmetric about (the same as the level
        solver's); a located instability whose mode breaks it raises :class:`Bifurcation`.

    Attributes
    ----------
    events : list of Event
        What happened on the path, in order.
    solves : int
        Load levels solved.
    qp_solves : int
        Linearisations (QPs) those levels solved, every attempt counted (``LevelOutcome.solves``).
    """

    def __init__(
        self,
        level: LevelSolver,
        functions: StateFunctions,
        settings: PathSettings,
        origin: Equilibrium,
        mirror: Mirror | None = None,
    ) -> None:
        self.level, self.functions, self.settings = level, functions, settings
        self._origin = origin
        self.phi_c = np.deg2rad(settings.phi_c_deg)
        self.solves = self.qp_solves = 0
        self.events: list[Event] = []
        self.mirror = mirror
        self.smooth_from = 0  # first state after the last jump (the curvature cap's window)
        self.unconfirmed = False  # an instability whose pushes found no lower energy (run)
        self.base_step: float | None = None  # the first run's first step: the step bounds (run)
        self.probe: Equilibrium | None = None  # the origin's linear response (first_step)

    def solve(self, start: Equilibrium, delta: float, index: int, descent: bool = False) -> LevelOutcome:
        """The level at depth ``delta`` from ``start`` under the level's rescue policy;
        ``descent``: by the plain fixed-point iteration, an energy descent in the K metric (the
        landing of a jump, sec. 4).  The rescues that fired join the path's events."""
        self.solves += 1
        outcome = self.level(start, delta, index, descent)
        self.qp_solves += outcome.solves
        self.events.extend(outcome.rescues)
        return outcome

    def energy(self, eq: Equilibrium) -> float:
        """Stored energy of a state (F* L)."""
        return self.functions.energy(eq)

    def stability(self, eq: Equilibrium) -> Stability:
        """The second-variation test of a converged state (sec. 4)."""
        return self.functions.stability(eq)

    def tilt_of(self, eq: Equilibrium) -> float:
        """Tilt of the loaded face (rad)."""
        return self.functions.tilt(eq)

    def free_balanced(self, eq: Equilibrium) -> bool:
        """Whether a held state is an equilibrium without the mirror constraints: the free
        increment QP linearised at it (its planes as they are) moves the DOFs by at most
        ``HELD_FREE_TOL``.  Only the sequential-QP level of a held path is tested; a free QP that
        the backend cannot solve says nothing (``level.qp_step``: no answer, whatever the backend
        did), and the state is kept (its level converged)."""
        if self.mirror is None or not isinstance(self.level, SQPLevels) or eq.contacts is None:
            return True
        qp, _ = replace(self.level, mirror=None).increment_qp(eq)
        self.qp_solves += 1
        res, _ = qp_step(qp, self.level.settings.solver, self.level.settings.accuracy, False, None)
        if res is None or res.x is None:
            return True
        return float(np.max(np.abs(res.x[: eq.q.size]), initial=0.0)) <= HELD_FREE_TOL

    def origin(self) -> Equilibrium:
        """The unloaded state."""
        return self._origin

    def branch_off(
        self, eq: Equilibrium, sv: Stability, sides: tuple[float, ...], resolved: bool = True
    ) -> Equilibrium:
        """Push ``eq`` along the unstable mode (each side given), re-solve at the same depth and
        keep the state of lowest energy (it lies on the branch the path takes).

        With ``resolved`` a landing counts only if it holds less energy than ``eq`` by more than
        the two states can resolve (``noise``): a push of 1e-4 L that the plain iteration brings
        back to ``eq`` changes the energy by round-off, and taking that as a branch restarted the
        path from ``eq`` itself and found the same instability again (fuzz design 140, sec. 4).
        The caller records the branch (``record_branch``) once it takes the landing.
        """
        energy = self.energy(eq)
        if resolved:
            energy -= self.noise(eq, eq)
        best: tuple[float, Equilibrium] | None = None
        for side in sides:
            start = Equilibrium(
                eq.q + side * BRANCH_PUSH * sv.mode, eq.delta, eq.F, eq.contacts, eq.lam, 0, 0.0
            )
            outcome = self.solve(start, eq.delta, -1, descent=True)
            if outcome.state is None:
                continue
            moved = outcome.state
            e = self.energy(moved)
            if e < energy and (best is None or e < best[0]):
                best = (e, moved)
        return best[1] if best else eq

    def record_branch(
        self, eq: Equilibrium, sv: Stability, landing: Equilibrium, confirmed: bool = True
    ) -> None:
        """Record the :class:`Branch` event of ``landing``, taken from the unstable ``eq``: the
        energy it released (zero when no push lowered the energy and ``landing`` is ``eq``)."""
        drop = self.energy(eq) - self.energy(landing) if landing is not eq else 0.0
        self.events.append(Branch(eq.delta, sv.min_eigenvalue, drop, confirmed))

    def breaks_symmetry(self, sv: Stability) -> bool:
        """On a symmetric path: the unstable mode is mostly antisymmetric (a bifurcation off the
        branch) rather than symmetric (a fold of the branch itself, crossed by a snap)."""
        if self.mirror is None:
            return False
        mode = sv.mode.ravel()
        return bool(np.linalg.norm(self.mirror.dof_rows @ mode) ** 2 > 0.5 * float(mode @ mode))

    def first_step(self, origin: Equilibrium) -> float:
        """Step from the linear response: delta at failure ~ phi_c / (d tilt / d delta).

        The probe's state is kept (``probe``): the path's first level starts from it, scaled to
        the level's depth (``_linear_response``; formulations/puncture.md sec. 2, Predictor)."""
        probe = 1e-4
        eq = self.solve(origin, probe, 0).unwrap()
        self.probe = eq
        rate = self.tilt_of(eq) / probe
        if not rate > 0:
            raise SolverFailure(self.settings.solver, "load does not tilt the scale", 0)
        return self.phi_c / rate / self.settings.increments

    def locate_failure(self, lo: Equilibrium, hi: Equilibrium, index: int) -> Equilibrium:
        """Illinois regula falsi on tilt(delta) - phi_c between two converged states (sec. 3)."""
        f_lo, f_hi = self.tilt_of(lo) - self.phi_c, self.tilt_of(hi) - self.phi_c
        a, b, side = lo, hi, 0
        for _ in range(60):
            if _round_off(a, b):
                # The bracket has closed onto one depth (a cut landed at the depth of its other
                # end): two states of one depth on either side of phi_c.  Interpolating between
                # them would divide by a zero width (a NaN start, which failed the 5x5 dart slanted
                # 60 deg towards 45 deg as an invalid input).
                return self._tilt_at_round_off(a, b, index)
            d = (a.delta * f_hi - b.delta * f_lo) / (f_hi - f_lo)
            eq = self._cut(a, b, d, index)
            f = self.tilt_of(eq) - self.phi_c
            if abs(f) <= TILT_TARGET * self.phi_c:
                return eq
            if f < 0:
                a, f_lo = eq, f
                if side == -1:
                    f_hi /= 2
                side = -1
            else:
                b, f_hi = eq, f
                if side == 1:
                    f_lo /= 2
                side = 1
        raise SolverFailure(self.settings.solver, "failure tilt not located", index)

    def _cut(self, a: Equilibrium, b: Equilibrium, d: float, index: int) -> Equilibrium:
        """The failure search's state at the cut ``d`` of its bracket ``a, b``.  A cut whose level
        fails is halved towards ``a``, as the path halves a step whose level fails (``halve_step``,
        sec. 2): any converged state inside the bracket narrows it.  After
        ``FAILURE_SEARCH_HALVINGS`` halvings the cut's failure ends the path."""
        for _ in range(FAILURE_SEARCH_HALVINGS):
            outcome = self.solve(_between(a, b, d), d, index)
            if outcome.state is not None:
                return outcome.state
            assert outcome.failure is not None
            self.events.append(Rescue("halve_step", d, index, outcome.failure.status))
            d = 0.5 * (a.delta + d)
        return self.solve(_between(a, b, d), d, index).unwrap()

    def _tilt_at_round_off(self, a: Equilibrium, b: Equilibrium, index: int) -> Equilibrium:
        """The failure search's bracket ``a, b`` is at round-off of the depth: the SQP's accuracy
        (~1e-8) limits how close the tilt gets, and within 1e-6 phi_c it is located (sec. 3); the
        end nearer phi_c.  A larger difference across the bracket is a jump of the tilt, no state
        lies at phi_c, and the search fails with its status."""
        best = min((a, b), key=lambda st: abs(self.tilt_of(st) - self.phi_c))
        if abs(self.tilt_of(best) - self.phi_c) <= TILT_LOCATED * self.phi_c:
            return best
        raise SolverFailure(
            self.settings.solver,
            "failure tilt not located",
            index,
            f"tilt jumps from {np.rad2deg(self.tilt_of(a)):.9g} to {np.rad2deg(self.tilt_of(b)):.9g}"
            f" deg at depth {a.delta:.10g} without a located snap",
        )

    def released(self, a: Equilibrium, b: Equilibrium) -> float:
        """Energy released between two states: work of the load (trapezoidal) minus the stored
        energy's change.  On a continuous path it is the quadrature error, O(h^3) (O(h^2) at a
        contact closing); a jump to another equilibrium releases a finite amount (sec. 2)."""
        return _work(a, b) - (self.energy(b) - self.energy(a))

    def snapped(self, a: Equilibrium, b: Equilibrium) -> bool:
        """The step's energy balance misses by more than ``SNAP_WORK`` of its work, either way.

        Relative to the work, the quadrature error falls with the step (h^2 smooth, h at a kink)
        while a jump's |R| grows as 1/h: bisection tells them apart.  R > 0 is a release (a snap,
        or the SQP leaping into a lower basin); R < 0 is an equilibrium holding more energy than
        the load supplied, which no quasi-static path reaches: the SQP leapt into a higher basin
        (seen on the 5x5 dart: a step of 1.4e-5 L to a state of 150 times the stored energy).

        Below what the states can resolve nothing is flagged: a state of the high accuracy is
        converged to ``STEP_TOL`` (1e-8) in q (within ``STATE_ERROR`` steps of it), so its stored
        energy is known to ``STATE_ERROR STEP_TOL |K q|_1``.  The floor stays at that of the high
        accuracy whatever the QP tolerance: scaled with a looser step test (1e-5 at ``mid``) it let
        a real jump of the 3x3 square's contact-mode path through (F_c 2.5e-3 off).  Without the
        floor a short step at a small load (W ~ 1e-9) was flagged on noise alone, its bisection
        stopped each increment at a few micro-L, and the 3x3 hexagon array slanted 60 deg at
        45 deg ended at a tilt of 0.04 deg after 400 increments (puncture.md sec. 2).
        """
        return abs(self.released(a, b)) > SNAP_WORK * abs(_work(a, b)) + self.noise(a, b)

    def noise(self, a: Equilibrium, b: Equilibrium) -> float:
        """What the stored energies of two converged states can resolve: each is within
        ``STATE_ERROR`` step tests (``STEP_TOL``) of its exact state, so its energy is known to that
        times ``|K q|_1`` (``snapped``)."""
        return STATE_ERROR * STEP_TOL * (self.functions.force_norm(a) + self.functions.force_norm(b))

    def run(self, states: list[Equilibrium] | None = None, step: float | None = None) -> list[Equilibrium]:
        """Step the load until the tilt reaches phi_c; continue from ``states`` if given.

        A step that releases energy, or ends in a state failing the stability test, is bisected
        (``ceiling``: the depth of the last such step) until the event is located within
        ``_resolution`` (a jump, and a loss of stability off a held path, to ``JUMP_RESOLUTION``,
        refined to ``SNAP_RESOLUTION`` when its landing passes phi_c; anything else to
        ``SNAP_RESOLUTION``); after each state kept inside a
        jump's bracket the ceiling is retested, until a retest reproduces the jump's release; a
        loss of stability is located by regula falsi (Illinois) on the
        smallest eigenvalue instead, which is smooth along the branch (``_split``), and its
        ceiling is retested once, when the bracket is below the resolution (a retest stable by
        less than ``VERDICT_NOISE`` confirms it).  The path then leaves
        its branch (the jump's landing state, or the unstable state pushed along its mode), and a
        landing past phi_c is the failure (sec. 3-4).
        On a symmetric path (``mirror``) a located instability whose mode breaks the symmetry
        raises :class:`Bifurcation` instead.
        """
        states = list(states) if states else [self.origin()]
        step = step if step is not None else self.first_step(states[0])
        # The bounds come from the path's first step, not from the step a continued path resumes
        # with: that is the step before a bisection, and a branch found late in one (DAQP's
        # default-scene path resumed at 1.2e-5 L) capped the whole branch at 100 times it, 400
        # increments of 1.2e-3 L short of phi_c.
        self.base_step = self.base_step or step
        min_step, max_step = self.base_step * 1e-4, self.base_step * 100
        ceiling, resume, retest = np.inf, step, False
        pending: list[tuple[float, str]] = []
        kind = ""
        g_last: float | None = None
        g_ceiling: float | None = None
        moved = 0
        fine = False  # a jump's landing passed phi_c: its bracket is refined to SNAP_RESOLUTION
        reproduced = False  # the jump's ceiling was flagged again from a nearer start (no retests)
        released = 0.0  # the energy the ceiling's step released (|R|)
        located = 0  # states kept inside a bracket: they locate an event, they are no steps
        while (
            len(states) - located <= self.settings.max_increments
            and len(states) <= (1 + LOCATED_PER_STEP) * self.settings.max_increments
        ):
            last = states[-1]
            bracketed = ceiling < np.inf
            if ceiling < np.inf:
                step = ceiling - last.delta if retest else _split(ceiling - last.delta, g_last, g_ceiling)
            guess = predict(states, last.delta + step, self.smooth_from)
            if guess is last and last.delta == 0.0 and self.probe is not None:
                guess = _linear_response(self.probe, last.delta + step)
            outcome = self.solve(guess, last.delta + step, len(states))
            if outcome.state is None:
                assert outcome.failure is not None
                if step >= 2.0 * min_step:
                    self.events.append(
                        Rescue("halve_step", last.delta + step, len(states), outcome.failure.status)
                    )
                    if ceiling < np.inf:
                        if kind != "failed":
                            pending.append((ceiling, kind))
                        ceiling, retest, kind = last.delta + step, False, "failed"
                    else:
                        step /= 2
                    continue
                # No step converges, however short: the plain iteration (an energy descent from
                # the last state, sec. 2 Landing) either follows the branch where the extrapolated
                # one leapt or cycled, or lands past a limit point; if it fails too, so does the path.
                eq = self.solve(last, last.delta + step, len(states), descent=True).unwrap()
                self.events.append(Rescue("plain_iteration", eq.delta, len(states), outcome.failure.status))
                if self.snapped(last, eq):
                    if self.left_branch(last, eq):
                        return states
                    self.smooth_from = len(states)
                    pending.clear()
                (ceiling, kind), retest, landed, reproduced = (
                    _next_ceiling(pending, eq.delta),
                    True,
                    True,
                    False,
                )
                g_ceiling = None
                if ceiling == np.inf:
                    step = resume
            else:
                eq, landed = outcome.state, False
            sv = self.stability(eq) if self.settings.check and not landed else None
            if (
                sv is not None
                and sv.stable
                and bracketed
                and retest
                and kind == "unstable"
                and sv.min_eigenvalue + STABILITY_TOL < VERDICT_NOISE
            ):
                # The ceiling's retest, stable by less than the verdict resolves: it confirms the
                # ceiling, and the instability is taken here.
                sv = replace(sv, stable=False)
            unstable = sv is not None and not sv.stable and not self.unconfirmed
            flagged = unstable or (self.settings.conservative and not landed and self.snapped(last, eq))
            if flagged and not unstable and ceiling == np.inf:
                # A step that releases energy is a jump only if the energy descent from the last
                # state releases it too: the plain iteration follows the branch the path is on,
                # where the accelerated level can leap into a neighbouring basin (a bistable
                # contact far from the load, sec. 2 "Leaps").  Bisected instead, each leap cost a
                # bracket and gained its width (the contact-only 5x5 staggered triangle: 2.8e-4
                # released by every step from delta 0.4526 on, 4.5e-6 L gained per bracket).
                # Below phi_c only: a followed state past it would bracket the failure search,
                # whose levels start from states interpolated across the whole step and can leap
                # into the same neighbouring basin (fuzz design 632: F_c* 1.793 from the other
                # basin against 1.902 on the branch); there the bisection brings the starts close.
                follow = self.solve(last, eq.delta, len(states), descent=True).state
                if (
                    follow is not None
                    and self.tilt_of(follow) < self.phi_c
                    and not self.snapped(last, follow)
                ):
                    sv_follow = self.stability(follow) if self.settings.check else None
                    if sv_follow is None or sv_follow.stable:
                        eq, sv, flagged = follow, sv_follow, False
            if flagged:
                now = "unstable" if unstable else "snap"
                if step > _resolution(now, fine, self.mirror is not None) * eq.delta:
                    # A jump flagged again from the nearer start of a retest, releasing as much
                    # energy over the shorter step, is a finite jump, neither a leap of the
                    # extrapolated iteration nor the quadrature error at a kink (whose release
                    # falls with the step, and whose bracket a retest from nearer passes): it is
                    # bisected without further retests.
                    release = abs(self.released(last, eq)) if now == "snap" else 0.0
                    again = retest and bracketed and kind == now == "snap" and release >= 0.5 * released
                    released = release
                    if ceiling == np.inf:
                        resume, moved, reproduced = step, 0, False
                    elif kind != now:
                        pending.append((ceiling, kind))
                        reproduced = False
                    reproduced = reproduced or again
                    ceiling, retest, kind = eq.delta, False, now
                    g_ceiling = sv.min_eigenvalue + STABILITY_TOL if unstable and sv is not None else None
                    if moved == 1 and g_last is not None:
                        g_last /= 2
                    moved = 1
                    continue
                if unstable:
                    assert sv is not None
                    if self.breaks_symmetry(sv):
                        raise Bifurcation(states, eq, sv, resume)
                    landing = self.branch_off(eq, sv, sides=(1.0, -1.0))
                    left = landing is not eq
                else:
                    landing = self.solve(last, eq.delta, len(states), descent=True).unwrap()
                    left = self.snapped(last, landing)
                if left and self.tilt_of(landing) >= self.phi_c and step > SNAP_RESOLUTION * eq.delta:
                    # The jump or the loss of stability is the failure (sec. 3): located to
                    # JUMP_RESOLUTION so far, it is located to SNAP_RESOLUTION first.
                    if ceiling == np.inf:
                        resume, moved = step, 0
                    elif kind != now:
                        pending.append((ceiling, kind))
                    ceiling, retest, kind, fine = eq.delta, False, now, True
                    g_ceiling = sv.min_eigenvalue + STABILITY_TOL if unstable and sv is not None else None
                    continue
                if unstable:
                    assert sv is not None
                    self.record_branch(eq, sv, landing, confirmed=left)
                fine = False
                if not unstable and not left:
                    # The plain iteration follows the path where the extrapolated one leapt into
                    # another basin: no jump, an ordinary step.
                    eq, ceiling, step = landing, np.inf, resume
                    pending.clear()
                elif landing is eq:
                    # No push along the mode lowers the energy: the negative eigenvalue is not
                    # confirmed (it depends on how hinged planes are turned, increment.md sec. 4b),
                    # and the path goes on without branching, as a continuous step, until a state
                    # passes.
                    self.unconfirmed = True
                    (ceiling, kind), retest, reproduced = _next_ceiling(pending, eq.delta), True, False
                    g_ceiling = None
                    if ceiling == np.inf:
                        step = resume
                else:
                    if self.left_branch(last, landing):
                        return states
                    eq, ceiling, step, self.smooth_from = landing, np.inf, resume, len(states)
                    pending.clear()
            elif ceiling < np.inf:
                # Below the ceiling the path is continuous.  Retest the rest of a snap's bracket (the
                # ceiling's state came from a farther start); an instability's once it is resolved.
                if eq.delta >= ceiling:
                    (ceiling, kind), reproduced = _next_ceiling(pending, eq.delta), False
                    g_ceiling = None
                    if ceiling == np.inf:
                        step = resume
                retest = (g_ceiling is None and not reproduced) or (
                    ceiling - eq.delta <= _resolution(kind, fine, self.mirror is not None) * eq.delta
                )
                if moved == -1 and g_ceiling is not None:
                    g_ceiling /= 2
                moved = -1
            if not self.free_balanced(eq):
                raise HeldBranchEnds(states, eq, resume if ceiling < np.inf else step)
            if self.tilt_of(eq) >= self.phi_c:
                final = self.locate_failure(last, eq, len(states))
                self.events.append(Failure("tilt", final.delta, self.settings.phi_c_deg))
                states.append(final)
                return states
            if sv is not None and sv.stable and eq is outcome.state:
                # Only a state the path keeps ends an unconfirmed instability: a stable state the
                # energy balance rejects lies past a jump, and resetting there made the bisection
                # locate the same unconfirmed instability again after every step (a 3x3 hexagon
                # array: 46 unconfirmed branch events, 808 levels).
                self.unconfirmed = False
            self._record_contact_change(last, eq)
            states.append(eq)
            located += bracketed
            g_last = sv.min_eigenvalue + STABILITY_TOL if sv is not None else None
            if ceiling == np.inf:
                cap = _curvature_cap(states[self.smooth_from :])
                predicted = not landed and eq is outcome.state and guess is not last
                error = float(np.max(np.abs(eq.q - guess.q))) if predicted else None
                g = _growth(error)
                step = min(max_step, step * g, self._remaining(states), cap)
        raise SolverFailure(
            self.settings.solver,
            "failure tilt not reached",
            len(states),
            f"tilt {np.rad2deg(self.tilt_of(states[-1])):.3f} deg after {len(states)} increments; "
            f"max_increments = {self.settings.max_increments} steps",
        )

    def switch(self, bifurcation: Bifurcation, mode: np.ndarray) -> list[Equilibrium]:
        """Leave a held-symmetric path at its located ``bifurcation`` and continue to failure.

        The unstable state is pushed along ``mode`` (the unstable mode, its side chosen by the
        caller) to one side only and landed by the plain iteration; a landing past phi_c is the
        failure by a snap, otherwise the path continues from it with the step it had (sec. 4).
        This path must hold no symmetry: the landing and what follows are free.
        """
        lo, hi = bifurcation.before[-1], bifurcation.state
        sv = replace(bifurcation.stability, mode=mode)
        on_branch = self.branch_off(hi, sv, sides=(1.0,), resolved=False)
        self.record_branch(hi, sv, on_branch)
        states = list(bifurcation.before)
        if self.left_branch(lo, on_branch):
            return states
        self.smooth_from = len(states)
        return self.run(states + [on_branch], step=bifurcation.step)

    def left_branch(self, last: Equilibrium, landing: Equilibrium) -> bool:
        """Record a located jump from ``last`` to ``landing``; True if it is the failure: the
        tilt passes phi_c within the jump, and F_c is the force carried just before it."""
        tilts = (float(np.rad2deg(self.tilt_of(last))), float(np.rad2deg(self.tilt_of(landing))))
        jump = Snap((last.delta, landing.delta), self.released(last, landing), tilts, (last.F, landing.F))
        self.events.append(jump)
        if self.tilt_of(landing) < self.phi_c:
            return False
        self.events.append(Failure("snap", last.delta, tilts[0], tilts[1]))
        return True

    def _remaining(self, states: list[Equilibrium]) -> float:
        """Largest step that keeps about ``increments`` states up to the predicted failure depth."""
        if len(states) < 2:
            return np.inf
        a, b = states[-2], states[-1]
        if not b.delta > a.delta:
            return np.inf  # a jump's landing, at the depth of the state before it
        rate = (self.tilt_of(b) - self.tilt_of(a)) / (b.delta - a.delta)
        if not rate > 0:
            return np.inf
        return 2.0 * (b.delta + (self.phi_c - self.tilt_of(b)) / rate) / self.settings.increments

    def _record_contact_change(self, before: Equilibrium, after: Equilibrium) -> None:
        changed = _active_pairs(before) ^ _active_pairs(after)
        if changed:
            self.events.append(ContactChange((before.delta, after.delta), tuple(sorted(changed))))


def unloaded(n_scales: int) -> Equilibrium:
    """The unloaded state of ``n_scales`` scales: q = 0, no force, no contact."""
    return Equilibrium(
        q=np.zeros((n_scales, 5)),
        delta=0.0,
        F=0.0,
        contacts=None,
        lam=np.zeros(0),
        iterations=0,
        penetration=0.0,
    )


def predict(states: list[Equilibrium], delta: float, since: int = 0) -> Equilibrium:
    """Secant predictor: start the next level from the states extrapolated to ``delta``.

    The sequential QP converges linearly from its start; extrapolating the last two states makes
    the first residual second order in the step (formulations/puncture.md, sec. 2).  Only the
    states of one continuous stretch of the path count (``states[since:]``, from the last jump's
    landing on), and the secant's base must be at least ``1 / PREDICTOR_REACH`` of the step: the
    nearest earlier state that gives such a base is taken, and with none the level starts from
    the last state.  Across a landing, or over the 1e-7 L base of a resolved bracket, the secant
    extrapolates the states' own error (and the jump) by up to 1e5 and starts the level in
    another basin (fuzz design 140: a push's landing 6e-8 L above the state before it, then a
    step of 0.03 L from their secant, a leap that was bisected back to the same instability
    without end).
    """
    segment = states[max(0, min(since, len(states) - 1)) :]
    last = segment[-1]
    step = delta - last.delta
    prev = next(
        (
            p
            for p in reversed(segment[:-1])
            if p.delta < last.delta and PREDICTOR_REACH * (last.delta - p.delta) >= step
        ),
        None,
    )
    if prev is None:
        return last
    ratio = step / (last.delta - prev.delta)
    guess = last.q + ratio * (last.q - prev.q)
    return Equilibrium(
        q=guess,
        delta=delta,
        F=last.F,
        contacts=last.contacts,
        lam=last.lam,
        iterations=0,
        penetration=last.penetration,
    )


def _linear_response(probe: Equilibrium, delta: float) -> Equilibrium:
    """The start of the path's first level at ``delta``: the probe's state (the response at a
    depth of 1e-4 L, ``Path.first_step``) scaled to ``delta``, with the probe's contact set."""
    return replace(probe, q=probe.q * (delta / probe.delta), delta=delta, iterations=0)


def _round_off(a: Equilibrium, b: Equilibrium) -> bool:
    """The two states' depths are equal to round-off (a bracket that cannot be split)."""
    return abs(b.delta - a.delta) <= 1e-15 * max(1.0, b.delta)


def _between(a: Equilibrium, b: Equilibrium, delta: float) -> Equilibrium:
    """The start of a level at ``delta`` inside the bracket of two states of one continuous
    stretch: their configurations interpolated (an O(h^2) start, like the secant predictor's),
    with the lower state's contact set.  Started from the lower state itself (an O(h) start), a
    failure search of the 5x5 dart slanted 60 deg towards 45 deg met a linearisation that PIQP
    could not solve (its iteration limit) 0.03 L above it (formulations/puncture.md sec. 3)."""
    t = (delta - a.delta) / (b.delta - a.delta)
    return replace(a, q=a.q + t * (b.q - a.q), delta=delta, iterations=0)


def _next_ceiling(pending: list[tuple[float, str]], delta: float) -> tuple[float, str]:
    """The nearest open ceiling above ``delta`` and its kind (removed from ``pending`` with those
    passed), or (inf, "") when none is left."""
    while pending and pending[-1][0] <= delta:
        pending.pop()
    return pending.pop() if pending else (np.inf, "")


def _resolution(kind: str, fine: bool, held: bool = False) -> float:
    """Fraction of its depth to which a bracket of ``kind`` is located: ``JUMP_RESOLUTION`` for a
    jump (``snap``) or a loss of stability (``unstable``) unless its landing passed phi_c
    (``fine``), or, for a loss of stability, the path is held symmetric (``held``: its
    bifurcation is where the free path starts); else ``SNAP_RESOLUTION``."""
    if fine or kind not in ("snap", "unstable") or (kind == "unstable" and held):
        return SNAP_RESOLUTION
    return JUMP_RESOLUTION


def _split(width: float, g_lo: float | None, g_hi: float | None) -> float:
    """Step into a bracket of ``width`` above the last state: where the straight line through the
    eigenvalue margins ``g_lo > 0`` (last state) and ``g_hi < 0`` (the ceiling's) crosses zero, kept
    1 % inside the bracket; half the bracket when a margin is unknown (a snap's bracket)."""
    if g_lo is None or g_hi is None or not g_lo > 0.0 > g_hi:
        return 0.5 * width
    return float(np.clip(g_lo / (g_lo - g_hi), 0.01, 0.99)) * width


def _work(a: Equilibrium, b: Equilibrium) -> float:
    """Work of the load from state ``a`` to ``b``, trapezoidal rule (F* L)."""
    return 0.5 * (a.F + b.F) * (b.delta - a.delta)


def _curvature_cap(states: list[Equilibrium]) -> float:
    """Largest step whose trapezoidal work error, h^3 |F''| / 12 from the last three states,
    stays below half the release ``snapped`` flags (SNAP_WORK F h): a jump to another
    equilibrium is then never hidden by the quadrature error (formulations/puncture.md sec. 2)."""
    if len(states) < 3:
        return np.inf
    a, b, c = states[-3:]
    if not a.delta < b.delta < c.delta:
        return np.inf
    curvature = (
        2.0 * ((c.F - b.F) / (c.delta - b.delta) - (b.F - a.F) / (b.delta - a.delta)) / (c.delta - a.delta)
    )
    if curvature == 0.0:
        return np.inf
    return float(np.sqrt(6.0 * SNAP_WORK * abs(c.F) / abs(curvature)))


def _growth(error: float | None) -> float:
    """Step factor from the secant predictor's error at the last level (sec. 2, Step size).

    The predictor's error is O(h^2), so ``sqrt(PREDICTOR_ERROR / error)`` scales the next step to
    an error of ``PREDICTOR_ERROR``, by at most a factor 2 either way.  The sequential QP's
    iteration count is no guide: it converges linearly from the predictor, so the count falls
    only with log(error), and on hinged planes it sits at 10-17 whatever the step; a rule that
    halved the step there left the 3x3 dart slanted 60 deg at 45 deg at a tilt of 9.2 deg after
    400 increments of 5e-4 L.  Nor is a count near the limit: halving the step after a level of
    over 30 iterations cost the 5x5 dart slanted 60 deg towards 45 deg 194 of its 1140 levels
    (and 22 % of its time) for the same F_c* (puncture.md sec. 2).  After a landing (``error``
    None) the step is kept.
    """
    if error is None:
        return 1.0
    return 2.0 if error == 0.0 else float(np.clip(np.sqrt(PREDICTOR_ERROR / error), 0.5, 2.0))


def _active_pairs(eq: Equilibrium) -> set[tuple[int, int]]:
    if eq.contacts is None or len(eq.lam) == 0:
        return set()
    scale = max(1e-9, 1e-6 * float(np.max(eq.lam)))
    on = eq.lam > scale
    return {(int(a), int(b)) for a, b in zip(eq.contacts.a[on], eq.contacts.b[on])}
