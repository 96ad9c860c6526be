"""Three-point bending of a scaled membrane: supports, plate, bonded scales, contact, curve, C_f*.

Implements formulations/membrane.md sections 6-8: the retained and held DOFs (eq. (9)), the
unilateral supports held closed until their reaction pulls (eqs. (10), (10b), (8c)), the plate
(eq. (11)), scale-scale contact by separating planes from ``qpscale.contact`` (eq. (12)), the
sequential QP at each plate position (eq. (13), iterated by the level driver of ``qpscale.level``,
formulations/increment.md sec. 4a) and the compliance read-out (eq. (14)).  The membrane is
condensed once (qpscale.membrane); every QP has only the retained DOFs and the planes.
"""

from __future__ import annotations

import hashlib
import threading
import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
import shapely
from shapely.geometry import Polygon, box

from .. import level
from ..contact import ContactSet, ContactSettings, detect_contacts, gap_jacobian, penetration
from ..errors import InvalidDesign, SolverFailure
from ..events import Rescue
from ..geometry import Array, rotation_matrices, rotation_matrix, skew, tangent_operator
from ..increment import PLANE_PROX, PlaneDamping, _pinned_only, map_labels, pressed_planes
from ..level import LevelControls, LevelOutcome, LevelStatus, Progress, Step, qp_step
from ..membrane import Condensed, MembraneMesh, MembraneModel, build_mesh, condense, generalised_map
from ..qp import IncrementQP, WarmStart, block_diagonal
from ..solvers import DEFAULT_SOLVER
from ..tiling import Design, Patch, build_patch
from ..units import compliance_star

MODES = ("scaled", "isolated", "bare")
SUPPORTS = ("roller", "strip")
MESHES = ("tensor", "fitted")
PENETRATION_TOL = 1e-9
STEP_TOL = 1e-9  # L: largest change of a retained DOF (scale DOFs, support and plate u_z)
ACCURACY = "high"  # KKT tolerance 1e-9 of each QP
# Linearisations of a plate position.  A hinged plane that swings by ~0.02 rad every other step
# restarts Anderson's history each time (the step's norm jumps), so such a position converges at the
# plain iteration's rate: 0.81 a step on the fitted trapezoid staggered array slanted towards 45 deg
# along y, which needed 76 (membrane.md sec. 9e).  A converged position stops at its own count.
MAX_ITER = 120
ROW_MEMORY = 4  # linearisations whose contact rows stay in the QP (_merge_rows)
RELEASE_TOL = 1e-9  # E_m L^2: a held support DOF whose reaction pulls harder is released (sec. 7)
MAX_RELEASE_ROUNDS = 20
# The damped planes' weight kappa F_j (increment.md eq. (4c), kappa = 1 L) is sized for puncture, where a
# contact force over the scales' stiffness is 0.1 L or more.  Here it is about 1e-4 L (forces of 1e-2
# E_m L^2, diagonal of S 70-200 E_m L for the scale DOFs: the membrane in the gaps), so the weight is
# scaled up by this factor to hold a hinged plane comparably firmly (membrane.md sec. 8).
FLEXURE_DAMPING = 100.0


