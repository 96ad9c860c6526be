"""Matplotlib drawings of patches and results (formulations/geometry.md for what is drawn)."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Polygon as MplPolygon  # noqa: E402

from .tiling import Patch  # noqa: E402


def draw_patch(patch: Patch, path: str | Path, load_point: tuple[float, float] | None = None) -> Path:
    """Draw the patch from above: base polygons, top faces (dashed), the punctured scale in red."""
    fig, ax = plt.subplots(figsize=(6, 6))
    off = patch.design.top_offset
    for i, base in enumerate(patch.base):
        colour = "tab:red" if i == 0 else "tab:blue"
        ax.add_patch(MplPolygon(base, closed=True, fc=colour, alpha=0.25, ec=colour, lw=1.0))
        ax.add_patch(MplPolygon(base + off, closed=True, fill=False, ec=colour, lw=0.8, ls="--"))
    if load_point is not None:
        ax.plot(*load_point, "k*", ms=12)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("x / L")
    ax.set_ylabel("y / L")
    ax.set_title(f"{patch.design.shape} ({patch.design.tiling}), {patch.n_scales} scales")
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:  # a file under its final name is always whole (interrupted or failed writes leave none)
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format=path.suffix[1:] or "png")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        tmp.unlink(missing_ok=True)
    return path
