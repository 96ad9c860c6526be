"""The ``qpscale`` command line (typer).  The only module that prints or sets exit codes.

Each subcommand prints a human summary, or one JSON object with ``--json``; field names
follow the contract in SPEC.md.  Invalid input exits with status 2 and one line on stderr
naming the parameter; a solver failure exits with status 3 and the solver's status.
It implements no formulation: each command calls the module that does, which names its
formulations/ file.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console

from . import __version__
from .errors import InvalidDesign, QpscaleError, SolverFailure, SolverUnavailable
from .tiling import Design, max_overlap_area, min_gap

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="3D mechanics of scaled skins: exact contact as a QP per load increment.",
)
console = Console()
err_console = Console(stderr=True)

F = TypeVar("F", bound=Callable[..., Any])

EXIT_INVALID = 2
EXIT_SOLVER = 3


def _fail(code: int, message: str) -> None:
    err_console.print(f"error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


# API parameter -> command-line flag, so the one-line error names what the user typed.
FLAG_OF = {
    "slant_deg": "--slant",
    "slant_dir_deg": "--slant-dir",
    "gap": "--gap",
    "thickness": "--thickness",
    "rings": "--rings",
    "shape": "--shape",
    "tiling": "--tiling",
    "nu": "--nu",
    "nu_s": "--nu",
    "coupling": "--coupling-factor",
    "phi_c_deg": "--phi-c",
    "solver": "--solver",
}


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
            if kwargs.get("as_json"):
                with json_stdout():
                    return func(*args, **kwargs)
            return func(*args, **kwargs)
        except InvalidDesign as exc:
            flag = FLAG_OF.get(exc.parameter, "--" + exc.parameter.replace("_", "-"))
            _fail(EXIT_INVALID, f"{flag}: {exc}")
        except SolverUnavailable as exc:
            _fail(EXIT_INVALID, str(exc))
        except SolverFailure as exc:
            _fail(EXIT_SOLVER, str(exc))
        except QpscaleError as exc:
            _fail(EXIT_SOLVER, str(exc))

    return wrapper  # type: ignore[return-value]


def emit(payload: dict[str, Any], as_json: bool, summary: Callable[[dict[str, Any]], None]) -> None:
    """Print ``payload`` as one JSON object, or a human summary of it."""
    if as_json:
        text = json.dumps(payload, allow_nan=False) + "\n"
        if _json_fd is not None:
            data = memoryview(text.encode())
            while data:  # a pipe may take a large payload in parts
                data = data[os.write(_json_fd, data) :]
        else:
            sys.stdout.write(text)
    else:
        summary(payload)


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


# Options shared by the design-based commands; names follow SPEC.md.
ShapeOpt = typer.Option("square", "--shape", help="triangle, square, trapezoid, dart or hexagon.")
TilingOpt = typer.Option(None, "--tiling", help="arrayed or staggered (triangle, square, trapezoid).")
SlantOpt = typer.Option(0.0, "--slant", help="Slant angle alpha from the vertical, degrees, [0, 90).")
SlantDirOpt = typer.Option(0.0, "--slant-dir", help="Slant direction, degrees from +x (0, 45 or 90).")
GapOpt = typer.Option(0.005, "--gap", help="Gap d between neighbouring bases, in L, >= 0.")
ThicknessOpt = typer.Option(1.0, "--thickness", help="Scale thickness t, in L, > 0.")
RingsOpt = typer.Option(2, "--rings", help="Rings of neighbours around the punctured scale (2: 5x5).")
JsonOpt = typer.Option(False, "--json", help="Print one JSON object.")


def make_design(
    shape: str, tiling: str | None, slant: float, slant_dir: float, gap: float, thickness: float, rings: int
) -> Design:
    return Design(
        shape=shape,
        tiling=tiling,
        slant_deg=slant,
        slant_dir_deg=slant_dir,
        gap=gap,
        thickness=thickness,
        rings=rings,
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
    rings: int = RingsOpt,
    png: Path | None = typer.Option(None, "--png", help="Draw the patch to FILE."),
    as_json: bool = JsonOpt,
) -> None:
    """Build a design's patch and check it: areas, gaps, overlaps, top-face offset."""
    design = make_design(shape, tiling, slant, slant_dir, gap, thickness, rings)
    patch = design.patch()
    areas = [p.area for p in patch.polygons()]
    payload = {
        "shape": design.shape,
        "tiling": design.tiling,
        "base_area": float(areas[0]),
        "base_area_spread": float(max(areas) - min(areas)),
        "n_scales": patch.n_scales,
        "n_neighbour_pairs": int(len(patch.neighbours)),
        "n_contact_pairs": int(len(patch.contact_pairs)),
        "min_gap": min_gap(patch) if patch.n_scales > 1 else None,
        "max_overlap_area": max_overlap_area(patch),
        "top_offset": [float(v) for v in design.top_offset],
        "volume": patch.prism(0).volume,
    }
    if png is not None:
        from .plotting import draw_patch

        draw_patch(patch, png)
        payload["png"] = str(png)

    def summary(p: dict[str, Any]) -> None:
        console.print(
            f"[bold]{p['shape']} ({p['tiling']})[/]: {p['n_scales']} scales, base area "
            f"{p['base_area']:.12g} L^2, min gap {p['min_gap']}, max overlap {p['max_overlap_area']:.3g}, "
            f"top offset ({p['top_offset'][0]:.4g}, {p['top_offset'][1]:.4g}) L"
        )

    emit(payload, as_json, summary)


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