@dataclass(frozen=True)
class FlexureSetup:
    """A three-point bending test of the membrane, bare or with bonded scales.

    Parameters
    ----------
    design : Design
        Scale design (its ``rings`` is ignored: the face is covered, see ``kept_scales``).
    mode : {"scaled", "isolated", "bare"}
        Scales covering the top face, one scale at the centre, or none.
    load_line : {"x", "y"}
        Direction of the plate; supports are parallel to it at +-span/2 across it.
    membrane : MembraneModel
    span, plate_width : float
        Distance between the support lines and the width of the flat rigid plate, in L.
    supports : {"roller", "strip"}
        Rigid frictionless rollers (cylinders of radius ``roller_radius`` whose axes lie at
        ``s = +-span/2`` under the membrane, eq. (10r)), or the former flat strips of width
        ``support_width`` centred there (the membrane then bears on their inner edges).
    roller_radius, support_width : float
        Roller radius and strip width, in L.
    roller_zone : float
        Bottom nodes whose initial gap to a roller is at most this (L) carry unilateral rows; the
        others are checked after the curve and the zone is doubled if one of them penetrates.
    contact_h : float
        Element size at the roller lines and (bare membrane) at the plate edges; the mesh is graded
        from it with the membrane's growth ratio (membrane.md sec. 2).
    max_deflection : float
        Final plate displacement, in L.
    increments : int
        Plate positions on the curve.
    contact : bool
        Scale-scale contact rows (False: scales interact through the membrane only).
    formulation : {"plane", "feature"}
        Scale-scale contact by separating planes (default) or by clipped features
        (formulations/contact.md sections 7 and 3-6; membrane.md sec. 8).
    grade : bool
        Mesh lines at the scales' axis-parallel edges, graded towards the gaps (False: uniform).
    gap_elements : int or None
        Elements across each gap between bonded footprints (scaled and isolated modes, gap d > 0):
        the element size at the graded lines and the top layer are both ``d / gap_elements``, so
        the membrane under a gap is resolved in both directions (membrane.md sec. 9c).  None: the
        membrane model's ``h_min`` and ``top_h`` as given (the gap is then one element wide).
    solver : str
        QP backend.
    mesh : {"tensor", "fitted"}
        The tensor mesh of section 2, or the footprint-fitted mesh (scales with a gap only; gmsh,
        installed with qpscale; membrane.md secs. 9d-9e) whose lines follow every gap.
    along : float
        Fitted mesh: element size along the gaps and the rings beside them, in L (the study's 0.5:
        the reductions move by tenths of a point to 0.25, membrane.md sec. 9e).
    """

    design: Design = field(default_factory=Design)
    mode: str = "scaled"
    load_line: str = "x"
    membrane: MembraneModel = field(default_factory=MembraneModel)
    span: float = 8.0
    plate_width: float = 0.5
    supports: str = "roller"
    roller_radius: float = 0.5
    support_width: float = 0.5
    roller_zone: float = 0.04
    contact_h: float = 0.05
    max_deflection: float = 0.2
    increments: int = 5
    contact: bool = True
    formulation: str = "plane"
    grade: bool = True
    gap_elements: int | None = 2
    solver: str = DEFAULT_SOLVER
    mesh: str = "tensor"
    along: float = 0.5

    def __post_init__(self) -> None:
        if self.mesh not in MESHES:
            raise InvalidDesign("mesh", self.mesh, "{" + ", ".join(MESHES) + "}")
        if self.mesh == "fitted" and (self.mode == "bare" or self.design.gap <= 0.0):
            raise InvalidDesign("mesh", self.mesh, "'tensor' for the bare membrane or a design without gaps")
        if not 0.0 < self.along <= 1.0:
            raise InvalidDesign("along", self.along, "(0, 1] L")
        if self.mode not in MODES:
            raise InvalidDesign("mode", self.mode, "{" + ", ".join(MODES) + "}")
        if self.load_line not in ("x", "y"):
            raise InvalidDesign("load_line", self.load_line, "{x, y}")
        if self.supports not in SUPPORTS:
            raise InvalidDesign("supports", self.supports, "{" + ", ".join(SUPPORTS) + "}")
        if self.formulation not in ("plane", "feature"):
            raise InvalidDesign("formulation", self.formulation, "{plane, feature}")
        if self.solver == "osqp" and self.formulation == "plane" and self.mode == "scaled":
            # Refused, not switched: OSQP cannot polish the plane formulation's dependent rows
            # (formulations/contact.md sec. 7); the feature rows must be asked for by name.
            raise InvalidDesign(
                "solver",
                self.solver,
                "a backend that solves the plane formulation (piqp, clarabel, cvxpy, qpsolvers:*); "
                "osqp only with formulation='feature'",
            )
        half = (self.membrane.width if self.load_line == "x" else self.membrane.length) / 2
        checks = [
            ("span", self.span, 0 < self.span / 2 + self.support_width / 2 < half),
            ("plate_width", self.plate_width, 0 < self.plate_width < self.span / 2),
            ("support_width", self.support_width, 0 < self.support_width < self.span / 2),
            ("roller_radius", self.roller_radius, 0 < self.roller_radius < self.span / 2 - self.plate_width),
            ("roller_zone", self.roller_zone, 0 < self.roller_zone <= self.roller_radius),
            ("contact_h", self.contact_h, 0 < self.contact_h <= self.membrane.h),
            ("max_deflection", self.max_deflection, 0 < self.max_deflection <= 1.0),
            ("increments", self.increments, 1 <= int(self.increments) == self.increments <= 200),
        ]
        if self.gap_elements is not None:
            n = self.gap_elements
            checks.append(("gap_elements", n, 1 <= int(n) == n <= 64))
        for name, value, ok in checks:
            if not ok:
                raise InvalidDesign(name, value, "a positive value that fits the membrane")

    @property
    def axis(self) -> int:
        """Coordinate across the load line (the bending direction): 1 for load line x."""
        return 1 if self.load_line == "x" else 0


@dataclass(frozen=True)
class FlexureResult:
    """Force-deflection curve and compliance (E_m = 1 units unless the model says otherwise).

    Attributes
    ----------
    deflection, force : ndarray (k,)
        Plate displacement (L) and plate reaction (E_m L^2), starting at (0, 0).
    C_f, Cf_star : float
        Compliance read at the end of the curve, eq. (14), and its normalisation.
    n_scales, n_retained, sqp_iterations, max_penetration, wall_s, condense_s
        Diagnostics.
    """

    deflection: Array
    force: Array
    C_f: float
    Cf_star: float
    n_scales: int
    n_retained: int
    sqp_iterations: int
    max_penetration: float
    wall_s: float
    condense_s: float
    z_final: Array = field(repr=False)
    extras: dict = field(default_factory=dict, repr=False)


def kept_scales(setup: FlexureSetup) -> Patch:
    """Scales whose base centroid lies on the membrane's top face (isolated: the centre one)."""
    if setup.mode == "isolated":
        return build_patch(setup.design.isolated())
    a, b = setup.membrane.length / 2, setup.membrane.width / 2
    rings, count = 2, -1
    patch = build_patch(setup.design.with_(rings=rings))
    while rings <= 40:
        patch = build_patch(setup.design.with_(rings=rings))
        inside = (np.abs(patch.centroids[:, 0]) < a) & (np.abs(patch.centroids[:, 1]) < b)
        if inside.sum() == count:
            break
        count, rings = int(inside.sum()), rings + 2
    return sub_patch(patch, np.flatnonzero(inside))


def sub_patch(patch: Patch, keep: np.ndarray) -> Patch:
    """The scales ``keep`` of ``patch`` as a patch of their own (neighbour pairs re-indexed)."""
    new = np.full(patch.n_scales, -1)
    new[keep] = np.arange(len(keep))
    nb = new[patch.neighbours]
    nb = nb[(nb >= 0).all(axis=1)]
    return Patch(
        patch.design,
        patch.sites[keep],
        patch.centroids[keep],
        patch.angles[keep],
        patch.ring[keep],
        nb.reshape(-1, 2),
    )


def _strips(setup: FlexureSetup) -> tuple[Polygon, list[Polygon]]:
    """Plate strip (top) and the two support strips (bottom) in the plane."""
    big = 10.0 * max(setup.membrane.length, setup.membrane.width)
    wp, ws, s = setup.plate_width / 2, setup.support_width / 2, setup.span / 2

    def strip(c: float, w: float) -> Polygon:
        return box(-big, c - w, big, c + w) if setup.axis == 1 else box(c - w, -big, c + w, big)

    return strip(0.0, wp), [strip(-s, ws), strip(s, ws)]


