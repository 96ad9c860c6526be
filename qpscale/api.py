"""The Python API for notebooks and scripts: ``geometry``, ``substrate``, ``puncture``, ``flexure``.

Each entry point takes the same parameters as the ``qpscale`` subcommand of the same name (docs/
cli.md), checks them all through :mod:`qpscale.validation` before any work (the command line calls
these functions, so there is one path and one set of ranges), and returns a frozen result whose
``to_dict()`` is exactly the JSON object ``qpscale <command> --json`` prints and whose
``curve_frame()`` is the force curve as a pandas DataFrame.  Units and normalisations are those of
docs/units.md: lengths in L, forces F* = F (1 - nu_s^2) / (E_s L^2), compliance C_f* = C_f E_m I_m / L^3.

The numerics live in :mod:`qpscale.experiments` (called through ``run_puncture`` and
``run_flexure`` only) and :mod:`qpscale.substrate`; they are imported when a function runs, so that
``import qpscale`` stays light.

>>> from qpscale.api import geometry
>>> geometry(shape="hexagon").to_dict()["n_scales"]
19
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from . import validation as v
from .errors import InvalidDesign, OutputNotWritten, SolverFailure
from .solvers import DEFAULT_SOLVER

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

    from .tiling import Design

__all__ = [
    "FlexureReport",
    "GeometryReport",
    "PunctureReport",
    "SubstrateReport",
    "flexure",
    "geometry",
    "puncture",
    "substrate",
]

DEFAULT_RINGS = 2
# Formats matplotlib writes without extra packages ("" is drawn as PNG).
DRAWING_SUFFIXES = ("", ".png", ".svg", ".pdf")
DEFAULT_L_MM = 2.0
# --condense: the screened, condensed QP (formulations/increment.md sec. 2c) from 49 scales, always, never.
CONDENSE: dict[str, bool | None] = {"auto": None, "on": True, "off": False}
DOF_KEYS = ("Kx", "Ky", "Kz", "Kphix", "Kphiy")
DESIGN_DEFAULTS: dict[str, Any] = {
    "shape": "square",
    "tiling": None,
    "slant_deg": 0.0,
    "slant_dir_deg": 0.0,
    "gap": 0.005,
    "thickness": 1.0,
}


def plain(value: Any) -> Any:
    """``value`` as JSON-ready data: records through their ``to_dict()``, arrays as lists, and a
    non-finite float as None (the JSON contract has no NaN: a missing number is null)."""
    import numpy as np

    if hasattr(value, "to_dict") and not isinstance(value, type):
        return plain(value.to_dict())
    if isinstance(value, Mapping):
        return {str(k): plain(x) for k, x in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(x) for x in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        x = float(value)
        return x if math.isfinite(x) else None
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "__dataclass_fields__"):
        from dataclasses import asdict

        return plain(asdict(value))
    return value


@dataclass(frozen=True)
class _Report:
    """Common part of the results: the JSON payload and the optional outputs' failures."""

    payload: Mapping[str, Any] = field(repr=False)
    output_errors: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        # Read-only view: a frozen result whose fields could still be edited in place is not frozen.
        object.__setattr__(self, "payload", MappingProxyType(dict(self.payload)))

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of the command line (a fresh copy: field names per docs/cli.md)."""
        return plain(self.payload)

    def __getitem__(self, key: str) -> Any:
        return self.payload[key]


@dataclass(frozen=True)
class GeometryReport(_Report):
    """A design's patch checked: ``base_area`` (L^2), ``n_scales``, ``min_gap`` (L, None for one
    scale), ``max_overlap_area`` (L^2, zero for a valid tiling), ``top_offset`` ([dx, dy], L)."""

    design: Design | None = field(default=None, repr=True)


@dataclass(frozen=True)
class SubstrateReport(_Report):
    """Normalised stiffness K* = K (1 - nu_s^2) / (E_s L) (translations) and K_phi* = K_phi (1 -
    nu_s^2) / (E_s L^3) (rotations) of the isolated punch, the self block K0 and the coupling blocks
    K1 to the neighbours (``to_dict()["neighbours"]``)."""

    def coupling_frame(self) -> pd.DataFrame:
        """One row per neighbour: offset (L), ratio |K1|/K0 and the diagonal of K1."""
        import pandas as pd

        rows = [
            {"dx": n["offset"][0], "dy": n["offset"][1], "ratio": n["ratio"], **n["K1"]}
            for n in self.payload.get("neighbours", [])
        ]
        return pd.DataFrame(rows, columns=["dx", "dy", "ratio", *DOF_KEYS])


@dataclass(frozen=True)
class PunctureReport(_Report):
    """A puncture path to the failure tilt: ``Fc_star`` (F_c*), ``delta_c_star``, ``load_point``
    (L, relative to the scale's reference point), ``tilt_deg``, the curve and the diagnostics.

    ``result`` is the full :class:`qpscale.experiments.puncture.PunctureResult` (states, contact
    forces) for plotting and export.
    """

    result: Any = field(default=None, repr=False, compare=False)

    @property
    def Fc_star(self) -> float:
        return float(self.payload["Fc_star"])

    def curve_frame(self) -> pd.DataFrame:
        """Columns ``w_star`` (puncture depth / L), ``F_star`` and ``tilt_deg``, one row per state."""
        import pandas as pd

        return pd.DataFrame(self.payload["curve"])


@dataclass(frozen=True)
class FlexureReport(_Report):
    """Three-point bending: ``Cf_star`` (C_f E_m I_m / L^3) and the force-deflection curve."""

    result: Any = field(default=None, repr=False, compare=False)

    @property
    def Cf_star(self) -> float:
        return float(self.payload["Cf_star"])

    def curve_frame(self) -> pd.DataFrame:
        """Columns ``deflection_star`` (plate displacement / L) and ``F_star`` (force / (E_m L^2))."""
        import pandas as pd

        return pd.DataFrame(self.payload["curve"])


def _design(values: Mapping[str, Any], rings: int) -> Design:
    from .tiling import Design

    return Design(**values, rings=rings)


def _write_optional(what: str, writer: Callable[[], Any], errors: list[str]) -> str | None:
    """Run an optional output's writer; a failure (disk full, permissions; a state whose reported
    contact forces could not be computed, with the solver's status) is recorded, not raised, so
    that the computed result is never lost for a file that could not be written."""
    try:
        return str(writer())
    except (OSError, SolverFailure) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        message = f"{what}: could not write: {reason}"
        errors.append(message)
        warnings.warn(message, OutputNotWritten, stacklevel=3)
        return None


def geometry(
    shape: str = "square",
    tiling: str | None = None,
    slant_deg: float = 0.0,
    slant_dir_deg: float = 0.0,
    gap: float = 0.005,
    thickness: float = 1.0,
    rings: int = DEFAULT_RINGS,
    png: str | Path | None = None,
) -> GeometryReport:
    """Build a design's patch and check it.

    Parameters
    ----------
    shape : str
        ``triangle, square, trapezoid, dart, hexagon`` (equal base areas, 4 L^2).
    tiling : str or None
        ``arrayed`` or ``staggered`` (triangle, square, trapezoid); None: the shape's first tiling.
    slant_deg : float
        Slant angle alpha from the vertical, degrees, [0, 90) with t tan(alpha) <= 10 L.
    slant_dir_deg : float
        Slant direction, degrees from +x, [0, 360).
    gap : float
        Gap d between neighbouring bases, in L, [0, 1).
    thickness : float
        Scale thickness t, in L, (0, 100].
    rings : int
        Rings of neighbours around the centre scale, [0, 50] (2: the paper's 5x5).
    png : path or None
        Draw the patch from above to this file (its directory is created).

    Returns
    -------
    GeometryReport

    Raises
    ------
    InvalidDesign
        A parameter outside its range, or a shape/tiling pair that is not a design.
    """
    values = v.design_values(shape, tiling, slant_deg, slant_dir_deg, gap, thickness)
    n_rings = v.integer("rings", rings, 0, v.MAX_RINGS)
    png_path = v.output_file("png", png) if png is not None else None
    if png_path is not None and png_path.suffix.lower() not in DRAWING_SUFFIXES:
        raise InvalidDesign("png", str(png_path), "a file ending in " + ", ".join(DRAWING_SUFFIXES[1:]))
    design = _design(values, n_rings)
    from .tiling import max_overlap_area, min_gap

    patch = design.patch()
    areas = [p.area for p in patch.polygons()]
    payload: dict[str, Any] = {
        "shape": design.shape,
        "tiling": design.tiling,
        "base_area": float(areas[0]),
        "base_area_spread": float(max(areas) - min(areas)),
        "n_scales": patch.n_scales,
        "n_neighbour_pairs": int(len(patch.neighbours)),
        "n_contact_pairs": int(len(patch.contact_pairs)),
        "min_gap": min_gap(patch) if patch.n_scales > 1 else None,
        "max_overlap_area": max_overlap_area(patch),
        "top_offset": [float(x) for x in design.top_offset],
        "volume": patch.prism(0).volume,
    }
    errors: list[str] = []
    if png_path is not None:

        def draw() -> Path:
            from .plotting import draw_patch

            return draw_patch(patch, png_path)

        written = _write_optional("png", draw, errors)
        if written is not None:
            payload["png"] = written
    return GeometryReport(payload, tuple(errors), design)


def substrate(
    shape: str = "square",
    tiling: str | None = None,
    gap: float | None = None,
    nu: float = 0.5,
    isolated: bool = False,
    refinement: int = 6,
) -> SubstrateReport:
    """Normalised substrate stiffness of a design: isolated punch, self block K0, couplings K1.

    Parameters
    ----------
    shape, tiling : str
        The design (see :func:`geometry`).
    gap : float or None
        Gap d in L, [0, 1) (default 0.005).  Not with ``isolated`` (one punch has no gap).
    nu : float
        Poisson's ratio nu_s of the half-space, [0, 0.5].
    isolated : bool
        Only the isolated single-punch stiffness (fast; no multi-punch calibration).
    refinement : int
        Panel strips per fan triangle of the boundary-element model, [2, 16].

    Returns
    -------
    SubstrateReport
        Diagonals as ``{"Kx", "Ky", "Kz", "Kphix", "Kphiy"}`` and the full 5x5 blocks.
    """
    if isolated and gap is not None:
        raise v.conflict("isolated", "gap", "one punch alone has no gap")
    if isolated and tiling is not None:
        raise v.conflict("isolated", "tiling", "one punch alone has no tiling")
    values = v.design_values(shape, tiling, 0.0, 0.0, 0.005 if gap is None else gap, 1.0)
    nu_s = v.real("nu", nu, 0.0, 0.5)
    n_ref = v.integer("refinement", refinement, 2, 16)
    design = _design(values, DEFAULT_RINGS)
    from .substrate import SubstrateModel, calibrate, coupling_ratio, isolated_block

    def diag(K: Any) -> dict[str, float]:
        return {k: float(x) for k, x in zip(DOF_KEYS, K.diagonal())}

    if isolated:
        K_iso = isolated_block(design.shape, nu_s, n_ref)
        payload: dict[str, Any] = {"isolated": diag(K_iso), "isolated_block": K_iso.tolist()}
    else:
        cal = calibrate(design, SubstrateModel(nu=nu_s, refinement=n_ref))
        near = [c for c in cal.couplings if c.source == 0]
        payload = {
            "isolated": diag(cal.K_iso),
            "K0": diag(cal.K0[0]),
            "K0_block": cal.K0[0].tolist(),
            "neighbours": [
                {
                    "offset": list(c.offset),
                    "site": [*c.site, c.receiver],
                    "K1": diag(c.K1),
                    "K1_block": c.K1.tolist(),
                    "ratio": coupling_ratio(c.K1, cal.K0[0]),
                }
                for c in near
            ],
            "asymmetry": cal.asymmetry,
            "n_panels": cal.n_panels,
        }
    payload.update(
        {"shape": design.shape, "tiling": design.tiling, "gap": None if isolated else design.gap, "nu": nu_s}
    )
    return SubstrateReport(payload)


def check_load_point(design: Design, load_point: object) -> tuple[float, float]:
    """``load_point`` as (x, y) on the centre scale's top face (relative to its reference point)."""
    from shapely.geometry import Point, Polygon

    from .experiments.puncture import top_vertices

    if not isinstance(load_point, (tuple, list)) or len(load_point) != 2:
        raise InvalidDesign("load_point", load_point, "two numbers x y, in L")
    xy = tuple(v.real("load_point", c, None, None, unit="L") for c in load_point)
    top = top_vertices(design.isolated().patch())
    face = Polygon(top)
    if not face.buffer(1e-9).covers(Point(xy)):
        lo, hi = top.min(axis=0), top.max(axis=0)
        raise InvalidDesign(
            "load_point",
            list(xy),
            "the top face of the centre scale",
            f"the point is off the scale (its top face spans x in [{lo[0]:.4g}, {hi[0]:.4g}], "
            f"y in [{lo[1]:.4g}, {hi[1]:.4g}] L about the reference point)",
        )
    return (float(xy[0]), float(xy[1]))


def puncture(
    shape: str = "square",
    tiling: str | None = None,
    slant_deg: float = 0.0,
    slant_dir_deg: float = 0.0,
    gap: float = 0.005,
    thickness: float = 1.0,
    rings: int | str | None = None,
    isolated: bool = False,
    interaction: str = "full",
    coupling_factor: float | None = None,
    solver: str = DEFAULT_SOLVER,
    formulation: str = "plane",
    accuracy: str | float | None = None,
    phi_c_deg: float = 13.0,
    nu: float = 0.5,
    load_point: tuple[float, float] | None = None,
    probe: bool = True,
    E_s: float | None = None,
    L_mm: float | None = None,
    vtk: str | Path | None = None,
    max_memory_gb: float | None = None,
    max_minutes: float | None = None,
    progress: Callable[[str], None] | None = None,
    rings_tol: float | None = None,
    max_increments: int = v.DEFAULT_MAX_INCREMENTS,
    edges: str = "clamped",
    condense: str = "auto",
) -> PunctureReport:
    """Puncture: push a top-face point of the centre scale down until its tilt reaches phi_c.

    Parameters
    ----------
    shape, tiling, slant_deg, slant_dir_deg, gap, thickness
        The design (see :func:`geometry`).
    rings : int, "auto" or None
        Rings of neighbours, [0, 50] within the memory limit (default 2: 5x5). Not with ``isolated``.
        ``"auto"`` grows the patch from 1 ring until F_c* changes by at most ``rings_tol``
        (formulations/substrate.md sec. 10); the report is the last patch's, with the sequence
        and, where the sequence has the form F_inf - a n^-p, the extrapolated F_inf and its error
        under ``"rings_auto"``.
    isolated : bool
        The punctured scale alone (rings = 0).
    interaction : {"full", "substrate", "contact"}
        Substrate coupling and contact; contact off; or coupling scaled by ``coupling_factor``.
    coupling_factor : float or None
        f in [0, 1] for ``substrate`` and ``contact`` (default 1, and 0.04 for ``contact``);
        ``full`` means f = 1.
    solver : str
        An installed QP backend (``qpscale.solvers.available_solvers()``) or ``penalty``.
    formulation : {"plane", "feature"}
        Scale-scale contact rows (formulations/contact.md): separating planes (the default, every
        backend but ``osqp``) or the feature rows of the best separating axis.
    accuracy : {"high", "mid", "low"} or float or None
        QP tolerance (1e-9, 1e-6, 1e-3, or a number in [1e-12, 1e-2]); default high.  Not with
        ``penalty``.
    phi_c_deg : float
        Critical tilt, degrees, (0, 60].
    nu : float
        Poisson's ratio nu_s of the substrate, [0, 0.5].
    load_point : (float, float) or None
        x, y of the load point on the top face relative to the reference point, in L; None: the
        worst top-face vertex.
    probe : bool
        Test every state by the second variation and follow branches.
    E_s : float or None
        Substrate modulus in Pa, (0, 1e12], to add ``Fc_N`` (F_c in newtons).
    L_mm : float or None
        L in millimetres, (0, 1e6] (default 2), with ``E_s`` only.
    vtk : path or None
        Directory for a ParaView series (.pvd + one .vtu per state); created before the run.  Its
        contact forces are the least-norm member of each state's multiplier set
        (``experiments.puncture.reported_forces``).
    max_memory_gb : float or None
        Refuse a scene whose estimated memory exceeds this (default ``$QPSCALE_MAX_MEMORY_GB`` or 4).
    max_minutes : float or None
        Refuse a scene whose estimated time exceeds this (default ``$QPSCALE_MAX_MINUTES`` or 60).
    progress : callable or None
        Called with a short message as the path advances.
    rings_tol : float or None
        Relative tolerance of ``rings="auto"``, (0, 0.5] (default 0.005); only with ``"auto"``.
    max_increments : int
        Steps each load point's path may take before it gives up (``failure tilt not reached``),
        integers in [16, 100000] (default 400; the states that locate an event are not counted,
        formulations/puncture.md sec. 2).
    edges : {"clamped", "local"}
        Self stiffness of the scales on the patch's edge: ``clamped`` (the default: every scale
        has the self block K0 of a scale whose neighbours are all present and clamped, so the
        outer ring is a stiff frame; the paper's 5x5 comparison) or ``local`` (each scale's own
        neighbourhood: the 5x5 matches a boundary-element solve of the whole patch to 0.02 %,
        formulations/substrate.md sec. 9).
    condense : {"auto", "on", "off"}
        Solve each QP on the contact rows that can act and the DOFs they touch, the rest of the
        patch eliminated through its stiffness factored once (formulations/increment.md sec. 2c):
        the same answer, in QPs the size of the contact region.  ``auto`` (default): from 49
        scales (7x7) on; ``on`` / ``off`` for every patch.  Not with ``penalty``.

    Returns
    -------
    PunctureReport

    Raises
    ------
    InvalidDesign
        A parameter outside its range, two parameters that conflict, or a scene over the memory
        limit; raised before any work.
    SolverFailure
        The path failed; the solver's status is in the message (never turned into a number).
    """
    from .experiments.puncture import INTERACTIONS

    if isinstance(rings, str) and rings.strip().lower() == "auto" or rings_tol is not None:
        args = {k: val for k, val in locals().items() if k != "INTERACTIONS"}
        return _puncture_rings_auto(args)
    values = v.design_values(shape, tiling, slant_deg, slant_dir_deg, gap, thickness)
    if isolated and rings is not None:
        raise v.conflict("isolated", "rings", "--isolated means rings = 0")
    n_rings = 0 if isolated else v.integer("rings", DEFAULT_RINGS if rings is None else rings, 0, v.MAX_RINGS)
    mode = v.choice("interaction", interaction, tuple(INTERACTIONS))
    f = None if coupling_factor is None else v.real("coupling_factor", coupling_factor, 0.0, 1.0)
    if mode == "full" and f is not None and f != 1.0:
        raise v.conflict(
            "interaction", "coupling_factor", "full interaction is f = 1; use --interaction contact"
        )
    backend = v.solver(solver)
    from .contact import FORMULATIONS
    from .substrate import EDGES

    rows = v.choice("formulation", formulation, FORMULATIONS)
    edge_model = v.choice("edges", edges, EDGES)
    condensed = v.choice("condense", condense, tuple(CONDENSE))
    if backend == "penalty" and condensed != "auto":
        raise v.conflict("solver", "condense", "the penalty baseline solves no QP")
    if backend == "penalty" and accuracy is not None:
        raise v.conflict("solver", "accuracy", "the penalty baseline has no QP tolerance")
    tol = v.accuracy("high" if accuracy is None else accuracy)
    phi_c = v.real("phi_c_deg", phi_c_deg, 0.0, 60.0, lo_open=True, unit="deg")
    nu_s = v.real("nu", nu, 0.0, 0.5)
    budget = v.integer("max_increments", max_increments, *v.MAX_INCREMENTS_RANGE)
    if E_s is None and L_mm is not None:
        raise v.conflict("L_mm", "E_s", "L converts F_c to newtons only together with E_s")
    modulus = None if E_s is None else v.real("E_s", E_s, 0.0, 1e12, lo_open=True, unit="Pa")
    length_mm = v.real("L_mm", DEFAULT_L_MM if L_mm is None else L_mm, 0.0, 1e6, lo_open=True, unit="mm")
    vtk_dir = v.output_dir("vtk", vtk) if vtk is not None else None
    design = _design(values, n_rings)
    xy = None if load_point is None else check_load_point(design, load_point)
    patch = design.patch()
    v.memory(
        v.puncture_memory_gb(patch.n_scales, len(patch.contact_pairs)),
        v.max_memory_gb(max_memory_gb),
        "rings",
        n_rings,
        f"a patch of {patch.n_scales} scales",
    )
    v.duration(
        v.puncture_time_s(patch.n_scales, len(patch.contact_pairs), bool(probe)),
        v.max_minutes(max_minutes),
        "rings",
        n_rings,
        f"a patch of {patch.n_scales} scales",
    )

    from .contact import ContactSettings
    from .experiments.puncture import PunctureSetup, run_puncture
    from .increment import SQPSettings

    setup = PunctureSetup(
        design=design,
        interaction=mode,
        coupling=f,
        nu=nu_s,
        phi_c_deg=phi_c,
        load_point=xy,
        probe=bool(probe),
        sqp=SQPSettings(solver=backend, accuracy=tol, condense=CONDENSE[condensed]),
        contact=ContactSettings(formulation=rows),
        max_increments=budget,
        edges=edge_model,
    )
    result = run_puncture(setup, progress=progress)
    payload: dict[str, Any] = {
        "Fc_star": result.Fc_star,
        "delta_c_star": result.delta_c_star,
        "load_point": [float(x) for x in result.load_point],
        "tilt_deg": float(result.tilt_deg[-1]),
        "max_penetration": result.max_penetration,
        "increments": len(result.states) - 1,
        "solver": backend,
        "formulation": rows,
        "accuracy": tol if backend != "penalty" else None,
        "wall_s": result.wall_s,
        "qp_solves": result.qp_solves,
        "load_levels": result.load_levels,
        "n_scales": patch.n_scales,
        "shape": design.shape,
        "tiling": design.tiling,
        "interaction": mode,
        "coupling_factor": setup.coupling_factor,
        "edges": edge_model,
        "condense": condensed,
        "curve": {
            "w_star": result.w_star.tolist(),
            "F_star": result.F_star.tolist(),
            "tilt_deg": result.tilt_deg.tolist(),
        },
        "candidates": [c.to_dict() for c in result.candidates],
        "branch": result.branch.to_dict(),
        "events": [e.to_dict() for e in result.events],
        "Fc_check": result.Fc_check.to_dict() if result.Fc_check is not None else None,
    }
    if modulus is not None:
        from .units import force_from_star

        payload["Fc_N"] = force_from_star(result.Fc_star, modulus, nu_s, length_mm * 1e-3)
        payload["E_s"], payload["L_mm"] = modulus, length_mm
    errors: list[str] = []
    if vtk_dir is not None:

        def write() -> Path:
            from .export_vtk import write_puncture_series

            return write_puncture_series(result, vtk_dir)

        written = _write_optional("vtk", write, errors)
        if written is not None:
            payload["vtk"] = written
    return PunctureReport(payload, tuple(errors), result)


DEFAULT_RINGS_TOL = 0.005
# rings = auto starts from the 3x3 patch: the 1-ring patch is the smallest with every neighbour.
AUTO_FIRST_RINGS = 1


def _puncture_rings_auto(args: dict[str, Any]) -> PunctureReport:
    """``puncture(rings="auto")``: one run per patch size until F_c* settles (substrate.md sec. 10)."""
    from .patch_convergence import grow_patch

    rings, tol = args.pop("rings"), args.pop("rings_tol")
    if not (isinstance(rings, str) and rings.strip().lower() == "auto"):
        raise v.conflict("rings_tol", "rings", "--rings-tol applies to --rings auto only")
    if args.pop("isolated"):
        raise v.conflict("isolated", "rings", "--isolated means rings = 0")
    tol = v.real("rings_tol", DEFAULT_RINGS_TOL if tol is None else tol, 0.0, 0.5, lo_open=True)
    progress = args.pop("progress")
    if args.pop("vtk") is not None:
        raise v.conflict(
            "vtk", "rings", "one ParaView series per patch size is not written; give an integer --rings"
        )
    reports: dict[int, PunctureReport] = {}

    def run(n: int) -> float:
        done = ", ".join(f"{r}: {rep.Fc_star:.4f}" for r, rep in reports.items())
        tag = f"rings {n}" + (f" (F_c* by rings {done})" if done else "")
        if progress:
            progress(tag)
        step = (lambda msg: progress(f"{tag}: {msg}")) if progress else None
        reports[n] = puncture(rings=n, progress=step, **args)
        return reports[n].Fc_star

    def limit(n: int) -> str:
        try:  # the next patch's own memory and time checks, without running it
            patch = _design(v.design_values(*(args[k] for k in DESIGN_KEYS)), n).patch()
            size = f"a patch of {patch.n_scales} scales"
            pairs = len(patch.contact_pairs)
            v.memory(
                v.puncture_memory_gb(patch.n_scales, pairs),
                v.max_memory_gb(args["max_memory_gb"]),
                "rings",
                n,
                size,
            )
            v.duration(
                v.puncture_time_s(patch.n_scales, pairs, bool(args["probe"])),
                v.max_minutes(args["max_minutes"]),
                "rings",
                n,
                size,
            )
        except InvalidDesign as exc:
            return str(exc)
        return ""

    seq = grow_patch(run, tol, AUTO_FIRST_RINGS, v.MAX_RINGS, stop=limit)
    last = reports[seq.rings[-1]]
    ext = seq.extrapolation
    payload = dict(last.payload)
    payload["rings_auto"] = {
        "tol": tol,
        "converged": seq.converged,
        "stop_reason": seq.stop_reason,
        "sequence": [
            {
                "rings": r,
                "n_scales": reports[r].payload["n_scales"],
                "Fc_star": F,
                "change": c,
                "wall_s": w,
            }
            for r, F, c, w in zip(seq.rings, seq.values, seq.changes, seq.wall_s)
        ],
        "extrapolation": None
        if ext is None
        else {"Fc_star_inf": ext.F_inf, "error": ext.error, "a": ext.a, "p": ext.p, "points": ext.points},
        "no_extrapolation": seq.no_extrapolation or None,
    }
    return PunctureReport(payload, last.output_errors, last.result)


DESIGN_KEYS = ("shape", "tiling", "slant_deg", "slant_dir_deg", "gap", "thickness")


FLEXURE_DESIGN_FLAGS = ("shape", "tiling", "slant_deg", "slant_dir_deg", "gap", "thickness")


def flexure(
    shape: str | None = None,
    tiling: str | None = None,
    slant_deg: float | None = None,
    slant_dir_deg: float | None = None,
    gap: float | None = None,
    thickness: float | None = None,
    load_line: str = "x",
    isolated: bool = False,
    bare: bool = False,
    nu_m: float = 0.5,
    mesh_h: float = 0.5,
    solver: str = DEFAULT_SOLVER,
    formulation: str = "plane",
    roller_radius: float = 0.5,
    top_h: float | None = None,
    mesh: str = "tensor",
    error: bool = True,
    vtk: str | Path | None = None,
    max_memory_gb: float | None = None,
    max_minutes: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> FlexureReport:
    """Three-point bending of the membrane (10 L x 10 L x 1.5 L, span 8 L): bare, one scale, or
    covered with scales; the compliance C_f* and the force-deflection curve.

    Parameters
    ----------
    shape, tiling, slant_deg, slant_dir_deg, gap, thickness
        The design (see :func:`geometry`; None: its default).  Not with ``bare``.
    load_line : {"x", "y"}
        Direction of the loading plate.
    isolated, bare : bool
        One scale at the centre, or the membrane alone (at most one of them).
    nu_m : float
        Poisson's ratio of the membrane, [0, 0.5].
    mesh_h : float
        In-plane element size, in L, [0.05, 2] within the memory limit (layers: max(2, 1.5/h)).
    solver : str
        An installed QP backend (``qpscale.solvers.available_solvers()``).
    formulation : {"plane", "feature"}
        Scale-scale contact by separating planes or by clipped features.
    roller_radius : float
        Radius of the rigid support rollers under the membrane, in L, (0, 3.75) (their axes lie at
        +-4 L: the span of 8 L, formulations/membrane.md sec. 1).
    top_h : float or None
        Thickness of the top layer when the layers are graded towards the top face, in L,
        (0, 1.5 / layers]; None: the default (with scales, the top layer is d / 2, membrane.md
        sec. 9c; bare membrane: uniform layers).
    mesh : {"tensor", "fitted"}
        The tensor mesh, or the footprint-fitted mesh whose lines follow every gap, oblique ones
        too (scales only; gmsh, whose library needs the system's OpenGL and X11; formulations/membrane.md
        secs. 9d-9e).  Its memory and time are estimated from its node count once it is built.
    error : bool
        Estimate the discretisation error of C_f*: the curve is run again on the companion mesh
        (twice the layers and the elements across each gap, and on the fitted mesh half the size
        along the gaps; formulations/membrane.md secs. 9c, 9e) and ``Cf_star_error`` is the
        two-level Richardson estimate (about three times the run time).
    vtk : path or None
        Directory for a ParaView series; created before the run.
    max_memory_gb : float or None
        Refuse a mesh whose estimated memory exceeds this (default ``$QPSCALE_MAX_MEMORY_GB`` or 4).
    max_minutes : float or None
        Refuse a mesh whose estimated time exceeds this (default ``$QPSCALE_MAX_MINUTES`` or 60).
    progress : callable or None
        Called with a short message as each curve starts.

    Returns
    -------
    FlexureReport
    """
    if isolated and bare:
        raise v.conflict("isolated", "bare", "one scale, or the membrane alone: pick one")
    given = {
        k: x
        for k, x in zip(FLEXURE_DESIGN_FLAGS, (shape, tiling, slant_deg, slant_dir_deg, gap, thickness))
        if x is not None
    }
    if bare and given:
        first = next(iter(given))
        raise v.conflict("bare", first, "the bare membrane has no scales to design")
    values = v.design_values(**{**DESIGN_DEFAULTS, **given})
    line = v.choice("load_line", load_line, ("x", "y"))
    nu = v.real("nu_m", nu_m, 0.0, 0.5)
    h = v.real("mesh_h", mesh_h, v.MESH_H_RANGE[0], v.MESH_H_RANGE[1], unit="L")
    backend = v.qp_solver(solver)
    form = v.choice("formulation", formulation, ("plane", "feature"))
    radius = v.real("roller_radius", roller_radius, 0.0, 3.75, lo_open=True, hi_open=True, unit="L")
    vtk_dir = v.output_dir("vtk", vtk) if vtk is not None else None
    nz = max(2, int(round(1.5 / h)))
    top = None if top_h is None else v.real("top_h", top_h, 0.0, 1.5 / nz, lo_open=True, unit="L")
    kind = v.choice("mesh", mesh, ("tensor", "fitted"))
    if kind == "fitted" and bare:
        raise v.conflict("mesh", "bare", "the fitted mesh follows the scales' gaps: use the tensor mesh")
    check = 2 * nz if error else nz  # the companion mesh of the error estimate has twice the layers
    limit_gb, limit_min = v.max_memory_gb(max_memory_gb), v.max_minutes(max_minutes)
    if kind == "tensor":
        v.memory(v.flexure_memory_gb(h, check), limit_gb, "mesh_h", h, "the membrane mesh")
        v.duration(v.flexure_time_s(h, check), limit_min, "mesh_h", h, "the membrane mesh")
    design = _design(values, DEFAULT_RINGS)
    mode = "bare" if bare else "isolated" if isolated else "scaled"

    from .experiments.flexure import (
        FlexureSetup,
        compliance_error,
        kept_scales,
        oblique_edges,
        refined,
        run_flexure,
    )
    from .membrane import MembraneModel

    setup = FlexureSetup(
        design=design,
        mode=mode,
        load_line=line,
        membrane=MembraneModel(nu=nu, h=h, nz=nz, top_h=top),
        solver=backend,
        formulation=form,
        roller_radius=radius,
        mesh=kind,
    )
    built = None
    if kind == "fitted":
        from .fitted_mesh import fitted_mesh

        if progress:
            progress("fitted mesh")
        built = fitted_mesh(setup, kept_scales(setup), along=setup.along)
        nodes = built.nodes.shape[0]
        v.memory(v.fitted_memory_gb(nodes, error), limit_gb, "mesh", kind, "the fitted membrane mesh")
        v.duration(v.fitted_time_s(nodes, error), limit_min, "mesh", kind, "the fitted membrane mesh")
    if progress:
        progress("curve")
    result = run_flexure(setup, built)
    if progress and error:
        progress("companion mesh (error estimate)")
    fine = run_flexure(refined(setup)) if error else None
    err = compliance_error(result.Cf_star, fine.Cf_star)[0] if fine is not None else None
    payload: dict[str, Any] = {
        "Cf_star": result.Cf_star,
        "Cf_star_error": err,
        "Cf_star_refined": None if fine is None else fine.Cf_star,
        "curve": {"deflection_star": result.deflection.tolist(), "F_star": result.force.tolist()},
        "wall_s": result.wall_s + (0.0 if fine is None else fine.wall_s),
        "mode": mode,
        "mesh": kind,
        "oblique_edges": False if bare else oblique_edges(design),
        "shape": None if bare else design.shape,
        "tiling": None if bare else design.tiling,
        "load_line": line,
        "n_scales": result.n_scales,
        "n_retained": result.n_retained,
        "sqp_iterations": result.sqp_iterations,
        "max_penetration": result.max_penetration,
        "released_supports": result.extras.get("released"),
        "formulation": setup.formulation,
        "roller_radius": setup.roller_radius,
        "top_h": top,
        "gap_elements": setup.gap_elements if mode != "bare" else None,
        "mesh_h": h,
        "nz": nz,
    }
    errors: list[str] = []
    if vtk_dir is not None:

        def write() -> Path:
            from .export_vtk_flexure import write_flexure_series

            return write_flexure_series(result, vtk_dir)

        written = _write_optional("vtk", write, errors)
        if written is not None:
            payload["vtk"] = written
    return FlexureReport(payload, tuple(errors), result)
