"""The sweep file (qpscale/studies/sweep.py) and the results table (qpscale/studies/sweep_run.py),
without a cluster: parsing, ranges named by key, grid and random expansion, design keys, the
journal a killed run leaves, and the command line's exit 2.  The runs on Dask are in
tests/test_sweep_dask.py."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from qpscale.cli import app
from qpscale.errors import InvalidDesign
from qpscale.studies.engine import Engine, check_workers
from qpscale.studies.sweep import MAX_DESIGNS, load_spec, parse_spec
from qpscale.studies.sweep_run import ResultTable, run_sweep


def test_grid_is_the_cartesian_product_with_defaults_filled_in():
    spec = parse_spec(
        {
            "parameters": {
                "shape": ["square", "triangle"],
                "slant_deg": {"min": 0, "max": 60, "num": 3},
                "rings": {"min": 0, "max": 1},
            }
        }
    )
    assert spec.experiment == "puncture" and spec.sample == "grid"
    assert len(spec.designs) == 2 * 3 * 2
    slants = sorted({d.params["slant_deg"] for d in spec.designs})
    assert slants == [0.0, 30.0, 60.0]  # linspace points, rounded to 10 digits: exact here
    first = spec.designs[0].params
    # API defaults (docs/cli.md): gap 0.005 L, t = L, full interaction (f = 1), phi_c = 13 deg.
    assert (first["gap"], first["thickness"], first["interaction"], first["coupling_factor"]) == (
        0.005,
        1.0,
        "full",
        1.0,
    )
    assert first["tiling"] == "arrayed" and all(not d.invalid for d in spec.designs)


def test_equal_designs_are_run_once_and_keys_name_every_parameter():
    # The coupling axis applies to contact/substrate; the full interaction is f = 1: one design.
    spec = parse_spec(
        {"parameters": {"interaction": ["full", "contact"], "coupling_factor": [0.04, 0.5], "rings": 0}}
    )
    keys = [d.key for d in spec.designs]
    assert len(keys) == 3 and len(set(keys)) == 3
    assert sum("interaction=full" in k for k in keys) == 1
    assert all(k.startswith("puncture shape=square tiling=arrayed") for k in keys)


def test_invalid_combination_is_kept_as_a_design_with_its_reason():
    spec = parse_spec({"parameters": {"shape": "hexagon", "tiling": ["honeycomb", "arrayed"], "rings": 0}})
    good, bad = spec.designs
    assert not good.invalid and "not a tiling of shape='hexagon'" in bad.invalid


def test_random_sample_is_reproducible_in_range_and_rounded():
    table = {
        "random": {"n": 50, "seed": 3},
        "parameters": {
            "slant_deg": {"min": 0, "max": 60},
            "rings": {"min": 0, "max": 2},
            "shape": ["square"],
        },
    }
    a, b = parse_spec(table), parse_spec(table)
    assert [d.key for d in a.designs] == [d.key for d in b.designs]
    slants = np.array([d.params["slant_deg"] for d in a.designs])
    rings = {d.params["rings"] for d in a.designs}
    assert slants.min() >= 0.0 and slants.max() <= 60.0 and rings == {0, 1, 2}
    # Six significant digits: the value run is the value written in the key and the table.
    assert all(float(f"{x:.6g}") == x for x in slants)
    other = parse_spec({**table, "random": {"n": 50, "seed": 4}})
    assert [d.key for d in other.designs] != [d.key for d in a.designs]


@pytest.mark.parametrize(
    ("table", "key", "allowed"),
    [
        ({"parameters": {"slant_deg": [0, 95]}}, "parameters.slant_deg", "[0, 90) deg"),
        ({"parameters": {"gap": {"min": 0, "max": 1.5, "num": 2}}}, "parameters.gap", "[0, 1) L"),
        ({"parameters": {"rings": [1, 2.5]}}, "parameters.rings", "integers in [0, 50]"),
        ({"parameters": {"shape": "circle"}}, "parameters.shape", "square"),
        ({"parameters": {"slant": [0]}}, "parameters.slant", "slant_deg"),
        ({"parameters": {"mesh_h": 1.0}}, "parameters.mesh_h", "the parameters of puncture"),
        ({"parameters": {"rings": 1}, "experiment": "bend"}, "experiment", "puncture, flexure"),
        ({"parameters": {"gap": {"min": 0, "max": 0.1}}}, "parameters.gap", "num"),
        ({"parameters": {"gap": {"min": 0.2, "max": 0.1, "num": 2}}}, "parameters.gap", "min <= max"),
        ({"random": {"n": 0}}, "random.n", "integers in [1, 100000]"),
        ({"random": {"size": 3}}, "random", "n = designs"),
        ({"time_limit_s": -1}, "time_limit_s", "[0, inf) s"),
        ({"grid": {}}, "grid", "parameters"),
        ({"parameters": {"solver": "nonesuch"}}, "parameters.solver", "clarabel"),
        ({"parameters": {"probe": "yes"}}, "parameters.probe", "true or false"),
    ],
)
def test_bad_value_names_its_key_and_range(table, key, allowed):
    with pytest.raises(InvalidDesign) as info:
        parse_spec(table)
    assert info.value.parameter == key and allowed in str(info.value)


def test_grid_larger_than_the_limit_is_refused():
    big = {
        "parameters": {
            "gap": {"min": 0, "max": 0.5, "num": 1000},
            "slant_deg": {"min": 0, "max": 60, "num": 101},
        }
    }
    with pytest.raises(InvalidDesign, match=f"at most {MAX_DESIGNS}"):
        parse_spec(big)


def test_flexure_sweep_takes_its_own_parameters():
    spec = parse_spec(
        {"experiment": "flexure", "parameters": {"load_line": ["x", "y"], "mode": "isolated", "mesh_h": 1.0}}
    )
    assert [d.params["load_line"] for d in spec.designs] == ["x", "y"]
    with pytest.raises(InvalidDesign, match="parameters.rings"):
        parse_spec({"experiment": "flexure", "parameters": {"rings": 1}})


def test_toml_file_is_read(tmp_path):
    path = tmp_path / "grid.toml"
    path.write_text('experiment = "puncture"\n[parameters]\nshape = ["square", "hexagon"]\nrings = 0\n')
    assert [d.params["tiling"] for d in load_spec(path).designs] == ["arrayed", "honeycomb"]
    path.write_text("[parameters\n")
    with pytest.raises(InvalidDesign, match="not valid TOML") as info:
        load_spec(path)
    assert info.value.parameter == "grid"


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[parameters]\nslant_deg = [0, 95]\n", "error: parameters.slant_deg: "),
        ("[parameters]\nthickness = {min = 0, max = 2, num = 3}\n", "error: parameters.thickness: "),
        ("[parameters\n", "error: grid: "),
    ],
)
def test_cli_bad_grid_exits_2_naming_the_key(tmp_path, text, needle):
    grid = tmp_path / "grid.toml"
    grid.write_text(text)
    result = CliRunner().invoke(app, ["sweep", str(grid), "--out", str(tmp_path / "r.parquet")])
    assert result.exit_code == 2, result.output
    assert needle in result.output and len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "r.parquet").exists()


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--workers", "0"], "--workers"),
        (["--workers", "1", "--scheduler", "tcp://127.0.0.1:1"], "--scheduler and --workers"),
        (["--out", "{tmp}/r.csv"], "--out"),
    ],
)
def test_cli_bad_options_exit_2(tmp_path, args, flag):
    grid = tmp_path / "grid.toml"
    grid.write_text("[parameters]\nrings = 0\n")
    args = [a.format(tmp=tmp_path) for a in args]
    result = CliRunner().invoke(app, ["sweep", str(grid), *args])
    assert result.exit_code == 2 and f"error: {flag}" in result.output, result.output


def test_workers_out_of_range_rejected():
    with pytest.raises(InvalidDesign, match="workers"):
        check_workers(0)
    with pytest.raises(InvalidDesign, match="workers"):
        Engine(10_000)


def _row(key: str, status: str = "ok", **extra) -> dict:
    return {"key": key, "experiment": "puncture", "status": status, "error": None, **extra}


def test_killed_run_keeps_its_rows_through_the_journal(tmp_path):
    path = tmp_path / "r.parquet"
    table = ResultTable(path, rewrite_spacing=0.0)
    table.add(_row("a", Fc_star=1.5))
    assert len(pd.read_parquet(path)) == 1 and not table.journal.exists()  # rewritten at once
    # Make the next rewrite not due (as for a large table), then "kill": no close().
    table.rewrite_spacing = 1e12
    table.add(_row("b", "time_limit", error="stopped at the wall-time limit of 1 s"))
    assert len(pd.read_parquet(path)) == 1 and table.journal.exists()
    again = ResultTable(path)  # the next run folds the journal in
    assert set(again.rows) == {"a", "b"} and not again.journal.exists()
    back = pd.read_parquet(path).set_index("key")
    assert back.loc["b", "status"] == "time_limit" and pd.isna(back.loc["b", "Fc_star"])
    assert back.loc["a", "Fc_star"] == 1.5


def test_invalid_designs_are_recorded_without_a_worker(tmp_path):
    # One worker and no scheduler: the engine runs here; the invalid combination never reaches it.
    spec = parse_spec({"parameters": {"shape": "hexagon", "tiling": "arrayed", "rings": 0}})
    with Engine(1) as engine:
        result = run_sweep(spec, tmp_path / "r.parquet", engine)
    assert result.statuses == {"invalid_design": 1} and result.n_run == 1
    row = pd.read_parquet(tmp_path / "r.parquet").iloc[0]
    assert row["status"] == "invalid_design" and "not a tiling" in row["error"]


def test_flexure_sweep_rows_equal_the_api_runs(tmp_path):
    # Coarse membrane (h = L), one scale: about a second per design, here in this process.
    from qpscale import api

    spec = parse_spec(
        {"experiment": "flexure", "parameters": {"mode": "isolated", "mesh_h": 1.0, "load_line": ["x", "y"]}}
    )
    with Engine(1) as engine:
        result = run_sweep(spec, tmp_path / "r.parquet", engine)
    assert result.statuses == {"ok": 2}
    table = pd.read_parquet(tmp_path / "r.parquet").set_index("key")
    for point in spec.designs:
        p = dict(point.params)
        serial = api.flexure(**{k: x for k, x in p.items() if k != "mode"}, isolated=True)
        # Same code, same input, same process: equal to round-off (1e-9 relative).
        assert table.loc[point.key, "Cf_star"] == pytest.approx(serial.Cf_star, rel=1e-9)


def test_an_output_that_is_not_a_sweep_table_is_refused(tmp_path):
    other = tmp_path / "other.parquet"
    pd.DataFrame({"x": [1.0]}).to_parquet(other)
    broken = tmp_path / "broken.parquet"
    broken.write_bytes(b"not parquet")
    for path, detail in ((other, "no column 'key'"), (broken, "a table written by qpscale sweep")):
        with pytest.raises(InvalidDesign, match=detail) as info:
            ResultTable(path)
        assert info.value.parameter == "out"


def test_an_edges_axis_and_a_table_written_before_it_existed(tmp_path):
    # A table written before the sweep knew `edges` has no such column and keys that do not name
    # it. Such a table must resume: the design that ran then (K0 everywhere, "clamped") has the same
    # key now and is skipped, while `edges = "local"` is a new design. An isolated scale has no
    # edge neighbourhood, so both give the same F_c* exactly (test_cli has the 3x3 that differs).
    out = tmp_path / "r.parquet"
    with Engine(1) as engine:
        run_sweep(parse_spec({"parameters": {"rings": 0}}), out, engine)
    old = pd.read_parquet(out).drop(columns="edges")
    assert "edges" not in old.iloc[0]["key"]
    old.to_parquet(out, index=False)
    spec = parse_spec({"parameters": {"rings": 0, "edges": ["clamped", "local"]}})
    with Engine(1) as engine:
        result = run_sweep(spec, out, engine)
    assert (result.n_run, result.n_skipped) == (1, 1)
    table = pd.read_parquet(out).set_index("key")
    local = table.loc[[k for k in table.index if "edges=local" in k][0]]
    clamped = table.loc[old.iloc[0]["key"]]
    assert local["edges"] == "local" and local["Fc_star"] == clamped["Fc_star"]


def test_the_command_line_fuzz_file_draws_every_design_kind_at_the_command_lines_settings():
    # docs/fuzz_command_line.toml (README, "What still fails"): its designs must be what
    # `qpscale puncture --rings 1` runs, so that a failure there is a failure of the command.
    from pathlib import Path

    from qpscale.studies.sweep import defaults

    spec = load_spec(Path(__file__).parents[1] / "docs" / "fuzz_command_line.toml")
    valid = [d for d in spec.designs if not d.invalid]
    assert len(spec.designs) == 1000 and len(valid) == 374
    kinds = {(d.params["shape"], d.params["tiling"]) for d in valid}
    assert len(kinds) == 8  # three shapes in two tilings, the dart and the hexagon in one
    command = defaults("puncture")
    fixed = ("interaction", "solver", "formulation", "accuracy", "phi_c_deg", "nu", "probe", "edges")
    for d in valid:
        assert d.params["rings"] == 1
        assert all(d.params[k] == command[k] for k in fixed)
