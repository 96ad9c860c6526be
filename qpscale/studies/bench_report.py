"""Charts, CSV and the robustness grids of ``qpscale bench`` (formulations/penalty.md sec. 7).

Work-precision chart (F_c error against wall time, one marker per method setting), the stability
map (gap, coupling, slant, k_pen; where each method fails and why) and the fuzz grid of random
designs through the QP path.  Every chart has its CSV beside it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InvalidDesign, QpscaleError
from ..penalty import PenaltySettings
from ..tiling import DESIGNS, Design
from .bench import BenchResult, Method, Reference, Run, Scene, run_method

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
    """Scenes of the stability map: 3x3 square patches over gap, coupling and slant."""
    gaps = (0.0, 0.1) if quick else (0.0, 0.005, 0.05, 0.1)
    couplings = (0.04, 1.0) if quick else (0.0, 0.04, 0.5, 1.0)
    slants = (0.0,) if quick else (0.0, 30.0, 60.0, 75.0)
    out = []
    for d in gaps:
        for f in couplings:
            for a in slants:
                design = Design(gap=d, slant_deg=a, rings=1)
                scene = Scene(f"d{d}_f{f}_a{a}", design, interaction="contact", coupling=f)
                out.append(({"gap": d, "coupling": f, "slant_deg": a}, scene))
    return out


def stability_map(
    quick: bool, out: Path, time_limit: float = 60.0, progress: Callable[[str], None] | None = None
) -> pd.DataFrame:
    """Run the grid; each point's reference is clarabel at high accuracy at the load point (1, 0)."""
    kappas = (1e2, 1e4) if quick else (1e1, 1e2, 1e3, 1e4, 1e5, 1e6)
    methods = [Method("osqp-mid", "osqp", "mid")]
    methods += [Method(f"penalty-k{k:.0e}", "penalty", penalty=PenaltySettings(k_pen=k)) for k in kappas]
    rows = []
    for params, scene in stability_grid(quick):
        if progress:
            progress(f"stability {scene.name}")
        ref_run = run_method(scene, Method("clarabel", "clarabel"), None, time_limit)
        rows.append({**params, **_row(ref_run)})
        ref = Reference(scene.name, ref_run.Fc_star, (1.0, 0.0), ref_run.wall_s) if ref_run.success else None
        for m in methods:
            run = (
                run_method(scene, m, ref, time_limit)
                if ref
                else Run(m.name, scene.name, "no reference", False, time_limit, failure="no reference")
            )
            rows.append({**params, **_row(run)})
    df = pd.DataFrame(rows)
    df.to_csv(out / "stability_map.csv", index=False)
    _plot_stability(df, out / "stability_map.png")
    return df


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


def fuzz(
    n: int,
    out: Path,
    seed: int = 0,
    solver: str = "clarabel",
    increments: int = 4,
    progress: Callable[[str], None] | None = None,
    limit_s: float | None = 60.0,
) -> pd.DataFrame:
    """``n`` random designs through the QP path (rings = 1, coarse increments): pass or fail clearly.

    Each design is loaded at one of its top-face vertices drawn at random (the fuzz asks whether
    every path ends in a checked answer or a clear error, not which vertex is worst; the search
    over vertices would cost ~4x).  Each design has ``limit_s`` seconds of CPU time (wall time
    on a busy machine would fail designs for the machine's load); one over it is recorded as
    ``time limit``.
    """
    import time

    from ..experiments.puncture import PunctureSetup, run_puncture, top_vertices
    from ..increment import SQPSettings
    from ..timelimit import TimeLimitReached, time_limit

    rng, rows = np.random.default_rng(seed), []
    for i in range(n):
        if progress and i % 10 == 0:
            progress(f"fuzz {i}/{n}")
        t0 = time.perf_counter()
        params: dict = {}
        try:
            design, extra = random_design(rng)
            verts = top_vertices(design.patch())
            xy = verts[int(rng.integers(len(verts)))]
            extra["load_x"], extra["load_y"] = float(xy[0]), float(xy[1])
            params = {**asdict(design), **extra}
            setup = PunctureSetup(
                design=design,
                load_point=(extra["load_x"], extra["load_y"]),
                interaction="contact",
                coupling=extra["coupling"],
                nu=extra["nu"],
                probe=False,
                increments=increments,
                sqp=SQPSettings(solver=solver),
            )
            with time_limit(limit_s, clock="cpu"):
                res = run_puncture(setup)
            ok = bool(np.isfinite(res.Fc_star) and res.max_penetration <= 1e-9)
            rows.append(
                {
                    "i": i,
                    "outcome": "pass" if ok else "check failed",
                    "Fc_star": res.Fc_star,
                    "max_penetration": res.max_penetration,
                    "n_increments": len(res.states) - 1,
                    **params,
                }
            )
        except InvalidDesign as exc:
            rows.append({"i": i, "outcome": "invalid design", "error": str(exc), **params})
        except QpscaleError as exc:
            status = getattr(exc, "status", type(exc).__name__)
            rows.append({"i": i, "outcome": "solver failure", "status": status, "error": str(exc), **params})
        except TimeLimitReached as exc:
            rows.append({"i": i, "outcome": "time limit", "error": str(exc), **params})
        rows[-1]["wall_s"] = time.perf_counter() - t0
    df = pd.DataFrame(rows)
    df.to_csv(out / "fuzz.csv", index=False)
    return df


def run_all(
    out: Path,
    quick: bool = True,
    time_limit: float = 60.0,
    progress: Callable[[str], None] | None = None,
    fuzz_n: int = 1000,
) -> dict:
    """The whole bench: scenes x methods, work-precision chart, stability map, fuzz (full only).

    Returns the JSON payload of ``qpscale bench`` (SPEC.md contract plus extras).
    """
    from .bench import default_methods, full_scenes, quick_scenes, run_bench

    out.mkdir(parents=True, exist_ok=True)
    result = run_bench(
        quick_scenes() if quick else full_scenes(), default_methods(quick), time_limit, progress
    )
    work_precision(result, out)
    pd.DataFrame(result.summary).drop(columns="statuses").to_csv(out / "summary.csv", index=False)
    stab = stability_map(quick, out, time_limit, progress)
    payload = {
        "reference": {k: asdict(v) for k, v in result.references.items()},
        "methods": result.summary,
        "runs": [asdict(r) for r in result.runs],
        "stability": {"points": int(len(stab)), "failures": int((~stab.success).sum())},
        "quick": quick,
        "time_limit_s": time_limit,
        "out": str(out),
    }
    if not quick:
        fz = fuzz(fuzz_n, out, progress=progress, limit_s=time_limit)
        payload["fuzz"] = {
            "n": int(len(fz)),
            "success_rate": float((fz.outcome == "pass").mean()),
            "outcomes": {str(k): int(v) for k, v in fz.outcome.value_counts().items()},
            "note": "rings = 1 patches, 4 target increments, clarabel, contact interaction",
        }
    return payload
