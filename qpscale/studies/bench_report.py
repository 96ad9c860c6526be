"""Charts, CSV and the robustness grids of ``qpscale bench`` (formulations/penalty.md sec. 7).

Work-precision chart (F_c error against wall time, one marker per method setting), the stability
map (gap, coupling, slant, k_pen; where each method fails and why) and the fuzz grid of random
designs through the QP path.  Every chart has its CSV beside it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InvalidDesign, QpscaleError
from ..experiments.puncture import top_vertices
from ..penalty import PenaltySettings
from ..tiling import DESIGNS, Design
from .bench import FC_TOL, BenchResult, Method, Reference, Run, Scene, _setup, backend_overrides, run_method
from .engine import Engine, map_tasks

FLOOR = 1e-16  # F_c errors are drawn at least at this value on the log axis


def runs_frame(result: BenchResult) -> pd.DataFrame:
    """One row per (method, scene) run."""
    return pd.DataFrame([asdict(r) for r in result.runs])


def work_precision(result: BenchResult, out: Path) -> Path:
    """PNG + CSV: F_c relative error against wall time per run; failures drawn hollow at the limit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    df = runs_frame(result)
    df.to_csv(out / "work_precision.csv", index=False)
    fig, ax = plt.subplots(figsize=(7, 5))
    for i, (name, g) in enumerate(df.groupby("method", sort=False)):
        ok = g[g.success]
        err = np.maximum(ok.Fc_rel_error.astype(float).fillna(FLOOR), FLOOR)
        ax.scatter(ok.wall_s, err, label=name, marker="osD^v<>ph*"[i % 10])
        bad = g[~g.success]
        if len(bad):
            ax.scatter([result.time_limit] * len(bad), [1.0] * len(bad), facecolors="none", edgecolors="k")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="wall time per whole curve (s)",
        ylabel="|F_c - F_c,ref| / F_c,ref",
        title="work-precision (hollow: failures at the time limit)",
    )
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "work_precision.png", dpi=110)
    plt.close(fig)
    return out / "work_precision.png"


def stability_grid(quick: bool) -> list[tuple[dict, Scene]]:
    """Scenes of the stability map: 3x3 square patches over gap, coupling and slant, each loaded at
    its top face's +x corner (every method and the reference at the same point: the map asks where
    methods fail, not which vertex is worst)."""
    gaps = (0.0, 0.1) if quick else (0.0, 0.005, 0.05, 0.1)
    couplings = (0.04, 1.0) if quick else (0.0, 0.04, 0.5, 1.0)
    slants = (0.0,) if quick else (0.0, 30.0, 60.0, 75.0)
    out = []
    for d in gaps:
        for f in couplings:
            for a in slants:
                design = Design(gap=d, slant_deg=a, rings=1)
                top = top_vertices(design.patch())
                xy = tuple(float(v) for v in max(top.tolist()))  # the +x corner, the same for all methods
                scene = Scene(f"d{d}_f{f}_a{a}", design, "contact", f, xy)  # type: ignore[arg-type]
                out.append(({"gap": d, "coupling": f, "slant_deg": a}, scene))
    return out


def stability_map(
    quick: bool,
    out: Path,
    time_limit: float = 60.0,
    progress: Callable[[str], None] | None = None,
    workers: int = 1,
    engine: Engine | None = None,
) -> pd.DataFrame:
    """Run the grid; each point's reference is clarabel at high accuracy at the scene's load point.

    The points are tasks of ``engine`` (None: one of ``workers`` processes)."""
    kappas = (1e2, 1e4) if quick else (1e1, 1e2, 1e3, 1e4, 1e5, 1e6)
    methods = [Method("osqp-feature-mid", "osqp", "mid", formulation="feature")]
    methods += [Method(f"penalty-k{k:.0e}", "penalty", penalty=PenaltySettings(k_pen=k)) for k in kappas]
    tasks = [(params, scene, methods, time_limit) for params, scene in stability_grid(quick)]
    label = lambda t: f"stability {t[1].name}"  # noqa: E731
    points = map_tasks(_stability_point, tasks, workers, engine, progress, label, "stability")
    df = pd.DataFrame([row for rows in points for row in rows])
    df.to_csv(out / "stability_map.csv", index=False)
    _plot_stability(df, out / "stability_map.png")
    return df