def _mesh(setup: FlexureSetup, patch: Patch | None) -> MembraneMesh:
    """Grid lines at the strip edges and at every axis-parallel scale edge (membrane.md sec. 2);
    or, with ``setup.mesh == "fitted"``, the footprint-fitted mesh (``fitted_mesh``).

    Scale edges parallel to the load line (across which the membrane bends) are graded lines:
    the mesh is refined geometrically towards them, so the free strip between two bonded regions
    is the gap d itself; the other axis-parallel edges are plain grid lines.
    Rollers: the roller lines ``s = +-span/2`` (and, bare membrane, the plate edges) are graded
    lines too, from ``contact_h``, so that the contact width under a roller (membrane.md sec. 7)
    and the plate's edge singularity are resolved.
    """
    if setup.mesh == "fitted" and patch is not None:
        from ..fitted_mesh import fitted_mesh

        return fitted_mesh(setup, patch, along=setup.along)
    s, wp, ws = setup.span / 2, setup.plate_width / 2, setup.support_width / 2
    xe, ye = _edge_lines(patch) if patch is not None and setup.grade else ((), ())
    mem = mesh_membrane(setup, patch)
    h_gap = mem.h_min
    fine, fine_h = tuple(ye if setup.axis == 1 else xe), [h_gap] * len(ye if setup.axis == 1 else xe)
    inside = _gap_interior(fine, setup.design.gap, setup.gap_elements) if mem is not setup.membrane else ()
    if setup.supports == "strip":
        cuts: tuple[float, ...] = (-s - ws, -s + ws, s - ws, s + ws, -wp, wp)
    else:
        cuts = (-wp, wp)
        lines = (-s, s) if patch is not None else (-s, s, -wp, wp)
        fine, fine_h = fine + lines, fine_h + [setup.contact_h] * len(lines)
    other, cuts = xe if setup.axis == 1 else ye, cuts + inside
    if setup.axis == 1:
        args = {"xbreaks": other, "ybreaks": cuts, "yfine": fine, "yfine_h": tuple(fine_h)}
    else:
        args = {"xbreaks": cuts, "ybreaks": other, "xfine": fine, "xfine_h": tuple(fine_h)}
    return MembraneMesh(mem, build_mesh(mem, **args))


def oblique_edges(design: Design) -> bool:
    """Whether the design's footprints have an edge parallel to neither x nor y (a gap the tensor
    mesh of sec. 2 cannot follow)."""
    base = np.asarray(design.patch().base[:1], dtype=float)
    E = np.roll(base, -1, axis=1) - base
    return bool(np.any((np.abs(E[..., 0]) > 1e-9) & (np.abs(E[..., 1]) > 1e-9)))


def mesh_membrane(setup: FlexureSetup, patch: Patch | None) -> MembraneModel:
    """The membrane model the mesh is built from (membrane.md sec. 9c).

    With scales, a gap d > 0 and ``gap_elements = n``: the size at the graded lines and the top
    layer are ``d / n`` (a ``top_h`` given in the model is kept); otherwise the model as given.
    """
    n, d = setup.gap_elements, setup.design.gap
    if patch is None or n is None or d <= 0.0:
        return setup.membrane
    mem = setup.membrane
    size = d / n
    top = min(size, mem.height / mem.nz) if mem.top_h is None else mem.top_h
    return replace(mem, h_min=min(size, mem.h), top_h=top)


def _gap_interior(lines: tuple[float, ...], gap: float, n: int | None) -> tuple[float, ...]:
    """``n - 1`` equally spaced lines inside every gap between two graded lines ``gap`` apart, so
    that each gap is ``n`` elements of ``d / n`` (the grading alone rounds their number)."""
    if n is None or n < 2 or gap <= 0.0:
        return ()
    x = np.unique(np.round(np.asarray(lines, dtype=float), 9))
    a = x[:-1][np.abs(np.diff(x) - gap) < 1e-7]
    return tuple((a[:, None] + gap * np.arange(1, n)[None, :] / n).ravel().tolist())


def _edge_lines(patch: Patch) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """x of the scales' edges parallel to y and y of those parallel to x (base polygons), in L."""
    P = patch.base
    E = np.roll(P, -1, axis=1) - P
    xs = np.unique(np.round(P[np.abs(E[..., 0]) < 1e-9][:, 0], 9))
    ys = np.unique(np.round(P[np.abs(E[..., 1]) < 1e-9][:, 1], 9))
    return tuple(xs.tolist()), tuple(ys.tolist())


def _in(poly: Polygon, xy: Array) -> np.ndarray:
    return shapely.contains_xy(poly.buffer(1e-9, join_style="mitre"), xy[:, 0], xy[:, 1])


@dataclass(frozen=True)
class FlexureModel:
    """Everything fixed across the curve: condensed membrane, retained DOF layout, plate points."""

    setup: FlexureSetup
    mm: MembraneMesh
    patch: Patch | None
    cond: Condensed
    n_q: int  # 5 * number of scales (first block of the retained DOFs)
    support_idx: np.ndarray  # positions in z_r of the released support u_z (unilateral rows)
    support_gap: np.ndarray  # their initial gaps g_0 to the support, eq. (10r): rows -u_z <= g_0
    plate_idx: np.ndarray  # bare: positions in z_r of the plate-node u_z
    plate_points: list  # scaled: (scale, body point (3,)) material points under the plate
    condense_s: float

    @cached_property
    def S(self) -> sp.csc_matrix:
        """The condensed stiffness, eq. (8), as the QP's CSC matrix (built once per curve)."""
        return sp.csc_matrix(self.cond.S)


