"""The ``qpscale`` command line (typer).  The only module that prints or sets exit codes.

Each subcommand prints a human summary, or one JSON object with ``--json``; field names follow
the contract in docs/cli.md (tested against this module by tests/test_docs.py).  Every command
calls :mod:`qpscale.api` or a study, which validate their input through :mod:`qpscale.validation`
before any work.  Exit status: 0 done; 2 invalid input, one line ``error: --flag: ...`` on stderr
(parse errors included: :class:`OneLineErrors` replaces click's boxed usage errors); 3 the run
failed (a solver's status, an output that could not be written: the JSON result is still
printed); 4 an internal error (a bug: one line, ``QPSCALE_DEBUG=1`` shows the traceback); 130
interrupted.  It implements no formulation.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from functools import wraps
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console
from typer.core import TyperGroup

from . import __version__
from .errors import InvalidDesign, OutputNotWritten, QpscaleError, SolverFailure, SolverUnavailable
from .solvers import DEFAULT_SOLVER
from .validation import DEFAULT_MAX_INCREMENTS, FLAG_OF, MAX_INCREMENTS_RANGE, Conflict

# soft_wrap: a summary piped to a file or another program is one line per result, never cut in the
# middle of a number at 80 columns.
console = Console(soft_wrap=True)
err_console = Console(stderr=True, soft_wrap=True)

F = TypeVar("F", bound=Callable[..., Any])

EXIT_OK = 0
EXIT_INVALID = 2
EXIT_FAILED = 3
EXIT_INTERNAL = 4
EXIT_SOLVER = EXIT_FAILED  # former name
EXIT_INTERRUPTED = 130

# The allowed range of every flag, as the help texts and the one-line parse errors state it
# (docs/cli.md copies this table; tests/test_docs.py checks the copy).
RANGES: dict[str, str] = {
    "--shape": "{triangle, square, trapezoid, dart, hexagon}",
    "--tiling": "{arrayed, staggered} for triangle, square, trapezoid; chevron (dart); honeycomb (hexagon)",
    "--slant": "[0, 90) deg, with t tan(alpha) <= 10 L",
    "--slant-dir": "[0, 360) deg from +x",
    "--gap": "[0, 1) L",
    "--thickness": "(0, 100] L",
    "--rings": "integers in [0, 50] (puncture: within the memory and time limits, or auto)",
    "--rings-tol": "(0, 0.5] (default 0.005), with --rings auto",
    "--interaction": "{full, substrate, contact}",
    "--coupling-factor": "[0, 1]",
    "--solver": "an installed backend (clarabel, piqp, osqp, cvxpy, active-set, qpsolvers:<name>) or penalty",
    "--accuracy": "{high, mid, low} or a number in [1e-12, 0.01]",
    "--phi-c": "(0, 60] deg",
    "--nu": "[0, 0.5]",
    "--nu-m": "[0, 0.5]",
    "--load-point": "two numbers x y in L on the centre scale's top face",
    "--E-s": "(0, 1e12] Pa",
    "--L-mm": "(0, 1e6] mm",
    "--load-line": "{x, y}",
    "--mesh-h": "[0.05, 2] L, within the memory and time limits",
    "--formulation": "{plane, feature}",
    "--mesh": "{tensor, fitted} (fitted: scales with a gap, gmsh installed)",
    "--edges": "{clamped, local}",
    "--condense": "{auto, on, off}",
    "--roller-radius": "(0, 3.75) L (half the span less the plate's width)",
    "--top-h": "(0, 1.5 / layers] L (default: d / 2 with scales, uniform layers bare)",
    "--refinement": "integers in [2, 16]",
    "--workers": "integers from 1 to the number of cores (paper: 1 or 2)",
    "--scheduler": "a Dask scheduler address, e.g. tcp://host:8786 (not with --workers)",
    "grid": "a TOML file: experiment, [random], [parameters] (docs/cli.md, qpscale sweep)",
    "--scene-time-limit": "[0, inf) s, 0 for none",
    "--time-limit": "(0, inf) s",
    "--fuzz": "integers in [0, 100000]",
    "--max-memory-gb": "(0, inf) GB (default $QPSCALE_MAX_MEMORY_GB or 4)",
    "--max-minutes": "(0, inf) min (default $QPSCALE_MAX_MINUTES or 60)",
    "--max-increments": "integers in [{}, {}] (default {})".format(
        *MAX_INCREMENTS_RANGE, DEFAULT_MAX_INCREMENTS
    ),
    "--png": "a .png, .svg or .pdf file path; its directory is created before the run",
    "--vtk": "a directory, created before the run; an earlier series there is replaced",
    "--out": "a directory (sweep: a .parquet file), created before the run",
}


def _click_exception_class() -> type[BaseException]:
    """click's ClickException, wherever this typer keeps click (vendored in recent versions)."""
    return next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