def _stability_point(params: dict, scene: Scene, methods: list[Method], time_limit: float) -> list[dict]:
    """One grid point: its reference run, then every method against it (a worker's task)."""
    ref_run = run_method(scene, Method("clarabel", "clarabel"), None, time_limit)
    rows = [{**params, **_row(ref_run)}]
    ref = None
    if ref_run.success and ref_run.Fc_star is not None:
        ref = Reference(scene.name, ref_run.Fc_star, scene.load_point, ref_run.wall_s)
    for m in methods:
        run = (
            run_method(scene, m, ref, time_limit)
            if ref
            else Run(m.name, scene.name, "no reference", False, time_limit, failure="no reference")
        )
        rows.append({**params, **_row(run)})
    return rows


def _row(run: Run) -> dict:
    return {
        "method": run.method,
        "success": run.success,
        "failure": run.failure,
        "status": run.status,
        "Fc_rel_error": run.Fc_rel_error,
        "max_penetration": run.max_penetration,
        "wall_s": run.wall_s,
    }


def _plot_stability(df: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    df = df.assign(point=[f"d={g}, f={c}, a={a}" for g, c, a in zip(df.gap, df.coupling, df.slant_deg)])
    methods, points = list(dict.fromkeys(df.method)), list(dict.fromkeys(df.point))
    codes = {
        "": 0,
        "solver": 1,
        "penetration": 2,
        "Fc error": 3,
        "non-finite": 4,
        "time limit": 5,
        "no reference": 6,
    }
    grid = np.full((len(methods), len(points)), np.nan)
    for r in df.itertuples():
        grid[methods.index(r.method), points.index(r.point)] = codes.get(r.failure, 6)
    fig, ax = plt.subplots(figsize=(1.2 + 0.6 * len(points), 1.0 + 0.45 * len(methods)))
    im = ax.imshow(grid, cmap=plt.get_cmap("tab10", 7), vmin=-0.5, vmax=6.5, aspect="auto")
    ax.set_xticks(range(len(points)), points, rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(len(methods)), methods, fontsize=7)
    cb = fig.colorbar(im, ticks=list(codes.values()))
    cb.ax.set_yticklabels(["ok", *list(codes)[1:]], fontsize=7)
    ax.set_title("stability map (3x3 square, contact interaction)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def random_design(rng: np.random.Generator) -> tuple[Design, dict]:
    """One fuzz sample: shape, tiling, slant angle and direction, gap, thickness (rings = 1)."""
    shape, tiling = DESIGNS[rng.integers(len(DESIGNS))]
    design = Design(
        shape=shape,
        tiling=tiling,
        slant_deg=float(rng.uniform(0, 75)),
        slant_dir_deg=float(rng.choice([0.0, 45.0, 90.0])),
        gap=float(rng.uniform(0, 0.1)),
        thickness=float(rng.uniform(0.5, 2.0)),
        rings=1,
    )
    return design, {"coupling": float(rng.uniform(0, 1)), "nu": float(rng.uniform(0, 0.5))}


# Designs per fuzz chunk: chunk k draws its designs from seed + k, so a design's parameters do not
# depend on how the grid is split over workers, and a run stopped midway resumes chunk by chunk.
FUZZ_CHUNK = 25
# Seed of the full bench's fuzz (chunk k uses FUZZ_SEED + k) and its CPU time per run: the median
# run took 2.6 s and 6 of the first 300 designs reached 30 s (measured, Clarabel).
FUZZ_SEED = 1000
FUZZ_LIMIT_S = 30.0
# Methods of the full bench's fuzz after the first (the default backend, PIQP, over every design):
# each over the first tenth of the designs, its F_c compared with PIQP's on the same design.
# Built when the fuzz runs, not at import: a Method checks that its backend is installed.
FUZZ_METHOD_ARGS = (
    ("piqp", "piqp"),
    ("clarabel", "clarabel"),
    ("osqp-feature", "osqp"),
    ("penalty-k1e+03", "penalty"),
)


def fuzz_methods() -> tuple[Method, ...]:
    """The fuzz's methods whose backend is installed here (see :func:`bench.skipped_methods`)."""
    from ..solvers import available_solvers

    have = {*available_solvers(), "penalty"}
    return tuple(
        Method(
            name,
            solver,
            penalty=PenaltySettings(k_pen=1e3) if solver == "penalty" else None,
            formulation="feature" if solver == "osqp" else "plane",
        )
        for name, solver in FUZZ_METHOD_ARGS
        if solver in have
    )


def fuzz(
    n: int,
    out: Path,
    seed: int = 0,
    methods: tuple[Method, ...] = (Method("clarabel", "clarabel"),),
    increments: int = 4,
    progress: Callable[[str], None] | None = None,
    limit_s: float | None = 60.0,
    workers: int = 1,
    n_others: int | None = None,
    engine: Engine | None = None,
) -> pd.DataFrame:
    """``n`` random designs through the puncture path (rings = 1, coarse increments): each run
    passes our checks or fails with a named status.

    The first method runs every design, the others the first ``n_others`` (default all), and
    their F_c is compared with the first method's on the same design (over 1 % is a failure,
    ``Fc error``).  Each design is loaded at one of its top-face vertices drawn at random (the
    fuzz asks whether every path ends in a checked answer or a clear error, not which vertex is
    worst; the search over vertices would cost ~4x).  Each run has ``limit_s`` seconds of CPU
    time (wall time on a busy machine would fail runs for the machine's load); one over it is
    recorded as ``time limit``.  Chunks of :data:`FUZZ_CHUNK` designs are the tasks of ``engine``
    (None: one of ``workers`` processes); they are kept under
    ``out/fuzz_chunks`` and not rerun (delete them after changing the code).  Returns one row
    per (method, design); writes fuzz.csv.
    """
    chunks = -(-n // FUZZ_CHUNK)
    others = chunks if n_others is None else -(-n_others // FUZZ_CHUNK)
    cache = out / "fuzz_chunks"
    cache.mkdir(parents=True, exist_ok=True)
    tasks = [
        (method, k * FUZZ_CHUNK, min(FUZZ_CHUNK, n - k * FUZZ_CHUNK), seed + k, increments, limit_s, cache)
        for j, method in enumerate(methods)
        for k in range(chunks if j == 0 else min(others, chunks))
    ]
    label = lambda t: f"fuzz {t[0].name} from {t[1]}"  # noqa: E731
    parts = map_tasks(_fuzz_chunk, tasks, workers, engine, progress, label, "fuzz")
    df = pd.concat(parts, ignore_index=True)
    if len(methods) > 1 and "Fc_star" in df:
        first = df[(df.method == methods[0].name) & (df.outcome == "pass")].set_index("i").Fc_star
        ref = df.i.map(first)
        df["Fc_rel_error"] = (df.Fc_star - ref).abs() / ref.abs()
        df.loc[(df.outcome == "pass") & (df.Fc_rel_error > FC_TOL), "outcome"] = "Fc error"
    df.to_csv(out / "fuzz.csv", index=False)
    return df


def _fuzz_chunk(
    method: Method, first: int, size: int, seed: int, increments: int, limit_s: float | None, cache: Path
) -> pd.DataFrame:
    """Designs ``first ... first + size - 1`` of the fuzz through ``method`` (a worker's task), or
    the chunk's CSV if an earlier run wrote it."""
    # The name holds everything that defines the chunk but the code: after changing the puncture
    # path, delete out/fuzz_chunks to measure the new code.
    name = f"{method.name.replace(':', '_')}_{first:05d}_{size}_{seed}_n{increments}_t{limit_s}.csv"
    path = cache / name
    if path.exists():
        return pd.read_csv(path)
    rng = np.random.default_rng(seed)
    df = pd.DataFrame([_fuzz_design(rng, method, increments, limit_s) for _ in range(size)])
    df.insert(0, "i", np.arange(size) + first)
    df.insert(1, "method", method.name)
    df.to_csv(path, index=False)
    return df


def fuzz_case(rng: np.random.Generator) -> tuple[Design, dict, tuple[float, float]]:
    """One draw of the fuzz: the design, its ``coupling`` and ``nu``, and the load point (one of
    its top-face vertices).  Raises InvalidDesign, as the fuzz records it, before the vertex is drawn."""
    design, extra = random_design(rng)
    verts = top_vertices(design.patch())
    vertex = verts[int(rng.integers(len(verts)))]
    return design, extra, (float(vertex[0]), float(vertex[1]))


def fuzz_design_number(i: int, seed: int = FUZZ_SEED) -> tuple[Design, dict, tuple[float, float]]:
    """Design ``i`` of the fuzz with ``seed`` as the fuzz drew it (chunk ``i // FUZZ_CHUNK`` from
    ``seed`` plus the chunk; an invalid design before it consumed its draws without a vertex)."""
    if not 0 <= i:
        raise InvalidDesign("i", i, "integers >= 0")
    rng = np.random.default_rng(seed + i // FUZZ_CHUNK)
    for _ in range(i % FUZZ_CHUNK):
        try:
            fuzz_case(rng)
        except InvalidDesign:
            pass
    return fuzz_case(rng)


def _fuzz_design(rng: np.random.Generator, method: Method, increments: int, limit_s: float | None) -> dict:
    """One random design through ``method``: a row with its outcome and parameters."""
    import time

    from ..experiments.puncture import run_puncture
    from ..timelimit import TimeLimitReached, time_limit

    t0 = time.perf_counter()
    params: dict = {}
    try:
        design, extra, xy = fuzz_case(rng)
        extra["load_x"], extra["load_y"] = xy
        params = {**asdict(design), **extra}
        scene = Scene("fuzz", design, "contact", extra["coupling"], xy)
        setup = replace(_setup(scene, replace(method, increments=increments), xy), nu=extra["nu"])
        with time_limit(limit_s, clock="cpu"), backend_overrides(method.options):
            res = run_puncture(setup)
        pen_ok = not method.exact_contact or res.max_penetration <= method.penetration_tol
        row = {
            "outcome": "pass" if np.isfinite(res.Fc_star) and pen_ok else "check failed",
            "Fc_star": res.Fc_star,
            "max_penetration": res.max_penetration,
            "n_increments": len(res.states) - 1,
            **params,
        }
    except InvalidDesign as exc:
        row = {"outcome": "invalid design", "error": str(exc), **params}
    except QpscaleError as exc:
        status = getattr(exc, "status", type(exc).__name__)
        row = {"outcome": "solver failure", "status": status, "error": str(exc), **params}
    except TimeLimitReached as exc:
        row = {"outcome": "time limit", "error": str(exc), **params}
    row["wall_s"] = time.perf_counter() - t0
    return row


def run_all(
    out: Path,
    quick: bool = True,
    time_limit: float = 60.0,
    progress: Callable[[str], None] | None = None,
    fuzz_n: int = 1000,
    workers: int = 1,
) -> dict:
    """The whole bench: scenes x methods, work-precision chart, stability map, fuzz (full only).

    Returns the JSON payload of ``qpscale bench`` (docs/cli.md contract plus extras).
    """
    from .bench import default_methods, flexure_section, full_scenes, quick_scenes, run_bench

    out.mkdir(parents=True, exist_ok=True)
    scenes = quick_scenes() if quick else full_scenes()
    # One engine for every stage: a local cluster starts once (and only for more than one worker).
    with Engine(workers) as engine:
        result = run_bench(scenes, default_methods(quick), time_limit, progress, workers, engine)
        work_precision(result, out)
        pd.DataFrame(result.summary).drop(columns="statuses").to_csv(out / "summary.csv", index=False)
        stab = stability_map(quick, out, time_limit, progress, workers, engine)
        payload = _payload(result, stab, quick, time_limit, workers, out, fuzz_n)
        payload["flexure"] = flexure_section(quick, out)  # flexure time against accuracy (bench.py)
        if not quick and fuzz_n > 0:
            payload["fuzz"] = _fuzz_summary(fuzz_n, out, progress, workers, engine)
    return payload


def _payload(
    result: BenchResult,
    stab: pd.DataFrame,
    quick: bool,
    time_limit: float,
    workers: int,
    out: Path,
    fuzz_n: int,
) -> dict:
    from .bench import skipped_methods

    payload = {
        "reference": {k: asdict(v) for k, v in result.references.items()},
        "methods": result.summary,
        "runs": [asdict(r) for r in result.runs],
        "stability": {"points": int(len(stab)), "failures": int((~stab.success).sum())},
        "skipped": [
            {"name": name, "reason": "not installed (pip install 'qpscale[solvers]')"}
            for name in skipped_methods(quick, fuzz=not quick and fuzz_n > 0)
        ],
        "quick": quick,
        "time_limit_s": time_limit,
        "workers": workers,
        "out": str(out),
    }
    return payload


def _fuzz_summary(
    fuzz_n: int, out: Path, progress: Callable[[str], None] | None, workers: int, engine: Engine
) -> dict:
    """The full bench's fuzz run on ``engine`` and its summary for the payload."""
    n_others = max(fuzz_n // 10, 1)
    fz = fuzz(
        fuzz_n,
        out,
        FUZZ_SEED,
        fuzz_methods(),
        progress=progress,
        limit_s=FUZZ_LIMIT_S,
        workers=workers,
        n_others=n_others,
        engine=engine,
    )
    return {
        "n": fuzz_n,
        "methods": {
            m: {
                "designs": int(len(g)),
                "success_rate": float((g.outcome == "pass").mean()),
                "outcomes": {str(k): int(v) for k, v in g.outcome.value_counts().items()},
            }
            for m, g in fz.groupby("method", sort=False)
        },
        "note": (
            f"rings = 1 patches, 4 target increments, contact interaction, one random top vertex, "
            f"{FUZZ_LIMIT_S:.0f} CPU-s per run; the first method over all designs, the others over "
            f"the first {n_others} (F_c within 1 % of the first's)"
        ),
    }
