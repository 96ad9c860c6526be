"""The paper's stated findings beside the numbers of a results table (README, "Reproducing the paper").

Each finding is read from the table of ``paper.run_paper`` with the normalisations of
formulations/normalisation.md (array over isolated scale of the same geometry; slanted over the same
design unslanted); the patch-size rows read the sequences of formulations/puncture.md sec. 7.  Failed
scenes stay out of every number and are counted instead.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd


def _ok(t: pd.DataFrame) -> pd.DataFrame:
    return t[t["status"] == "ok"]


def _span(values: pd.Series, fmt: str = "{:.2f}") -> str:
    v = values.dropna()
    if not len(v):
        return "no converged scene"
    return fmt.format(v.min()) if len(v) == 1 else f"{fmt.format(v.min())} to {fmt.format(v.max())}"


def _interaction(t: pd.DataFrame, mode: str) -> pd.DataFrame:
    ok = _ok(t)
    return ok[(ok["study"] == "interaction") & (ok["interaction"] == mode)]


def _by_design(rows: pd.DataFrame, column: str) -> str:
    return ", ".join(f"{r['shape']} {r['tiling']} {r[column]:.2f}" for _, r in rows.iterrows()) or "none"


def arrays_raise(t: pd.DataFrame) -> str:
    full = _interaction(t, "full")
    return f"F_c/F_c,iso = {_span(full['ratio_iso'])} ({_by_design(full, 'ratio_iso')})"


def best_designs(t: pd.DataFrame) -> str:
    full = _interaction(t, "full").sort_values("ratio_iso", ascending=False)
    return "ranking: " + _by_design(full, "ratio_iso")


def substrate_only(t: pd.DataFrame) -> str:
    return f"contact off: {_span(_interaction(t, 'substrate')['ratio_iso'])}"


def contact_only(t: pd.DataFrame) -> str:
    return f"f = 0.04: {_span(_interaction(t, 'contact')['ratio_iso'])}"


def slant_doubles(t: pd.DataFrame) -> str:
    ok = _ok(t)
    s = ok[(ok["study"] == "slant") & (ok["rings"] > 0)]
    return f"F_c(alpha=60)/F_c(alpha=0) = {_span(s['ratio_unslanted'])}"


def square_slants(t: pd.DataFrame) -> str:
    ok = _ok(t)
    s = ok[
        (ok["study"] == "slant") & (ok["rings"] > 0) & (ok["shape"] == "square") & (ok["tiling"] == "arrayed")
    ]
    return (
        ", ".join(f"alpha_{r['slant_dir_deg']:g}: {r['ratio_unslanted']:.2f}" for _, r in s.iterrows())
        or "none"
    )


def dart_slanted(t: pd.DataFrame) -> str:
    ok = _ok(t)
    s = ok[
        (ok["study"] == "slant") & (ok["rings"] > 0) & (ok["shape"] == "dart") & (ok["slant_dir_deg"] == 0)
    ]
    return _span(s["ratio_iso"], "{:.1f}")


def isolated_lever(t: pd.DataFrame) -> str:
    ok = _ok(t)
    iso = ok[ok["study"] == "isolated"].sort_values("Fc_star", ascending=False)
    ratio = iso["Fc_star"] / iso["Fc_rigid_star"]
    order = ", ".join(f"{r['shape']} {r['Fc_star']:.3f}" for _, r in iso.iterrows())
    return f"{order}; F_c*/(phi_c K_phi*/delta_c*) = {_span(ratio, '{:.3f}')}"


def compliance_drop(t: pd.DataFrame) -> str:
    ok = _ok(t)
    fx = ok[ok["study"] == "flexure"]
    iso = fx[fx["flex_mode"] == "isolated"].groupby(["shape", "load_line"])["Cf_star"].mean()
    sc = fx[fx["flex_mode"] == "scaled"]
    drops = [
        1 - r["Cf_star"] / iso[(r["shape"], r["load_line"])]
        for _, r in sc.iterrows()
        if (r["shape"], r["load_line"]) in iso.index
    ]
    return f"C_f drop {_span(pd.Series(drops) * 100, '{:.0f}')} %"


def load_line_effect(t: pd.DataFrame) -> str:
    ok = _ok(t)
    sc = ok[(ok["study"] == "flexure") & (ok["flex_mode"] == "scaled") & (ok["slant_deg"] > 0)]
    sc = sc[sc["slant_dir_deg"].isin([0.0, 90.0])]
    piv = sc.pivot_table(index=["shape", "tiling", "slant_dir_deg"], columns="load_line", values="Cf_star")
    if piv.empty or not {"x", "y"} <= set(piv.columns):
        return "no converged pair"
    par = np.where(
        piv.index.get_level_values("slant_dir_deg") == 0.0, piv["x"] / piv["y"], piv["y"] / piv["x"]
    )
    return f"C_f(load line parallel to slant)/C_f(perpendicular) = {_span(pd.Series(par))}"


def _patch_sequences(t: pd.DataFrame, slanted: bool) -> str:
    """The 5x5 ratio against the patch-size study's estimate of the skin's, design by design
    (the unslanted or the slanted designs)."""
    ok = _ok(t)
    p = ok[(ok["kind"] == "patch") & ((ok["slant_deg"] > 0) == slanted)]
    if not len(p):
        return "not run"
    parts = []
    for _, r in p.iterrows():
        big = f"{r['ratio_iso_patch']:.2f}"
        if r["patch_verdict"] == "extrapolated":
            big += f" +- {r['ratio_iso_patch_err']:.2f}"
        elif r["patch_verdict"] == "converged":
            big += " (converged)"
        elif r["patch_verdict"] == "not converged":
            big += f" (not converged: {100 * r['patch_change']:.1f} % at the last ring)"
        slant = f" a{r['slant_dir_deg']:g}" if slanted else ""
        parts.append(f"{r['shape']} {r['tiling']}{slant} {r['ratio_iso']:.2f} -> {big}")
    return "5x5 -> larger patches: " + ", ".join(parts)


def patch_size(t: pd.DataFrame) -> str:
    """The unslanted designs' 5x5 ratios against their patch-size estimates."""
    return _patch_sequences(t, slanted=False)


