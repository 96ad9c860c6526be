"""Property tests of the command line (hypothesis): random argument vectors never cost a traceback.

For argument vectors built from every flag of the cheap commands (``geometry``, ``substrate
--isolated``) and of ``puncture``/``flexure`` with random values (NaN, inf, huge, empty, wrong
types, conflicting flags): the exit status is 0, 2 or 3 (4 would be an internal error, i.e. a
bug), the output holds no traceback and no NaN, stderr holds at most one line, and each run
finishes within a bound.  ``puncture`` and ``flexure`` run with the numerics replaced by a stub
that fails with a solver status (exit 3): what is tested is that validation decides, fast, before
any work.
"""

from __future__ import annotations

import json
import re
import time
from unittest import mock

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from qpscale.cli import app
from qpscale.errors import SolverFailure

runner = CliRunner()
ALLOWED_EXIT = {0, 2, 3}
SECONDS = 20.0  # a generous bound for one in-process run on a loaded 2-core machine

WILD_NUMBERS = st.sampled_from(
    ["nan", "-nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "0", "-0", "", "abc", "1,5", "0x10", "1e999"]
)
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-(10**30), max_value=10**30).map(str),
    WILD_NUMBERS,
)
WORDS = st.sampled_from(
    ["square", "hexagon", "dart", "triangle", "trapezoid", "circle", "", "arrayed", "staggered",
     "chevron", "honeycomb", "x", "y", "z", "full", "contact", "substrate", "clarabel", "osqp",
     "penalty", "high", "1e-7", "qpsolvers:nope", "plane", "feature", "clamped", "local"]
)  # fmt: skip

NUMERIC_FLAGS = {
    "geometry": ["--slant", "--slant-dir", "--gap", "--thickness", "--rings"],
    "substrate": ["--nu", "--refinement", "--gap"],
    "puncture": ["--slant", "--slant-dir", "--gap", "--thickness", "--rings", "--coupling-factor", "--phi-c",
                 "--nu", "--E-s", "--L-mm", "--max-memory-gb", "--max-minutes", "--accuracy",
                 "--max-increments"],
    "flexure": ["--slant", "--slant-dir", "--gap", "--thickness", "--nu-m", "--mesh-h", "--max-memory-gb",
                "--max-minutes"],
}  # fmt: skip
WORD_FLAGS = {
    "geometry": ["--shape", "--tiling"],
    "substrate": ["--shape", "--tiling"],
    "puncture": ["--shape", "--tiling", "--interaction", "--solver", "--accuracy", "--edges"],
    "flexure": ["--shape", "--tiling", "--load-line", "--solver", "--formulation"],
}
SWITCHES = {
    "geometry": [],
    "substrate": ["--isolated"],
    "puncture": ["--isolated", "--no-probe"],
    "flexure": ["--isolated", "--bare"],
}


@st.composite
def argv(draw, command: str) -> list[str]:
    args: list[str] = [command]
    for _ in range(draw(st.integers(0, 4))):
        kind = draw(st.sampled_from(["number", "word", "switch", "point"]))
        if kind == "number":
            args += [draw(st.sampled_from(NUMERIC_FLAGS[command])), draw(NUMBERS)]
        elif kind == "word":
            args += [draw(st.sampled_from(WORD_FLAGS[command])), draw(WORDS | NUMBERS)]
        elif kind == "switch" and SWITCHES[command]:
            args.append(draw(st.sampled_from(SWITCHES[command])))
        elif kind == "point" and command == "puncture":
            args += ["--load-point", draw(NUMBERS), draw(NUMBERS)]
    if command == "substrate":
        args.append("--isolated")  # the multi-punch calibration is not cheap
    if command == "geometry":
        # Keep the patch small: the property is about validation, not about drawing 10^4 scales.
        args += ["--rings", draw(st.sampled_from(["0", "1", "2", "-1", "51", "1.5", "nan"]))]
    args += draw(st.sampled_from([[], ["--json"]]))
    return args


def _stub(*a, **k):
    raise SolverFailure("stub", "not run")


def check(args: list[str]) -> None:
    t0 = time.perf_counter()
    with (
        mock.patch("qpscale.experiments.puncture.run_puncture", _stub),
        mock.patch("qpscale.experiments.flexure.run_flexure", _stub),
    ):
        result = runner.invoke(app, args)
    elapsed = time.perf_counter() - t0
    assert result.exit_code in ALLOWED_EXIT, (args, result.exit_code, result.output, result.exception)
    assert result.exception is None or isinstance(result.exception, SystemExit), (args, result.exception)
    assert "Traceback" not in result.output, (args, result.output)
    assert len([ln for ln in result.stderr.splitlines() if ln.strip()]) <= 1, (args, result.stderr)
    assert elapsed < SECONDS, (args, elapsed)
    if result.exit_code == 0:
        assert not re.search(r"\bnan\b", result.stdout, re.IGNORECASE), (args, result.stdout)
        if "--json" in args:
            json.loads(result.stdout, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    else:
        assert result.stderr.startswith("error: "), (args, result.stderr)


PROPERTY = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@PROPERTY
@given(argv("geometry"))
def test_geometry_random_arguments(args):
    check(args)


@PROPERTY
@given(argv("substrate"))
def test_substrate_isolated_random_arguments(args):
    check(args)


@PROPERTY
@given(argv("puncture"))
def test_puncture_random_arguments_are_decided_before_work(args):
    check(args)


@PROPERTY
@given(argv("flexure"))
def test_flexure_random_arguments_are_decided_before_work(args):
    check(args)


def test_explicit_wild_vectors():
    # One of each kind the strategies draw, so a failure here names its class without shrinking.
    for args in (
        ["geometry", "--slant", "nan", "--json"],
        ["geometry", "--rings", "1e999"],
        ["geometry", "--rings", "100000000000000000000000000000000000"],
        ["geometry", "--shape", ""],
        ["substrate", "--isolated", "--nu", "inf"],
        ["substrate", "--isolated", "--refinement", "2.5"],
        ["puncture", "--load-point", "inf", "0"],
        ["puncture", "--accuracy", "1e999"],
        ["puncture", "--max-memory-gb", "-1"],
        ["flexure", "--mesh-h", "1e-320"],
        ["flexure", "--bare", "--isolated", "--shape", "circle"],
        ["--version"],
        [],
    ):
        check(args)
