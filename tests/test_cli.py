"""The command line: JSON contract of docs/cli.md and exit status 2 on bad input."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from qpscale import __version__
from qpscale.cli import app

runner = CliRunner()


def run(*args: str):
    return runner.invoke(app, list(args))


def test_version():
    result = run("--version")
    assert result.exit_code == 0 and __version__ in result.stdout


def test_geometry_json_contract():
    result = run("geometry", "--json")
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert {"base_area", "n_scales", "min_gap", "max_overlap_area", "top_offset"} <= set(data)
    assert data["n_scales"] == 25
    assert data["base_area"] == pytest.approx(4.0, rel=1e-12)
    assert data["min_gap"] == pytest.approx(0.005, abs=1e-9)
    assert data["max_overlap_area"] == 0.0


def test_geometry_slanted_offset_and_png(tmp_path):
    png = tmp_path / "patch.png"
    result = run(
        "geometry", "--shape", "dart", "--slant", "60", "--slant-dir", "90", "--png", str(png), "--json"
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    # t tan(60 deg) along +y, t = 1.
    assert data["top_offset"] == pytest.approx([0.0, 3**0.5], abs=1e-12)
    assert png.stat().st_size > 1000


def test_geometry_human_summary():
    result = run("geometry", "--shape", "hexagon")
    assert result.exit_code == 0 and "19 scales" in result.stdout


@pytest.mark.parametrize(
    "args,flag",
    [
        (["--shape", "circle"], "--shape"),
        (["--shape", "hexagon", "--tiling", "arrayed"], "--tiling"),
        (["--tiling", "spiral"], "--tiling"),
        (["--slant", "90"], "--slant"),
        (["--slant", "-5"], "--slant"),
        (["--gap", "-0.01"], "--gap"),
        (["--thickness", "0"], "--thickness"),
        (["--rings", "-1"], "--rings"),
    ],
)
def test_bad_input_exits_2_with_one_line(args, flag):
    result = run("geometry", *args)
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {flag}")


def test_an_unknown_option_is_named_without_another_commands_range():
    # --rings is puncture's; substrate has none, and puncture's range appended to the error misled.
    result = run("substrate", "--rings", "1")
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: --rings: No such option")
    assert "allowed" not in lines[0]


@pytest.mark.parametrize(
    "args, start",
    [
        (["--condense", "yes"], "error: --condense"),
        (["--condense", "on", "--solver", "penalty"], "error: --solver and --condense"),
    ],
)
def test_puncture_refuses_a_bad_condense_naming_the_flags(args, start):
    # A value outside {auto, on, off}, and an explicit choice with the penalty baseline (which
    # solves no QP): exit 2 before any run, one line naming the flags as the user typed them.
    result = run("puncture", *args)
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(start), lines


@pytest.mark.parametrize(
    "args, start",
    [
        (["--mesh", "octree"], "error: --mesh"),
        (["--mesh", "fitted", "--bare"], "error: --mesh and --bare"),
    ],
)
def test_flexure_refuses_a_bad_mesh_naming_the_flags(args, start):
    # Outside {tensor, fitted}, and the fitted mesh (which follows the scales' gaps) without scales:
    # exit 2 before any run, one line.
    result = run("flexure", *args)
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(start), lines


@pytest.mark.parametrize("shape, noted", [("triangle", True), ("square", False)])
def test_flexure_notes_oblique_gaps_the_tensor_mesh_leaves_unresolved(shape, noted):
    # The triangle's flanks are oblique: on the tensor mesh its gaps are about an element wide, and
    # the summary says so and names --mesh fitted; the square's gaps are grid lines.  (A coarse
    # isolated scale: the note depends on the design and the mesh, not on the run.)
    args = ("flexure", "--shape", shape, "--isolated", "--mesh-h", "1", "--no-error")
    result = run(*args)
    assert result.exit_code == 0, result.output
    assert ("--mesh fitted" in result.stdout) is noted
    data = json.loads(run(*args, "--json").stdout)
    assert data["mesh"] == "tensor" and data["oblique_edges"] is noted


@pytest.mark.parametrize("value", ["0", "-150e3"])
def test_puncture_rejects_nonpositive_substrate_modulus_before_running(value):
    # E_s <= 0 (issue #4's bad input) is refused up front: exit 2, one line naming the flag, and no
    # run (the CliRunner would otherwise spend seconds on the puncture path).
    result = run("puncture", "--E-s", value)
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: --E-s")


def test_json_stdout_holds_the_json_alone_whatever_a_c_library_prints(tmp_path):
    # HiGHS prints a banner from C++ to fd 1; with --json that would corrupt the output scripts
    # parse.  In a real process, bytes written to fd 1 during the command go to stderr and the
    # JSON object (here 200 kB, more than a pipe takes at once) alone to stdout.
    import subprocess
    import sys

    code = (
        "import os\n"
        "from qpscale.cli import json_stdout, emit\n"
        "with json_stdout():\n"
        "    os.write(1, b'Running HiGHS banner\\n')\n"
        "    print('a python print')\n"
        "    emit({'x': list(range(40000))}, True, None)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == {"x": list(range(40000))}
    assert "Running HiGHS banner" in out.stderr and "a python print" in out.stderr


def test_puncture_edges_local_softens_the_frame_and_leaves_an_isolated_scale_alone():
    # --edges local gives the scales on the patch's edge the self block of their own neighbourhood
    # (formulations/substrate.md eq. (18)) instead of K0, as if their absent neighbours were there
    # and clamped. The outer ring then stops acting as a stiff frame that the in-plane force chain
    # leans on, so the corner-loaded 3x3's F_c* falls, from 1.2250 to 1.0177 (substrate.md
    # secs. 9-10; the bound 0.9 leaves room for the increments). An isolated scale has no
    # neighbourhood to change, so both settings must give the same number to the last digit.
    def fc(*args: str) -> dict:
        result = run("puncture", *args, "--json")
        assert result.exit_code == 0, result.output
        return json.loads(result.stdout)

    clamped, local = fc("--rings", "1"), fc("--rings", "1", "--edges", "local")
    assert (clamped["edges"], local["edges"]) == ("clamped", "local")
    assert local["Fc_check"]["status"] == "verified"
    assert local["Fc_star"] < 0.9 * clamped["Fc_star"]
    assert fc("--isolated", "--edges", "local")["Fc_star"] == fc("--isolated")["Fc_star"]