ClickException = _click_exception_class()


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def usage_error_line(exc: Any) -> str:
    """One line for a click usage error: the flag, the problem and the flag's allowed range."""
    param = getattr(exc, "param", None)
    flag = getattr(exc, "option_name", None)  # BadOptionUsage, NoSuchOption
    if param is not None and getattr(param, "opts", None):
        flag = max(param.opts, key=len)
    message = _one_line(exc.format_message())
    if flag is None:
        return f"error: {message}"
    # click says "Invalid value for '--slant': 'x' is not a valid float."; keep the reason only.
    for prefix in (f"Invalid value for '{flag}': ", f"Invalid value for {flag}: ", f"Option '{flag}' "):
        message = message.replace(prefix, "")
    # An option the command does not have gets no range: the one RANGES holds for that name is
    # another command's (``substrate --rings`` named puncture's).
    allowed = None if type(exc).__name__ == "NoSuchOption" else RANGES.get(flag)
    return f"error: {flag}: {message.rstrip('.')}" + (f"; allowed: {allowed}" if allowed else "")


class OneLineErrors(TyperGroup):
    """The command group with one-line errors: a usage error (unknown option, a value that does not
    parse, a missing argument) prints ``error: --flag: ...`` with the range and exits 2, instead
    of click's multi-line box; a broken pipe or full disk on stdout exits 3 without a traceback."""

    def main(  # type: ignore[override]
        self, args: Sequence[str] | None = None, prog_name: str | None = None, **extra: Any
    ) -> Any:
        standalone = extra.pop("standalone_mode", True)
        extra["standalone_mode"] = False
        try:
            rv = super().main(args, prog_name, **extra)
            code = rv if isinstance(rv, int) else EXIT_OK
        except ClickException as exc:
            if type(exc).__name__ == "NoArgsIsHelpError":  # typer printed the help already
                code = EXIT_OK
            else:
                _print_error(usage_error_line(exc))
                code = EXIT_INVALID  # every click error is about the input (click's FileError says 1)
        except typer.Abort:
            code = EXIT_INTERRUPTED
        except OSError as exc:
            code = _output_failure(exc)
        if not standalone:
            return code
        sys.exit(code)


def _print_info(line: str) -> None:
    """A line for the person watching (stderr: stdout is the result's)."""
    with contextlib.suppress(OSError):
        err_console.print(line, markup=False, highlight=False, soft_wrap=True)


def _print_error(line: str) -> None:
    with contextlib.suppress(OSError):
        err_console.print(line, markup=False, highlight=False, soft_wrap=True)