@app.command()
@handles_errors
def puncture(
    shape: str = ShapeOpt,
    tiling: str | None = TilingOpt,
    slant: float = SlantOpt,
    slant_dir: float = SlantDirOpt,
    gap: float = GapOpt,
    thickness: float = ThicknessOpt,
    rings: int = RingsOpt,
    isolated: bool = typer.Option(False, "--isolated", help="The punctured scale alone (rings = 0)."),
    interaction: str = typer.Option(
        "full", "--interaction", help="full, substrate (contact off) or contact."
    ),
    coupling_factor: float | None = typer.Option(
        None,
        "--coupling-factor",
        help="Substrate coupling f in [0, 1] (default 1; 0.04 for --interaction contact).",
    ),
    solver: str = typer.Option("clarabel", "--solver", help="clarabel, osqp, cvxpy or qpsolvers:<name>."),
    accuracy: str = typer.Option("high", "--accuracy", help="QP tolerance: high 1e-9, mid 1e-6, low 1e-3."),
    phi_c: float = typer.Option(13.0, "--phi-c", help="Critical tilt, degrees, (0, 60]."),
    nu: float = typer.Option(0.5, "--nu", help="Poisson's ratio of the substrate, [0, 0.5]."),
    load_point: tuple[float, float] | None = typer.Option(
        None,
        "--load-point",
        help="x y of the load point relative to the scale's reference point, in L "
        "(default: the worst top-face vertex).",
    ),
    probe: bool = typer.Option(
        True,
        "--probe/--no-probe",
        help="Test every state by the second variation and follow branches.",
    ),
    E_s: float | None = typer.Option(
        None, "--E-s", help="Substrate modulus in Pa, to report F_c in newtons."
    ),
    L_mm: float = typer.Option(2.0, "--L-mm", help="L in millimetres, to report F_c in newtons."),
    vtk: Path | None = typer.Option(None, "--vtk", help="Write a ParaView series (.pvd + .vtu) to DIR."),
    as_json: bool = JsonOpt,
) -> None:
    """Puncture: push a top-face point of the centre scale down until its tilt reaches phi_c."""
    from .experiments.puncture import PunctureSetup, run_puncture
    from .increment import SQPSettings
    from .solvers import available_solvers

    allowed = [*available_solvers(), "penalty"]
    if solver not in allowed:
        raise InvalidDesign("solver", solver, "{" + ", ".join(allowed) + "}")
    if E_s is not None and not (math.isfinite(E_s) and E_s > 0):
        raise InvalidDesign("E_s", E_s, "(0, inf) Pa")  # before the run, not after it
    design = make_design(shape, tiling, slant, slant_dir, gap, thickness, 0 if isolated else rings)
    setup = PunctureSetup(
        design=design,
        interaction=interaction,
        coupling=coupling_factor,
        nu=nu,
        phi_c_deg=phi_c,
        load_point=load_point,
        probe=probe,
        sqp=SQPSettings(solver=solver, accuracy=accuracy),
    )
    with _progress("puncture") as bar:
        task = bar.add_task("puncture", total=None)
        result = run_puncture(setup, progress=lambda msg: bar.update(task, description=f"puncture: {msg}"))
    payload = {
        "Fc_star": result.Fc_star,
        "delta_c_star": result.delta_c_star,
        "load_point": [float(v) for v in result.load_point],
        "tilt_deg": float(result.tilt_deg[-1]),
        "max_penetration": result.max_penetration,
        "increments": len(result.states) - 1,
        "solver": solver,
        "wall_s": result.wall_s,
        "qp_solves": result.qp_solves,
        "n_scales": design.patch().n_scales,
        "interaction": interaction,
        "coupling_factor": setup.coupling_factor,
        "curve": {
            "w_star": result.w_star.tolist(),
            "F_star": result.F_star.tolist(),
            "tilt_deg": result.tilt_deg.tolist(),
        },
        "candidates": result.candidates,
        "branch": result.branch,
        "events": result.events,
    }
    if E_s is not None:
        from .units import force_from_star

        payload["Fc_N"] = force_from_star(result.Fc_star, E_s, nu, L_mm * 1e-3)
    if vtk is not None:
        from .export_vtk import write_puncture_series

        payload["vtk"] = str(write_puncture_series(result, vtk))

    def summary(p: dict[str, Any]) -> None:
        extra = f" = {p['Fc_N']:.4g} N" if "Fc_N" in p else ""
        branch = " (branched: followed the asymmetric path)" if p["branch"].get("branched") else ""
        console.print(
            f"[bold]{design.shape} ({design.tiling})[/], {p['n_scales']} scales, {interaction}: "
            f"F_c* = {p['Fc_star']:.6g}{extra} at tilt {p['tilt_deg']:.4g} deg, load point "
            f"({p['load_point'][0]:.3f}, {p['load_point'][1]:.3f}), delta_c* = {p['delta_c_star']:.4g}"
            f"{branch}; {p['increments']} increments, {p['qp_solves']} sequential QPs, "
            f"max penetration {p['max_penetration']:.2g} L, {p['wall_s']:.2f} s"
        )

    emit(payload, as_json, summary)