def build_model(setup: FlexureSetup, mesh: MembraneMesh | None = None) -> FlexureModel:
    """Mesh, tie, pin and condense the membrane once (formulations/membrane.md eqs. (5)-(9)).

    ``mesh`` replaces the mesh of section 2 (e.g. a scaled design's mesh for the bare membrane).
    The support DOFs start held closed (``Condensed.held``); see ``_release_tensile``.
    """
    t0 = time.perf_counter()
    patch = None if setup.mode == "bare" else kept_scales(setup)
    mm = _mesh(setup, patch) if mesh is None else mesh
    xyz = mm.nodes
    top, bottom = mm.face_nodes(True), mm.face_nodes(False)
    plate, supports = _strips(setup)
    ties = []
    if patch is not None:
        taken = np.zeros(len(top), bool)
        for i, poly in enumerate(patch.polygons()):
            mask = _in(poly, xyz[top, :2]) & ~taken
            taken |= mask
            ties.append((top[mask], xyz[top[mask], :2], patch.centroids[i]))
    pins = _pins(xyz, bottom)
    T, gen_of = generalised_map(len(xyz), ties, pins, mm.slaves)
    if setup.supports == "strip":
        sup_nodes = bottom[_in(supports[0], xyz[bottom, :2]) | _in(supports[1], xyz[bottom, :2])]
        rows, gap0 = np.zeros(0, int), np.zeros(0)
    else:
        sup_nodes, rows, gap0 = _roller_nodes(setup, xyz, bottom)
    n_q = 5 * len(ties)
    n_free = T.shape[1] - n_q
    plate_nodes = top[_in(plate, xyz[top, :2])] if patch is None else np.zeros(0, int)
    retained = np.r_[n_free + np.arange(n_q), gen_of[3 * plate_nodes + 2], gen_of[3 * rows + 2]]
    held = gen_of[3 * sup_nodes + 2]
    if (held < 0).any() or (retained < 0).any():
        raise InvalidDesign("mesh", "a support or plate node is tied or pinned", "untied nodes")
    cond = _condensed(mm, T, retained, held)
    points = _plate_points(patch, plate) if patch is not None else []
    plate_idx = n_q + np.arange(len(plate_nodes))
    support_idx = n_q + len(plate_nodes) + np.arange(len(rows))
    return FlexureModel(
        setup, mm, patch, cond, n_q, support_idx, gap0, plate_idx, points, time.perf_counter() - t0
    )


# The last condensation this process made, for the next model with the same inputs (a slanted
# design has its unslanted footprints, hence the same mesh, ties and condensation: membrane.md
# sec. 5, "Reuse").  One entry: a miss drops it before condensing, so the peak memory of a build
# stays that of one condensation.
_LAST: dict[str, tuple[str, Condensed]] = {}
_LAST_LOCK = threading.Lock()


def forget_condensation() -> None:
    """Drop the condensation this process keeps for reuse (its factor can hold a gigabyte on the
    finest default meshes); the next model condenses afresh."""
    with _LAST_LOCK:
        _LAST.clear()


def _digest(*parts: object) -> str:
    """A hash of strings and arrays (dtype, shape and bytes): equal digests, equal inputs."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, str):
            h.update(part.encode())
        else:
            a = np.ascontiguousarray(part)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()


def _condensed(mm: MembraneMesh, T: sp.csr_matrix, retained: np.ndarray, held: np.ndarray) -> Condensed:
    """``condense(mm.K, T, retained, held)``, or the last one made here if its inputs were the same.

    The key is a hash of everything the condensation reads: the membrane model, the mesh's nodes
    and elements (hence K), the map T (ties and pins) and the retained and held DOFs.  A
    condensation is never modified after it is made (``Condensed`` is frozen and ``released``
    returns a new one), so a model may share it.
    """
    T = sp.csr_matrix(T)
    mesh = (repr(mm.model), mm.mesh.p, mm.mesh.t)
    key = _digest(*mesh, T.indptr, T.indices, T.data, np.asarray(retained), np.asarray(held))
    with _LAST_LOCK:
        last = _LAST.get("cond")
        if last is not None and last[0] == key:
            return last[1]
        _LAST.clear()  # before condensing: never two factors held at once
        cond = condense(mm.K, T, retained, held)
        _LAST["cond"] = (key, cond)
        return cond


def roller_gap(setup: FlexureSetup, s: Array) -> Array:
    """Vertical gap ``g_0(s) = r - sqrt(r^2 - (s - s_c)^2)`` of bottom points over the nearer roller,
    eq. (10r) (inf where no roller lies below: ``|s - s_c| >= r``)."""
    r, sc = setup.roller_radius, setup.span / 2
    ds = np.abs(np.abs(s) - sc)
    out = np.full(np.shape(s), np.inf)
    below = ds < r
    out[below] = r - np.sqrt(r**2 - ds[below] ** 2)
    return out


def roller_penetration(model: FlexureModel, states: list[FlexureState]) -> float:
    """Largest penetration (L) of a bottom node without a row into a roller over the curve's states."""
    if model.setup.supports != "roller":
        return 0.0
    bottom = model.mm.face_nodes(False)
    g0 = roller_gap(model.setup, model.mm.nodes[bottom, model.setup.axis])
    free = np.isfinite(g0) & (g0 > model.setup.roller_zone)
    if not free.any():
        return 0.0
    uz = [model.cond.displacement(st.z)[bottom[free], 2] for st in states]
    return max(0.0, float(np.max(-(np.array(uz) + g0[free]))))


def _roller_nodes(
    setup: FlexureSetup, xyz: Array, bottom: np.ndarray
) -> tuple[np.ndarray, np.ndarray, Array]:
    """Bottom nodes over the rollers: those on a roller line (gap 0, held closed) and the others
    within the zone (``0 < g_0 <= roller_zone``; retained with the rows of eq. (10r)) and their gaps."""
    g0 = roller_gap(setup, xyz[bottom, setup.axis])
    on_line = g0 < 1e-12
    near = (g0 <= setup.roller_zone) & ~on_line
    return bottom[on_line], bottom[near], g0[near]


def _release_tensile(model: FlexureModel, z: Array) -> tuple[FlexureModel, Array, int]:
    """Support DOFs held closed whose reaction pulls (eq. (10b)) become unilateral QP rows.

    Returns the model with those DOFs released (appended to the retained DOFs), ``z`` padded
    with their current value 0, and how many were released.
    """
    if not len(model.cond.held):
        return model, z, 0
    r = model.cond.reactions(z)
    pull = model.cond.held[r < -RELEASE_TOL]
    if not len(pull):
        return model, z, 0
    return released_supports(model, pull), np.r_[z, np.zeros(len(pull))], len(pull)


