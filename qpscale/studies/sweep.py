"""The design grid of ``qpscale sweep``: a TOML file read, checked and expanded into designs, each
with a key that names it.

Implements no formulation: this is plumbing.  The file names the experiment (``puncture`` or
``flexure``, the functions of :mod:`qpscale.api`), how to sample (every combination, or ``n``
designs drawn with a seed) and, per parameter, one value, a list of values or a range::

    experiment = "puncture"        # or "flexure"
    time_limit_s = 600             # per design; 0: none (default 3600)

    [random]                       # absent: the grid of every combination
    n = 40
    seed = 1

    [parameters]
    shape = ["square", "hexagon"]
    slant_deg = {min = 0, max = 60, num = 4}   # a grid takes num points; a sample draws uniformly
    rings = {min = 0, max = 2}                 # integers: every one in a grid, uniform in a sample
    interaction = ["full", "contact"]
    coupling_factor = 0.04

Every value is checked against the range of its parameter (the API's ranges, docs/cli.md); an
error names the key (``parameters.slant_deg``) and the range.  Combinations that are not a design
(a tiling the shape does not have, a slant whose top face lies too far out) are kept as designs
whose status will say so, not run.  Parameters left out take the API's defaults.  Designs are
normalised before they are keyed: the shape's own tiling filled in, ``coupling_factor`` 1 for the
``full`` interaction (the coupling axis of a grid applies to ``substrate`` and ``contact``), no
accuracy for the penalty solver; equal designs are run once.
"""

from __future__ import annotations

import itertools
import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import validation as v
from ..errors import InvalidDesign
from ..solvers import DEFAULT_SOLVER

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

EXPERIMENTS = ("puncture", "flexure")
TOP_KEYS = ("experiment", "time_limit_s", "random", "parameters")
MAX_DESIGNS = 100_000
DEFAULT_TIME_LIMIT_S = 3600.0
# Significant digits kept of a real value: grid points (linspace round-off) to 10, drawn values to
# 6, so that the value run is exactly the value in the key and in the table.
GRID_DIGITS = 10
DRAW_DIGITS = 6

Check = Callable[[str, Any], Any]


def _real(lo: float | None, hi: float | None, unit: str = "", **open_: bool) -> Check:
    return lambda key, x: v.real(key, x, lo, hi, unit=unit, **open_)


def _int(lo: int, hi: int) -> Check:
    return lambda key, x: v.integer(key, x, lo, hi)


def _choice(*options: str) -> Check:
    return lambda key, x: v.choice(key, x, options)


def _bool(key: str, x: Any) -> bool:
    if not isinstance(x, bool):
        raise InvalidDesign(key, x, "true or false")
    return x


def _solver(key: str, x: Any) -> str:
    return _renamed(key, v.solver, x)


def _qp_solver(key: str, x: Any) -> str:
    return _renamed(key, v.qp_solver, x)


def _accuracy(key: str, x: Any) -> str | float:
    return _renamed(key, v.accuracy, x)


def _renamed(key: str, check: Callable[[Any], Any], x: Any) -> Any:
    """``check(x)``, its error naming ``key`` (the validators name their API parameter)."""
    try:
        return check(x)
    except InvalidDesign as exc:
        raise InvalidDesign(key, x, exc.allowed) from None


def _design_checks() -> dict[str, Check]:
    from ..geometry import SHAPES
    from ..tiling import TILINGS

    return {
        "shape": _choice(*SHAPES),
        "tiling": _choice(*TILINGS),
        "slant_deg": _real(0.0, 90.0, "deg", hi_open=True),
        "slant_dir_deg": _real(0.0, 360.0, "deg", hi_open=True),
        "gap": _real(0.0, 1.0, "L", hi_open=True),
        "thickness": _real(0.0, 100.0, "L", lo_open=True),
    }


def parameter_checks(experiment: str) -> dict[str, Check]:
    """Every parameter a sweep of ``experiment`` may set, with its range check, in key order."""
    from ..contact import FORMULATIONS
    from ..experiments.puncture import INTERACTIONS
    from ..substrate import EDGES

    checks = _design_checks()
    if experiment == "puncture":
        checks.update(
            {
                "rings": _int(0, v.MAX_RINGS),
                "interaction": _choice(*INTERACTIONS),
                "coupling_factor": _real(0.0, 1.0),
                "solver": _solver,
                "formulation": _choice(*FORMULATIONS),
                "accuracy": _accuracy,
                "phi_c_deg": _real(0.0, 60.0, "deg", lo_open=True),
                "nu": _real(0.0, 0.5),
                "probe": _bool,
                "edges": _choice(*EDGES),
            }
        )
    else:
        checks.update(
            {
                "load_line": _choice("x", "y"),
                "mode": _choice("scaled", "isolated"),
                "mesh_h": _real(*v.MESH_H_RANGE, "L"),
                "nu_m": _real(0.0, 0.5),
                "solver": _qp_solver,
                "formulation": _choice(*FORMULATIONS),
                "roller_radius": _real(0.0, 3.75, "L", lo_open=True, hi_open=True),
            }
        )
    return checks