def _output_failure(exc: OSError) -> int:
    """Writing the output failed (stdout closed by the reader, disk full): one line, exit 3."""
    if exc.errno == errno.EPIPE:
        # The reader is gone: nothing more goes to stdout (Python's flush at exit would fail again).
        with contextlib.suppress(OSError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        _print_error("error: output: the reader closed the pipe")
    else:
        _print_error(f"error: output: could not write: {exc.strerror or exc}")
    return EXIT_FAILED


app = typer.Typer(
    cls=OneLineErrors,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="3D mechanics of scaled skins: exact contact as a QP per load increment.",
)


def _fail(code: int, message: str) -> None:
    _print_error(f"error: {_one_line(message)}")
    raise typer.Exit(code)


def flag_of(parameter: str) -> str:
    """The command-line flag of an API parameter (an unknown name is shown as it is, no dashes
    invented: an internal parameter is not a flag)."""
    return FLAG_OF.get(parameter, parameter)


# While a --json command computes, file descriptor 1 points at stderr and the real stdout is kept
# here for the one JSON object: a C library's banner (HiGHS prints one from C++) must not
# corrupt the output that scripts parse.
_json_fd: int | None = None


def _real_stdout() -> bool:
    """Whether ``sys.stdout`` is the process's fd 1 (not a test runner's buffer)."""
    try:
        return sys.stdout.fileno() == 1
    except (AttributeError, OSError, ValueError):
        return False


@contextlib.contextmanager
def json_stdout() -> Any:
    """Send everything written to fd 1 to stderr meanwhile; :func:`emit` writes to the real stdout."""
    global _json_fd
    if not _real_stdout():
        yield
        return
    sys.stdout.flush()
    _json_fd = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            sys.stdout.flush()
        os.dup2(_json_fd, 1)
        os.close(_json_fd)
        _json_fd = None


def handles_errors(func: F) -> F:
    """Map qpscale exceptions to one line on stderr and an exit status; with ``--json``, keep
    stdout for the JSON object alone (:func:`json_stdout`)."""

    @wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with warnings.catch_warnings():
                # A failed optional output is reported as one error line by finish(), not twice.
                warnings.simplefilter("ignore", OutputNotWritten)
                if kwargs.get("as_json"):
                    with json_stdout():
                        return func(*args, **kwargs)
                return func(*args, **kwargs)
        except Conflict as exc:
            first, second = (flag_of(p) for p in exc.parameters)
            _fail(EXIT_INVALID, f"{first} and {second}: cannot be combined: {exc.detail}")
        except InvalidDesign as exc:
            _fail(EXIT_INVALID, f"{flag_of(exc.parameter)}: {exc}")
        except SolverUnavailable as exc:
            _fail(EXIT_INVALID, f"--solver: {exc}")
        except SolverFailure as exc:
            _fail(EXIT_FAILED, str(exc))
        except QpscaleError as exc:
            _fail(EXIT_FAILED, str(exc))
        except (KeyboardInterrupt, typer.Exit, typer.Abort, SystemExit):
            raise
        except OSError as exc:
            raise typer.Exit(_output_failure(exc)) from None
        except Exception as exc:  # a bug: one line, not a traceback; QPSCALE_DEBUG=1 shows it
            if os.environ.get("QPSCALE_DEBUG"):
                raise
            _fail(EXIT_INTERNAL, f"internal error ({type(exc).__name__}: {exc}); please report it")

    return wrapper  # type: ignore[return-value]


def emit(payload: dict[str, Any], as_json: bool, summary: Callable[[dict[str, Any]], None] | None) -> None:
    """Print ``payload`` as one JSON object, or a human summary of it."""
    if as_json:
        text = json.dumps(payload, allow_nan=False) + "\n"
        if _json_fd is not None:
            data = memoryview(text.encode())
            while data:  # a pipe may take a large payload in parts
                data = data[os.write(_json_fd, data) :]
        else:
            sys.stdout.write(text)
            sys.stdout.flush()
    elif summary is not None:
        summary(payload)


def _fmt(value: Any, spec: str) -> str:
    """A number for a summary; a missing one (null in the JSON) reads "n/a", never "nan"."""
    return "n/a" if value is None else format(value, spec)


def finish(report: Any, as_json: bool, summary: Callable[[dict[str, Any]], None]) -> None:
    """Print a report; then, if an optional output (png, vtk) could not be written, say so on
    stderr and exit 3: the computed result is printed first, never lost for a file."""
    emit(report.to_dict(), as_json, summary)
    errors = getattr(report, "output_errors", ())
    for message in errors:
        _print_error(f"error: {flag_of(message.split(':')[0])}: {message}")
    if errors:
        raise typer.Exit(EXIT_FAILED)


def _version(value: bool) -> None:
    if value:
        console.print(f"qpscale {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version."
    ),
) -> None:
    """3D mechanics of scaled skins."""


def _help(flag: str, text: str) -> str:
    return f"{text} Allowed: {RANGES[flag]}."


# Options shared by the design-based commands; names and ranges follow docs/cli.md.
ShapeOpt = typer.Option("square", "--shape", help=_help("--shape", "Base shape."))
TilingOpt = typer.Option(None, "--tiling", help=_help("--tiling", "Tiling (default: the shape's first)."))
SlantOpt = typer.Option(0.0, "--slant", help=_help("--slant", "Slant angle alpha from the vertical."))
SlantDirOpt = typer.Option(0.0, "--slant-dir", help=_help("--slant-dir", "Slant direction."))
GapOpt = typer.Option(0.005, "--gap", help=_help("--gap", "Gap d between neighbouring bases."))
ThicknessOpt = typer.Option(1.0, "--thickness", help=_help("--thickness", "Scale thickness t."))
JsonOpt = typer.Option(False, "--json", help="Print one JSON object (fields: docs/cli.md).")
MemoryOpt = typer.Option(
    None, "--max-memory-gb", help=_help("--max-memory-gb", "Refuse a scene estimated to need more memory.")
)
MinutesOpt = typer.Option(
    None, "--max-minutes", help=_help("--max-minutes", "Refuse a scene estimated to take longer.")
)


@app.command()
@handles_errors
def geometry(
    shape: str = ShapeOpt,
    tiling: str | None = TilingOpt,
    slant: float = SlantOpt,
    slant_dir: float = SlantDirOpt,
    gap: float = GapOpt,
    thickness: float = ThicknessOpt,
    rings: int = typer.Option(2, "--rings", help=_help("--rings", "Rings of neighbours (2: 5x5).")),
    png: Path | None = typer.Option(None, "--png", help="Draw the patch to FILE (directory created)."),
    as_json: bool = JsonOpt,
) -> None:
    """Build a design's patch and check it: areas, gaps, overlaps, top-face offset."""
    from .api import geometry as run

    report = run(shape, tiling, slant, slant_dir, gap, thickness, rings, png)

    def summary(p: dict[str, Any]) -> None:
        gap_text = "none (one scale)" if p["min_gap"] is None else f"{p['min_gap']:.6g} L"
        console.print(
            f"[bold]{p['shape']} ({p['tiling']})[/]: {p['n_scales']} scales, base area "
            f"{p['base_area']:.12g} L^2, min gap {gap_text}, max overlap {p['max_overlap_area']:.3g} L^2, "
            f"top offset ({p['top_offset'][0]:.4g}, {p['top_offset'][1]:.4g}) L"
        )

    finish(report, as_json, summary)


