"""One validation layer for the command line and the Python API (docs/cli.md, "Ranges").

Every parameter a user can give is checked here, before any work: finite numbers only, each in
its documented range; output paths are checked (their directories created) before the
computation; flags that contradict each other are refused; and a scene whose estimated memory
exceeds the limit (``--max-memory-gb``, ``$QPSCALE_MAX_MEMORY_GB``, default 4 GB) or whose
estimated time exceeds ``--max-minutes`` (``$QPSCALE_MAX_MINUTES``, default 60) is refused with
the estimate.  Errors are :class:`~qpscale.errors.InvalidDesign` naming the API parameter;
:data:`FLAG_OF` names the command-line flag it comes from, so that the CLI's one-line error
names what the user typed.
"""

from __future__ import annotations

import math
import numbers
import os
from pathlib import Path

from .errors import InvalidDesign

# API parameter -> command-line flag.  Internal names that a deeper layer may still raise (the
# membrane's ``h`` and ``nz``) map to the flag that sets them.
FLAG_OF: dict[str, str] = {
    "shape": "--shape",
    "tiling": "--tiling",
    "slant_deg": "--slant",
    "slant_dir_deg": "--slant-dir",
    "gap": "--gap",
    "thickness": "--thickness",
    "rings": "--rings",
    "rings_tol": "--rings-tol",
    "isolated": "--isolated",
    "bare": "--bare",
    "interaction": "--interaction",
    "coupling": "--coupling-factor",
    "coupling_factor": "--coupling-factor",
    "solver": "--solver",
    "accuracy": "--accuracy",
    "phi_c_deg": "--phi-c",
    "nu": "--nu",
    "nu_s": "--nu",
    "nu_m": "--nu-m",
    "load_point": "--load-point",
    "E_s": "--E-s",
    "L_mm": "--L-mm",
    "vtk": "--vtk",
    "png": "--png",
    "out": "--out",
    "load_line": "--load-line",
    "mesh_h": "--mesh-h",
    "roller_radius": "--roller-radius",
    "top_h": "--top-h",
    "h": "--mesh-h",
    "nz": "--mesh-h",
    "formulation": "--formulation",
    "mesh": "--mesh",
    "edges": "--edges",
    "condense": "--condense",
    "refinement": "--refinement",
    "workers": "--workers",
    "scheduler": "--scheduler",
    "scene_time_limit": "--scene-time-limit",
    "time_limit": "--time-limit",
    "fuzz": "--fuzz",
    "max_memory_gb": "--max-memory-gb",
    "max_minutes": "--max-minutes",
    "max_increments": "--max-increments",
    "smoke": "--smoke",
    "quick": "--quick",
}

# --- documented ranges (docs/cli.md copies them; tests/test_docs.py checks the copy) -----------
SLANT_RANGE = "[0, 90)"
# The top face's offset t tan(alpha) is bounded: the contact search and the candidate margin grow
# with it, and near 90 deg it grows without bound (a slant of 89.9 deg at t = 1 puts the top face
# 573 L away).  10 L allows alpha up to 84.3 deg at t = 1 and 78.7 deg at t = 2 (the fuzz of the
# bench draws up to 75 deg at t <= 2).
MAX_TOP_OFFSET = 10.0
# The steps a puncture path may take before it gives up (formulations/puncture.md sec. 2): at least
# the 16 increments a path aims at.
DEFAULT_MAX_INCREMENTS = 400
MAX_INCREMENTS_RANGE = (16, 100_000)
MAX_RINGS = 50  # Design's own bound; the memory estimate is the real limit on a machine
MESH_H_RANGE = (0.05, 2.0)  # in L; coarser than 2 L leaves fewer than 5 elements over the 10 L block
DEFAULT_MAX_MEMORY_GB = 4.0
MEMORY_ENV = "QPSCALE_MAX_MEMORY_GB"
DEFAULT_MAX_MINUTES = 60.0
MINUTES_ENV = "QPSCALE_MAX_MINUTES"
ACCURACY_WORDS = ("high", "mid", "low")
ACCURACY_RANGE = (1e-12, 1e-2)


