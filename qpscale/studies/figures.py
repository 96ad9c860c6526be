"""The paper's figures drawn from a results table and its curves (PNG and SVG).

Draws what formulations/puncture.md and formulations/membrane.md define: force-displacement
curves in newtons and millimetres (Figs. 3, 11), F_c* against phi_c K_phi*/delta_c* (Fig. 4, the
isolated-scale estimate of formulations/normalisation.md), normalised puncture resistance by
interaction mode and slant (Figs. 6a, 9a), displacement fields at failure (Figs. 6b, 7, 9b),
compliance C_f* (Fig. 12) and the Ashby chart (Fig. 13, with the patch-size estimates of
formulations/puncture.md sec. 7).  Every number comes from the table.
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

from ..tiling import Design  # noqa: E402

MODES = ("full", "substrate", "contact")


def _save(fig: plt.Figure, out: Path, name: str) -> list[Path]:
    paths = [out / f"{name}.png", out / f"{name}.svg"]
    for p in paths:
        # Drawn to a temporary name, then renamed: an interrupted study leaves no truncated figure.
        tmp = p.with_name(f".{p.stem}.tmp{p.suffix}")
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format=p.suffix[1:])
        os.replace(tmp, p)
    plt.close(fig)
    return paths


def _ok(table: pd.DataFrame, **where: object) -> pd.DataFrame:
    mask = table["status"] == "ok"
    for k, v in where.items():
        mask &= table[k] == v
    return table[mask]


def _label(r: pd.Series) -> str:
    slant = "" if r["slant_deg"] == 0 else f" a{r['slant_dir_deg']:g}={r['slant_deg']:g}"
    return f"{r['shape']} {r['tiling']}{slant}"


def fig3_validation(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """Puncture force (N) against displacement (mm), E_s = 150 kPa, L = t = 2 mm."""
    from ..units import force_from_star
    from .paper_run import E_S_PA, L_M, NU_S

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for _, r in _ok(table, study="validation").iterrows():
        d = data[r["scene"]]
        F = force_from_star(1.0, E_S_PA, NU_S, L_M) * np.asarray(d["F_star"])
        name = "isolated" if r["rings"] == 0 else f"{r['n_scales']} scales"
        label = f"{name}, alpha0={r['slant_deg']:g}"
        ax.plot(np.asarray(d["w_star"]) * L_M * 1e3, F, "o-", ms=3, label=label)
    ax.set(xlabel="puncture displacement (mm)", ylabel="puncture force (N)", title="Validation scenes")
    _legend(ax)
    return _save(fig, out, "fig03_validation")


def fig4_isolated(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """F_c* of isolated scales against K_phi*/delta_c*, with the rigid estimate phi_c K_phi*/delta_c*."""
    t = _ok(table, study="isolated")
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    x = t["K_phi_star"] / t["delta_c_star"]
    ax.plot(x, t["Fc_star"], "o")
    for xi, yi, s in zip(x, t["Fc_star"], t["shape"]):
        ax.annotate(s, (xi, yi), textcoords="offset points", xytext=(4, 4))
    if len(t):
        xs = np.linspace(0, 1.1 * x.max(), 2)
        ax.plot(xs, np.deg2rad(13.0) * xs, "k--", lw=0.8, label="phi_c K_phi*/delta_c*")
        _legend(ax)
    ax.set(xlabel="K_phi* / delta_c*", ylabel="F_c*", title="Isolated scales (worst vertex)")
    return _save(fig, out, "fig04_isolated")


def _legend(ax: plt.Axes) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend()


def _bars(ax: plt.Axes, t: pd.DataFrame, group: str, series: list, column: str) -> None:
    labels = list(dict.fromkeys(t[group]))
    width = 0.8 / max(1, len(series))
    for k, (name, mask) in enumerate(series):
        sub = t[mask].set_index(group)[column]
        vals = [sub.get(g, np.nan) for g in labels]
        ax.bar(np.arange(len(labels)) + k * width, vals, width, label=name)
    ax.set_xticks(np.arange(len(labels)) + 0.4 - width / 2, labels, rotation=30, ha="right")
    _legend(ax)


def fig6a_interaction(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """Array F_c* over the isolated scale's, by interaction mode (blank: failed scene)."""
    t = table[table["study"] == "interaction"].copy()
    t["design"] = t["shape"] + " " + t["tiling"]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    _bars(ax, t, "design", [(m, t["interaction"] == m) for m in MODES], "ratio_iso")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set(ylabel="F_c / F_c (isolated)", title="Interaction modes (contact: f = 0.04)")
    return _save(fig, out, "fig06a_interaction")