def _progress(description: str):
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    return Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=err_console,
        transient=True,
        disable=not err_console.is_terminal,
    )


@contextlib.contextmanager
def _spinner(name: str) -> Iterator[Callable[[str], None]]:
    """A spinner named ``name`` on stderr while the block runs; yields the ``progress`` callback
    that shows a stage's message beside the name."""
    with _progress(name) as bar:
        task = bar.add_task(name, total=None)
        yield lambda msg: bar.update(task, description=f"{name}: {msg}")


def _rings_value(text: str | None) -> int | str | None:
    """``--rings`` as an integer, or "auto"; anything else is refused naming the flag."""
    if text is None or text.strip().lower() == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise InvalidDesign("rings", text, RANGES["--rings"]) from None


def _rings_summary(auto: dict[str, Any]) -> None:
    """The patch-size sequence of ``--rings auto``, one line per patch, and its extrapolation."""
    for row in auto["sequence"]:
        change = "" if row["change"] is None else f", change {100 * row['change']:.2f} %"
        console.print(
            f"  rings {row['rings']} ({row['n_scales']} scales): F_c* = {_fmt(row['Fc_star'], '.6g')}"
            f"{change}, {_fmt(row['wall_s'], '.1f')} s"
        )
    state = "converged" if auto["converged"] else "not converged"
    console.print(f"  {state} at --rings-tol {auto['tol']:g}: {auto['stop_reason']}")
    ext = auto["extrapolation"]
    if ext is not None:
        console.print(
            f"  extrapolated F_c*(infinite patch) = {_fmt(ext['Fc_star_inf'], '.5g')}"
            f" +- {_fmt(ext['error'], '.2g')}"
            f" (fit F_inf - a n^-p over {ext['points']} patches, p = {_fmt(ext['p'], '.3g')})"
        )
    else:
        console.print(f"  no extrapolation: {auto['no_extrapolation']}")


