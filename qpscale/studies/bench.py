"""The solver and formulation benchmark of ``qpscale bench`` (runs and metrics).

Implements formulations/penalty.md sec. 7 (the benchmark protocol): every method runs the same
puncture path of every scene, at the load point the reference run chose; a run succeeds only if
its solver says so and its answer passes our checks; metrics are computed from the runs in the
manner of qpbenchmark (success rate, shifted geometric mean and median of wall time with
failures at the time limit, F_c error, penetration, complementarity, solves).  Charts and CSV
are in :mod:`qpscale.studies.bench_report`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..contact import ContactSettings
from ..errors import InvalidDesign, QpscaleError
from ..experiments.puncture import PunctureSetup, run_puncture
from ..increment import SQPSettings
from ..penalty import PenaltySettings
from ..qp import resolve_tolerance
from ..solvers import DEFAULT_SOLVER, available_solvers, is_available
from ..tiling import Design
from ..timelimit import TimeLimitReached
from ..timelimit import time_limit as wall_limit
from .engine import Engine, map_tasks

FC_TOL = 1e-2  # F_c relative error above 1 % is a failure (issue #6 stability map)
PEN_TOL = 1e-9  # exact-contact methods must not overlap more than this (L)
SHIFT_S = 10.0  # shift of the shifted geometric mean, seconds (qpbenchmark)
# The reference (every symmetry-distinct vertex, tight tolerance) may take this many time limits.
REFERENCE_LIMIT_FACTOR = 10.0
QP_EXTRA = ("piqp", "daqp", "proxqp", "quadprog", "highs", "osqp", "clarabel", "cvxopt")


@dataclass(frozen=True)
class Method:
    """One method setting: a QP backend at an accuracy, or the penalty baseline at a k_pen.

    Parameters
    ----------
    name : str
        Label in tables and charts.
    solver : str
        Backend key or ``"penalty"``.
    accuracy : str or float
        QP tolerance (``high`` 1e-9, ``mid`` 1e-6, ``low`` 1e-3).
    penalty : PenaltySettings or None
        Penalty settings (``solver == "penalty"``).
    options : dict or None
        Backend option overrides (e.g. OSQP ``{"polishing": False}``).
    increments : int
        Target increments of the path.
    formulation : str
        Contact formulation of the exact-contact methods: ``plane`` (the default) or ``feature``
        (OSQP, which cannot solve the plane formulation, runs on it and says so in its name).
    """

    name: str
    solver: str
    accuracy: str | float = "high"
    penalty: PenaltySettings | None = None
    options: dict | None = None
    increments: int = 16
    formulation: str = "plane"

    def __post_init__(self) -> None:
        if self.solver != "penalty" and not is_available(self.solver):
            raise InvalidDesign("solver", self.solver, "an installed backend or 'penalty'")

    @property
    def exact_contact(self) -> bool:
        return self.solver != "penalty"

    @property
    def penetration_tol(self) -> float:
        """Largest overlap a successful exact-contact run may leave: 1e-9 L at the high accuracy,
        the QP tolerance at a looser one (its rows hold to that, no better: qpbenchmark judges each
        accuracy setting by its own tolerance)."""
        return max(PEN_TOL, resolve_tolerance(self.accuracy))


@dataclass(frozen=True)
class Scene:
    """A bench scene: a design and its interaction; the load point comes from the reference
    (the worst top-face vertex) unless ``load_point`` gives it."""

    name: str
    design: Design
    interaction: str = "full"
    coupling: float | None = None
    load_point: tuple[float, float] | None = None


@dataclass
class Run:
    """One method on one scene: status, checks and metrics (None where not defined)."""

    method: str
    scene: str
    status: str
    success: bool
    wall_s: float
    Fc_star: float | None = None
    Fc_rel_error: float | None = None
    max_penetration: float | None = None
    complementarity: float | None = None
    qp_solves: int | None = None
    failure: str = ""
    detail: str = ""  # the error message of a failed run (the residuals a rejected answer missed by)


@dataclass
class Reference:
    """The tightest converged QP solution of a scene (the default backend, high accuracy)."""

    scene: str
    Fc_star: float
    load_point: tuple[float, float] | None  # None: the worst vertex is searched
    wall_s: float


# The 3x3 dart at alpha0 = 60 deg: its worst top-face vertex (F_c* 3.9455 against 4.93-11.35 at
# the other five; the full bench's scene "dart3_a60_search" finds it again).
DART3_WORST = (float(np.sqrt(3.0)), 1.5)


def quick_scenes() -> list[Scene]:
    """5x5 square array at alpha = 0 and the isolated dart at alpha0 = 60 deg: the two-minute
    budget of the quick bench.  The dart arrays are too slow for it: one curve of the 3x3 dart at
    its worst vertex took 5-37 s per backend (CVXPY over 60 s) and the 5x5 dart's ~40 s."""
    dart_iso = Design(shape="dart", slant_deg=60.0, rings=0)
    return [Scene("square_a0", Design()), Scene("dart_iso_a60", dart_iso)]