def _patch_panel(ax: plt.Axes, design: Design, q: np.ndarray, colour: np.ndarray, arrows: bool) -> None:
    patch = design.patch()
    coll = PolyCollection(list(patch.base), array=colour, cmap="viridis", edgecolors="k", linewidths=0.3)
    ax.add_collection(coll)
    if arrows:
        c = patch.centroids
        ax.quiver(c[:, 0], c[:, 1], q[:, 0], q[:, 1], color="r", angles="xy")
    ax.plot(*patch.centroids[0], "r*", ms=8)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    plt.colorbar(coll, ax=ax, shrink=0.7)


def _field_grid(t: pd.DataFrame, data: dict, out: Path, name: str, inplane: bool) -> list[Path]:
    n = max(1, len(t))
    cols = min(4, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.4 * rows), squeeze=False)
    for ax, (_, r) in zip(axes.flat, t.iterrows()):
        q = np.asarray(data[r["scene"]]["q_final"])
        design = Design(
            r["shape"],
            r["tiling"],
            r["slant_deg"],
            r["slant_dir_deg"],
            r["gap"],
            r["thickness"],
            int(r["rings"]),
        )
        colour = np.hypot(q[:, 0], q[:, 1]) if inplane else -q[:, 2]
        _patch_panel(ax, design, q, colour, inplane)
        c0 = design.patch().centroids[0]
        for dx, dy in data[r["scene"]].get("effective_neighbours", []) if not inplane else []:
            ax.plot(c0[0] + dx, c0[1] + dy, "o", color="orange")
        ax.set_title(_label(r), fontsize=8)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    return _save(fig, out, name)


