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

    df = bench_report.fuzz(4, tmp_path, seed=1)
    assert len(df) == 4 and (tmp_path / "fuzz.csv").exists()
    assert set(df.outcome) <= {"pass", "check failed", "invalid design", "solver failure", "time limit"}
    passed = df[df.outcome == "pass"]
    assert len(passed) >= 1
    assert np.all(np.isfinite(passed.Fc_star)) and np.all(passed.max_penetration <= 1e-9)

    def broken(setup, progress=None):
        raise SolverFailure("clarabel", "MaxIterations", increment=2)

    import qpscale.experiments.puncture as puncture

    monkeypatch.setattr(puncture, "run_puncture", broken)
    bad = bench_report.fuzz(2, tmp_path, seed=1)
    assert list(bad.outcome) == ["solver failure"] * 2 and list(bad.status) == ["MaxIterations"] * 2
    assert (
        "Fc_star" not in bad and bad.shape_.notna().all() if "shape_" in bad else bad["shape"].notna().all()
    )
