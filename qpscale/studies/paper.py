"""Every study of the paper in one call: scenes on the engine, one tidy table, curves, figures.

Implements the normalisations of formulations/normalisation.md: an array's F_c* over the worst
F_c* of the isolated scale of the same shape, slant and slant direction (paper Fig. 6a, 13), and
over the same design without slant (Fig. 9a).  The scenes are listed in ``paper_scenes``; one
scene runs in ``paper_run``, on the workers of :mod:`qpscale.studies.engine`; the figures are
drawn in ``figures``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .engine import Engine
from .paper_run import SCENE_CLOCK, paper_sibling, run_scene_group, scene_limit, task_group
from .paper_scenes import Scene, paper_scenes

MAX_WORKERS = 2
# CPU-time limit of one scene in seconds (full run, quick run; paper_run.SCENE_CLOCK; a patch scene
# twice it, paper_run.scene_limit): a scene over it is recorded with the status "time_limit" and the
# study goes on.  Each scene's times are in the table (wall_s, cpu_s).  The slowest scenes that
# ended took 470 s (full) and, on the slower machine of 2026-11-28, 61 s (quick: the square array
# slanted 60 deg towards 45 deg, 4,349 QPs; the quick limit was 60 s until then, and the quick
# hexagon at that slant, which once did not end, takes 35 s).
SCENE_LIMIT_S = {False: 900.0, True: 120.0}
# Result columns always present (empty where a scene failed or does not apply).
RESULT_COLUMNS = ("status", "error", "Fc_star", "delta_c_star", "K_phi_star", "Cf_star", "wall_s", "cpu_s")


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
    on_done: Callable[[Scene, dict, dict], None] | None = None,
    engine: Engine | None = None,
    known: dict[Scene, dict] | None = None,
) -> tuple[list[dict], dict]:
    """Run ``scenes`` on ``engine`` (None: a local one of ``workers`` processes, 1: this process),
    rows in the order given.

    ``limit_s`` is each scene's time limit (None: none; CPU seconds, ``paper_run.SCENE_CLOCK``).
    ``on_done(scene, row, data)`` is called as each scene finishes (:func:`run_paper` saves it
    there).  An exception here (Ctrl-C, SIGTERM turned into one by the command line) cancels the
    scenes not yet done and, for a local cluster, ends its worker processes: no worker keeps
    computing a scene nobody will read.  A scene whose task the cluster gave up (its workers
    killed, e.g. out of memory) is a row with the exception's class as its status.  A task is one
    scene, or the scenes that share work (:func:`_groups`), run one after another in one process.
    ``known`` maps scenes run before (a resumed study's) to their rows: a patch scene whose sibling
    is among them reads its worst vertex there instead of running the paper's patch again.
    """
    rows: dict[str, dict] = {}
    data: dict[str, dict] = {}
    groups = _groups(scenes)

    def done(g: int, results: list[tuple[dict, dict]]) -> None:
        for i, result in zip(groups[g], results):
            scene = scenes[i]
            rows[scene.key], data[scene.key] = result
            if on_done:
                on_done(scene, *result)
            if progress:
                progress(scene, result[0])

    def lost(g: int, exc: BaseException) -> list[tuple[dict, dict]]:
        status = {"status": type(exc).__name__, "error": str(exc)}
        return [({**scenes[i].as_dict(), **status}, {}) for i in groups[g]]

    if engine is None:
        # No cluster to start for one task (or none left to run after a resume).
        n = min(workers, MAX_WORKERS, os.cpu_count() or 1) if len(groups) > 1 else 1
        with Engine(n) as own:
            return run_scenes(scenes, workers, progress, limit_s, on_done, own, known)
    known = known or {}
    tasks = []
    for group in groups:
        members = [scenes[i] for i in group]
        sibs = [sib for sib in map(paper_sibling, members) if sib is not None and sib in known]
        tasks.append((members, limit_s, {sib: known[sib] for sib in sibs}))
    engine.map(run_scene_group, tasks, on_done=done, failure=lost, name="scene")
    return [rows[s.key] for s in scenes], data


def _groups(scenes: list[Scene]) -> list[list[int]]:
    """The tasks: scenes that share work (``paper_run.task_group``: the flexure scenes of one
    condensation; a patch scene and the puncture scene it starts from) together, in the order of
    the first of them, puncture scenes before patch scenes; every other scene alone."""
    groups: list[list[int]] = []
    at: dict[Scene, int] = {}
    for i, scene in enumerate(scenes):
        key = task_group(scene)
        if key not in at:
            at[key] = len(groups)
            groups.append([i])
        else:
            groups[at[key]].append(i)
    return [sorted(g, key=lambda i: scenes[i].kind == "patch") for g in groups]


def _lookup(table: pd.DataFrame, mask: pd.Series, column: str) -> float:
    hit = table.loc[mask & (table["status"] == "ok"), column]
    return float(hit.iloc[0]) if len(hit) else np.nan


def add_ratios(table: pd.DataFrame) -> pd.DataFrame:
    """Add ``Fc_iso_star``, ``ratio_iso`` (array / isolated, same geometry) and ``ratio_unslanted``;
    on the patch-size study's rows ``ratio_iso_patch`` and its error ``ratio_iso_patch_err`` too
    (``Fc_patch`` over the same isolated scale).

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
        ref_iso.append(_lookup(t, iso & same, "Fc_star") if r["kind"] != "flexure" else np.nan)
        flat = (t["study"] == "interaction") & (t["tiling"] == r["tiling"]) & (t["interaction"] == "full")
        flat &= (t["shape"] == r["shape"]) & np.isclose(t["slant_deg"], 0.0)
        ref_flat.append(_lookup(t, flat, "Fc_star") if r["study"] == "slant" and r["rings"] > 0 else np.nan)
    t["Fc_iso_star"] = ref_iso
    t["ratio_iso"] = t["Fc_star"] / t["Fc_iso_star"]
    t["ratio_unslanted"] = t["Fc_star"] / pd.Series(ref_flat, index=t.index)
    if "Fc_patch" in t:
        # The patch-size study: the skin's estimate over the same isolated scale (with its error).
        t["ratio_iso_patch"] = t["Fc_patch"] / t["Fc_iso_star"]
        t["ratio_iso_patch_err"] = t["Fc_patch_err"] / t["Fc_iso_star"]
        t.loc[t["status"] != "ok", ["ratio_iso_patch", "ratio_iso_patch_err"]] = np.nan
    t.loc[t["status"] != "ok", ["ratio_iso", "ratio_unslanted"]] = np.nan
    return t


def _atomic(path: Path, write: Callable[[Path], object]) -> None:
    """``write(tmp)`` then rename to ``path``: a file under its final name is always whole."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_table(table: pd.DataFrame, data: dict, out: Path) -> dict:
    """Write ``results.csv``, ``results.parquet`` and ``curves.json`` into ``out`` (each atomically)."""
    out.mkdir(parents=True, exist_ok=True)
    files = {"csv": out / "results.csv", "parquet": out / "results.parquet", "curves": out / "curves.json"}
    _atomic(files["csv"], lambda p: table.to_csv(p, index=False))
    _atomic(files["parquet"], lambda p: table.to_parquet(p, index=False))
    _atomic(files["curves"], lambda p: p.write_text(json.dumps(data, allow_nan=False)))
    return files


# Per-scene results of a run in progress: one JSON file per finished scene, so that an interrupted
# study resumes where it stopped.  A file is reused only if it was written for the same scene, time
# limit and package version (the fingerprint).
SCENES_DIR = "scenes"
PROGRESS_FILE = "progress.json"
FINAL_FILES = ("results.csv", "results.parquet", "curves.json", "findings.md")


def _fingerprint(scene: Scene, limit_s: float | None) -> str:
    from .. import __version__

    return json.dumps(
        {
            "scene": repr(scene),
            "limit_s": scene_limit(scene, limit_s),
            "clock": SCENE_CLOCK,
            "version": __version__,
        },
        sort_keys=True,
    )


def _scene_file(out: Path, scene: Scene) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in scene.key)
    return out / SCENES_DIR / f"{safe}.json"


def saved_scene(out: Path, scene: Scene, limit_s: float | None) -> tuple[dict, dict] | None:
    """The row and data a previous run saved for ``scene``, or None (absent, stale or unreadable)."""
    path = _scene_file(out, scene)
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(saved, dict) or saved.get("fingerprint") != _fingerprint(scene, limit_s):
        return None
    return saved["row"], saved["data"]


def save_scene(out: Path, scene: Scene, limit_s: float | None, row: dict, data: dict) -> None:
    path = _scene_file(out, scene)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps({"fingerprint": _fingerprint(scene, limit_s), "row": row, "data": data})
    _atomic(path, lambda p: p.write_text(text))


def write_progress(out: Path, done: int, total: int, complete: bool) -> None:
    """``progress.json``: scenes done of total, and whether the table and figures are complete."""
    text = json.dumps({"complete": complete, "scenes_done": done, "scenes_total": total})
    _atomic(out / PROGRESS_FILE, lambda p: p.write_text(text))


def run_paper(
    out: str | Path,
    quick: bool = False,
    workers: int = MAX_WORKERS,
    progress: Callable[[Scene, dict], None] | None = None,
    scenes: list[Scene] | None = None,
    scene_limit_s: float | None = None,
    engine: Engine | None = None,
) -> PaperResult:
    """Run every study of the paper and write the table, curves and figures into ``out``.

    Parameters
    ----------
    out : path
        Output directory (created).
    quick : bool
        Two designs, fewer increments, coarse membrane: the CI variant (a few minutes).
    workers : int
        Worker processes of a local Dask cluster (at most ``MAX_WORKERS``; 1: this process).
    progress : callable or None
        Called with (scene, row) as each scene finishes.
    scenes : list of Scene or None
        Run these instead of ``paper_scenes(quick)``.
    scene_limit_s : float or None
        Wall-time limit of each scene in seconds (default ``SCENE_LIMIT_S[quick]``; 0: none). A
        scene over it gets the status ``time_limit`` and empty results; the study goes on.
    engine : Engine or None
        Run the scenes there (entered; e.g. a Dask cluster at an address) instead of ``workers``.

    Notes
    -----
    Each finished scene is saved at once under ``out/scenes/`` and ``out/progress.json`` counts
    them with ``"complete": false``; a rerun into the same ``out`` skips the scenes already saved
    (same scene, time limit and version).  The table, curves and findings are written last, each
    through a temporary file and a rename, and ``progress.json`` says ``"complete": true`` only
    after them: an interrupted run leaves no file claiming to be the study's result.
    """
    from .figures import all_figures
    from .paper_findings import write_findings

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    limit = SCENE_LIMIT_S[quick] if scene_limit_s is None else scene_limit_s
    todo_all = scenes if scenes is not None else paper_scenes(quick)
    # A previous run's table would claim to describe this one while it runs: remove it (the scenes
    # it was built from are kept under scenes/ and reused below).
    for name in FINAL_FILES:
        (out / name).unlink(missing_ok=True)
    rows: dict[str, dict] = {}
    data: dict[str, dict] = {}
    todo = []
    for s in todo_all:
        saved = saved_scene(out, s, limit)
        if saved is None:
            todo.append(s)
        else:
            rows[s.key], data[s.key] = saved
            if progress:
                progress(s, saved[0])
    write_progress(out, len(rows), len(todo_all), complete=False)

    def on_done(scene: Scene, row: dict, d: dict) -> None:
        save_scene(out, scene, limit, row, d)
        rows[scene.key], data[scene.key] = row, d
        write_progress(out, len(rows), len(todo_all), complete=False)

    run_scenes(
        todo, workers, progress, limit, on_done, engine, {s: rows[s.key] for s in todo_all if s.key in rows}
    )
    table = add_ratios(pd.DataFrame([rows[s.key] for s in todo_all]))
    curves = {s.key: data[s.key] for s in todo_all}
    figures = all_figures(table, curves, out)
    findings = write_findings(table, out)
    files = write_table(table, curves, out)
    files["findings"] = findings
    write_progress(out, len(rows), len(todo_all), complete=True)
    return PaperResult(table, curves, figures, time.perf_counter() - t0, files)


def load_results(out: str | Path) -> tuple[pd.DataFrame, dict]:
    """Read back a table and curves written by :func:`run_paper`."""
    out = Path(out)
    return pd.read_parquet(out / "results.parquet"), json.loads((out / "curves.json").read_text())
