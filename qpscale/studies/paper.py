"""Every study of the paper in one call: scenes in parallel, one tidy table, curves, figures.

Implements the normalisations of formulations/normalisation.md: an array's F_c* over the worst
F_c* of the isolated scale of the same shape, slant and slant direction (paper Fig. 6a, 13), and
over the same design without slant (Fig. 9a).  The scenes are listed in ``paper_scenes``; one
scene runs in ``paper_run``; the figures are drawn in ``figures``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .paper_run import run_scene
from .paper_scenes import Scene, paper_scenes

MAX_WORKERS = 2
# Wall-time limit of one scene in seconds (full run, quick run): a scene over it is recorded with
# the status "time_limit" and the study goes on.  Each scene's time is in the table (wall_s).  The
# slowest scenes that ended took 470 s (full) and 22 s (quick); the quick hexagon at alpha_45 =
# 60 deg does not end (it held a notebook past its 600 s cell limit).
SCENE_LIMIT_S = {False: 900.0, True: 60.0}
# Result columns always present (empty where a scene failed or does not apply).
RESULT_COLUMNS = ("status", "error", "Fc_star", "delta_c_star", "K_phi_star", "Cf_star", "wall_s")


@dataclass
class PaperResult:
    """The outcome of :func:`run_paper`.

    Attributes
    ----------
    table : DataFrame
        One row per scene: every parameter, every result, ``status`` ("ok" or the solver's).
    data : dict
        Scene key -> curves and final configurations (``w_star``, ``F_star``, ``q_final``...).
    figures : list of Path
        PNG and SVG files written.
    wall_s : float
        Wall-clock time of the whole run, seconds.
    """

    table: pd.DataFrame
    data: dict
    figures: list[Path] = field(default_factory=list)
    wall_s: float = 0.0
    files: dict = field(default_factory=dict)


def run_scenes(
    scenes: list[Scene],
    workers: int = MAX_WORKERS,
    progress: Callable[[Scene, dict], None] | None = None,
    limit_s: float | None = None,
) -> tuple[list[dict], dict]:
    """Run ``scenes`` on ``workers`` processes (1: in this process), rows in the order given.

    ``limit_s`` is each scene's wall-time limit (None: none).
    """
    rows: dict[str, dict] = {}
    data: dict[str, dict] = {}

    def done(scene: Scene, row: dict, d: dict) -> None:
        rows[scene.key], data[scene.key] = row, d
        if progress:
            progress(scene, row)

    if workers <= 1:
        for s in scenes:
            done(s, *run_scene(s, limit_s))
    else:
        with ProcessPoolExecutor(max_workers=min(workers, MAX_WORKERS)) as pool:
            futures = {pool.submit(run_scene, s, limit_s): s for s in scenes}
            for fut in as_completed(futures):
                done(futures[fut], *fut.result())
    return [rows[s.key] for s in scenes], data


def _lookup(table: pd.DataFrame, mask: pd.Series, column: str) -> float:
    hit = table.loc[mask & (table["status"] == "ok"), column]
    return float(hit.iloc[0]) if len(hit) else np.nan


def add_ratios(table: pd.DataFrame) -> pd.DataFrame:
    """Add ``Fc_iso_star``, ``ratio_iso`` (array / isolated, same geometry) and ``ratio_unslanted``.

    Only rows whose status is ok enter a ratio; a missing reference leaves the ratio empty.
    """
    t = table.copy()
    for col in RESULT_COLUMNS:
        if col not in t:
            t[col] = np.nan
    iso = (t["kind"] == "puncture") & (t["rings"] == 0)
    ref_iso, ref_flat = [], []
    for _, r in t.iterrows():
        same = (t["shape"] == r["shape"]) & np.isclose(t["slant_deg"], r["slant_deg"])
        same &= np.isclose(t["slant_dir_deg"], r["slant_dir_deg"]) | np.isclose(r["slant_deg"], 0.0)
        ref_iso.append(_lookup(t, iso & same, "Fc_star") if r["kind"] == "puncture" else np.nan)
        flat = (t["study"] == "interaction") & (t["tiling"] == r["tiling"]) & (t["interaction"] == "full")
        flat &= (t["shape"] == r["shape"]) & np.isclose(t["slant_deg"], 0.0)
        ref_flat.append(_lookup(t, flat, "Fc_star") if r["study"] == "slant" and r["rings"] > 0 else np.nan)
    t["Fc_iso_star"] = ref_iso
    t["ratio_iso"] = t["Fc_star"] / t["Fc_iso_star"]
    t["ratio_unslanted"] = t["Fc_star"] / pd.Series(ref_flat, index=t.index)
    t.loc[t["status"] != "ok", ["ratio_iso", "ratio_unslanted"]] = np.nan
    return t


def write_table(table: pd.DataFrame, data: dict, out: Path) -> dict:
    """Write ``results.csv``, ``results.parquet`` and ``curves.json`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    files = {"csv": out / "results.csv", "parquet": out / "results.parquet", "curves": out / "curves.json"}
    table.to_csv(files["csv"], index=False)
    table.to_parquet(files["parquet"], index=False)
    files["curves"].write_text(json.dumps(data, allow_nan=False))
    return files


def run_paper(
    out: str | Path,
    quick: bool = False,
    workers: int = MAX_WORKERS,
    progress: Callable[[Scene, dict], None] | None = None,
    scenes: list[Scene] | None = None,
    scene_limit_s: float | None = None,
) -> PaperResult:
    """Run every study of the paper and write the table, curves and figures into ``out``.

    Parameters
    ----------
    out : path
        Output directory (created).
    quick : bool
        Two designs, fewer increments, coarse membrane: the CI variant (a few minutes).
    workers : int
        Processes (at most ``MAX_WORKERS``).
    progress : callable or None
        Called with (scene, row) as each scene finishes.
    scenes : list of Scene or None
        Run these instead of ``paper_scenes(quick)``.
    scene_limit_s : float or None
        Wall-time limit of each scene in seconds (default ``SCENE_LIMIT_S[quick]``; 0: none). A
        scene over it gets the status ``time_limit`` and empty results; the study goes on.
    """
    from .figures import all_figures
    from .paper_findings import write_findings

    t0 = time.perf_counter()
    out = Path(out)
    limit = SCENE_LIMIT_S[quick] if scene_limit_s is None else scene_limit_s
    rows, data = run_scenes(scenes if scenes is not None else paper_scenes(quick), workers, progress, limit)
    table = add_ratios(pd.DataFrame(rows))
    files = write_table(table, data, out)
    figures = all_figures(table, data, out)
    files["findings"] = write_findings(table, out)
    return PaperResult(table, data, figures, time.perf_counter() - t0, files)


def load_results(out: str | Path) -> tuple[pd.DataFrame, dict]:
    """Read back a table and curves written by :func:`run_paper`."""
    out = Path(out)
    return pd.read_parquet(out / "results.parquet"), json.loads((out / "curves.json").read_text())