def released_supports(model: FlexureModel, dofs: np.ndarray) -> FlexureModel:
    """``model`` with the held support DOFs ``dofs`` turned into retained DOFs with unilateral rows."""
    idx = np.r_[model.support_idx, len(model.cond.retained) + np.arange(len(dofs))]
    gap = np.r_[model.support_gap, np.zeros(len(dofs))]
    return replace(model, cond=model.cond.released(dofs), support_idx=idx, support_gap=gap)


def support_forces(model: FlexureModel, z: Array) -> tuple[np.ndarray, Array, Array]:
    """Every support DOF (generalised index), its u_z and the force the support puts on it, eq. (10b).

    The force is ``(K_g g)`` at the DOF: the reaction of a held DOF, the row's multiplier for a
    released one (they agree at a converged state).
    """
    cond = model.cond
    dofs = np.r_[cond.held, cond.retained[model.support_idx]]
    g = cond.generalised(z)
    return dofs, g[dofs], sp.csr_matrix(cond.K_g)[dofs] @ g


def _pins(xyz: Array, bottom: np.ndarray) -> np.ndarray:
    """Three reaction-free pins removing the in-plane rigid modes (eq. (9)).

    u_x, u_y at the bottom node nearest the centre and u_y at the bottom node nearest (a/4, 0) off
    the centre node's line x = const (on a narrow membrane the nearest node to (a/4, 0) can be the
    centre node itself, which would leave the rotation about z free and ``K_cc`` singular).
    """
    b = xyz[bottom]
    c = bottom[np.argmin(np.hypot(b[:, 0], b[:, 1]))]
    a = 0.25 * b[:, 0].max()
    dist = np.hypot(b[:, 0] - a, b[:, 1])
    dist[np.abs(b[:, 0] - xyz[c, 0]) < 1e-9] = np.inf
    e = bottom[np.argmin(dist)]
    return np.array([3 * c, 3 * c + 1, 3 * e + 1])


def _plate_points(patch: Patch, plate: Polygon) -> list[tuple[int, Array]]:
    """Vertices of (top face ∩ plate strip) of every scale, as body-frame material points."""
    d = patch.design
    out = []
    for i, base in enumerate(patch.base):
        top = Polygon(base + d.top_offset)
        inter = top.intersection(plate)
        if inter.is_empty or inter.area < 1e-12:
            continue
        corners = [np.asarray(g.exterior.coords)[:-1] for g in shapely.get_parts(inter) if g.area > 1e-12]
        for xy in np.vstack(corners):
            out.append(
                (i, np.array([xy[0] - patch.centroids[i, 0], xy[1] - patch.centroids[i, 1], d.thickness]))
            )
    return out


def _plate_rows(model: FlexureModel, z: Array, z_plate: float) -> tuple[Array, Array, Array]:
    """Plate rows ``G z <= h`` linearised at ``z`` and the exact overlaps there, eq. (11)."""
    m = len(model.plate_points) if model.patch is not None else len(model.plate_idx)
    G = np.zeros((m, len(z)))
    if model.patch is None:
        G[np.arange(m), model.plate_idx] = 1.0
        H = model.setup.membrane.height
        return G, np.full(m, z_plate - H), z[model.plate_idx] + H - z_plate
    h, over = np.zeros(m), np.zeros(m)
    q = z[: model.n_q].reshape(-1, 5)
    for k, (i, r) in enumerate(model.plate_points):
        Rr = rotation_matrix(q[i, 3:]) @ r
        zp = model.setup.membrane.height + q[i, 2] + Rr[2]
        dz = np.r_[0.0, 0.0, 1.0, (-skew(Rr) @ tangent_operator(q[i, 3:]))[2]]
        G[k, 5 * i : 5 * i + 5] = dz
        h[k] = z_plate - zp + dz @ q[i]
        over[k] = zp - z_plate
    return G, h, over


FEATURE = ContactSettings(formulation="feature")
PLANE = ContactSettings(formulation="plane")


def _contact_rows(
    model: FlexureModel,
    z: Array,
    previous: ContactSet | None,
    refresh: float | None = None,
    pressed: frozenset = frozenset(),
) -> tuple[sp.csr_matrix, Array, ContactSet | None]:
    """Scale-scale rows ``-J (z, theta) <= g - J_q q_n`` from qpscale.contact, eq. (12), and their set.

    Columns: the retained DOFs ``z``, then the plane unknowns ``theta`` of the set (plane
    formulation; none for the feature formulation).  ``previous`` carries the planes moved by the
    last QP (plane) or each pair's sticky axis (feature); of the planes, those in ``pressed`` (the
    last QP pressed them) restart from their best axis once stale by ``STALE_PLANE_TOL``
    (contact.md sec. 7, membrane.md sec. 8).
    """
    n = len(z)
    if model.patch is None or model.patch.n_scales < 2 or not model.setup.contact:
        return sp.csr_matrix((0, n)), np.zeros(0), None
    q = z[: model.n_q].reshape(-1, 5)
    settings = PLANE if model.setup.formulation == "plane" else FEATURE
    cs = detect_contacts(model.patch, q, settings, previous=previous, refresh=refresh, pressed=pressed)
    J = sp.csr_matrix(gap_jacobian(cs, model.patch, q))
    Jq = J[:, : model.n_q]
    G = sp.hstack([-Jq, sp.csr_matrix((cs.m, n - model.n_q)), -J[:, model.n_q :]], format="csr")
    return G, np.asarray(cs.gap) - Jq @ z[: model.n_q], cs


@dataclass(frozen=True)
class FlexureState:
    """A converged state at one plate position.

    Attributes
    ----------
    w : float
        Plate displacement, in L.
    force : float
        Plate reaction (sum of the plate rows' multipliers), E_m L^2.
    z : ndarray (m,)
        Retained generalised DOFs.
    contacts : ContactSet or None
        Scale-scale contact rows of the last QP; ``lam`` their multipliers (>= 0, E_m L^2).
    lam : ndarray (contacts.m,)
    iterations : int
    penetration : float
        Largest exact overlap (plate and scale-scale), in L.
    """

    w: float
    force: float
    z: Array = field(repr=False)
    contacts: ContactSet | None = field(repr=False)
    lam: Array = field(repr=False)
    iterations: int
    penetration: float