@app.command()
@handles_errors
def puncture(
    shape: str = ShapeOpt,
    tiling: str | None = TilingOpt,
    slant: float = SlantOpt,
    slant_dir: float = SlantDirOpt,
    gap: float = GapOpt,
    thickness: float = ThicknessOpt,
    rings: str | None = typer.Option(
        None,
        "--rings",
        help=_help(
            "--rings",
            "Rings of neighbours around the punctured scale (default 2: 5x5); auto: grow the patch "
            "until F_c* settles.",
        ),
    ),
    rings_tol: float | None = typer.Option(
        None,
        "--rings-tol",
        help=_help("--rings-tol", "Relative change of F_c* at which --rings auto stops."),
    ),
    isolated: bool = typer.Option(False, "--isolated", help="The punctured scale alone (rings = 0)."),
    interaction: str = typer.Option(
        "full",
        "--interaction",
        help=_help("--interaction", "Substrate coupling and contact; contact off; or f-scaled."),
    ),
    coupling_factor: float | None = typer.Option(
        None,
        "--coupling-factor",
        help=_help(
            "--coupling-factor", "Substrate coupling f for substrate/contact (default 1; contact 0.04)."
        ),
    ),
    solver: str = typer.Option(DEFAULT_SOLVER, "--solver", help=_help("--solver", "QP backend.")),
    formulation: str = typer.Option(
        "plane",
        "--formulation",
        help=_help("--formulation", "Scale-scale contact: plane (every backend but osqp) or feature."),
    ),
    accuracy: str | None = typer.Option(
        None, "--accuracy", help=_help("--accuracy", "QP tolerance: high 1e-9 (default), mid 1e-6, low 1e-3.")
    ),
    phi_c: float = typer.Option(13.0, "--phi-c", help=_help("--phi-c", "Critical tilt.")),
    nu: float = typer.Option(0.5, "--nu", help=_help("--nu", "Poisson's ratio of the substrate.")),
    max_increments: int = typer.Option(
        DEFAULT_MAX_INCREMENTS,
        "--max-increments",
        help=_help("--max-increments", "Steps a load point's path may take before it gives up."),
    ),
    edges: str = typer.Option(
        "clamped",
        "--edges",
        help=_help(
            "--edges",
            "Self stiffness of the patch's edge scales: clamped (K0, the paper's comparison) or "
            "local (their own neighbourhood).",
        ),
    ),
    condense: str = typer.Option(
        "auto",
        "--condense",
        help=_help(
            "--condense",
            "Solve each QP on the contact region's rows and DOFs, the rest of the patch eliminated "
            "(auto: from 7x7 on).",
        ),
    ),
    load_point: tuple[float, float] | None = typer.Option(
        None,
        "--load-point",
        help=_help(
            "--load-point", "Load point relative to the scale's reference point (default: the worst vertex)."
        ),
    ),
    probe: bool = typer.Option(
        True, "--probe/--no-probe", help="Test every state by the second variation and follow branches."
    ),
    E_s: float | None = typer.Option(
        None, "--E-s", help=_help("--E-s", "Substrate modulus, to report F_c in newtons.")
    ),
    L_mm: float | None = typer.Option(
        None, "--L-mm", help=_help("--L-mm", "L in millimetres, with --E-s (default 2).")
    ),
    vtk: Path | None = typer.Option(
        None,
        "--vtk",
        help="Write a ParaView series (.pvd + .vtu) to DIR; the contact forces are the least-norm member"
        " of each state's multiplier set, the same from every backend (formulations/stability.md eq. (8c)).",
    ),
    max_memory_gb: float | None = MemoryOpt,
    max_minutes: float | None = MinutesOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Puncture: push a top-face point of the centre scale down until its tilt reaches phi_c."""
    from .api import puncture as run

    with _spinner("puncture") as progress:
        report = run(
            shape,
            tiling,
            slant,
            slant_dir,
            gap,
            thickness,
            rings=_rings_value(rings),
            isolated=isolated,
            interaction=interaction,
            coupling_factor=coupling_factor,
            solver=solver,
            formulation=formulation,
            accuracy=accuracy,
            phi_c_deg=phi_c,
            nu=nu,
            load_point=load_point,
            probe=probe,
            E_s=E_s,
            L_mm=L_mm,
            vtk=vtk,
            max_memory_gb=max_memory_gb,
            max_minutes=max_minutes,
            progress=progress,
            rings_tol=rings_tol,
            max_increments=max_increments,
            edges=edges,
            condense=condense,
        )

    def summary(p: dict[str, Any]) -> None:
        if "rings_auto" in p:
            _rings_summary(p["rings_auto"])
        extra = f" = {_fmt(p.get('Fc_N'), '.4g')} N" if "Fc_N" in p else ""
        branch = " (branched: followed the asymmetric path)" if (p["branch"] or {}).get("branched") else ""
        console.print(
            f"[bold]{p['shape']} ({p['tiling']})[/], {p['n_scales']} scales, {p['interaction']}: "
            f"F_c* = {_fmt(p['Fc_star'], '.6g')}{extra} at tilt {_fmt(p['tilt_deg'], '.4g')} deg, load point "
            f"({_fmt(p['load_point'][0], '.3f')}, {_fmt(p['load_point'][1], '.3f')}), "
            f"delta_c* = {_fmt(p['delta_c_star'], '.4g')}{branch}; {p['increments']} increments, "
            f"{p['load_levels']} load levels, {p['qp_solves']} QPs, "
            f"max penetration {_fmt(p['max_penetration'], '.2g')} L, "
            f"{_fmt(p['wall_s'], '.2f')} s"
        )

    finish(report, as_json, summary)


@app.command()
@handles_errors
def flexure(
    shape: str | None = typer.Option(None, "--shape", help=_help("--shape", "Base shape (default square).")),
    tiling: str | None = TilingOpt,
    slant: float | None = typer.Option(None, "--slant", help=_help("--slant", "Slant angle (default 0).")),
    slant_dir: float | None = typer.Option(
        None, "--slant-dir", help=_help("--slant-dir", "Slant direction (default 0).")
    ),
    gap: float | None = typer.Option(None, "--gap", help=_help("--gap", "Gap d (default 0.005).")),
    thickness: float | None = typer.Option(
        None, "--thickness", help=_help("--thickness", "Scale thickness t (default 1).")
    ),
    load_line: str = typer.Option(
        "x", "--load-line", help=_help("--load-line", "Direction of the loading plate.")
    ),
    isolated: bool = typer.Option(False, "--isolated", help="One scale at the centre of the membrane."),
    bare: bool = typer.Option(False, "--bare", help="The membrane alone, no scales (no design flags)."),
    nu_m: float = typer.Option(0.5, "--nu-m", help=_help("--nu-m", "Poisson's ratio of the membrane.")),
    mesh_h: float = typer.Option(
        0.5, "--mesh-h", help=_help("--mesh-h", "In-plane element size (layers: max(2, 1.5/h)).")
    ),
    solver: str = typer.Option(
        DEFAULT_SOLVER, "--solver", help=_help("--solver", "QP backend (not penalty).")
    ),
    formulation: str = typer.Option(
        "plane",
        "--formulation",
        help=_help("--formulation", "Scale-scale contact: separating planes or features."),
    ),
    vtk: Path | None = typer.Option(None, "--vtk", help="Write a ParaView series (.pvd + .vtu) to DIR."),
    roller_radius: float = typer.Option(
        0.5, "--roller-radius", help=_help("--roller-radius", "Radius of the support rollers.")
    ),
    top_h: float | None = typer.Option(
        None, "--top-h", help=_help("--top-h", "Grade the layers from this thickness at the top face.")
    ),
    mesh: str = typer.Option(
        "tensor",
        "--mesh",
        help=_help(
            "--mesh",
            "The tensor mesh, or the footprint-fitted one that follows oblique gaps too "
            "(gmsh, which needs the system's OpenGL and X11 libraries).",
        ),
    ),
    error: bool = typer.Option(
        True,
        "--error/--no-error",
        help="Estimate C_f*'s discretisation error on a refined companion mesh (about 3x the time).",
    ),
    max_memory_gb: float | None = MemoryOpt,
    max_minutes: float | None = MinutesOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Flexure: three-point bending of the membrane (bare, one scale, or covered), C_f*."""
    from .api import flexure as run

    with _spinner("flexure") as progress:
        report = run(
            shape,
            tiling,
            slant,
            slant_dir,
            gap,
            thickness,
            load_line=load_line,
            isolated=isolated,
            bare=bare,
            nu_m=nu_m,
            mesh_h=mesh_h,
            solver=solver,
            formulation=formulation,
            roller_radius=roller_radius,
            top_h=top_h,
            mesh=mesh,
            error=error,
            vtk=vtk,
            max_memory_gb=max_memory_gb,
            max_minutes=max_minutes,
            progress=progress,
        )

    def summary(p: dict[str, Any]) -> None:
        design = "membrane" if p["mode"] == "bare" else f"{p['shape']} ({p['tiling']})"
        console.print(
            f"[bold]{p['mode']}[/] {design}, load line {p['load_line']}: "
            f"C_f* = {_fmt(p['Cf_star'], '.5g')}"
            + (f" ± {_fmt(p['Cf_star_error'], '.2g')}" if p["Cf_star_error"] is not None else "")
            + f", {p['n_scales']} scales, {_fmt(p['wall_s'], '.2f')} s"
        )
        if p["mesh"] == "tensor" and p["oblique_edges"]:
            console.print(
                "note: the tensor mesh cannot follow this design's oblique edges (its reductions are up "
                "to 5.5 points low there); --mesh fitted does (formulations/membrane.md sec. 9e)"
            )

    finish(report, as_json, summary)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that a study cleans up as on Ctrl-C."""


@contextlib.contextmanager
def terminate_as_interrupt() -> Any:
    """While a study runs, SIGTERM raises :class:`_Terminated` (the pool's workers are then
    terminated and no partial file is left claiming to be complete)."""

    def handler(signum: int, frame: Any) -> None:
        raise _Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread (a test runner's worker): leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@app.command()
@handles_errors
def paper(
    out: Path = typer.Option(Path("paper_out"), "--out", help="Directory for the table and figures."),
    quick: bool = typer.Option(False, "--quick", help="Two designs, coarse settings (a few minutes)."),
    smoke: bool = typer.Option(
        False, "--smoke", help="With --quick: one scene per study (the plain-install check; under a minute)."
    ),
    workers: int | None = typer.Option(
        None, "--workers", help=_help("--workers", "Worker processes of the local Dask cluster (default 2).")
    ),
    scheduler: str | None = typer.Option(
        None, "--scheduler", help=_help("--scheduler", "Run the scenes on this Dask cluster.")
    ),
    scene_time_limit: float | None = typer.Option(
        None,
        "--scene-time-limit",
        help=_help(
            "--scene-time-limit",
            "CPU seconds per scene before it is recorded as time_limit (default 900, quick 120;"
            " patch scenes twice that).",
        ),
    ),
    as_json: bool = JsonOpt,
) -> None:
    """Every study of the paper: results table (CSV, Parquet) and figures (PNG, SVG) in --out.

    Each finished scene is saved in --out/scenes at once; a rerun into the same --out resumes.
    """
    from . import validation as v
    from .studies.engine import Engine
    from .studies.paper import MAX_WORKERS, run_paper
    from .studies.paper_scenes import paper_scenes, smoke_scenes

    if scheduler is not None and workers is not None:
        raise v.conflict("scheduler", "workers", "the cluster at --scheduler has its own workers")
    n_workers = v.integer("workers", MAX_WORKERS if workers is None else workers, 1, MAX_WORKERS)
    limit = None if scene_time_limit is None else v.real("scene_time_limit", scene_time_limit, 0.0, None)
    if smoke and not quick:
        raise v.conflict("smoke", "quick", "--smoke is a subset of the quick study: give --quick too")
    out_dir = v.output_dir("out", out)
    scenes = smoke_scenes() if smoke else paper_scenes(quick)
    engine = Engine(min(n_workers, os.cpu_count() or 1), scheduler, announce=_print_info)
    with terminate_as_interrupt(), _progress("paper") as bar:
        task = bar.add_task(f"paper: 0/{len(scenes)} scenes", total=len(scenes))

        def step(scene: Any, row: dict[str, Any]) -> None:
            bar.advance(task)
            done = int(bar.tasks[0].completed)
            bar.update(
                task, description=f"paper: {done}/{len(scenes)} scenes, last {scene.key} {row['status']}"
            )

        try:
            with engine:
                result = run_paper(
                    out_dir, quick=quick, progress=step, scenes=scenes, scene_limit_s=limit, engine=engine
                )
        except KeyboardInterrupt as exc:
            what = "terminated" if isinstance(exc, _Terminated) else "interrupted"
            _print_error(
                f"error: {what}: finished scenes are saved in {out_dir / 'scenes'}; rerun the same "
                "command to resume"
            )
            raise typer.Exit(143 if isinstance(exc, _Terminated) else EXIT_INTERRUPTED) from None
    failed = result.table[result.table["status"] != "ok"]
    payload = {
        "out": str(out_dir),
        "n_scenes": len(result.table),
        "n_failed": len(failed),
        "failed": [{"scene": r["scene"], "status": r["status"]} for _, r in failed.iterrows()],
        "table": {k: str(x) for k, x in result.files.items()},
        "figures": [str(p) for p in result.figures],
        "wall_s": result.wall_s,
    }

    def summary(p: dict[str, Any]) -> None:
        console.print(
            f"[bold]paper[/]: {p['n_scenes']} scenes, {p['n_failed']} failed, "
            f"{len(p['figures'])} figure files, table {p['table']['csv']}, {p['wall_s']:.0f} s"
        )
        for f in p["failed"]:
            console.print(f"  failed: {f['scene']}: {f['status']}", markup=False)

    emit(payload, as_json, summary)


@app.command()
@handles_errors
def substrate(
    shape: str = ShapeOpt,
    tiling: str | None = TilingOpt,
    gap: float | None = typer.Option(
        None, "--gap", help=_help("--gap", "Gap d (default 0.005; not with --isolated).")
    ),
    nu: float = typer.Option(0.5, "--nu", help=_help("--nu", "Poisson's ratio of the substrate.")),
    isolated: bool = typer.Option(False, "--isolated", help="Only the isolated single-punch stiffness."),
    refinement: int = typer.Option(
        6, "--refinement", help=_help("--refinement", "Panel strips per fan triangle.")
    ),
    as_json: bool = JsonOpt,
) -> None:
    """Normalised substrate stiffness: isolated punch, self block K0, coupling blocks K1."""
    from .api import substrate as run

    report = run(shape, tiling, gap, nu, isolated, refinement)

    def summary(p: dict[str, Any]) -> None:
        console.print(
            f"[bold]{p['shape']} ({p['tiling']})[/], nu = {p['nu']}: isolated "
            + ", ".join(f"{k} {x:.4g}" for k, x in p["isolated"].items())
        )
        if "K0" in p:
            console.print(
                "K0 "
                + ", ".join(f"{k} {x:.4g}" for k, x in p["K0"].items())
                + f"; {len(p['neighbours'])} coupling blocks, asymmetry {p['asymmetry']:.2g}"
            )

    finish(report, as_json, summary)


@app.command()
@handles_errors
def bench(
    out: Path = typer.Option(Path("bench_out"), "--out", help="Directory for the charts (PNG) and CSV."),
    quick: bool = typer.Option(False, "--quick", help="Two scenes, fewer methods, a small stability grid."),
    time_limit: float = typer.Option(
        60.0, "--time-limit", help=_help("--time-limit", "Seconds per curve counted for a failure.")
    ),
    workers: int = typer.Option(
        1, "--workers", help=_help("--workers", "Worker processes (more than 1: a local Dask cluster).")
    ),
    fuzz_n: int = typer.Option(
        1000, "--fuzz", help=_help("--fuzz", "Random designs of the fuzz grid (full bench; 0: none).")
    ),
    as_json: bool = JsonOpt,
) -> None:
    """Solver and formulation comparison: speed against accuracy, stability where methods fail.

    A backend that is not installed is skipped and listed as skipped.
    """
    from . import validation as v
    from .studies.bench_report import run_all
    from .studies.engine import check_workers

    limit = v.real("time_limit", time_limit, 0.0, None, lo_open=True, unit="s")
    check_workers(v.integer("workers", workers, 1, 1024))
    n_fuzz = v.integer("fuzz", fuzz_n, 0, 100_000)
    out_dir = v.output_dir("out", out)
    with _spinner("bench") as progress, terminate_as_interrupt():
        payload = run_all(
            out_dir,
            quick,
            limit,
            progress=progress,
            fuzz_n=n_fuzz,
            workers=workers,
        )

    def summary(p: dict[str, Any]) -> None:
        for m in p["methods"]:
            ratio = m["time_ratio_to_cvxpy"]
            console.print(
                f"{m['name']:>22}: success {m['success_rate']:.0%}, median {m['median_wall_s']:.2f} s"
                + (f", x{ratio:.2f} of cvxpy" if ratio is not None else "")
                + (f", F_c error {m['Fc_rel_error']:.1e}" if m["Fc_rel_error"] is not None else "")
            )
        for sk in p.get("skipped", []):
            console.print(f"{sk['name']:>22}: skipped, {sk['reason']}", markup=False)
        for name, f in p.get("fuzz", {}).get("methods", {}).items():
            console.print(f"fuzz {name:>17}: {f['success_rate']:.1%} of {f['designs']} designs pass")
        console.print(f"charts and CSV in {p['out']}")

    emit(payload, as_json, summary)


def _bar(description: str):
    """A progress bar with a count and the time left (stderr, only on a terminal)."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err_console,
        transient=True,
        disable=not err_console.is_terminal,
    )


