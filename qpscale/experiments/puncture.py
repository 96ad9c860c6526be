"""The puncture test: a vertical displacement imposed on a top-face point of the punctured scale.

Implements formulations/puncture.md sec. 1 (the set-up and the interaction modes), the puncture
test's use of the path of qpscale/continuation.py (secs. 2-4: one path per load point, tested by
the second variation where the contact rows allow it; on a mirror line the held-symmetric branch
first, left at its bifurcation to a fixed side, sec. 4) and the worst case over the top-face
vertices distinct under the design's symmetry (sec. 5).  All forces are F* (E* = L = 1,
formulations/normalisation.md).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..certify import ForceCheck, check_force
from ..contact import ContactSet, ContactSettings
from ..contact.symmetry import Mirror, map_dofs
from ..continuation import (
    Bifurcation,
    BranchRecord,
    HeldBranchEnds,
    LevelSolver,
    Path,
    PathSettings,
    PenaltyLevels,
    SQPLevels,
    StateFunctions,
    unloaded,
)
from ..errors import InvalidDesign, SolverFailure
from ..events import Event
from ..geometry import tilt
from ..increment import Equilibrium, LoadPoint, SQPSettings
from ..penalty import PenaltySettings
from ..substrate import EDGES, SubstrateModel, stiffness_matrix
from ..threads import limited_blas
from ..tiling import Design, Patch
from ..validation import DEFAULT_MAX_INCREMENTS
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
    edges : str
        Self stiffness of the scales on the patch's edge: ``clamped`` (K0 on every scale, as if
        the absent neighbours were present and clamped: the paper's 5x5 comparison) or ``local``
        (each scale's own neighbourhood, formulations/substrate.md eq. (18); ``bem`` fidelity only).
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
    edges: str = "clamped"
    sqp: SQPSettings = field(default_factory=SQPSettings)
    contact: ContactSettings = field(default_factory=ContactSettings)
    increments: int = 16
    max_increments: int = DEFAULT_MAX_INCREMENTS
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
        if self.edges not in EDGES:
            raise InvalidDesign("edges", self.edges, "{" + ", ".join(EDGES) + "}")
        if self.edges == "local" and self.fidelity != "bem":
            raise InvalidDesign("edges", self.edges, "{clamped} with fidelity springs (local needs bem)")
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
                "a backend that solves the plane formulation (piqp, clarabel, cvxpy, qpsolvers:*); "
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


@dataclass(frozen=True)
class Candidate:
    """One load point tried in the worst-case search (sec. 5): its F_c* and what its path's
    stability probe found."""

    load_point: tuple[float, float]
    Fc_star: float
    branch: BranchRecord

    def to_dict(self) -> dict[str, object]:
        """The JSON object of the command line's ``candidates`` list (docs/cli.md)."""
        return {"load_point": list(self.load_point), "Fc_star": self.Fc_star, "branch": self.branch.to_dict()}


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
    branch : BranchRecord
        What the stability probe found on the chosen load point's path (``branched``,
        ``delta_branch``, ``followed``).
    candidates : list of Candidate
        Every load point tried, with its F_c* and its branch record.
    Fc_check : ForceCheck or None
        F_c* against the exact active-set solution of the QP at the failure state
        (``qpscale.certify``); None for the penalty baseline and for a scale without contact.
    """

    setup: PunctureSetup
    Fc_star: float
    delta_c_star: float
    load_point: np.ndarray
    states: list[Equilibrium]
    events: list[Event]
    branch: BranchRecord
    wall_s: float
    qp_solves: int
    load_levels: int
    candidates: list[Candidate] = field(default_factory=list)
    Fc_check: ForceCheck | None = None

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


def build_model(setup: PunctureSetup) -> tuple[Patch, sp.csc_matrix]:
    """The patch and its substrate stiffness K(f) (sparse, 5n x 5n, E* = L = 1)."""
    patch = setup.design.patch()
    model = SubstrateModel(
        nu=setup.nu, fidelity=setup.fidelity, coupling=setup.coupling_factor, edges=setup.edges
    )
    return patch, stiffness_matrix(patch, model)


def reported_forces(
    setup: PunctureSetup, state: Equilibrium, load_point: tuple[float, float] | np.ndarray
) -> tuple[ContactSet | None, np.ndarray]:
    """The contact forces of a converged ``state`` by the stated rule (formulations/stability.md
    sec. 7, "The reported forces"): the least-norm member of the state's multiplier set.

    Returns the contact set of the increment QP linearised at the state (its rows are the
    state's, detected again at its configuration) and one force per row (zero on rows no member
    loads).  Read from the state, not from the backend's multipliers (``state.lam``): where the
    rows in contact are dependent (a hinged plane, a face on a face, a locked group's self-stress)
    the forces that balance the state are a set, and each backend returns its own point of it.
    The feature formulation and the penalty baseline (no multiplier set, ``_checkable``) report
    the path's own: ``state.contacts`` and ``state.lam``.
    """
    from ..increment import PunctureLevel
    from ..multipliers import force_scale_of, least_norm_member, multiplier_set

    if state.contacts is None or not len(state.contacts.gap) or not _checkable(setup):
        return state.contacts, np.asarray(state.lam)
    patch, K = build_model(setup)
    load = _load_point(patch, (float(load_point[0]), float(load_point[1])))
    level = PunctureLevel(
        patch, K, state.q, load, state.delta, setup.contact, setup.sqp, previous=state.contacts
    )
    qp, rows = level.increment_qp()
    if rows is None:
        return None, np.zeros(0)
    ms = multiplier_set(qp, force_scale_of(state))
    lam, _ = least_norm_member(ms)
    out = np.zeros(len(rows.gap))
    out[ms.rows] = lam
    return rows, out


def top_vertices(patch: Patch) -> np.ndarray:
    """Top-face vertices ``(n, 2)`` of the punctured scale relative to its reference point."""
    return patch.prism(0).vertices[patch.prism(0).n_base :, :2]


def _load_point(patch: Patch, xy: tuple[float, float] | np.ndarray) -> LoadPoint:
    return LoadPoint(0, np.array([xy[0], xy[1], patch.design.thickness]))


def _checkable(setup: PunctureSetup) -> bool:
    """The second-variation test needs the plane formulation's rows (or no contact at all)."""
    if setup.sqp.solver == "penalty":
        return False
    return not setup.contact_on or setup.contact.formulation == "plane"


def puncture_path(
    setup: PunctureSetup,
    patch: Patch,
    K: sp.csc_matrix,
    load: LoadPoint,
    mirror: Mirror | None = None,
    check: bool = False,
) -> Path:
    """The path of one load point of ``setup`` (formulations/puncture.md secs. 2-4).

    Its levels are the sequential QP's, or the penalty baseline's with ``sqp.solver == "penalty"``;
    ``mirror`` holds it on the symmetric branch of that reflection; ``check`` runs the
    second-variation test on every converged state.  Jumps are located where the energy balance
    holds (``_checkable``).
    """
    contact = setup.contact if setup.contact_on else None
    level: LevelSolver
    if setup.sqp.solver == "penalty":
        penalty = setup.penalty if setup.penalty is not None else PenaltySettings()
        level = PenaltyLevels(patch, K, load, contact, penalty)
    else:
        level = SQPLevels(patch, K, load, contact, setup.sqp, mirror)
    settings = PathSettings(
        phi_c_deg=setup.phi_c_deg,
        increments=setup.increments,
        max_increments=setup.max_increments,
        solver=setup.sqp.solver,
        check=check,
        # The energy balance that locates jumps holds for exact frictionless contact only (the
        # feature rows' sticky axis and the penalty dissipate ~1e-3 of the work).
        conservative=_checkable(setup),
    )
    functions = StateFunctions.of_point_load(patch, K, load, level if isinstance(level, SQPLevels) else None)
    return Path(level, functions, settings, unloaded(patch.n_scales), mirror=mirror)


def _one_point(
    setup: PunctureSetup, patch: Patch, K: sp.csc_matrix, xy: np.ndarray
) -> tuple[list[Equilibrium], list[Event], tuple[int, int], BranchRecord, LevelSolver]:
    """The path of one load point and what its stability check found (sec. 4)."""
    load = _load_point(patch, xy)
    check = setup.probe and _checkable(setup)
    mirror = mirror_through(patch, xy) if check and setup.contact_on else None
    if mirror is None:
        path = puncture_path(setup, patch, K, load, check=check)
        states = path.run()
        count = (path.solves, path.qp_solves)
        return states, path.events, count, BranchRecord.of_events(path.events, check), path.level
    return _symmetric_point(setup, patch, K, load, xy, mirror)


def _symmetric_point(
    setup: PunctureSetup, patch: Patch, K: sp.csc_matrix, load: LoadPoint, xy: np.ndarray, mirror: tuple
) -> tuple[list[Equilibrium], list[Event], tuple[int, int], BranchRecord, LevelSolver]:
    """A load point on a mirror line: the symmetric branch, held by constraints, until a state
    fails the second-variation test (located by the path's bisection); the path then continues,
    unconstrained, from the state pushed along the unstable mode to a fixed side."""
    M, perm = mirror
    sym = puncture_path(setup, patch, K, load, mirror=Mirror.of(patch, M, perm), check=True)
    try:
        states = sym.run()
        count = (sym.solves, sym.qp_solves)
        return states, sym.events, count, BranchRecord("second variation", mirror=True), sym.level
    except (Bifurcation, HeldBranchEnds) as exc:
        lost = exc
    free = puncture_path(setup, patch, K, load, check=True)
    free.base_step = sym.base_step  # the free branch continues the held path's step bounds
    min_eigenvalue = None
    if isinstance(lost, Bifurcation):
        sv = lost.stability
        states = free.switch(lost, sv.mode * _side(sv.mode[load.scale], M))
        min_eigenvalue = sv.min_eigenvalue
    else:
        # The held branch stopped being an equilibrium of the free problem: no unstable mode to
        # push along; the path goes on free from the last held state it balances (puncture.md
        # sec. 4).
        free.smooth_from = len(lost.before)
        states = free.run(list(lost.before), step=lost.step)
    record = BranchRecord(
        "second variation",
        mirror=True,
        branched=True,
        delta_branch=(lost.before[-1].delta, lost.state.delta),
        min_eigenvalue=min_eigenvalue,
        followed="asymmetric",
        asymmetry_at_failure=_asymmetry(states[-1].q, M, perm),
    )
    count = (sym.solves + free.solves, sym.qp_solves + free.qp_solves)
    return states, sym.events + free.events, count, record, free.level


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
    candidates: list[Candidate] = []
    best = None
    levels = solves = 0
    for xy in points:
        if progress:
            progress(f"load point ({xy[0]:.3f}, {xy[1]:.3f})")
        states, events, (n_levels, n_qps), record, level = _one_point(setup, patch, K, xy)
        levels, solves = levels + n_levels, solves + n_qps
        candidates.append(Candidate((float(xy[0]), float(xy[1])), states[-1].F, record))
        if best is None or states[-1].F < best[0][-1].F:
            best = (states, events, xy, record, level)
    assert best is not None
    states, events, xy, branch, level = best
    Fc_check = _check_Fc(level, states[-1], patch.n_scales * 5)
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
        load_levels=levels,
        candidates=candidates,
        Fc_check=Fc_check,
    )


def _check_Fc(level: LevelSolver, final: Equilibrium, n_dof: int) -> ForceCheck | None:
    """F_c against the exact active-set solution of the QP linearised at the failure state
    (formulations/increment-qp.md sec. 8); None for the penalty baseline, whose force is not a
    QP's multiplier.  A certified exact answer that disagrees is a failure, never a number."""
    if not isinstance(level, SQPLevels) or final.contacts is None:
        return None
    check = check_force(level.increment_qp(final)[0], final.F, n_dof)
    if check.status == "disagrees":
        raise SolverFailure(level.settings.solver, "F_c check failed", None, check.detail)
    return check


def _asymmetry(q: np.ndarray, M: np.ndarray, perm: np.ndarray) -> float:
    return float(np.max(np.abs(q - map_dofs(q, M, perm))))