def _exact_penetration(model: FlexureModel, z: Array, z_plate: float) -> float:
    over = float(np.max(_plate_rows(model, z, z_plate)[2], initial=0.0))
    if model.patch is None or model.patch.n_scales < 2 or not model.setup.contact:
        return max(0.0, over)
    return max(0.0, over, float(penetration(model.patch, z[: model.n_q].reshape(-1, 5))))


def _merge_rows(
    model: FlexureModel, history: list[tuple[sp.csr_matrix, Array, ContactSet | None]], z: Array
) -> tuple[sp.csr_matrix, Array, ContactSet | None]:
    """The current contact rows plus, for contact points that just left the set, their last rows.

    Near-coincident faces make the clipped point set flicker between linearisations (a cycle of
    2-4 sets was seen on the square array); keeping the rows of the last ``ROW_MEMORY``
    linearisations, each at its own linearisation point, lets the iteration settle on their
    union (formulations/membrane.md sec. 8).  Stale rows are re-linearised at the current
    ``z``: their material points follow their scales' exact rigid motion (``_relinearise``).
    """
    G, h, cs = history[-1]
    if cs is None or model.patch is None:
        return G, h, cs
    seen = set(_row_keys(cs))
    Gs, hs, parts = [G], [h], [cs]
    for _, _, ck in reversed(history[:-1]):
        keys = _row_keys(ck)
        keep = np.array([k not in seen for k in keys], dtype=bool)
        if keep.any():
            seen.update(k for k, kp in zip(keys, keep) if kp)
            moved = _relinearise(_take(ck, keep), model.patch, cs)
            J = sp.csr_matrix(gap_jacobian(moved, model.patch, cs.q))
            Gs.append(sp.hstack([-J, sp.csr_matrix((moved.m, len(z) - model.n_q))], format="csr"))
            hs.append(moved.gap - J @ z[: model.n_q])
            parts.append(moved)
    if len(parts) == 1:
        return G, h, cs
    return sp.vstack(Gs, format="csr"), np.concatenate(hs), _concat(parts)


def _relinearise(ck: ContactSet, patch: Patch, cs: ContactSet) -> ContactSet:
    """Rows of ``ck`` moved to the configuration of ``cs``: points ride on their scales, the normal on a."""
    Ra_old, Ra = _rotations(ck.q[ck.a]), _rotations(cs.q[ck.a])
    Rb_old, Rb = _rotations(ck.q[ck.b]), _rotations(cs.q[ck.b])

    def move(x: Array, idx: np.ndarray, R_old: Array, R: Array) -> Array:
        local = np.einsum("mji,mj->mi", R_old, x - ck.centre[idx])
        return cs.centre[idx] + np.einsum("mij,mj->mi", R, local)

    xa, xb = move(ck.xa, ck.a, Ra_old, Ra), move(ck.xb, ck.b, Rb_old, Rb)
    n = np.einsum("mij,mj->mi", Ra, np.einsum("mji,mj->mi", Ra_old, ck.normal))
    gap = np.einsum("mi,mi->m", n, xb - xa)
    return replace(ck, xa=xa, xb=xb, normal=n, gap=gap, q=cs.q, centre=cs.centre)


def _set_keys(cs: ContactSet | None, formulation: str) -> frozenset:
    """What identifies the linearised map for the Anderson reset: with separating planes their keys
    (a slack row entering or leaving a plane's band changes nothing, as for puncture:
    ``increment.map_labels``), feature rows by label and point (``_row_keys``)."""
    if cs is None:
        return frozenset()
    if formulation == "plane":
        return frozenset(map_labels(cs))
    return frozenset(_row_keys(cs))


def _rotations(q: Array) -> Array:
    return rotation_matrices(q[:, 3:5])


def _row_keys(cs: ContactSet) -> list[tuple]:
    """A row's identity: its feature label and where its point on b sits (to 1e-3 L)."""
    return [(lab, *np.round(x, 3)) for lab, x in zip(cs.labels, cs.xb)]


_ROW_FIELDS = ("a", "b", "piece_a", "piece_b", "normal", "xa", "xb", "gap", "kind", "side", "plane")


def _take(cs: ContactSet, keep: np.ndarray) -> ContactSet:
    rows: dict[str, Any] = {f: getattr(cs, f)[keep] for f in _ROW_FIELDS}
    labels = tuple(lab for lab, k in zip(cs.labels, keep) if k)
    return replace(cs, labels=labels, **rows)


def _concat(parts: list[ContactSet]) -> ContactSet:
    rows: dict[str, Any] = {f: np.concatenate([getattr(c, f) for c in parts]) for f in _ROW_FIELDS}
    labels = tuple(lab for c in parts for lab in c.labels)
    return replace(parts[0], labels=labels, **rows)


# QP (13) linearised at an iterate z: the QP over (z, theta), its plate-row count, the contact set
# of this linearisation and the rows it was solved with (feature formulation: with the rows of the
# last ROW_MEMORY linearisations, ``_merge_rows``).
_Linearised = tuple[Array, IncrementQP, int, ContactSet | None, ContactSet | None]