@app.command()
@handles_errors
def sweep(
    grid: Path = typer.Argument(..., help=_help("grid", "The designs to run.")),
    out: Path = typer.Option(
        Path("sweep.parquet"),
        "--out",
        help=_help("--out", "The results table (Parquet); rows in it are skipped."),
    ),
    workers: int | None = typer.Option(
        None,
        "--workers",
        help=_help("--workers", "Worker processes of the local Dask cluster (default: the cores)."),
    ),
    scheduler: str | None = typer.Option(
        None, "--scheduler", help=_help("--scheduler", "Run the designs on this Dask cluster.")
    ),
    retry_failed: bool = typer.Option(
        False, "--retry-failed", help="Also rerun the designs whose row in --out did not end ok."
    ),
    as_json: bool = JsonOpt,
) -> None:
    """Many designs on Dask: a grid or a random sample from GRID, one row per design in --out.

    Resumable: designs already in --out are skipped; a killed run keeps its finished rows.
    """
    from . import validation as v
    from .studies.engine import Engine, check_workers
    from .studies.sweep import load_spec
    from .studies.sweep_run import run_sweep

    if scheduler is not None and workers is not None:
        raise v.conflict("scheduler", "workers", "the cluster at --scheduler has its own workers")
    n_workers = check_workers((os.cpu_count() or 1) if workers is None else workers)
    spec = load_spec(grid)
    out_file = v.output_file("out", out)
    if out_file.suffix.lower() != ".parquet":
        raise InvalidDesign("out", str(out_file), "a .parquet file")
    engine = Engine(n_workers, scheduler, local_cluster=True, announce=_print_info)
    with terminate_as_interrupt(), _bar("sweep") as bar:
        task = bar.add_task("sweep", total=None)

        def start(todo: int, skipped: int) -> None:
            _print_info(f"sweep: {len(spec.designs)} designs, {skipped} already in {out_file}, {todo} to run")
            bar.update(task, total=todo)

        def step(row: dict[str, Any]) -> None:
            bar.update(task, advance=1, description=f"sweep: last {row['status']}")

        try:
            with engine:
                result = run_sweep(spec, out_file, engine, retry_failed, on_start=start, on_done=step)
        except KeyboardInterrupt as exc:
            what = "terminated" if isinstance(exc, _Terminated) else "interrupted"
            _print_error(
                f"error: {what}: finished designs are in {out_file}; rerun the same command to resume"
            )
            raise typer.Exit(143 if isinstance(exc, _Terminated) else EXIT_INTERRUPTED) from None
    payload = {
        "out": str(result.out),
        "experiment": spec.experiment,
        "sample": spec.sample,
        "n_designs": result.n_designs,
        "n_skipped": result.n_skipped,
        "n_run": result.n_run,
        "n_rows": sum(result.statuses.values()),
        "n_failed": len(result.failed),
        "statuses": result.statuses,
        "failed": result.failed,
        "engine": engine.started or engine.describe(),
        "wall_s": result.wall_s,
    }

    def summary(p: dict[str, Any]) -> None:
        counts = ", ".join(f"{n} {s}" for s, n in sorted(p["statuses"].items()))
        console.print(
            f"[bold]sweep[/] ({p['experiment']}, {p['sample']}): {p['n_designs']} designs, "
            f"{p['n_skipped']} skipped, {p['n_run']} run; table {p['out']}: {counts}; {p['wall_s']:.0f} s"
        )
        for f in p["failed"][:20]:
            console.print(f"  {f['status']}: {f['key']}", markup=False)
        if len(p["failed"]) > 20:
            console.print(f"  ... and {len(p['failed']) - 20} more (column status of the table)")

    emit(payload, as_json, summary)


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