def defaults(experiment: str) -> dict[str, Any]:
    """The API's default of every parameter (:func:`qpscale.api.puncture`, ``flexure``)."""
    from ..api import DEFAULT_RINGS, DESIGN_DEFAULTS

    out: dict[str, Any] = dict(DESIGN_DEFAULTS)
    if experiment == "puncture":
        out.update(
            rings=DEFAULT_RINGS,
            interaction="full",
            coupling_factor=None,
            solver=DEFAULT_SOLVER,
            formulation="plane",
            accuracy="high",
            phi_c_deg=13.0,
            nu=0.5,
            probe=True,
            edges="clamped",
        )
    else:
        out.update(
            load_line="x",
            mode="scaled",
            mesh_h=0.5,
            nu_m=0.5,
            solver=DEFAULT_SOLVER,
            formulation="plane",
            roller_radius=0.5,
        )
    return out


@dataclass(frozen=True)
class DesignPoint:
    """One design of a sweep: its key, its parameters (normalised) and, for a combination that is
    not a design, the reason (it is then recorded, not run)."""

    key: str
    experiment: str
    params: Mapping[str, Any]
    invalid: str = ""


@dataclass(frozen=True)
class SweepSpec:
    """A checked sweep file: the experiment, each design once (in grid or draw order), the time
    limit of one design in seconds (None: none) and how the designs were sampled."""

    experiment: str
    designs: tuple[DesignPoint, ...]
    time_limit_s: float | None
    sample: str = "grid"
    seed: int | None = None
    source: str = field(default="", compare=False)


