"""A user's own design through the paper's chain: puncture (array and isolated), flexure, Ashby point.

Implements, for one design, the read-outs of formulations/puncture.md (F_c* at phi_c, worst
vertex) and formulations/membrane.md eq. (14) (C_f* for both load lines), normalised as in
formulations/normalisation.md (array over the isolated scale of the same geometry).  Used by
notebooks/design_exploration.ipynb; the scenes run through ``paper_run.run_scene``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from ..tiling import Design
from .paper import add_ratios, run_scenes
from .paper_scenes import Scene

NOTEBOOK_QUICK = (("hexagon", "honeycomb"),)


def design_scenes(design: Design, quick: bool = True) -> list[Scene]:
    """Isolated and arrayed puncture (full, substrate, contact) and flexure along x and y."""
    inc, h = (6, 1.0) if quick else (16, 0.5)
    common: dict[str, Any] = {
        "shape": design.shape,
        "tiling": design.tiling,
        "slant_deg": design.slant_deg,
        "slant_dir_deg": design.slant_dir_deg,
        "gap": design.gap,
        "thickness": design.thickness,
    }
    study = "slant" if design.slant_deg > 0 else "interaction"
    scenes = [Scene(study, "puncture", **common, rings=0, increments=inc)]
    modes = ("full",) if quick else ("full", "substrate", "contact")
    scenes += [Scene(study, "puncture", **common, rings=2, interaction=m, increments=inc) for m in modes]
    scenes += [
        Scene("flexure", "flexure", **common, load_line=ln, increments=2 if quick else 5, mesh_h=h)
        for ln in ("x", "y")
    ]
    return scenes


def explore_design(design: Design, quick: bool = True, workers: int = 2) -> pd.DataFrame:
    """Run :func:`design_scenes` and return their rows with the ratios of ``paper.add_ratios``."""
    rows, _ = run_scenes(design_scenes(design, quick), workers)
    return add_ratios(pd.DataFrame(rows))


def notebook_scenes(quick: bool = True) -> list[Scene]:
    """The studies of notebooks/paper.ipynb: with ``quick``, one design (hexagon) in every study."""
    from .paper_scenes import paper_scenes

    scenes = paper_scenes(quick=quick)
    if not quick:
        return scenes
    keep = {s for s, _ in NOTEBOOK_QUICK}
    # Every study keeps its hexagon scenes; the bare membrane and the isolated validation scale
    # (both cheap) stay as references.
    bare = {s.key for s in scenes if s.kind == "flexure" and s.flex_mode == "bare"}
    iso = {s.key for s in scenes if s.study == "validation" and s.rings == 0 and s.slant_deg == 0}
    return [s for s in scenes if (s.shape in keep and "validation" not in s.study) or s.key in bare | iso]


def ashby_with(design_rows: pd.DataFrame, paper_out: str | Path | None = None) -> pd.DataFrame:
    """Ashby points of the user's design, plus those of a previous ``run_paper`` output if given."""
    from .figures import ashby_points

    tables = [design_rows]
    if paper_out is not None and (Path(paper_out) / "results.parquet").exists():
        tables.insert(0, pd.read_parquet(Path(paper_out) / "results.parquet"))
    return ashby_points(pd.concat(tables, ignore_index=True))