def fig6b_displacement(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """Downward displacement -u_z* of every scale at failure (full interaction), effective neighbours."""
    return _field_grid(_ok(table, study="interaction", interaction="full"), data, out, "fig06b_uz", False)


def fig7_inplane(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """In-plane displacement (arrows, colour |u|) at failure: rows that slide or interlock."""
    return _field_grid(_ok(table, study="interaction", interaction="full"), data, out, "fig07_inplane", True)


def fig9b_inplane(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    t = _ok(table, study="slant")
    return _field_grid(t[t["rings"] > 0], data, out, "fig09b_inplane", True)


def fig9a_slant(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """F_c* of every design at slant 0 and 60 deg towards 0, 45, 90 deg (full interaction)."""
    flat = table[(table["study"] == "interaction") & (table["interaction"] == "full")]
    t = pd.concat([flat, table[(table["study"] == "slant") & (table["rings"] > 0)]]).copy()
    t["design"] = t["shape"] + " " + t["tiling"]
    series = [("alpha = 0", t["slant_deg"] == 0)]
    for d in sorted(set(t.loc[t["slant_deg"] > 0, "slant_dir_deg"])):
        series.append((f"alpha_{d:g} = 60", (t["slant_deg"] > 0) & (t["slant_dir_deg"] == d)))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    _bars(ax, t, "design", series, "Fc_star")
    ax.set(ylabel="F_c*", title="Slant 60 deg, full interaction (worst vertex)")
    return _save(fig, out, "fig09a_slant")


def fig11_flexure_validation(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """Three-point bending force (N) against deflection (mm), E_m = 700 kPa, L = t = 2 mm."""
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for _, r in _ok(table, study="flexure_validation").iterrows():
        d = data[r["scene"]]
        ax.plot(
            d["deflection_mm"],
            d["force_N"],
            "o-",
            ms=3,
            label=f"alpha0={r['slant_deg']:g}, load line {r['load_line']}",
        )
    ax.set(xlabel="deflection (mm)", ylabel="force (N)", title="Flexure validation scenes")
    _legend(ax)
    return _save(fig, out, "fig11_flexure_validation")


def fig12_compliance(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """C_f* of every design for both load lines; the bare membrane as a line."""
    t = table[(table["study"] == "flexure") & (table["flex_mode"] != "bare")].copy()
    t["design"] = [
        f"{r['shape']} isolated" if r["flex_mode"] == "isolated" else _label(r) for _, r in t.iterrows()
    ]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    _bars(ax, t, "design", [(f"load line {ln}", t["load_line"] == ln) for ln in ("x", "y")], "Cf_star")
    for _, r in _ok(table, study="flexure", flex_mode="bare").iterrows():
        ax.axhline(r["Cf_star"], ls="--", lw=0.8, color="k")
    ax.set(ylabel="C_f*", title="Flexural compliance (dashed: bare membrane)")
    return _save(fig, out, "fig12_compliance")


#: Columns of a design's patch-size estimate carried into its Ashby point (empty without one).
PATCH_COLUMNS = ["ratio_iso_patch", "ratio_iso_patch_err", "patch_verdict"]


def ashby_points(table: pd.DataFrame) -> pd.DataFrame:
    """Designs with both a puncture ratio (full interaction) and C_f* (mean of the two load lines),
    with the patch-size study's estimate of the ratio where the design has one (``PATCH_COLUMNS``)."""
    keys = ["shape", "tiling", "slant_deg", "slant_dir_deg"]
    punct = _ok(table, kind="puncture", interaction="full")
    punct = punct[(punct["rings"] > 0) & punct["study"].isin(["interaction", "slant"])]
    flex = _ok(table, study="flexure", flex_mode="scaled").groupby(keys, as_index=False)["Cf_star"].mean()
    iso = _ok(table, study="flexure", flex_mode="isolated").groupby("shape", as_index=False)["Cf_star"].mean()
    pts = punct[keys + ["ratio_iso"]].merge(flex, on=keys)
    patch = _ok(table, kind="patch", interaction="full")
    patch = patch.reindex(columns=keys + PATCH_COLUMNS).drop_duplicates(keys)
    pts = pts.merge(patch, on=keys, how="left")
    iso = iso.assign(ratio_iso=1.0, tiling="isolated", slant_deg=0.0, slant_dir_deg=0.0)
    return pd.concat([pts, iso[keys + ["ratio_iso", "Cf_star"]]], ignore_index=True)


def _ashby_panel(ax, pts: pd.DataFrame, label_size: float, patch: bool = True) -> None:
    """The points of ``pts`` on ``ax``: the 5x5 ratio filled and, with ``patch``, the patch-size
    estimate beside it."""
    for _, r in pts.iterrows():
        iso = r["tiling"] == "isolated"
        (dot,) = ax.plot(r["Cf_star"], r["ratio_iso"], "s" if iso else "o", color="grey" if iso else None)
        big = r.get("ratio_iso_patch", np.nan)
        if patch and not iso and np.isfinite(big):
            rising = big > r["ratio_iso"]
            marker = {"not converged": "^" if rising else "v"}.get(r["patch_verdict"], "o")
            err = r["ratio_iso_patch_err"] if np.isfinite(r["ratio_iso_patch_err"]) else None
            x = r["Cf_star"]
            ax.plot([x, x], [r["ratio_iso"], big], ":", lw=0.8, color=dot.get_color())
            ax.errorbar(x, big, yerr=err, fmt=marker, mfc="none", color=dot.get_color(), capsize=2)
        slant = "" if r["slant_deg"] == 0 else f" a{r['slant_dir_deg']:g}"
        ax.annotate(
            f"{r['shape']} {r['tiling']}{slant}",
            (r["Cf_star"], r["ratio_iso"]),
            fontsize=label_size,
            xytext=(3, 3),
            textcoords="offset points",
        )


def fig13_ashby(table: pd.DataFrame, data: dict, out: Path) -> list[Path]:
    """Normalised puncture resistance against normalised flexural compliance: (a) every design on
    the paper's 5x5 patch, as the paper draws it; (b) the unslanted and (c) the slanted arrays, with
    the patch-size study's estimate of the skin beside each 5x5 point (open circle: converged or
    extrapolated, with its error bar; a triangle: the largest patch, not converged, pointing the
    way the sequence last moved)."""
    pts = ashby_points(table)
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    arrays = pts["tiling"] != "isolated"
    panels = [
        ("(a) Every design, 5x5 patch", pts, 6, False),
        (
            "(b) Unslanted arrays: 5x5 (filled), larger patches (open)",
            pts[arrays & (pts["slant_deg"] == 0)],
            7,
            True,
        ),
        (
            "(c) Slanted arrays: 5x5 (filled), larger patches (open)",
            pts[arrays & (pts["slant_deg"] > 0)],
            6,
            True,
        ),
    ]
    for ax, (title, sub, size, patch) in zip(axes, panels):
        _ashby_panel(ax, sub, size, patch)
        ax.set(
            xlabel="C_f* (mean of load lines x, y)", ylabel="F_c / F_c (isolated, same geometry)", title=title
        )
    fig.tight_layout()
    return _save(fig, out, "fig13_ashby")


FIGURES = (
    fig3_validation,
    fig4_isolated,
    fig6a_interaction,
    fig6b_displacement,
    fig7_inplane,
    fig9a_slant,
    fig9b_inplane,
    fig11_flexure_validation,
    fig12_compliance,
    fig13_ashby,
)


def all_figures(table: pd.DataFrame, data: dict, out: str | Path) -> list[Path]:
    """Draw every figure into ``out``; returns the PNG and SVG paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return [p for f in FIGURES for p in f(table, data, out)]
