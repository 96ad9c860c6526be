"""Tests of the benchmark metrics (qpscale/studies/bench.py): every number comes from the runs."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from qpscale.errors import InvalidDesign
from qpscale.penalty import PenaltySettings
from qpscale.studies.bench import FC_TOL, Method, Run, Scene, run_bench, shifted_geomean, summarise
from qpscale.tiling import Design

# Isolated scales (rings = 0): each curve takes well under a second, so the whole file stays fast.
SCENES = [Scene("iso_a0", Design(rings=0)), Scene("iso_a30", Design(rings=0, slant_deg=30.0))]
METHODS = [
    Method("clarabel", "clarabel"),
    Method("cvxpy", "cvxpy"),
    Method("penalty-k1e+03", "penalty", penalty=PenaltySettings(k_pen=1e3)),
    # Deliberately failing: one Newton step per level cannot converge a load level.
    Method("penalty-broken", "penalty", penalty=PenaltySettings(k_pen=1e3, max_iter=1)),
]
LIMIT = 30.0


@cache
def _result():
    return run_bench(SCENES, METHODS, time_limit=LIMIT)


def _row(name):
    return next(r for r in _result().summary if r["name"] == name)


def test_summary_has_contract_fields():
    res = _result()
    assert set(res.references) == {"iso_a0", "iso_a30"}
    for row in res.summary:
        for key in (
            "name",
            "success_rate",
            "median_wall_s",
            "Fc_rel_error",
            "max_penetration",
            "shifted_geomean_s",
            "complementarity",
            "qp_solves",
            "time_ratio_to_cvxpy",
        ):
            assert key in row
    assert len(res.runs) == len(SCENES) * len(METHODS)


def test_failing_method_counted_at_time_limit():
    row = _row("penalty-broken")
    assert row["success_rate"] == 0.0
    assert row["median_wall_s"] == LIMIT  # failures are timed at the limit (qpbenchmark)
    assert row["Fc_rel_error"] is None  # a failure is a status, never a number
    assert all("newton did not converge" in s for s in row["statuses"])
    runs = [r for r in _result().runs if r.method == "penalty-broken"]
    assert all("penalty" in r.detail and "did not converge" in r.detail for r in runs)  # the message


def test_successes_pass_checks_against_reference():
    # Isolated scale: no contact, every method solves the same equality-constrained problem, so F_c
    # agrees with the reference to the QP tolerance (1e-9 on residuals -> ~1e-8 relative on F_c).
    for name in ("clarabel", "cvxpy", "penalty-k1e+03"):
        row = _row(name)
        assert row["success_rate"] == 1.0
        assert row["Fc_rel_error"] < 1e-7
        assert row["max_penetration"] == 0.0


def test_ratio_is_ratio_of_measured_times():
    res = _result()
    t = {(r.method, r.scene): r.wall_s for r in res.runs}
    for name in ("clarabel", "penalty-k1e+03"):
        expect = np.exp(np.mean([np.log(t[(name, s.name)] / t[("cvxpy", s.name)]) for s in SCENES]))
        assert _row(name)["time_ratio_to_cvxpy"] == pytest.approx(expect, rel=1e-12)
    assert _row("cvxpy")["time_ratio_to_cvxpy"] == pytest.approx(1.0, rel=1e-12)
    times = [t[("clarabel", s.name)] for s in SCENES]
    assert _row("clarabel")["median_wall_s"] == pytest.approx(np.median(times), rel=1e-12)


def test_shifted_geomean_by_hand():
    # (1 + 10)(4 + 10) -> sqrt(154) - 10; shift 0 gives the plain geometric mean.
    assert shifted_geomean(np.array([1.0, 4.0])) == pytest.approx(np.sqrt(154.0) - 10.0, rel=1e-14)
    assert shifted_geomean(np.array([1.0, 4.0]), shift=0.0) == pytest.approx(2.0, rel=1e-14)


def test_summarise_applies_fc_error_and_time_limit():
    runs = [
        Run("m", "a", "solved", True, 2.0, 1.0, 0.5 * FC_TOL, 0.0, 0.0, 3),
        Run("m", "b", "max iter", False, 5.0, failure="solver"),
    ]
    row = summarise(runs, ["m"], time_limit=20.0)[0]
    assert row["success_rate"] == 0.5
    assert row["median_wall_s"] == pytest.approx(11.0)  # (2 + 20) / 2: the failure counts at the limit
    assert row["Fc_rel_error"] == pytest.approx(0.5 * FC_TOL)


def test_unknown_method_rejected():
    with pytest.raises(InvalidDesign, match="solver"):
        Method("x", "no-such-solver")


def test_fuzz_rows_pass_the_checks_or_carry_a_status(tmp_path, monkeypatch):
    # Every fuzz design ends in "pass" (finite F_c, overlap <= 1e-9 L) or a named failure; a
    # failure keeps the design's parameters and the solver's status, never a number.
    from qpscale.errors import SolverFailure
    from qpscale.studies import bench_report

    df = bench_report.fuzz(4, tmp_path, seed=3)  # seed 1 has a design at the 60 s limit
    assert len(df) == 4 and (tmp_path / "fuzz.csv").exists()
    assert set(df.outcome) <= {"pass", "check failed", "invalid design", "solver failure", "time limit"}
    passed = df[df.outcome == "pass"]
    assert len(passed) >= 1
    assert np.all(np.isfinite(passed.Fc_star)) and np.all(passed.max_penetration <= 1e-9)

    def broken(setup, progress=None):
        raise SolverFailure("clarabel", "MaxIterations", increment=2)

    import qpscale.experiments.puncture as puncture

    monkeypatch.setattr(puncture, "run_puncture", broken)
    bad = bench_report.fuzz(2, tmp_path / "bad", seed=1)
    assert list(bad.outcome) == ["solver failure"] * 2 and list(bad.status) == ["MaxIterations"] * 2
    assert "Fc_star" not in bad and bad["shape"].notna().all()
    # The tests' fuzz designs are drawn by number: the number reproduces the fuzz's own rows, in
    # the first chunk and past it (a chunk is 25 designs drawn from seed + chunk).
    many = bench_report.fuzz(bench_report.FUZZ_CHUNK + 3, tmp_path / "many", seed=1)
    drawn = many[many.outcome == "solver failure"]
    assert drawn["i"].max() >= bench_report.FUZZ_CHUNK
    for _, row in drawn.iterrows():
        design, extra, point = bench_report.fuzz_design_number(int(row["i"]), seed=1)
        assert (design.shape, design.slant_deg, design.gap, extra["nu"]) == (
            row["shape"],
            row["slant_deg"],
            row["gap"],
            row["nu"],
        )
        assert point == (row["load_x"], row["load_y"])
    # A finished chunk is read back, not rerun: the broken solver cannot change the first result.
    again = bench_report.fuzz(4, tmp_path, seed=3)
    assert list(again.outcome) == list(df.outcome)
    np.testing.assert_array_equal(again.Fc_star.to_numpy(), df.Fc_star.to_numpy())


def test_fuzz_on_two_workers_equals_the_serial_fuzz_and_compares_a_second_method(tmp_path, monkeypatch):
    # Chunk k draws its designs from seed + k, so two workers give the designs and answers of the
    # serial run (F_c to 1e-9: a path's step sequence can follow round-off, its F_c cannot).  The
    # second method (CVXPY, the same QP) is compared with the first on the same designs: F_c
    # within the QP tolerance (1e-9 residuals -> ~1e-7 relative), far below the 1 % of "Fc error".
    from qpscale.studies import bench_report

    monkeypatch.setattr(bench_report, "FUZZ_CHUNK", 2)
    methods = (Method("clarabel", "clarabel"), Method("cvxpy", "cvxpy"))
    par = bench_report.fuzz(4, tmp_path / "a", seed=7, methods=methods, n_others=2, workers=2)
    ser = bench_report.fuzz(2, tmp_path / "b", seed=7)
    first = par[par.method == "clarabel"]
    assert list(first.i) == [0, 1, 2, 3] and list(par[par.method == "cvxpy"].i) == [0, 1]
    np.testing.assert_array_equal(first.slant_deg.to_numpy()[:2], ser.slant_deg.to_numpy())
    assert list(first.outcome[:2]) == list(ser.outcome)
    np.testing.assert_allclose(first.Fc_star.to_numpy()[:2], ser.Fc_star.to_numpy(), rtol=1e-9)
    assert first.slant_deg.nunique() == 4  # chunk 1 (seed 8) is not a copy of chunk 0
    both = par[(par.method == "cvxpy") & (par.outcome == "pass")]
    assert len(both) >= 1 and np.all(both.Fc_rel_error < 1e-6)


def test_parallel_bench_equals_the_serial_one():
    # Two worker processes run the same (scene, method) tasks: identical statuses and F_c (each run
    # is deterministic and alone in its process), the runs in the serial order.
    par = run_bench(SCENES, METHODS[:2], time_limit=LIMIT, workers=2)
    ser = _result()
    assert [(r.scene, r.method) for r in par.runs] == [
        (r.scene, r.method) for r in ser.runs if r.method in ("clarabel", "cvxpy")
    ]
    for r in par.runs:
        s = next(x for x in ser.runs if (x.scene, x.method) == (r.scene, r.method))
        assert r.status == s.status and r.Fc_star == pytest.approx(s.Fc_star, rel=1e-9)
    for k, v in par.references.items():
        assert v.Fc_star == pytest.approx(ser.references[k].Fc_star, rel=1e-9)
    assert set(par.references) == set(ser.references)


def test_stability_point_runs_every_method_at_the_references_load_point():
    # The map's reference and its methods load the same top vertex: CVXPY solving the same QP must
    # then agree with Clarabel to the QP tolerance (at different vertices they differed by 20-30 %).
    from qpscale.studies.bench_report import _stability_point, stability_grid

    params, scene = stability_grid(quick=True)[0]
    assert scene.load_point == (1.0, 1.0)  # the square's +x corner
    iso = Scene("iso", Design(rings=0, slant_deg=30.0), "contact", 0.5, scene.load_point)
    rows = _stability_point(params, iso, [Method("cvxpy", "cvxpy")], LIMIT)
    assert [r["method"] for r in rows] == ["clarabel", "cvxpy"] and rows[1]["success"]
    assert rows[1]["Fc_rel_error"] < 1e-7


def test_workers_out_of_range_rejected():
    from qpscale.studies.engine import check_workers

    with pytest.raises(InvalidDesign, match="workers"):
        check_workers(0)


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--workers", "0"], "--workers"),
        (["--fuzz", "-1"], "--fuzz"),
        (["--time-limit", "0"], "--time-limit"),
    ],
)
def test_bench_cli_rejects_bad_options_with_exit_2(args, flag):
    from typer.testing import CliRunner

    from qpscale.cli import app

    bad = CliRunner().invoke(app, ["bench", "--quick", *args])
    assert bad.exit_code == 2 and flag in bad.output