@app.command()
@handles_errors
def flexure(
    shape: str = ShapeOpt,
    tiling: str | None = TilingOpt,
    slant: float = SlantOpt,
    slant_dir: float = SlantDirOpt,
    gap: float = GapOpt,
    thickness: float = ThicknessOpt,
    load_line: str = typer.Option("x", "--load-line", help="Direction of the loading plate: x or y."),
    isolated: bool = typer.Option(False, "--isolated", help="One scale at the centre of the membrane."),
    bare: bool = typer.Option(False, "--bare", help="The membrane alone, no scales."),
    nu_m: float = typer.Option(0.5, "--nu-m", help="Poisson's ratio of the membrane, [0, 0.5]."),
    mesh_h: float = typer.Option(0.5, "--mesh-h", help="In-plane element size, in L."),
    solver: str = typer.Option("clarabel", "--solver", help="clarabel, osqp, cvxpy or qpsolvers:<name>."),
    formulation: str = typer.Option(
        "plane", "--formulation", help="Scale-scale contact: plane (separating planes) or feature."
    ),
    vtk: Path | None = typer.Option(None, "--vtk", help="Write a ParaView series (.pvd + .vtu) to DIR."),
    # issue 21: roller supports and top-layer grading (formulations/membrane.md secs. 1, 9c)
    roller_radius: float = typer.Option(0.5, "--roller-radius", help="Radius of the support rollers, in L."),
    top_h: float | None = typer.Option(
        None, "--top-h", help="Grade the membrane's layers from this thickness at the top face, in L."
    ),
    as_json: bool = JsonOpt,
) -> None:
    """Flexure: three-point bending of the membrane (bare, one scale, or covered), C_f*."""
    from .experiments.flexure import FlexureSetup, run_flexure
    from .membrane import MembraneModel

    if isolated and bare:
        raise InvalidDesign("--isolated/--bare", "both", "at most one of them")
    design = make_design(shape, tiling, slant, slant_dir, gap, thickness, 2)
    nz = max(2, int(round(1.5 / mesh_h)))
    mode = "bare" if bare else "isolated" if isolated else "scaled"
    setup = FlexureSetup(
        design=design,
        mode=mode,
        load_line=load_line,
        membrane=MembraneModel(nu=nu_m, h=mesh_h, nz=nz, top_h=top_h),
        solver=solver,
        formulation=formulation,
        roller_radius=roller_radius,
    )
    result = run_flexure(setup)
    payload = {
        "Cf_star": result.Cf_star,
        "curve": {"deflection_star": result.deflection.tolist(), "F_star": result.force.tolist()},
        "wall_s": result.wall_s,
        "mode": mode,
        "load_line": load_line,
        "n_scales": result.n_scales,
        "n_retained": result.n_retained,
        "sqp_iterations": result.sqp_iterations,
        "max_penetration": result.max_penetration,
        "released_supports": result.extras["released"],
        "formulation": setup.formulation,
        "roller_radius": setup.roller_radius,
    }
    if vtk is not None:
        from .export_vtk_flexure import write_flexure_series

        payload["vtk"] = str(write_flexure_series(result, vtk))

    def summary(p: dict[str, Any]) -> None:
        console.print(
            f"[bold]{mode}[/] {design.shape} ({design.tiling}), load line {load_line}: "
            f"C_f* = {p['Cf_star']:.5g}, {p['n_scales']} scales, {p['wall_s']:.2f} s"
        )

    emit(payload, as_json, summary)


