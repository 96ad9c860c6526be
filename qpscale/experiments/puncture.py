"""The puncture test: a vertical displacement imposed on a top-face point of the punctured scale.

Implements formulations/puncture.md: the path with adaptive increments (sec. 2), the exact
location of the failure event tilt = phi_c (sec. 3), the stability check of every state and the
branching of symmetric paths (sec. 4, with qpscale/stability.py) and the worst case over the
top-face vertices distinct under the design's symmetry (sec. 5).  All forces are F* (E* = L = 1,
formulations/normalisation.md).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..contact import ContactSettings
from ..contact.symmetry import Mirror, map_dofs
from ..errors import InvalidDesign, SolverFailure
from ..events import Branch, ContactChange, Event, Failure, Rescue, Snap
from ..geometry import tilt
from ..increment import STEP_TOL, Equilibrium, LevelOutcome, LoadPoint, SQPSettings, solve_level
from ..penalty import PenaltySettings
from ..stability import Stability, second_variation
from ..substrate import SubstrateModel, stiffness_matrix
from ..threads import limited_blas
from ..tiling import Design, Patch
from .symmetry import mirror_through, vertex_orbits

log = logging.getLogger(__name__)

INTERACTIONS = ("full", "substrate", "contact")
PAPER_CONTACT_COUPLING = 0.04
#: Backends refused on the plane formulation: measured on the 3x3 square array, OSQP reached its
#: iteration limit at the ninth increment (14 s) without a polished answer.
PLANE_INCAPABLE = ("osqp",)


@dataclass(frozen=True)
class PunctureSetup:
    """Everything that defines one puncture run.

    Parameters
    ----------
    design : Design
        Shape, tiling, slant, gap, thickness and rings (rings = 0: the isolated scale).
    interaction : str
        ``full`` (substrate coupling and contact), ``substrate`` (contact off) or ``contact``
        (coupling through the substrate scaled by ``coupling``), docs/cli.md.
    coupling : float or None
        Coupling factor f in [0, 1]; None means 1 for ``full``/``substrate`` and 0.04 for ``contact``.
    nu : float
        Poisson's ratio of the substrate, [0, 0.5].
    phi_c_deg : float
        Critical tilt of the top face, degrees, (0, 60].
    load_point : tuple or None
        (x, y) in L, relative to the punctured scale's reference point, on its top face; None
        evaluates the worst top-face vertex.
    increments : int
        Target number of increments up to failure (the adaptive step starts from it), >= 2.
    penalty : PenaltySettings or None
        Settings of the penalty baseline, used when ``sqp.solver == "penalty"``.
    """

    design: Design = field(default_factory=Design)
    interaction: str = "full"
    coupling: float | None = None
    nu: float = 0.5
    phi_c_deg: float = 13.0
    load_point: tuple[float, float] | None = None
    fidelity: str = "bem"
    sqp: SQPSettings = field(default_factory=SQPSettings)
    contact: ContactSettings = field(default_factory=ContactSettings)
    increments: int = 16
    max_increments: int = 400
    probe: bool = True
    penalty: PenaltySettings | None = None

    def __post_init__(self) -> None:
        if self.interaction not in INTERACTIONS:
            raise InvalidDesign("interaction", self.interaction, "{" + ", ".join(INTERACTIONS) + "}")
        if self.coupling is not None and not 0.0 <= self.coupling <= 1.0:
            raise InvalidDesign("coupling", self.coupling, "[0, 1]")
        if not 0.0 < self.phi_c_deg <= 60.0:
            raise InvalidDesign("phi_c_deg", self.phi_c_deg, "(0, 60]")
        if not 0.0 <= self.nu <= 0.5:
            raise InvalidDesign("nu", self.nu, "[0, 0.5]")
        if self.penalty is not None and not isinstance(self.penalty, PenaltySettings):
            raise InvalidDesign("penalty", type(self.penalty).__name__, "PenaltySettings or None")
        if not 2 <= self.increments <= self.max_increments:
            raise InvalidDesign("increments", self.increments, f"[2, {self.max_increments}]")
        if self.sqp.solver in PLANE_INCAPABLE and self.contact.formulation == "plane" and self.contact_on:
            # Refused, not switched: the plane formulation's dependent rows defeat OSQP's polishing
            # and ADMM alone stops at its iteration limit (formulations/contact.md sec. 7).
            raise InvalidDesign(
                "solver",
                self.sqp.solver,
                "a backend that solves the plane formulation (clarabel, cvxpy, qpsolvers:*); "
                "osqp only with formulation='feature'",
            )

    @property
    def coupling_factor(self) -> float:
        if self.coupling is not None:
            return float(self.coupling)
        return PAPER_CONTACT_COUPLING if self.interaction == "contact" else 1.0

    @property
    def contact_on(self) -> bool:
        return self.interaction != "substrate" and self.design.rings > 0


@dataclass
class PunctureResult:
    """One puncture path up to the failure tilt.

    Attributes
    ----------
    Fc_star : float
        Puncture resistance F_c* at tilt = phi_c exactly.
    delta_c_star : float
        In-plane distance from the reference point to the load point, delta_c / L.
    load_point : ndarray (2,)
        The load point relative to the reference point, in L.
    states : list of Equilibrium
        Converged states from the unloaded one to failure (q, F, contact forces).
    events : list of Event
        Located events (``qpscale.events``): contact changes, snaps, branches, the rescues that
        fired and the failure, each with its depth.
    branch : dict
        What the stability probe found (``branched``, ``delta``, ``followed``).
    """

    setup: PunctureSetup
    Fc_star: float
    delta_c_star: float
    load_point: np.ndarray
    states: list[Equilibrium]
    events: list[Event]
    branch: dict
    wall_s: float
    qp_solves: int
    candidates: list[dict] = field(default_factory=list)

    @property
    def w_star(self) -> np.ndarray:
        return np.array([s.delta for s in self.states])

    @property
    def F_star(self) -> np.ndarray:
        return np.array([s.F for s in self.states])

    @property
    def tilt_deg(self) -> np.ndarray:
        return np.rad2deg([tilt(s.q[0, 3:5]) for s in self.states])

    @property
    def max_penetration(self) -> float:
        return float(max(s.penetration for s in self.states))


def build_model(setup: PunctureSetup) -> tuple[Patch, object]:
    """The patch and its substrate stiffness K(f) (sparse, 5n x 5n, E* = L = 1)."""
    patch = setup.design.patch()
    model = SubstrateModel(nu=setup.nu, fidelity=setup.fidelity, coupling=setup.coupling_factor)
    return patch, stiffness_matrix(patch, model)


def top_vertices(patch: Patch) -> np.ndarray:
    """Top-face vertices ``(n, 2)`` of the punctured scale relative to its reference point."""
    return patch.prism(0).vertices[patch.prism(0).n_base :, :2]


def _load_point(patch: Patch, xy: tuple[float, float] | np.ndarray) -> LoadPoint:
    return LoadPoint(0, np.array([xy[0], xy[1], patch.design.thickness]))


class _Unstable(Exception):
    """A state of a symmetry-constrained path failed the second-variation test."""

    def __init__(
        self, before: list[Equilibrium], state: Equilibrium, stability: Stability, step: float
    ) -> None:
        super().__init__("symmetric path lost stability")
        self.before, self.state, self.stability, self.step = before, state, stability, step


# Size of the push along an unstable mode before the path is continued on the branch, in L.
BRANCH_PUSH = 1e-4
# A step releasing more than this fraction of its work is bisected as a possible jump between
# equilibria, and a jump surviving down to SNAP_RESOLUTION * delta is a snap (sec. 2).
SNAP_WORK = 1e-3
# Smallest eigenvalue of the second variation (relative to K's largest diagonal) still counted as
# stable: the Hessian is exact (the state's accuracy moves mu by ~1e-7), and a pitchfork's eigenvalue falls
# through zero at a slope of order 1e-3 per L of depth, so the branch point moves by ~1e-3 L.
STABILITY_TOL = 1e-6
# Iterations allowed to the landing of a jump: the plain iteration leaves an unstable state at the
# rate of its negative eigenvalue, slowly near the branch point.
LANDING_MAX_ITER = 3000
SNAP_RESOLUTION = 1e-7
# A converged state lies within this many step tolerances of the exact one (the sequential QP
# stops at |dq| <= step_tol and contracts at a rate of 0.5-0.9): the energy balance's noise floor.
STATE_ERROR = 10.0
# Target error of the secant predictor, in L or rad (``_growth``): the step is sized by it.
PREDICTOR_ERROR = 1e-3
# A level that needed more sequential-QP iterations than this halves the next step.
HARD_LEVEL = 30
# The failure state's tilt must lie within this fraction of phi_c (issue #5: F_c at phi_c to 1e-6).
TILT_LOCATED = 1e-6


class _Path:
    """State of one loading path: the solver closure, counters, events.

    ``mirror`` holds the path on the symmetric branch of that reflection (configuration and
    separating planes); ``check`` runs the second-variation test on every converged state
    (formulations/puncture.md sec. 4).
    """

    def __init__(
        self,
        setup: PunctureSetup,
        patch: Patch,
        K: object,
        load: LoadPoint,
        mirror: Mirror | None = None,
        check: bool = False,
    ) -> None:
        self.setup, self.patch, self.K, self.load = setup, patch, K, load
        self.contact = setup.contact if setup.contact_on else None
        self.phi_c = np.deg2rad(setup.phi_c_deg)
        self.solves = 0
        self.events: list[Event] = []
        self.mirror, self.check = mirror, check
        # The energy balance that locates jumps holds for exact frictionless contact only (the
        # feature rows' sticky axis and the penalty dissipate ~1e-3 of the work).
        self.conservative = _checkable(setup)
        self.smooth_from = 0  # first state after the last jump (the curvature cap's window)
        self.unconfirmed = False  # an instability whose pushes found no lower energy (run)

    def solve(self, start: Equilibrium, delta: float, index: int, descent: bool = False) -> LevelOutcome:
        """The level at depth ``delta`` from ``start`` under the level's rescue policy
        (``increment.solve_level``); ``descent``: by the plain fixed-point iteration, an energy
        descent in the K metric (the landing of a jump, sec. 4).  The rescues that fired join the
        path's events."""
        self.solves += 1
        if self.setup.sqp.solver == "penalty":
            return self._penalty_solve(start, delta, index)
        outcome = solve_level(
            self.patch,
            self.K,  # type: ignore[arg-type]
            start.q,
            self.load,
            delta,
            self.contact,
            self.sqp(descent),
            increment=index,
            previous=start.contacts,
            mirror=self.mirror,
        )
        self.events.extend(outcome.rescues)
        return outcome

    def _penalty_solve(self, start: Equilibrium, delta: float, index: int) -> LevelOutcome:
        from ..penalty import penalty_level

        settings = self.setup.penalty if self.setup.penalty is not None else PenaltySettings()
        return penalty_level(
            self.patch,
            self.K,  # type: ignore[arg-type]
            start.q,
            self.load,
            delta,
            self.contact,
            settings,
            increment=index,
            previous=start.contacts,
        )

    def sqp(self, descent: bool = False) -> SQPSettings:
        """The SQP settings of this path: the plain iteration for a landing (``descent``), and no
        plane damping on a held-symmetry path: it moves no converged state, but a fold located
        with it depended on the step (1.4e-5 over 6-30 increments against 4e-7 without,
        formulations/puncture.md sec. 4)."""
        settings = self.setup.sqp
        if self.mirror is not None:
            settings = replace(settings, plane_damping=False)
        if descent:
            settings = replace(settings, anderson_depth=0, max_iter=LANDING_MAX_ITER)
        return settings

    def energy(self, eq: Equilibrium) -> float:
        """Stored energy 1/2 q'Kq of a state (F* L)."""
        x = eq.q.ravel()
        return 0.5 * float(x @ (self.K @ x))  # type: ignore[operator]

    def stability(self, eq: Equilibrium) -> Stability:
        return second_variation(self.patch, self.K, eq, self.load, tol=STABILITY_TOL)

    def branch_off(self, eq: Equilibrium, sv: Stability, sides: tuple[float, ...]) -> Equilibrium:
        """Push ``eq`` along the unstable mode (each side given), re-solve at the same depth and
        keep the state of lowest energy (it lies on the branch the path takes)."""
        energy = self.energy(eq)
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
        self.events.append(Branch(eq.delta, sv.min_eigenvalue, energy - best[0] if best else 0.0))
        return best[1] if best else eq

    def breaks_symmetry(self, sv: Stability) -> bool:
        """On a symmetric path: the unstable mode is mostly antisymmetric (a bifurcation off the
        branch) rather than symmetric (a fold of the branch itself, crossed by a snap)."""
        if self.mirror is None:
            return False
        mode = sv.mode.ravel()
        return bool(np.linalg.norm(self.mirror.dof_rows @ mode) ** 2 > 0.5 * float(mode @ mode))

    def tilt_of(self, eq: Equilibrium) -> float:
        return tilt(eq.q[self.load.scale, 3:5])

    def first_step(self, origin: Equilibrium) -> float:
        """Step from the linear response: delta at failure ~ phi_c / (d tilt / d delta)."""
        probe = 1e-4
        eq = self.solve(origin, probe, 0).unwrap()
        rate = self.tilt_of(eq) / probe
        if not rate > 0:
            raise SolverFailure(self.setup.sqp.solver, "load does not tilt the scale", 0)
        return self.phi_c / rate / self.setup.increments

    def locate_failure(self, lo: Equilibrium, hi: Equilibrium, index: int) -> Equilibrium:
        """Illinois regula falsi on tilt(delta) - phi_c between two converged states (sec. 3)."""
        f_lo, f_hi = self.tilt_of(lo) - self.phi_c, self.tilt_of(hi) - self.phi_c
        a, b, side = lo, hi, 0
        for _ in range(60):
            d = (a.delta * f_hi - b.delta * f_lo) / (f_hi - f_lo)
            eq = self.solve(a, d, index).unwrap()
            f = self.tilt_of(eq) - self.phi_c
            if abs(f) <= 1e-12 * self.phi_c:
                return eq
            if abs(b.delta - a.delta) <= 1e-15 * max(1.0, b.delta):
                # The bracket is at round-off of the depth: the SQP's accuracy (~1e-8) limits how
                # close the tilt gets; within 1e-6 phi_c it is located (sec. 3).  A larger
                # difference across it is a jump of the tilt, and no state lies at phi_c.
                best = min((a, b, eq), key=lambda st: abs(self.tilt_of(st) - self.phi_c))
                if abs(self.tilt_of(best) - self.phi_c) <= TILT_LOCATED * self.phi_c:
                    return best
                raise SolverFailure(
                    self.setup.sqp.solver,
                    "failure tilt not located",
                    index,
                    f"tilt jumps from {np.rad2deg(self.tilt_of(a)):.9g} to {np.rad2deg(self.tilt_of(b)):.9g}"
                    f" deg at depth {a.delta:.10g} without a located snap",
                )
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
        raise SolverFailure(self.setup.sqp.solver, "failure tilt not located", index)

    def origin(self) -> Equilibrium:
        return Equilibrium(
            q=np.zeros((self.patch.n_scales, 5)),
            delta=0.0,
            F=0.0,
            contacts=None,
            lam=np.zeros(0),
            iterations=0,
            penetration=0.0,
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
        floor = STATE_ERROR * STEP_TOL * (self._force_norm(a) + self._force_norm(b))
        return abs(self.released(a, b)) > SNAP_WORK * abs(_work(a, b)) + floor

    def _force_norm(self, eq: Equilibrium) -> float:
        """|K q|_1: how much the stored energy moves per unit of error in q."""
        return float(np.abs(self.K @ eq.q.ravel()).sum())  # type: ignore[operator]

    def run(self, states: list[Equilibrium] | None = None, step: float | None = None) -> list[Equilibrium]:
        """Step the load until the tilt reaches phi_c; continue from ``states`` if given.

        A step that releases energy, or ends in a state failing the stability test, is bisected
        (``ceiling``: the depth of the last such step) until the event is located within
        ``SNAP_RESOLUTION``; the path then leaves its branch (the jump's landing state, or the
        unstable state pushed along its mode), and a landing past phi_c is the failure (sec. 3-4).
        On a symmetric path (``mirror``) a located instability raises ``_Unstable`` instead.
        """
        states = list(states) if states else [self.origin()]
        step = step if step is not None else self.first_step(states[0])
        min_step, max_step = step * 1e-4, step * 100
        ceiling, resume, retest = np.inf, step, False
        while len(states) <= self.setup.max_increments:
            last = states[-1]
            if ceiling < np.inf:
                step = ceiling - last.delta if retest else 0.5 * (ceiling - last.delta)
            guess = _predict(states, last.delta + step)
            outcome = self.solve(guess, last.delta + step, len(states))
            if outcome.state is None:
                assert outcome.failure is not None
                if step >= 2.0 * min_step:
                    self.events.append(
                        Rescue("halve_step", last.delta + step, len(states), outcome.failure.status)
                    )
                    if ceiling < np.inf:
                        ceiling, retest = last.delta + step, False
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
                ceiling, step, landed = np.inf, resume, True
            else:
                eq, landed = outcome.state, False
            sv = self.stability(eq) if self.check and not landed else None
            unstable = sv is not None and not sv.stable and not self.unconfirmed
            if sv is not None and sv.stable:
                self.unconfirmed = False
            if unstable or (self.conservative and not landed and self.snapped(last, eq)):
                if step > SNAP_RESOLUTION * eq.delta:
                    if ceiling == np.inf:
                        resume = step
                    ceiling, retest = eq.delta, False
                    continue
                if unstable:
                    assert sv is not None
                    if self.breaks_symmetry(sv):
                        raise _Unstable(states, eq, sv, resume)
                    landing = self.branch_off(eq, sv, sides=(1.0, -1.0))
                else:
                    landing = self.solve(last, eq.delta, len(states), descent=True).unwrap()
                if not unstable and not self.snapped(last, landing):
                    # The plain iteration follows the path where the extrapolated one leapt into
                    # another basin: no jump, an ordinary step.
                    eq, ceiling, step = landing, np.inf, resume
                elif landing is eq:
                    # No push along the mode lowers the energy: the negative eigenvalue is not
                    # confirmed (it depends on how hinged planes are turned, increment.md sec. 4b),
                    # and the path goes on without branching, as a continuous step, until a state
                    # passes.
                    self.unconfirmed = True
                    at = max(i for i, e in enumerate(self.events) if isinstance(e, Branch))
                    branch = self.events[at]
                    assert isinstance(branch, Branch)
                    self.events[at] = replace(branch, confirmed=False)
                    ceiling, step = np.inf, resume
                else:
                    if self.left_branch(last, landing):
                        return states
                    eq, ceiling, step, self.smooth_from = landing, np.inf, resume, len(states)
            elif ceiling < np.inf:
                # Below the ceiling the path is continuous; retest the rest of the bracket.
                if eq.delta >= ceiling:
                    ceiling, step = np.inf, resume
                retest = True
            if self.tilt_of(eq) >= self.phi_c:
                final = self.locate_failure(last, eq, len(states))
                self.events.append(Failure("tilt", final.delta, self.setup.phi_c_deg))
                states.append(final)
                return states
            self._record_contact_change(last, eq)
            states.append(eq)
            if ceiling == np.inf:
                cap = _curvature_cap(states[self.smooth_from :])
                predicted = not landed and eq is outcome.state and guess is not last
                error = float(np.max(np.abs(eq.q - guess.q))) if predicted else None
                g = _growth(error, eq.iterations)
                step = min(max_step, step * g, self._remaining(states), cap)
        raise SolverFailure(
            self.setup.sqp.solver,
            "failure tilt not reached",
            len(states),
            f"tilt {np.rad2deg(self.tilt_of(states[-1])):.3f} deg after {len(states)} increments",
        )

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
        return 2.0 * (b.delta + (self.phi_c - self.tilt_of(b)) / rate) / self.setup.increments

    def _record_contact_change(self, before: Equilibrium, after: Equilibrium) -> None:
        changed = _active_pairs(before) ^ _active_pairs(after)
        if changed:
            self.events.append(ContactChange((before.delta, after.delta), tuple(sorted(changed))))


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


def _growth(error: float | None, iterations: int) -> float:
    """Step factor from the secant predictor's error at the last level (sec. 2, Step size).

    The predictor's error is O(h^2), so ``sqrt(PREDICTOR_ERROR / error)`` scales the next step to
    an error of ``PREDICTOR_ERROR``, by at most a factor 2 either way.  The sequential QP's
    iteration count is no guide: it converges linearly from the predictor, so the count falls
    only with log(error), and on hinged planes it sits at 10-17 whatever the step; a rule that
    halved the step there left the 3x3 dart slanted 60 deg at 45 deg at a tilt of 9.2 deg after
    400 increments of 5e-4 L.  A level that needed over ``HARD_LEVEL`` iterations halves the step
    (it came close to failing).  After a landing (``error`` None) the step is kept.
    """
    if iterations > HARD_LEVEL:
        return 0.5
    if error is None:
        return 1.0
    return 2.0 if error == 0.0 else float(np.clip(np.sqrt(PREDICTOR_ERROR / error), 0.5, 2.0))


def _predict(states: list[Equilibrium], delta: float) -> Equilibrium:
    """Secant predictor: start the next level from the states extrapolated to ``delta``.

    The sequential QP converges linearly from its start; extrapolating the last two states makes
    the first residual second order in the step (formulations/puncture.md, sec. 2).
    """
    last = states[-1]
    if len(states) < 2 or last.delta <= states[-2].delta:
        return last
    prev = states[-2]
    ratio = (delta - last.delta) / (last.delta - prev.delta)
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


def _active_pairs(eq: Equilibrium) -> set[tuple[int, int]]:
    if eq.contacts is None or len(eq.lam) == 0:
        return set()
    scale = max(1e-9, 1e-6 * float(np.max(eq.lam)))
    on = eq.lam > scale
    return {(int(a), int(b)) for a, b in zip(eq.contacts.a[on], eq.contacts.b[on])}


def _checkable(setup: PunctureSetup) -> bool:
    """The second-variation test needs the plane formulation's rows (or no contact at all)."""
    if setup.sqp.solver == "penalty":
        return False
    return not setup.contact_on or setup.contact.formulation == "plane"


def _one_point(
    setup: PunctureSetup, patch: Patch, K: object, xy: np.ndarray
) -> tuple[list[Equilibrium], list, int, dict]:
    """The path of one load point and what its stability check found (sec. 4)."""
    load = _load_point(patch, xy)
    check = setup.probe and _checkable(setup)
    mirror = mirror_through(patch, xy) if check and setup.contact_on else None
    if mirror is None:
        path = _Path(setup, patch, K, load, check=check)
        states = path.run()
        branches = [e for e in path.events if isinstance(e, Branch) and e.confirmed]
        info: dict[str, Any] = {"check": "second variation" if check else "off", "branched": bool(branches)}
        if branches:
            info.update({"delta_branch": branches[0].delta, "followed": "lower-energy side"})
        return states, path.events, path.solves, info
    return _symmetric_point(setup, patch, K, load, xy, mirror)


def _symmetric_point(
    setup: PunctureSetup, patch: Patch, K: object, load: LoadPoint, xy: np.ndarray, mirror: tuple
) -> tuple[list[Equilibrium], list, int, dict]:
    """A load point on a mirror line: the symmetric branch, held by constraints, until a state
    fails the second-variation test (located by the path's bisection); the path then continues,
    unconstrained, from the state pushed along the unstable mode to a fixed side."""
    M, perm = mirror
    sym = _Path(setup, patch, K, load, mirror=Mirror.of(patch, M, perm), check=True)
    info: dict = {"check": "second variation", "mirror": True}
    try:
        states = sym.run()
        info["branched"] = False
        return states, sym.events, sym.solves, info
    except _Unstable as exc:
        lost = exc
    lo, hi, sv = lost.before[-1], lost.state, lost.stability
    free = _Path(setup, patch, K, load, check=True)
    sv = replace(sv, mode=sv.mode * _side(sv.mode[load.scale], M))
    on_branch = free.branch_off(hi, sv, sides=(1.0,))
    states = list(lost.before)
    if not free.left_branch(lo, on_branch):
        free.smooth_from = len(states)
        states = free.run(states + [on_branch], step=lost.step)
    info.update(
        {
            "branched": True,
            "delta_branch": [lo.delta, hi.delta],
            "min_eigenvalue": sv.min_eigenvalue,
            "followed": "asymmetric",
            "asymmetry_at_failure": _asymmetry(states[-1].q, M, perm),
        }
    )
    return states, sym.events + free.events, sym.solves + free.solves, info


def _side(mode: np.ndarray, M: np.ndarray) -> float:
    """+1 or -1 so the loaded scale's part of an antisymmetric mode points to a fixed side of the
    mirror line (its translation across the line, else its rotation about it): every backend
    then follows the same one of the two mirror-image branches."""
    normal = np.linalg.eigh(M)[1][:, 0]
    normal = normal * np.sign(normal[np.argmax(np.abs(normal))])
    across = float(mode[:2] @ normal)
    if abs(across) > 1e-6:
        return float(np.sign(across))
    along = np.array([-normal[1], normal[0]])
    return float(np.sign(mode[3:5] @ along)) or 1.0


def run_puncture(setup: PunctureSetup, progress: Callable[[str], None] | None = None) -> PunctureResult:
    """Run the puncture test; with ``setup.load_point = None`` take the worst top-face vertex.

    Examples
    --------
    >>> r = run_puncture(PunctureSetup(design=Design(rings=0)))
    >>> 0.2 < r.Fc_star < 0.6
    True
    """
    with limited_blas():
        return _run_puncture(setup, progress)


def _run_puncture(setup: PunctureSetup, progress: Callable[[str], None] | None) -> PunctureResult:
    t0 = time.perf_counter()
    patch, K = build_model(setup)
    if setup.load_point is not None:
        points = [np.asarray(setup.load_point, dtype=float)]
    else:
        verts = top_vertices(patch)
        points = [verts[orbit[0]] for orbit in vertex_orbits(patch, verts)]
    candidates, best = [], None
    solves = 0
    for xy in points:
        if progress:
            progress(f"load point ({xy[0]:.3f}, {xy[1]:.3f})")
        states, events, n, info = _one_point(setup, patch, K, xy)
        solves += n
        candidates.append({"load_point": xy.tolist(), "Fc_star": states[-1].F, "branch": info})
        if best is None or states[-1].F < best[0][-1].F:
            best = (states, events, xy, info)
    assert best is not None
    states, events, xy, branch = best
    return PunctureResult(
        setup=setup,
        Fc_star=states[-1].F,
        delta_c_star=float(np.hypot(*xy)),
        load_point=np.asarray(xy),
        states=states,
        events=events,
        branch=branch,
        wall_s=time.perf_counter() - t0,
        qp_solves=solves,
        candidates=candidates,
    )


def _asymmetry(q: np.ndarray, M: np.ndarray, perm: np.ndarray) -> float:
    return float(np.max(np.abs(q - map_dofs(q, M, perm))))