def full_scenes() -> list[Scene]:
    """The quick scenes, the 3x3 dart (worst vertex given, and searched), the 5x5 dart at alpha0 =
    60 deg (its reference searches the six vertices: ~3 min), square alpha45 = 60 deg, the hexagon
    and a d = 0 square (issues #5, #6)."""
    dart3 = Design(shape="dart", slant_deg=60.0, rings=1)
    return quick_scenes() + [
        Scene("dart3_a60", dart3, load_point=DART3_WORST),
        Scene("dart3_a60_search", dart3),
        Scene("dart_a60", Design(shape="dart", slant_deg=60.0)),
        Scene("square_a45_60", Design(slant_deg=60.0, slant_dir_deg=45.0)),
        Scene("hexagon", Design(shape="hexagon")),
        Scene("square_d0", Design(gap=0.0)),
    ]


def default_methods(quick: bool = True) -> list[Method]:
    """Method settings: direct backends, the same solvers through qpsolvers and CVXPY, penalty."""
    have = set(available_solvers())
    # OSQP at 1e-9 took over 40 s on one 5x5 square curve (measured, ADMM at eps 1e-10), OSQP at 1e-6
    # 33 s and the penalty path 27 s: the quick bench (2-minute budget) keeps the direct Clarabel
    # and PIQP paths, the same solvers through qpsolvers and CVXPY (wrapper overhead); the rest is full.
    out = [Method("clarabel", "clarabel"), Method("piqp", "piqp"), Method("cvxpy", "cvxpy")]
    extra = _qpsolvers_wanted(quick)
    out += [Method(f"qpsolvers:{n}", f"qpsolvers:{n}") for n in extra if f"qpsolvers:{n}" in have]
    if not quick:
        # the package's own exact method (formulations/increment-qp.md sec. 3.5): 10x PIQP's time
        # on the default curve, so not in the quick bench's budget
        out += [Method("active-set", "active-set")]
        out += [Method("osqp-feature-mid", "osqp", "mid", formulation="feature")]
        out += [
            Method(f"penalty-k{k:.0e}", "penalty", penalty=PenaltySettings(k_pen=k))
            for k in (1e1, 1e2, 1e3, 1e4, 1e5)
        ]
        out += [
            Method("osqp-feature", "osqp", formulation="feature"),
            Method("clarabel-mid", "clarabel", "mid"),
            Method("clarabel-low", "clarabel", "low"),
            Method("osqp-feature-low", "osqp", "low", formulation="feature"),
            Method(
                "osqp-feature-nopolish-mid",
                "osqp",
                "mid",
                options={"polishing": False},
                formulation="feature",
            ),
            Method("penalty-k1e+03-n32", "penalty", penalty=PenaltySettings(k_pen=1e3), increments=32),
        ]
    return out


def _qpsolvers_wanted(quick: bool) -> tuple[str, ...]:
    return ("piqp", "clarabel") if quick else QP_EXTRA


def skipped_methods(quick: bool, fuzz: bool = False) -> list[str]:
    """Backends the bench would run that are not installed here: skipped, and listed as such in
    the bench's output (a plain install has no ProxQP, quadprog or HiGHS)."""
    have = set(available_solvers())
    wanted = [f"qpsolvers:{n}" for n in _qpsolvers_wanted(quick)]
    if fuzz:
        wanted.append("qpsolvers:piqp")
    return list(dict.fromkeys(w for w in wanted if w not in have))


@contextlib.contextmanager
def backend_overrides(options: dict | None) -> Iterator[None]:
    """Temporarily merge ``options`` into every backend's settings (SQPSettings has no such field)."""
    if not options:
        yield
        return
    from .. import qp

    original = qp.backend_options
    qp.backend_options = lambda solver, tol: {**original(solver, tol), **options}
    try:
        yield
    finally:
        qp.backend_options = original


def _setup(scene: Scene, method: Method, load_point: tuple[float, float] | None) -> PunctureSetup:
    """The puncture run of a method on a scene: the path a user gets (stability probe on), so a
    symmetric path branches where the second variation says, the same for every backend, instead of
    wherever one backend's round-off leaves it (formulations/penalty.md sec. 7)."""
    return PunctureSetup(
        design=scene.design,
        interaction=scene.interaction,
        coupling=scene.coupling,
        load_point=load_point,
        probe=True,
        increments=method.increments,
        sqp=SQPSettings(solver=method.solver, accuracy=method.accuracy),
        contact=ContactSettings(formulation=method.formulation),
        penalty=method.penalty,
    )