@app.command()
@handles_errors
def paper(
    out: Path = typer.Option(Path("paper_out"), "--out", help="Directory for the table and figures."),
    quick: bool = typer.Option(False, "--quick", help="Two designs, coarse settings (a few minutes)."),
    workers: int = typer.Option(2, "--workers", help="Parallel processes, 1 or 2."),
    scene_time_limit: float | None = typer.Option(
        None,
        "--scene-time-limit",
        help="Seconds per scene before it is recorded as time_limit (default 900, quick 60; 0: none).",
    ),
    as_json: bool = JsonOpt,
) -> None:
    """Every study of the paper: results table (CSV, Parquet) and figures (PNG, SVG) in --out."""
    from .studies.paper import run_paper
    from .studies.paper_scenes import paper_scenes

    if workers not in (1, 2):
        raise InvalidDesign("workers", workers, "{1, 2}")
    if scene_time_limit is not None and not scene_time_limit >= 0:
        raise InvalidDesign("scene-time-limit", scene_time_limit, "[0, inf) seconds, 0 for none")
    scenes = paper_scenes(quick)
    with _progress("paper") as bar:
        task = bar.add_task(f"paper: 0/{len(scenes)} scenes", total=len(scenes))

        def step(scene: Any, row: dict[str, Any]) -> None:
            bar.advance(task)
            done = int(bar.tasks[0].completed)
            bar.update(
                task, description=f"paper: {done}/{len(scenes)} scenes, last {scene.key} {row['status']}"
            )

        result = run_paper(
            out, quick=quick, workers=workers, progress=step, scenes=scenes, scene_limit_s=scene_time_limit
        )
    failed = result.table[result.table["status"] != "ok"]
    payload = {
        "out": str(out),
        "n_scenes": len(result.table),
        "n_failed": len(failed),
        "failed": [{"scene": r["scene"], "status": r["status"]} for _, r in failed.iterrows()],
        "table": {k: str(v) for k, v in result.files.items()},
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


_DOF_KEYS = ("Kx", "Ky", "Kz", "Kphix", "Kphiy")


@app.command()
@handles_errors
def substrate(
    shape: str = ShapeOpt,
    tiling: str | None = TilingOpt,
    gap: float = GapOpt,
    nu: float = typer.Option(0.5, "--nu", help="Poisson's ratio of the substrate, [0, 0.5]."),
    isolated: bool = typer.Option(False, "--isolated", help="Only the isolated single-punch stiffness."),
    refinement: int = typer.Option(6, "--refinement", help="Panel strips per fan triangle, [2, 16]."),
    as_json: bool = JsonOpt,
) -> None:
    """Normalised substrate stiffness: isolated punch, self block K0, coupling blocks K1."""
    from .substrate import SubstrateModel, calibrate, coupling_ratio, isolated_block

    design = Design(shape=shape, tiling=tiling, gap=gap)
    model = SubstrateModel(nu=nu, refinement=refinement)

    def diag(K: Any) -> dict[str, float]:
        return {k: float(v) for k, v in zip(_DOF_KEYS, K.diagonal())}

    if isolated:
        K_iso = isolated_block(design.shape, nu, refinement)
        payload: dict[str, Any] = {"isolated": diag(K_iso), "isolated_block": K_iso.tolist()}
    else:
        cal = calibrate(design, model)
        near = [c for c in cal.couplings if c.source == 0]
        payload = {
            "isolated": diag(cal.K_iso),
            "K0": diag(cal.K0[0]),
            "K0_block": cal.K0[0].tolist(),
            "neighbours": [
                {
                    "offset": list(c.offset),
                    "site": [*c.site, c.receiver],
                    "K1": diag(c.K1),
                    "K1_block": c.K1.tolist(),
                    "ratio": coupling_ratio(c.K1, cal.K0[0]),
                }
                for c in near
            ],
            "asymmetry": cal.asymmetry,
            "n_panels": cal.n_panels,
        }
    payload.update({"shape": design.shape, "tiling": design.tiling, "gap": gap, "nu": nu})

    def summary(p: dict[str, Any]) -> None:
        console.print(
            f"[bold]{p['shape']} ({p['tiling']})[/], nu = {p['nu']}: isolated "
            + ", ".join(f"{k} {v:.4g}" for k, v in p["isolated"].items())
        )
        if "K0" in p:
            console.print(
                "K0 "
                + ", ".join(f"{k} {v:.4g}" for k, v in p["K0"].items())
                + f"; {len(p['neighbours'])} coupling blocks, asymmetry {p['asymmetry']:.2g}"
            )

    emit(payload, as_json, summary)


@app.command()
@handles_errors
def bench(
    out: Path = typer.Option(Path("bench_out"), "--out", help="Directory for the charts (PNG) and CSV."),
    quick: bool = typer.Option(False, "--quick", help="Two scenes, fewer methods, a small stability grid."),
    time_limit: float = typer.Option(60.0, "--time-limit", help="Seconds per curve counted for a failure."),
    workers: int = typer.Option(1, "--workers", help="Parallel processes (at most the core count)."),
    fuzz_n: int = typer.Option(1000, "--fuzz", help="Random designs of the fuzz grid (full bench; 0: none)."),
    as_json: bool = JsonOpt,
) -> None:
    """Solver and formulation comparison: speed against accuracy, stability where methods fail."""
    from .studies.bench_report import run_all
    from .studies.parallel import check_workers

    if not time_limit > 0:
        raise InvalidDesign("time-limit", time_limit, "(0, inf) seconds")
    check_workers(workers)
    if fuzz_n < 0:
        raise InvalidDesign("fuzz", fuzz_n, "an integer >= 0")
    with _progress("bench") as bar:
        task = bar.add_task("bench", total=None)
        payload = run_all(
            out,
            quick,
            time_limit,
            progress=lambda m: bar.update(task, description=f"bench: {m}"),
            fuzz_n=fuzz_n,
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
        for name, f in p.get("fuzz", {}).get("methods", {}).items():
            console.print(f"fuzz {name:>17}: {f['success_rate']:.1%} of {f['designs']} designs pass")
        console.print(f"charts and CSV in {p['out']}")

    emit(payload, as_json, summary)


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