def _is_number(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def real(
    name: str,
    value: object,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
) -> float:
    """``value`` as a finite float in the interval, or :class:`InvalidDesign` stating the interval.

    >>> real("gap", 0.01, 0.0, 1.0, hi_open=True)
    0.01
    """
    left = "(" if lo_open or lo is None else "["
    right = ")" if hi_open or hi is None else "]"
    text = f"{left}{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}{right}"
    text += f" {unit}" if unit else ""
    if not _is_number(value):
        raise InvalidDesign(name, value, text, "not a number")
    x = float(value)  # type: ignore[arg-type]
    if not math.isfinite(x):
        raise InvalidDesign(name, value, text, "finite numbers only")
    below = lo is not None and (x <= lo if lo_open else x < lo)
    above = hi is not None and (x >= hi if hi_open else x > hi)
    if below or above:
        raise InvalidDesign(name, value, text)
    return x


def integer(name: str, value: object, lo: int, hi: int) -> int:
    """``value`` as an int in ``[lo, hi]`` (an integral float such as 2.0 is accepted).

    >>> integer("rings", 2.0, 0, 50)
    2
    """
    text = f"integers in [{lo}, {hi}]"
    if isinstance(value, numbers.Integral) and not isinstance(value, bool):
        n = int(value)  # exact, however large (float() of a 400-digit integer overflows)
    elif _is_number(value) and math.isfinite(x := float(value)) and x == int(x):  # type: ignore[arg-type]
        n = int(x)
    else:
        raise InvalidDesign(name, value, text)
    if not lo <= n <= hi:
        raise InvalidDesign(name, value, text)
    return n


def choice(name: str, value: object, options: tuple[str, ...] | list[str]) -> str:
    """``value`` if it is one of ``options``."""
    if not isinstance(value, str) or value not in options:
        raise InvalidDesign(name, value, "{" + ", ".join(options) + "}")
    return value


class Conflict(InvalidDesign):
    """Two parameters that cannot be given together; ``parameters`` names both."""

    def __init__(self, first: str, second: str, detail: str) -> None:
        self.parameters = (first, second)
        self.detail = detail
        super().__init__(first, "given", "", detail)
        self.args = (f"{first} and {second} cannot be combined: {detail}",)

    def __str__(self) -> str:
        return str(self.args[0])


def conflict(first: str, second: str, detail: str) -> Conflict:
    """The error for two parameters given together (raise it)."""
    return Conflict(first, second, detail)


def top_offset(slant_deg: float, thickness: float) -> None:
    """Refuse slants whose top face lies more than :data:`MAX_TOP_OFFSET` L from its base."""
    offset = thickness * math.tan(math.radians(slant_deg))
    if offset > MAX_TOP_OFFSET:
        limit = math.degrees(math.atan(MAX_TOP_OFFSET / thickness))
        raise InvalidDesign(
            "slant_deg",
            slant_deg,
            f"[0, {limit:.4g}] at thickness {thickness:g}",
            f"t tan(alpha) = {offset:.3g} L exceeds {MAX_TOP_OFFSET:g} L",
        )


def design_values(
    shape: object, tiling: object, slant_deg: object, slant_dir_deg: object, gap: object, thickness: object
) -> dict:
    """The design fields checked (types, finiteness, ranges); ``Design`` checks the tiling."""
    from .geometry import SHAPES

    out = {
        "shape": choice("shape", shape, tuple(SHAPES)),
        "tiling": tiling
        if tiling is None
        else choice("tiling", tiling, ("arrayed", "staggered", "chevron", "honeycomb")),
        "slant_deg": real("slant_deg", slant_deg, 0.0, 90.0, hi_open=True, unit="deg"),
        "slant_dir_deg": real("slant_dir_deg", slant_dir_deg, 0.0, 360.0, hi_open=True, unit="deg"),
        "gap": real("gap", gap, 0.0, 1.0, hi_open=True, unit="L"),
        "thickness": real("thickness", thickness, 0.0, 100.0, lo_open=True, unit="L"),
    }
    top_offset(float(out["slant_deg"]), float(out["thickness"]))  # type: ignore[arg-type]
    return out


def accuracy(value: object) -> str | float:
    """``high``, ``mid``, ``low`` or a QP tolerance in [1e-12, 1e-2] (a number or its text)."""
    allowed = f"{{high, mid, low}} or a number in [{ACCURACY_RANGE[0]:g}, {ACCURACY_RANGE[1]:g}]"
    if isinstance(value, str):
        if value in ACCURACY_WORDS:
            return value
        try:
            value = float(value)
        except ValueError:
            raise InvalidDesign("accuracy", value, allowed) from None
    if not _is_number(value) or not math.isfinite(float(value)):  # type: ignore[arg-type]
        raise InvalidDesign("accuracy", value, allowed)
    x = float(value)  # type: ignore[arg-type]
    if not ACCURACY_RANGE[0] <= x <= ACCURACY_RANGE[1]:
        raise InvalidDesign("accuracy", value, allowed)
    return x


def solver(name: object) -> str:
    """A backend key that is installed here (``qpscale.solvers.available_solvers()``) or ``penalty``."""
    from .solvers import available_solvers, is_available

    if isinstance(name, str) and (name == "penalty" or is_available(name)):
        return name  # listing every backend imports qpsolvers; a known key need not
    allowed = [*available_solvers(), "penalty"]
    return choice("solver", name, allowed)


def qp_solver(name: object) -> str:
    """A QP backend installed here (no penalty: flexure solves QPs only)."""
    from .solvers import available_solvers

    return choice("solver", name, list(available_solvers()))


# --- output paths ---------------------------------------------------------------------------


def _writable_dir(name: str, folder: Path, value: object) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise InvalidDesign(name, str(value), "", f"{folder} or a parent of it is not a directory") from None
    except OSError as exc:
        raise InvalidDesign(name, str(value), "", f"cannot create {folder}: {exc.strerror or exc}") from None
    if not folder.is_dir():
        raise InvalidDesign(name, str(value), "", "exists and is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InvalidDesign(name, str(value), "", f"{folder} is not writable")


def output_file(name: str, path: object) -> Path:
    """``path`` as a file we can write: its directory is created, it is not a directory."""
    if not isinstance(path, (str, os.PathLike)) or str(path) == "":
        raise InvalidDesign(name, path, "a file path")
    p = Path(path)
    if p.is_dir():
        raise InvalidDesign(name, str(p), "", "is a directory, not a file")
    _writable_dir(name, p.parent if str(p.parent) else Path("."), path)
    if p.exists() and not os.access(p, os.W_OK):
        raise InvalidDesign(name, str(p), "", "the file is not writable")
    return p


def output_dir(name: str, path: object) -> Path:
    """``path`` as a directory we can write into (created if absent; an existing file is refused)."""
    if not isinstance(path, (str, os.PathLike)) or str(path) == "":
        raise InvalidDesign(name, path, "a directory path")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InvalidDesign(name, str(p), "", "exists and is not a directory")
    _writable_dir(name, p, path)
    return p


# --- bounded cost ---------------------------------------------------------------------------


def _limit(name: str, value: object, env_name: str, default: float, unit: str, units: str) -> float:
    """A positive limit: ``value``, else the environment variable ``env_name``, else ``default``."""
    if value is None:
        env = os.environ.get(env_name)
        if env is None:
            return default
        try:
            value = float(env)
        except ValueError:
            raise InvalidDesign(env_name, env, f"a number of {units} in (0, inf)") from None
    return real(name, value, 0.0, None, lo_open=True, unit=unit)


def max_memory_gb(value: object = None) -> float:
    """The memory limit in GB: ``value``, else ``$QPSCALE_MAX_MEMORY_GB``, else 4."""
    return _limit("max_memory_gb", value, MEMORY_ENV, DEFAULT_MAX_MEMORY_GB, "GB", "GB")


def _check_unknowns(n_scales: int, n_contact_pairs: int) -> int:
    """Unknowns of the increment QP at the failure state: five per scale, three per separating plane
    (every contact pair has one there: 1221 = 5 x 81 + 3 x 272 on the 9x9 square array)."""
    return 5 * n_scales + 3 * n_contact_pairs


#: certify.DENSE_UP_TO: up to this many unknowns the check may also run DAQP's dense solve (first,
#: or after the sparse one failed), so its dense cost is part of the estimate there.
DENSE_CHECK_UP_TO = 1500


def _check_memory_gb(N: int, n_contact_pairs: int) -> float:
    """The F_c check's memory above the path's, GB: the sparse solve's KKT factors, PIQP's start and
    the LPs, 10 kB per unknown (measured 3.7-4.2 kB: peaks 1.4, 4.5, 9.6, 19.5 and 26.7 MB at
    N = 341, 1221, 2645, 4613 and 7125); up to DENSE_CHECK_UP_TO unknowns also DAQP's dense P and
    rows, 24 (N^2 + 8 pairs N) bytes."""
    dense = 24.0 * (float(N) * N + 8.0 * n_contact_pairs * N) if N <= DENSE_CHECK_UP_TO else 0.0
    return (1e4 * N + dense) / 1e9


def puncture_memory_gb(n_scales: int, n_contact_pairs: int) -> float:
    """Estimated peak memory of a puncture run, GB (formulations/substrate.md sec. 11).

    The path itself is linear in the patch: the stiffness, the increment QPs, the stability probe
    and the mirror map are sparse (stability.md sec. 8), 1 MB per scale as an upper bound (the path
    peaked 0.07 GB above the interpreter on the 11x11 patch, 0.6 MB per scale), plus 0.3 GB for the
    interpreter and the libraries.  The final check of F_c (certify.solve_exact) is sparse from
    certify.SPARSE_FROM = 200 unknowns on (N = 5 n_scales + 3 n_contact_pairs; measured up to 4.2 kB
    per unknown, estimated 10 kB); DAQP's dense solve, 24 (N^2 + 8 pairs N) bytes (it raised the
    peak by 75 MB at N = 1221, estimate 100 MB, and by 357 MB at N = 2645), is counted only up to
    1500 unknowns, where the check may run it.
    """
    N = _check_unknowns(n_scales, n_contact_pairs)
    return 0.3 + 1e-3 * n_scales + _check_memory_gb(N, n_contact_pairs)


def flexure_memory_gb(mesh_h: float, nz: int, length: float = 10.0, width: float = 10.0) -> float:
    """Estimated peak memory of a flexure run, GB (measured fit, docs/cli.md "Cost limits").

    The membrane's sparse factorisation of n = 3 (nx+1)(ny+1)(nz+1) unknowns fills in like a 3D
    nested dissection, ~ n^(4/3) entries.  Measured peaks (bare membrane, default nz = 1.5/h):
    0.20 GB at h = 0.5 L (n = 5292, 1.3 s), 0.36 GB at 0.35 L (13500, 2.9 s), 0.81 GB at 0.25 L
    (35301, 9.2 s): 5.4-6.6e-7 n^(4/3) GB above 0.15 GB.  The estimate takes 8e-7 and 0.2 GB, so
    it over-estimates rather than under-estimates.
    """
    nx, ny = math.ceil(length / mesh_h), math.ceil(width / mesh_h)
    n = 3 * (nx + 1) * (ny + 1) * (nz + 1)
    return 8.0e-7 * n ** (4.0 / 3.0) + 0.2


def memory(estimate_gb: float, limit_gb: float, parameter: str, value: object, what: str) -> None:
    """Refuse a run whose estimate exceeds the limit, naming the parameter that sets the size, the
    limit and how to raise it."""
    if estimate_gb > limit_gb:
        raise InvalidDesign(
            parameter,
            value,
            "",
            f"{what} needs about {estimate_gb:.3g} GB, over the memory limit of {limit_gb:g} GB "
            f"(--max-memory-gb or ${MEMORY_ENV})",
        )


def max_minutes(value: object = None) -> float:
    """The time limit in minutes: ``value``, else ``$QPSCALE_MAX_MINUTES``, else 60."""
    return _limit("max_minutes", value, MINUTES_ENV, DEFAULT_MAX_MINUTES, "min", "minutes")


def puncture_time_s(n_scales: int, n_contact_pairs: int, probe: bool = True) -> float:
    """An upper estimate of a puncture run's wall time on one core, seconds (substrate.md sec. 11).

    150 load levels at 4 ms per scale each (PIQP: measured 2.5-3.4 ms per scale per level in wall
    time on the loaded development machine, 58-96 levels of 4-5 QPs each, 5x5 to 11x11); with the
    stability probe 80 states of the sparse test at 0.2 ms per unknown (measured 55 ms at 830
    unknowns); and the final check of F_c in N = 5 n_scales + 3 n_contact_pairs unknowns: the
    sparse exact solve and the range's LPs, 2 ms per unknown (measured 0.05-0.36 ms: 0.018 s,
    0.056 s, 0.13 s, 1.7 s and 0.54 s for N = 341, 1221, 2645, 4613 and 7125), plus DAQP's dense
    solve, up to 1e-8 N^3 s, where the check may run it (N <= 1500; measured 2.8-6.2 s at
    N = 1221, and 21-125 s at N = 2645 before the sparse solve replaced it there).
    Measured runs took up to 3.6 s, 14 s, 28 s and 49 s (5x5 to 11x11, load 4-7 on two cores,
    with the dense check: 20 s of the 49 s) and 102 s (13x13 with the sparse check, 1.1 s of it
    from zero, 0.09 s from PIQP's start in an 81 s run; 219 s with the dense one) against
    estimates of 22 s, 46 s, 89 s, 106 s and 149 s.
    """
    N = _check_unknowns(n_scales, n_contact_pairs)
    qp = 150 * 0.004 * n_scales
    dense = 1e-8 * float(N) ** 3 if N <= DENSE_CHECK_UP_TO else 0.0
    return qp + (80 * 2e-4 * N if probe else 0.0) + 2e-3 * N + dense


def flexure_time_s(mesh_h: float, nz: int, length: float = 10.0, width: float = 10.0) -> float:
    """An upper estimate of a flexure run's wall time on one core, seconds: 1.5 ms per unknown of
    the membrane (the bare membrane measured 0.25 ms at h = 0.5 L and 0.26 ms at 0.25 L; a covered
    one adds the scales' contact, 2.7 s at h = 0.5 L, i.e. 0.5 ms)."""
    nx, ny = math.ceil(length / mesh_h), math.ceil(width / mesh_h)
    return 1.5e-3 * 3 * (nx + 1) * (ny + 1) * (nz + 1)


def fitted_memory_gb(nodes: int, error: bool) -> float:
    """Estimated peak memory of a flexure run on the fitted mesh of ``nodes`` nodes, GB.

    Measured peaks of the two-slab fitted meshes (membrane.md sec. 9e): 2.1 GB at 62.6k nodes
    (honeycomb), 3.0 GB at 89k (square array), 3.5 GB at 111k, 7.9 GB at 227k (dart chevron):
    3.0-3.5e-5 GB a node.  The estimate takes 3.6e-5 and 0.2 GB; the error estimate's companion
    mesh has about 2.2 times the nodes (half the size along the gaps, twice the layers), and its
    condensation is taken as the run's peak.  The first curve's factor stays referenced by its
    result meanwhile (as on the tensor mesh), so the combined peak, not measured, lies above it.
    """
    return 0.2 + 3.6e-5 * nodes * (2.2 if error else 1.0)


def fitted_time_s(nodes: int, error: bool) -> float:
    """An upper estimate of a fitted-mesh flexure run's wall time on one core, seconds: 1 ms a
    node (measured 0.5-0.85 ms), and the companion mesh's 2.2 times as many nodes after it."""
    return 1.0e-3 * nodes * (3.2 if error else 1.0)


def duration(estimate_s: float, limit_min: float, parameter: str, value: object, what: str) -> None:
    """Refuse a run whose estimated time exceeds the limit, naming the parameter that sets it."""
    if estimate_s > 60.0 * limit_min:
        raise InvalidDesign(
            parameter,
            value,
            "",
            f"{what} is estimated to take up to {estimate_s / 60:.3g} min, over the time limit of "
            f"{limit_min:g} min (--max-minutes or ${MINUTES_ENV})",
        )
