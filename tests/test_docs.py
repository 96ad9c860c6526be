"""docs/cli.md and docs/units.md against the code: the contract in the repository cannot drift.

Every flag the page documents must exist on its command with the range the page states (the
ranges come from ``cli.RANGES``, which the help texts and the one-line parse errors also use), every
flag of a command must be documented, and the JSON of every command must hold the fields the page
lists.  Nothing in the repository may point at the developers' SPEC.md, which users never see.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import typer.main
from typer.testing import CliRunner

from qpscale.cli import RANGES, app

ROOT = Path(__file__).resolve().parents[1]
CLI_MD = (ROOT / "docs" / "cli.md").read_text()
COMMANDS = ("geometry", "substrate", "puncture", "flexure", "paper", "bench", "sweep")


def _section(command: str, title: str) -> list[list[str]]:
    """Rows (cells) of the table under '### title' of '## qpscale command'."""
    body = CLI_MD.split(f"## qpscale {command}\n", 1)[1].split("\n## ", 1)[0]
    table = body.split(f"### {title}\n", 1)[1].split("\n### ", 1)[0]
    rows = []
    for line in table.splitlines():
        if line.startswith("| `"):
            rows.append([c.strip() for c in line.strip().strip("|").split(" | ")])
    return rows


def _documented_flags(command: str) -> dict[str, str]:
    return {row[0].strip("`"): row[2] for row in _section(command, "Flags")}


def _documented_fields(command: str) -> tuple[set[str], set[str]]:
    """(always present, present only with an option) field names of a command's JSON."""
    always, optional = set(), set()
    for row in _section(command, "JSON fields"):
        names = set(re.findall(r"`([A-Za-z_]+)`", row[0]))
        (optional if "only with" in row[-1] else always).update(names)
    return always, optional


def _command_flags(command: str) -> dict[str, str]:
    cmd = typer.main.get_command(app).commands[command]  # type: ignore[attr-defined]
    out = {}
    for p in cmd.params:
        if p.name == "help":
            continue
        flag = max(p.opts, key=len)
        name = flag + ("/" + p.secondary_opts[0] if p.secondary_opts else "")
        out[name] = RANGES.get(flag, "flag" if getattr(p, "is_flag", False) else "")
    return out


@pytest.mark.parametrize("command", COMMANDS)
def test_every_flag_documented_with_its_range_and_none_invented(command):
    # Both directions: a flag the page names must exist (with the range the code enforces), and a
    # flag the code has must be on the page.
    assert _documented_flags(command) == _command_flags(command)


def _default_text(p) -> str:
    """A parameter's default as the page writes it: (none), on/off for a flag, else the value."""
    if getattr(p, "is_flag", False) or p.secondary_opts:
        return "on" if p.default else "off"
    return "(none)" if p.default is None else str(p.default)


@pytest.mark.parametrize("command", COMMANDS)
def test_every_documented_default_is_the_codes(command):
    # The page's default column against the command's own defaults (the --solver rows had said
    # clarabel after the default backend became PIQP).
    cmd = typer.main.get_command(app).commands[command]  # type: ignore[attr-defined]
    rows = {row[0].strip("`").split("/")[0]: row for row in _section(command, "Flags")}
    for p in cmd.params:
        if p.name == "help" or not p.opts:
            continue
        flag = max(p.opts, key=len)
        if flag not in rows:
            continue
        _, documented, _, meaning = rows[flag]
        if p.required:
            assert documented == "(required)", flag
        elif p.default is None and documented != "(none)":
            # resolved at run time (the workers): the page states the value, and so does the help
            assert f"default {documented})" in meaning or f"default: {documented})" in meaning, flag
        else:
            assert documented == _default_text(p), flag


@pytest.mark.parametrize("command", COMMANDS)
def test_every_documented_flag_is_in_the_help(command):
    result = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": "300"}, terminal_width=300)
    assert result.exit_code == 0
    for flag in _documented_flags(command):
        assert flag.split("/")[0] in result.stdout, flag


def _json(*args: str) -> dict:
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


@pytest.mark.parametrize(
    "command,args",
    [
        ("geometry", ()),
        ("geometry", ("--shape", "dart", "--slant", "60", "--rings", "1")),
        ("puncture", ("--isolated",)),
        ("flexure", ("--bare", "--mesh-h", "1")),
    ],
)
def test_json_holds_the_documented_fields(command, args):
    always, _ = _documented_fields(command)
    assert always <= set(_json(command, *args)), always - set(_json(command, *args))


def test_substrate_json_holds_the_documented_fields():
    always, _ = _documented_fields("substrate")
    full = _json("substrate", "--shape", "square")
    assert always <= set(full)
    isolated = _json("substrate", "--isolated")
    # K0 and the couplings need the multi-punch calibration that --isolated skips (stated on the page).
    assert {"isolated", "isolated_block", "shape", "nu"} <= set(isolated) and "K0" not in isolated
    assert {"offset", "K1", "ratio"} <= set(full["neighbours"][0])


def test_optional_fields_appear_with_their_option(tmp_path):
    _, optional = _documented_fields("puncture")
    data = _json("puncture", "--isolated", "--E-s", "150e3", "--L-mm", "2", "--vtk", str(tmp_path / "v"))
    # rings_auto comes with --rings auto, which excludes --isolated and --vtk: test_large_patch.py
    assert optional - {"rings_auto"} <= set(data)
    # units.md's worked example: E* L^2 = 150 kPa / 0.75 * (2 mm)^2 = 0.8 N, so F_c = 0.8 F_c*.
    assert data["Fc_N"] == pytest.approx(0.8 * data["Fc_star"], rel=1e-12)
    assert "0.8 N" in (ROOT / "docs" / "units.md").read_text()


def test_paper_and_bench_json_hold_the_documented_fields(tmp_path, monkeypatch):
    import pandas as pd

    import qpscale.studies.bench as bench
    import qpscale.studies.bench_report as report
    import qpscale.studies.paper_scenes as ps
    from qpscale.studies.paper_scenes import Scene

    iso = Scene("isolated", "puncture", "square", rings=0, increments=4)
    monkeypatch.setattr(ps, "paper_scenes", lambda quick: [iso])
    always, _ = _documented_fields("paper")
    assert always <= set(_json("paper", "--out", str(tmp_path / "p"), "--workers", "1"))
    # The bench on one cheap scene and one method; its stability map replaced by an empty one.
    monkeypatch.setattr(bench, "quick_scenes", lambda: [bench.Scene("iso", iso.design)])
    monkeypatch.setattr(bench, "default_methods", lambda quick: [bench.Method("clarabel", "clarabel")])
    monkeypatch.setattr(report, "stability_map", lambda *a, **k: pd.DataFrame({"success": []}))
    always, _ = _documented_fields("bench")
    data = _json("bench", "--quick", "--out", str(tmp_path / "b"))
    assert always <= set(data)
    assert {"name", "success_rate", "median_wall_s", "Fc_rel_error", "max_penetration"} <= set(
        data["methods"][0]
    )


def test_nothing_points_at_the_developers_spec():
    hits = []
    for path in [ROOT / "README.md", *ROOT.glob("qpscale/**/*.py"), *ROOT.glob("docs/*.md")]:
        if "SPEC.md" in path.read_text() or "SPEC " in path.read_text():
            hits.append(str(path.relative_to(ROOT)))
    assert hits == []