class _FlexureLevel:
    """One plate position as a :class:`qpscale.level.LevelProblem`, eq. (13).

    The QP's unknowns are the retained DOFs ``z`` themselves (the step is the answer minus the
    iterate).  Plane formulation: the planes' unknowns follow ``z`` with the proximal weight
    ``PLANE_PROX`` and unpinned planes are zeroed (as in ``qpscale.increment``).  Feature
    formulation: rows of the last ``ROW_MEMORY`` linearisations are merged (``_merge_rows``; the
    attempt's memory).
    """

    def __init__(self, model: FlexureModel, w: float, inc: int, damped: bool = False) -> None:
        setup = model.setup
        top = setup.membrane.height + (setup.design.thickness if model.patch is not None else 0.0)
        n, ns = len(model.cond.retained), len(model.support_idx)
        self.model, self.w, self.z_plate = model, w, top - w
        self.damped, self.damping = damped, PlaneDamping()
        self.Gs = sp.csr_matrix((-np.ones(ns), (np.arange(ns), model.support_idx)), shape=(ns, n))
        self.controls = LevelControls(setup.solver, w, inc, STEP_TOL, PENETRATION_TOL, MAX_ITER)
        self.history: list[tuple[sp.csr_matrix, Array, ContactSet | None]] = []
        self.pressed: frozenset = frozenset()  # keys of the planes the last QP's rows pressed
        # the last answer, its multipliers by row key and its DOFs: the next QP's warm start
        self.last: tuple[dict[Any, float], Array] | None = None

    def linearise(self, z: Array, rows: ContactSet | None, refresh: float | None) -> _Linearised:
        Gp, hp, _ = _plate_rows(self.model, z, self.z_plate)
        Gc, hc, cs = _contact_rows(self.model, z, rows, refresh, self.pressed)
        merged = cs
        if self.model.setup.formulation == "feature":
            self.history = [*self.history[-(ROW_MEMORY - 1) :], (Gc, hc, cs)]
            Gc, hc, merged = _merge_rows(self.model, self.history, z)
        weight = None
        if self.damped and cs is not None and cs.n_extra:
            w = self.damping.weights(cs).reshape(-1, 3)
            pressed = w[:, :2] > PLANE_PROX  # weights() floors the others at PLANE_PROX: kept there
            w[:, :2] = np.where(pressed, FLEXURE_DAMPING * w[:, :2], PLANE_PROX)
            weight = w.ravel()
        qp = _membrane_qp(self.model.S, Gp, hp, self.Gs, self.model.support_gap, Gc, hc, weight)
        return z, qp, len(hp), cs, merged

    def solve(self, lin: _Linearised, tightened: bool) -> Step[FlexureState]:
        z, qp, n_plate, cs, merged = lin
        c = self.controls
        keys = self._warm_keys(n_plate, merged)
        res, step = qp_step(qp, c.solver, ACCURACY, tightened, c.increment, self._warm_start(qp, keys))
        if res is None:
            return step
        x, zs = np.asarray(res.x), np.asarray(res.z)
        self.last = (dict(zip(keys, zs.tolist())), x[: len(z)])
        n, lam = len(z), zs[n_plate + len(self.model.support_idx) :]
        swing = 0.0
        if cs is not None and cs.planes is not None and cs.planes.count:
            theta = _pinned_only(x[n:], cs, lam, violated=self.damped)
            swing = float(np.max(np.abs(theta), initial=0.0))
            self.pressed = pressed_planes(cs, lam)
            cs = merged = replace(cs, plane_memory=cs.planes.advanced(theta))
            if self.damped:
                self.damping.update(cs, theta, lam)
        answer = FlexureState(self.w, float(np.sum(zs[:n_plate])), z, merged, lam, 0, 0.0)
        labels = _set_keys(merged, self.model.setup.formulation)
        return replace(step, answer=answer, dx=x[:n] - z, rows=cs, labels=labels, swing=swing)

    def _warm_keys(self, n_plate: int, rows: ContactSet | None) -> list[Any]:
        """The identity of each row of QP (13): plate and support rows by position (fixed within
        a position), contact rows by their label and its count so far (a plane's row names the
        pair, the plane and the vertex, so its count is 0; not ``_row_keys``, whose point moves
        with the scales: it matched 244 of 879 rows between the first two QPs of a slanted
        triangle array)."""
        plate = [("plate", i) for i in range(n_plate)]
        support = [("support", i) for i in range(len(self.model.support_idx))]
        seen: dict[str, int] = {}
        contact = []
        for label in rows.labels if rows is not None else ():
            contact.append((label, seen.get(label, 0)))
            seen[label] = seen.get(label, 0) + 1
        return plate + support + contact

    def _warm_start(self, qp: IncrementQP, keys: list[Any]) -> WarmStart | None:
        """The last answer carried to ``qp``'s rows: multipliers by row key (0 for a new row), the
        DOFs as they were and the planes' unknowns at 0 (their increments from the planes the last
        answer moved); None for the first QP."""
        if self.last is None:
            return None
        z_of, dofs = self.last
        z0 = np.array([z_of.get(k, 0.0) for k in keys])
        return WarmStart(np.r_[dofs, np.zeros(qp.n - len(dofs))], z0, np.zeros(0))

    def penetration(self, z: Array) -> float:
        return _exact_penetration(self.model, z, self.z_plate)

    def state(self, z: Array, answer: FlexureState, progress: Progress) -> FlexureState:
        return replace(answer, z=z, iterations=progress.iterations, penetration=progress.penetration)


def _membrane_qp(
    S: sp.csc_matrix,
    Gp: Array,
    hp: Array,
    Gs: sp.csr_matrix,
    hs: Array,
    Gc: sp.csr_matrix,
    hc: Array,
    plane_weight: Array | None = None,
) -> IncrementQP:
    """QP (13) over ``(z, theta)``: plate, support (``Gs z <= hs``) and contact rows; ``PLANE_PROX``
    on the planes, or the damped planes' weights ``plane_weight`` (increment.md sec. 4b)."""
    n = Gs.shape[1]
    extra = Gc.shape[1] - n
    w = np.full(extra, PLANE_PROX) if plane_weight is None else np.asarray(plane_weight, dtype=float)
    P = block_diagonal(S, sp.diags(w, format="csc")) if extra else S
    pad = sp.csr_matrix((Gp.shape[0] + Gs.shape[0], extra))
    G = sp.vstack([sp.hstack([sp.vstack([sp.csr_matrix(Gp), Gs]), pad]), Gc], format="csc")
    return IncrementQP(P, np.zeros(n + extra), G, np.r_[hp, hs, hc])


