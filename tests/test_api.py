"""The Python API (qpscale.api): the same results and the same validation as the command line.

The CLI calls the API, so ``to_dict()`` must be the JSON object the command prints (up to the wall
time); ranges and conflicts raise InvalidDesign before any work; ``import qpscale`` stays light.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

import qpscale
from qpscale import InvalidDesign
from qpscale.api import flexure, geometry, puncture, substrate
from qpscale.cli import app


def _cli_json(*args: str) -> dict:
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def _without_times(d: dict) -> dict:
    return {k: x for k, x in d.items() if k not in ("wall_s",)}


def test_public_names_are_exported():
    for name in ("puncture", "flexure", "design_geometry", "substrate_stiffness"):
        assert name in qpscale.__all__ and callable(getattr(qpscale, name))
    assert qpscale.design_geometry is geometry and qpscale.substrate_stiffness is substrate


def test_import_is_light():
    # Neither the solver stack nor pandas loads at ``import qpscale`` (a notebook's first cell).
    code = (
        "import sys, qpscale\n"
        "heavy = {'cvxpy', 'osqp', 'qpsolvers', 'clarabel', 'pandas', 'scipy.sparse.linalg', 'skfem'}\n"
        "print(sorted(heavy & set(sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_geometry_matches_the_cli():
    api = geometry(shape="dart", slant_deg=60.0, slant_dir_deg=90.0, rings=1).to_dict()
    assert api == _cli_json(
        "geometry", "--shape", "dart", "--slant", "60", "--slant-dir", "90", "--rings", "1"
    )
    # t tan(60 deg) along +y with t = 1: an independent value for the offset.
    assert api["top_offset"] == pytest.approx([0.0, 3**0.5], abs=1e-12)


def test_puncture_isolated_matches_the_cli_and_the_rigid_lever():
    report = puncture(isolated=True)
    assert _without_times(report.to_dict()) == _without_times(_cli_json("puncture", "--isolated"))
    frame = report.curve_frame()
    assert list(frame.columns) == ["w_star", "F_star", "tilt_deg"]
    assert frame["F_star"].iloc[-1] == pytest.approx(report.Fc_star, rel=1e-12)
    # The isolated square at its corner (delta_c* = sqrt 2, t = 1): README's 0.2947 from
    # F (delta_c cos phi + t sin phi) = K_phi phi at phi_c = 13 deg (formulations/puncture.md).
    assert report.Fc_star == pytest.approx(0.2947, abs=5e-4)
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.output_errors = ("x",)  # type: ignore[misc]
    with pytest.raises(TypeError):
        report.payload["Fc_star"] = 1.0  # type: ignore[index]
    changed = report.to_dict()
    changed["Fc_star"] = 1.0  # a copy: the report keeps its value
    assert report.Fc_star != 1.0


def test_flexure_bare_matches_the_cli():
    report = flexure(bare=True, mesh_h=1.0)
    assert _without_times(report.to_dict()) == _without_times(_cli_json("flexure", "--bare", "--mesh-h", "1"))
    frame = report.curve_frame()
    assert list(frame.columns) == ["deflection_star", "F_star"] and frame.iloc[0].tolist() == [0.0, 0.0]


def test_substrate_isolated_and_its_coupling_frame():
    iso = substrate(isolated=True)
    assert iso.to_dict() == _cli_json("substrate", "--isolated")
    # The square punch is symmetric under x <-> y: Kx = Ky and Kphix = Kphiy (round-off 1e-12).
    k = iso["isolated"]
    assert k["Kx"] == pytest.approx(k["Ky"], rel=1e-12) and k["Kphix"] == pytest.approx(k["Kphiy"], rel=1e-12)
    assert iso.coupling_frame().empty


@pytest.mark.parametrize(
    "call,parameter",
    [
        (lambda: puncture(slant_deg=float("nan")), "slant_deg"),
        (lambda: puncture(rings=3, isolated=True), "isolated"),
        (lambda: puncture(load_point=(3.0, 0.0)), "load_point"),
        (lambda: puncture(solver="penalty", accuracy="mid"), "solver"),
        (lambda: puncture(rings=True), "rings"),  # a bool is not a number of rings
        (lambda: flexure(mesh_h=0.0), "mesh_h"),
        (lambda: flexure(bare=True, gap=0.1), "bare"),
        (lambda: geometry(gap="0.1"), "gap"),  # type: ignore[arg-type]  # a string is not a number
        (lambda: substrate(nu=0.6), "nu"),
        (lambda: puncture(max_increments=15), "max_increments"),  # below the 16 a path aims at
    ],
)
def test_api_validation_is_the_clis(call, parameter):
    with pytest.raises(InvalidDesign) as err:
        call()
    assert err.value.parameter == parameter


def test_events_as_records_or_dicts_serialise_alike():
    # The numerical core may turn events into frozen dataclasses with to_dict(): the JSON is the same.
    from qpscale.api import plain

    @dataclasses.dataclass(frozen=True)
    class Event:
        kind: str
        delta: float

        def to_dict(self) -> dict:
            return {"kind": self.kind, "delta": self.delta}

    assert plain([Event("contact", 0.5)]) == plain([{"kind": "contact", "delta": 0.5}])
    assert plain({"x": float("nan"), "y": [float("inf"), 1.0]}) == {"x": None, "y": [None, 1.0]}


def test_max_increments_is_the_paths_budget():
    # The 3x3 square array at a corner takes 30 increments (measured; the default budget is 400): with 16 it
    # stops with its status and says which budget it ran out of; the isolated scale needs 15.
    from qpscale.errors import SolverFailure

    with pytest.raises(SolverFailure) as err:
        puncture(rings=1, load_point=(0.5, 0.5), max_increments=16)
    assert err.value.status == "failure tilt not reached"
    assert "max_increments = 16" in str(err.value)
    assert puncture(isolated=True, max_increments=16).payload["increments"] <= 16