def reference_run(scene: Scene, limit_s: float | None = None) -> Reference:
    """The default backend at high accuracy over every symmetry-distinct vertex (or at the scene's own
    ``load_point``): F_c and the load point it belongs to.

    Raises :class:`TimeLimitReached` after ``limit_s`` seconds (None: no limit).
    """
    t0 = time.perf_counter()
    with wall_limit(limit_s):
        res = run_puncture(_setup(scene, Method("reference", DEFAULT_SOLVER), scene.load_point))
    xy = (float(res.load_point[0]), float(res.load_point[1]))
    return Reference(scene.name, float(res.Fc_star), xy, time.perf_counter() - t0)


def complementarity(res) -> float:
    """max_k lam_k |g_k| over the path's states (F* L): zero for exact contact."""
    worst = 0.0
    for st in res.states:
        if st.contacts is not None and len(st.lam):
            worst = max(worst, float(np.max(np.abs(st.lam * st.contacts.gap))))
    return worst


def run_method(scene: Scene, method: Method, ref: Reference | None, time_limit: float) -> Run:
    """Run one method on one scene and apply the checks; a failure keeps its status.

    A run is stopped at ``time_limit`` seconds and counted as a failure there.
    """
    t0 = time.perf_counter()
    try:
        with wall_limit(time_limit), backend_overrides(method.options):
            res = run_puncture(_setup(scene, method, ref.load_point if ref else scene.load_point))
    except TimeLimitReached as exc:
        return Run(method.name, scene.name, exc.status, False, time_limit, failure="time limit")
    except QpscaleError as exc:
        status = getattr(exc, "status", type(exc).__name__)
        wall = time.perf_counter() - t0
        return Run(method.name, scene.name, str(status), False, wall, failure="solver", detail=str(exc))
    wall = time.perf_counter() - t0
    run = Run(
        method.name,
        scene.name,
        "solved",
        True,
        wall,
        float(res.Fc_star),
        None,
        res.max_penetration,
        complementarity(res),
        res.qp_solves,
    )
    return _check(run, method, ref, time_limit)


def _check(run: Run, method: Method, ref: Reference | None, time_limit: float) -> Run:
    """Our checks on a solved run: finite output, F_c error, penetration, time limit."""
    if run.Fc_star is None or not np.isfinite(run.Fc_star):
        return replace(run, success=False, failure="non-finite")
    if ref is not None:
        run = replace(run, Fc_rel_error=abs(run.Fc_star - ref.Fc_star) / abs(ref.Fc_star))
    if run.Fc_rel_error is not None and run.Fc_rel_error > FC_TOL:
        return replace(run, success=False, failure="Fc error")
    if method.exact_contact and (run.max_penetration or 0.0) > method.penetration_tol:
        return replace(run, success=False, failure="penetration")
    if run.wall_s > time_limit:
        return replace(run, success=False, failure="time limit")
    return run


@dataclass
class BenchResult:
    """Every run, the references, and the per-method summary."""

    references: dict[str, Reference]
    runs: list[Run]
    time_limit: float
    summary: list[dict] = field(default_factory=list)
    extras: dict = field(default_factory=dict)


def _reference_or_failure(scene: Scene, limit_s: float) -> Reference | str:
    """The scene's reference, or the status that stopped it (a worker's return value)."""
    try:
        return reference_run(scene, limit_s)
    except (QpscaleError, TimeLimitReached) as exc:
        return str(getattr(exc, "status", exc))


def run_bench(
    scenes: list[Scene],
    methods: list[Method],
    time_limit: float = 60.0,
    progress: Callable[[str], None] | None = None,
    workers: int = 1,
    engine: Engine | None = None,
) -> BenchResult:
    """Reference per scene, then every method on every scene with a reference; summarised.

    The references, then the (scene, method) runs, are tasks of ``engine`` (None: one of
    ``workers`` processes, :mod:`qpscale.studies.engine`), one run per worker process at a time:
    with no more workers than cores each run's wall time is what it would be alone, so the ratios
    of one run stay comparable.
    """
    found = map_tasks(
        _reference_or_failure,
        [(s, REFERENCE_LIMIT_FACTOR * time_limit) for s in scenes],
        workers,
        engine,
        progress,
        lambda t: f"{t[0].name}: reference",
        "reference",
    )
    refs = {s.name: r for s, r in zip(scenes, found, strict=True) if isinstance(r, Reference)}
    tasks = [(s, m, refs[s.name], time_limit) for s in scenes if s.name in refs for m in methods]
    label = lambda t: f"{t[0].name}: {t[1].name}"  # noqa: E731
    done = map_tasks(run_method, tasks, workers, engine, progress, label, "run")
    by_key = {(r.scene, r.method): r for r in done}
    runs: list[Run] = []
    for s, r in zip(scenes, found, strict=True):
        for m in methods:
            if isinstance(r, Reference):
                runs.append(by_key[(s.name, m.name)])
            else:
                runs.append(
                    Run(m.name, s.name, f"no reference: {r}", False, time_limit, failure="no reference")
                )
    result = BenchResult(refs, runs, time_limit)
    result.summary = summarise(runs, [m.name for m in methods], time_limit)
    return result