def solve_position(
    model: FlexureModel, z: Array, w: float, inc: int, previous: ContactSet | None
) -> LevelOutcome[FlexureState]:
    """The sequential QP at one plate position, eq. (13), by the level driver
    (:func:`qpscale.level.solve`): Anderson-accelerated while the rows are unchanged, the
    ``stall_tighten`` and ``qp_retry`` rescues recorded in the outcome (increment.md sec. 5).

    A position whose plain (undamped) iteration does not converge with separating planes is
    solved again from the same start with the planes' trust region (``increment.PlaneDamping``
    weighted by ``FLEXURE_DAMPING``; membrane.md sec. 8, the hinged planes of the slanted triangle
    arrays), the ``other_plane_update`` rescue of puncture; a converged state is a fixed point of
    both updates.  A QP the backend failed is not retried (no trust region cures it).  Failing
    both ways, the first attempt's failure is reported.
    """
    first = level.solve(_FlexureLevel(model, w, inc), z, previous)
    if (
        first.status is not LevelStatus.NOT_CONVERGED
        or model.setup.formulation != "plane"
        or model.patch is None
    ):
        return first
    second = level.solve(_FlexureLevel(model, w, inc, damped=True), z, previous)
    if not second.converged:
        return replace(first, rescues=first.rescues + second.rescues)
    fired = Rescue("other_plane_update", w, inc, "damped")
    return replace(second, rescues=first.rescues + (fired,) + second.rescues)


#: Order of the companion estimate (membrane.md sec. 9c): the gap's corners, where a bonded footprint
#: meets the free surface, carry stresses ~ r^(-1/2) (incompressible membrane), so the energy error of
#: a mesh refined by 2 there falls by 2^(2 x 1/2); measured 0.7-0.9 on the square array.
ERROR_ORDER = 1.0


def refined(setup: FlexureSetup) -> FlexureSetup:
    """The companion mesh of the error estimate (membrane.md sec. 9c): twice the layers, twice the
    elements across each gap (and half an explicit top layer), half the size at the rollers; on
    the fitted mesh also half the size along the gaps (sec. 9e)."""
    mem = setup.membrane
    top = None if mem.top_h is None else mem.top_h / 2
    n = None if setup.gap_elements is None else 2 * setup.gap_elements
    mem = replace(mem, nz=2 * mem.nz, top_h=top)
    along = setup.along / 2 if setup.mesh == "fitted" else setup.along
    return replace(setup, membrane=mem, gap_elements=n, contact_h=setup.contact_h / 2, along=along)


def compliance_error(coarse: float, fine: float, order: float = ERROR_ORDER) -> tuple[float, float]:
    """Error estimate of ``coarse`` and the extrapolated C_f* from a mesh and its ``refined`` companion.

    Two-level Richardson with a known order p: the limit is ``fine + (fine - coarse) / (2^p - 1)``
    and the estimate of ``|coarse - limit|`` is ``|fine - coarse| 2^p / (2^p - 1)``.

    >>> compliance_error(0.9, 1.0)
    (0.2, 1.1)
    """
    d = fine - coarse
    r = 2.0**order - 1.0
    return round(abs(d) * (r + 1.0) / r, 15), round(fine + d / r, 15)


def run_flexure(setup: FlexureSetup, mesh: MembraneMesh | None = None) -> FlexureResult:
    """The force-deflection curve of three-point bending and C_f* (formulations/membrane.md eq. (14)).

    ``mesh`` replaces the mesh of section 2 (``build_model``).  Rollers: if a bottom node outside
    ``roller_zone`` ends up inside a roller, the zone is doubled and the curve run again
    (membrane.md sec. 7).
    """
    t0 = time.perf_counter()
    while True:
        result = run_model(build_model(setup, mesh), t0)
        over = roller_penetration(result.extras["model"], result.extras["states"])
        if over <= PENETRATION_TOL or setup.roller_zone >= setup.roller_radius:
            return replace(result, max_penetration=max(result.max_penetration, over))
        setup = replace(setup, roller_zone=min(2.0 * setup.roller_zone, setup.roller_radius))


def run_model(model: FlexureModel, t0: float | None = None) -> FlexureResult:
    """The curve of a built model (``t0``: when the wall clock of ``FlexureResult`` started).

    At each plate position the sequential QP is solved with the support DOFs that are still held
    closed; if a held DOF's reaction pulls, it is released into the QP as a unilateral row and
    the position is solved again (sec. 7), so the accepted state satisfies every support's
    complementarity.
    """
    t0 = time.perf_counter() if t0 is None else t0
    setup = model.setup
    z = np.zeros(len(model.cond.retained))
    n_rows0 = len(model.support_idx)
    ws = np.linspace(0.0, setup.max_deflection, setup.increments + 1)
    states: list[FlexureState] = []
    cs = None
    rescues: list[Rescue] = []
    for inc, w in enumerate(ws[1:], start=1):
        its = 0
        for _ in range(MAX_RELEASE_ROUNDS):
            outcome = solve_position(model, z, float(w), inc, cs)
            rescues.extend(outcome.rescues)
            state = outcome.unwrap()  # a position that fails ends the curve with its failure
            its += state.iterations
            model, z, released = _release_tensile(model, state.z)
            cs = state.contacts
            if not released:
                break
        else:
            raise SolverFailure(setup.solver, "support release did not settle", increment=inc)
        states.append(replace(state, iterations=its))
    m = len(model.cond.retained)  # earlier states held the later-released DOFs at 0
    states = [replace(st, z=np.r_[st.z, np.zeros(m - len(st.z))]) for st in states]
    F = np.r_[0.0, [s.force for s in states]]
    iters = sum(s.iterations for s in states)
    pen = max(s.penetration for s in states)
    if not F[-1] > 0:
        raise SolverFailure(setup.solver, "no plate force", detail=f"F={F[-1]:.3g}")
    C_f = float(ws[-1] / F[-1])
    mem = setup.membrane
    I_m = (mem.length if setup.axis == 1 else mem.width) * mem.height**3 / 12.0
    n_scales = 0 if model.patch is None else model.patch.n_scales
    wall = time.perf_counter() - t0
    Cf_star = compliance_star(C_f, mem.E, I_m, 1.0)
    return FlexureResult(
        ws,
        F,
        C_f,
        Cf_star,
        n_scales,
        len(model.cond.retained),
        iters,
        pen,
        wall,
        model.condense_s,
        z,
        {"model": model, "states": states, "released": len(model.support_idx) - n_rows0, "rescues": rescues},
    )