def load_spec(path: str | Path) -> SweepSpec:
    """Read and check a sweep file (:class:`InvalidDesign` naming the key, also for bad TOML)."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise InvalidDesign("grid", str(p), "a readable TOML file", exc.strerror or str(exc)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InvalidDesign("grid", str(p), "", f"not valid TOML: {exc}") from None
    return parse_spec(data, source=str(p))


def parse_spec(data: Mapping[str, Any], source: str = "") -> SweepSpec:
    """Check a sweep's table and expand it into designs.

    >>> spec = parse_spec({"parameters": {"shape": ["square", "hexagon"], "rings": 0}})
    >>> [d.params["tiling"] for d in spec.designs]
    ['arrayed', 'honeycomb']
    """
    unknown = [k for k in data if k not in TOP_KEYS]
    if unknown:
        raise InvalidDesign(
            unknown[0], data[unknown[0]], "{" + ", ".join(TOP_KEYS) + "} (the keys of a sweep file)"
        )
    experiment = v.choice("experiment", data.get("experiment", "puncture"), EXPERIMENTS)
    limit = v.real("time_limit_s", data.get("time_limit_s", DEFAULT_TIME_LIMIT_S), 0.0, None, unit="s")
    params = data.get("parameters", {})
    if not isinstance(params, Mapping):
        raise InvalidDesign("parameters", params, "a table of parameter = value, [values] or {min, max}")
    checks = parameter_checks(experiment)
    for key in params:
        if key not in checks:
            raise InvalidDesign(
                f"parameters.{key}",
                params[key],
                "{" + ", ".join(checks) + f"}} (the parameters of {experiment})",
            )
    sample = data.get("random")
    if sample is None:
        axes = {k: _grid_values(k, params[k], checks[k]) for k in checks if k in params}
        size = math.prod(len(x) for x in axes.values())
        if size > MAX_DESIGNS:
            raise InvalidDesign("parameters", f"{size} combinations", f"at most {MAX_DESIGNS} designs")
        points = [dict(zip(axes, combo)) for combo in itertools.product(*axes.values())]
        seed = None
    else:
        n, seed = _sample_size(sample)
        points = _draw(params, checks, n, seed)
    designs: dict[str, DesignPoint] = {}
    for given in points:
        point = normalise(experiment, given)
        designs.setdefault(point.key, point)
    return SweepSpec(
        experiment,
        tuple(designs.values()),
        limit or None,
        "grid" if sample is None else "random",
        seed,
        source,
    )


def _is_range(value: Any) -> bool:
    return isinstance(value, Mapping)


def _range_bounds(key: str, value: Mapping[str, Any], check: Check) -> tuple[Any, Any]:
    extra = [k for k in value if k not in ("min", "max", "num")]
    if extra or "min" not in value or "max" not in value:
        raise InvalidDesign(key, dict(value), "a range {min = a, max = b} (a grid also takes num = n)")
    lo, hi = check(key, value["min"]), check(key, value["max"])
    if not isinstance(lo, (int, float)) or isinstance(lo, bool):
        raise InvalidDesign(key, dict(value), "a list of values: this parameter has no numeric range")
    if hi < lo:
        raise InvalidDesign(key, dict(value), "a range with min <= max")
    return lo, hi


def _grid_values(name: str, value: Any, check: Check) -> list[Any]:
    key = f"parameters.{name}"
    if _is_range(value):
        lo, hi = _range_bounds(key, value, check)
        if isinstance(lo, int) and "num" not in value:
            return list(range(lo, hi + 1))
        if "num" not in value:
            raise InvalidDesign(key, dict(value), "a range with num = n points in a grid (no [random] table)")
        num = v.integer(f"{key}.num", value["num"], 1, MAX_DESIGNS)
        step = (hi - lo) / (num - 1) if num > 1 else 0.0
        values = [lo + i * step for i in range(num)]
        if isinstance(lo, int):
            values = sorted({int(round(x)) for x in values})
        return [check(key, _round(x, GRID_DIGITS)) for x in values]
    values = value if isinstance(value, list) else [value]
    if not values:
        raise InvalidDesign(key, value, "one value, a non-empty list or a range")
    checked = [check(key, x) for x in values]
    return [_round(x, GRID_DIGITS) for x in checked]


def _round(x: Any, digits: int) -> Any:
    return float(f"{x:.{digits}g}") if isinstance(x, float) else x


def _sample_size(sample: Any) -> tuple[int, int]:
    if not isinstance(sample, Mapping) or set(sample) - {"n", "seed"} or "n" not in sample:
        raise InvalidDesign("random", sample, "a table {n = designs, seed = integer}")
    n = v.integer("random.n", sample["n"], 1, MAX_DESIGNS)
    seed = v.integer("random.seed", sample.get("seed", 0), 0, 2**63 - 1)
    return n, seed


def _draw(params: Mapping[str, Any], checks: dict[str, Check], n: int, seed: int) -> list[dict[str, Any]]:
    """``n`` designs: each listed parameter drawn uniformly from its list or range."""
    import numpy as np

    rng = np.random.default_rng(seed)
    pick = {name: _drawer(name, params[name], checks[name], rng) for name in checks if name in params}
    return [{name: draw() for name, draw in pick.items()} for _ in range(n)]


def _drawer(name: str, value: Any, check: Check, rng: Any) -> Callable[[], Any]:
    """A function drawing one value of parameter ``name`` (uniform over its list or range)."""
    key = f"parameters.{name}"
    if not _is_range(value):
        options = _grid_values(name, value, check)
        return lambda: options[int(rng.integers(len(options)))]
    lo, hi = _range_bounds(key, value, check)
    if isinstance(lo, int):
        return lambda: int(rng.integers(lo, hi + 1))
    return lambda: check(key, min(_round(float(rng.uniform(lo, hi)), DRAW_DIGITS), hi))


def normalise(experiment: str, given: Mapping[str, Any]) -> DesignPoint:
    """The design with defaults filled in and equal designs made equal, and its key."""
    p = {**defaults(experiment), **given}
    invalid = ""
    try:
        from ..tiling import Design

        values = v.design_values(
            p["shape"], p["tiling"], p["slant_deg"], p["slant_dir_deg"], p["gap"], p["thickness"]
        )
        p["tiling"] = Design(**values, rings=0).tiling
    except InvalidDesign as exc:
        invalid = str(exc)
    if experiment == "puncture":
        if p["interaction"] == "full":
            p["coupling_factor"] = 1.0
        elif p["coupling_factor"] is None:
            p["coupling_factor"] = 0.04 if p["interaction"] == "contact" else 1.0
        if p["solver"] == "penalty":
            p["accuracy"] = None
    ordered = {k: p[k] for k in parameter_checks(experiment)}
    return DesignPoint(design_key(experiment, ordered), experiment, ordered, invalid)


#: Parameters added after sweep tables existed, with the value every earlier row ran with: a key
#: names them only when they differ from it, so a table written before still resumes (its rows'
#: keys are those of the same designs now).
KEY_SINCE: dict[str, Any] = {"edges": "clamped"}


def design_key(experiment: str, params: Mapping[str, Any]) -> str:
    """A design's name in the results table: the experiment and every parameter, in order
    (one of ``KEY_SINCE`` only when it is not the value the earlier rows ran with).

    >>> design_key("puncture", {"shape": "square", "gap": 0.005, "rings": 1, "probe": True})
    'puncture shape=square gap=0.005 rings=1 probe=true'
    >>> design_key("puncture", {"shape": "square", "edges": "clamped"})
    'puncture shape=square'
    >>> design_key("puncture", {"shape": "square", "edges": "local"})
    'puncture shape=square edges=local'
    """

    def text(x: Any) -> str:
        if isinstance(x, bool):
            return str(x).lower()
        if isinstance(x, float):
            return f"{x:.{GRID_DIGITS}g}"
        return "none" if x is None else str(x)

    named = [(k, x) for k, x in params.items() if k not in KEY_SINCE or x != KEY_SINCE[k]]
    return " ".join([experiment, *(f"{k}={text(x)}" for k, x in named)])