def patch_size_slanted(t: pd.DataFrame) -> str:
    """The slanted designs' 5x5 ratios against their patch-size estimates."""
    return _patch_sequences(t, slanted=True)


FINDINGS: tuple[tuple[str, str, Callable[[pd.DataFrame], str]], ...] = (
    ("Fig. 4", "isolated: F_c* ~ phi_c K_phi*/delta_c*; dart and hexagon highest", isolated_lever),
    ("Fig. 6a", "arrays raise puncture resistance 4 to 8 times", arrays_raise),
    ("Fig. 6a", "hexagon and dart highest, 20-30 % above the rest", best_designs),
    ("Fig. 6a", "contact off: neighbours still stabilise strongly (substrate)", substrate_only),
    ("Fig. 6a", "contact with 4 % coupling: barely above the isolated scale", contact_only),
    ("Fig. 9a", "slant 60 deg roughly doubles F_c", slant_doubles),
    ("Fig. 9a", "square arrayed: alpha_45 = 60 is the best slant", square_slants),
    ("Fig. 13", "dart alpha_0 = 60: about 42 times the isolated scale", dart_slanted),
    ("Fig. 13", "(not in the paper) the 5x5 patch against larger ones", patch_size),
    ("Fig. 13", "(not in the paper) the same, slanted 60 deg", patch_size_slanted),
    ("Fig. 12", "scales cut flexural compliance by 85-93 % against the isolated scale", compliance_drop),
    ("Fig. 12", "load line parallel to the slant: more compliant", load_line_effect),
)


def findings_table(table: pd.DataFrame) -> pd.DataFrame:
    """One row per finding: figure, the paper's statement, our number from ``table``."""
    cols = "study kind shape tiling rings interaction flex_mode load_line slant_deg slant_dir_deg".split()
    cols += ["Fc_star", "Fc_rigid_star", "ratio_iso", "ratio_unslanted", "Cf_star"]
    cols += ["ratio_iso_patch", "ratio_iso_patch_err", "patch_verdict", "patch_change"]
    table = table.reindex(columns=list(dict.fromkeys([*table.columns, *cols])))
    rows = [{"figure": f, "paper": text, "ours": fn(table)} for f, text, fn in FINDINGS]
    failed = int((table["status"] != "ok").sum())
    rows.append({"figure": "-", "paper": "failed scenes (status kept in the table)", "ours": str(failed)})
    return pd.DataFrame(rows)


def write_findings(table: pd.DataFrame, out: str | Path) -> Path:
    """Write ``findings.md`` (a Markdown table) into ``out``."""
    f = findings_table(table)
    lines = ["| figure | paper | ours |", "|---|---|---|"]
    lines += [f"| {r['figure']} | {r['paper']} | {r['ours']} |" for _, r in f.iterrows()]
    path = Path(out) / "findings.md"
    path.write_text("\n".join(lines) + "\n")
    return path