def shifted_geomean(times: np.ndarray, shift: float = SHIFT_S) -> float:
    """exp(mean(log(t + shift))) - shift (qpbenchmark's shifted geometric mean), seconds."""
    return float(np.exp(np.mean(np.log(np.asarray(times) + shift))) - shift)


def summarise(runs: list[Run], names: list[str], time_limit: float) -> list[dict]:
    """Per method: success rate, shifted geomean / median wall time (failures at the time limit),
    worst F_c error, penetration and complementarity over its successes, solves, ratio to CVXPY."""
    by = {n: [r for r in runs if r.method == n] for n in names}
    timed = {n: np.array([r.wall_s if r.success else time_limit for r in rs]) for n, rs in by.items()}
    out = []
    for n, rs in by.items():
        ok = [r for r in rs if r.success]
        row = {
            "name": n,
            "runs": len(rs),
            "success_rate": len(ok) / len(rs) if rs else 0.0,
            "median_wall_s": float(np.median(timed[n])) if rs else None,
            "shifted_geomean_s": shifted_geomean(timed[n]) if rs else None,
            "Fc_rel_error": _worst([r.Fc_rel_error for r in ok]),
            "max_penetration": _worst([r.max_penetration for r in ok]),
            "complementarity": _worst([r.complementarity for r in ok]),
            "qp_solves": int(sum(r.qp_solves or 0 for r in rs)),
            "statuses": sorted({f"{r.scene}: {r.failure} ({r.status})" for r in rs if not r.success}),
        }
        row["time_ratio_to_cvxpy"] = _ratio(timed[n], timed.get("cvxpy"))
        out.append(row)
    return out


def _worst(values: list) -> float | None:
    vals = [v for v in values if v is not None]
    return float(max(vals)) if vals else None


def _ratio(t: np.ndarray, ref: np.ndarray | None) -> float | None:
    """Geometric mean over scenes of t_method / t_cvxpy (same run, failures at the time limit)."""
    if ref is None or len(ref) != len(t) or len(t) == 0:
        return None
    return float(np.exp(np.mean(np.log(t / ref))))


# --- Flexure: time against accuracy (formulations/membrane.md secs. 9, 9c) --------------------
# Self-contained: it calls the flexure refinement study, not the puncture scenes and methods above.

#: Cheap bare-membrane meshes of the quick bench (one plate position each, under 2 s together).
FLEXURE_QUICK_LEVELS = ((1.0, 2, 0.1), (0.5, 3, 0.05))


def flexure_section(quick: bool, out: Path | None = None) -> dict:
    """The flexure table of ``qpscale bench``: per mesh, C_f*, wall time and the relative error.

    Quick: the bare membrane (one plate position) on ``FLEXURE_QUICK_LEVELS`` against its stored
    converged value (``flexure_bench.BARE_LIMIT``).  Full: the bare membrane's refinement study
    recomputed (each direction refined twice) and its meshes against it, and the square staggered
    array along the companion ladder of the default mesh against the ladder's Richardson limit.
    Writes ``flexure_bench.csv`` into ``out``; returns the JSON payload's ``flexure`` entry.
    """
    import pandas as pd

    from ..experiments.flexure import FlexureSetup
    from .flexure_bench import (
        BARE_LIMIT,
        DEFAULT_LEVEL,
        SCALED_BENCH,
        MeshLevel,
        companion_bench,
        converged_compliance,
        flexure_bench,
    )

    bare = FlexureSetup(mode="bare", increments=1)
    levels = [MeshLevel(h, nz, c) for h, nz, c in FLEXURE_QUICK_LEVELS]
    payload: dict = {}
    if quick:
        reference, error = BARE_LIMIT
        rows = flexure_bench(bare, levels, reference)
    else:
        conv = converged_compliance(bare, DEFAULT_LEVEL)
        reference, error = conv.Cf_star, conv.error
        rows = flexure_bench(bare, [*levels, MeshLevel(0.25, 6, 0.025)], conv)
    for r in rows:
        r["case"] = "bare"
    payload["bare"] = {"reference": reference, "reference_error": error}
    if not quick:
        scaled, (limit, order, err) = companion_bench(SCALED_BENCH, DEFAULT_LEVEL)
        for r in scaled:
            r["case"] = "square staggered x"
        rows += scaled
        payload["square_staggered_x"] = {"reference": limit, "order": order, "reference_error": err}
    payload["rows"] = rows
    if out is not None:
        pd.DataFrame(rows).to_csv(out / "flexure_bench.csv", index=False)
    return payload
