"""Running one scene of the paper's studies and turning it into a table row (plus its curves).

Implements the read-outs of formulations/puncture.md (F_c* at tilt = phi_c, delta_c*, worst
vertex) and formulations/membrane.md eq. (14) (C_f*), and the isolated-scale estimate
F_c* ~ phi_c K_phi* / delta_c* of formulations/normalisation.md.  A solver failure becomes the
row's ``status`` (the solver's own word) with empty results: never a number.
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import replace

import numpy as np

from ..errors import QpscaleError, SolverFailure
from ..timelimit import TimeLimitReached, time_limit
from ..units import force_from_star
from .paper_scenes import Scene

log = logging.getLogger(__name__)

# Physical units of the validation scenes (Martini et al.): substrate and membrane moduli, L in m.
E_S_PA = 150e3
NU_S = 0.5
E_M_PA = 700e3
L_M = 2e-3
COUPLING_THRESHOLD = 0.01


def directional_rot_stiffness(K_iso: np.ndarray, load_xy: np.ndarray) -> float:
    """K_phi* about the axis a vertical load at ``load_xy`` (in L) tilts the scale around.

    A downward force at (x, y) has the moment (-y, x) F about the reference point, so the
    stiffness is n' K_rr n with n = (-y, x) / |(x, y)| and K_rr the rotational 2x2 block.

    >>> float(directional_rot_stiffness(np.diag([1, 1, 1, 2.0, 3.0]), np.array([1.0, 0.0])))
    3.0
    """
    n = np.array([-load_xy[1], load_xy[0]]) / np.hypot(*load_xy)
    return float(n @ np.asarray(K_iso)[3:5, 3:5] @ n)


def effective_neighbours(scene: Scene) -> list[list[float]]:
    """Offsets (dx, dy) of the neighbours whose coupling ratio |K1|/K0 exceeds 0.01 (paper Fig. 6a)."""
    from ..substrate import SubstrateModel, calibrate, coupling_ratio

    cal = calibrate(scene.design, SubstrateModel(nu=NU_S))
    return [
        [float(c.offset[0]), float(c.offset[1])]
        for c in cal.couplings
        if c.source == 0 and coupling_ratio(c.K1, cal.K0[0]) > COUPLING_THRESHOLD
    ]


def _puncture_setup(scene: Scene, rings: int | None = None, point: tuple[float, float] | None = None):
    """The puncture set-up of a puncture or patch scene, on ``rings`` rings instead of the scene's
    and at ``point`` instead of the worst vertex when given."""
    from ..experiments.puncture import PunctureSetup

    design = scene.design if rings is None else replace(scene.design, rings=rings)
    return PunctureSetup(
        design=design, interaction=scene.interaction, nu=NU_S, increments=scene.increments, load_point=point
    )


def check_status(result) -> str:
    """The exact F_c check's status of a puncture result (``verified``, ``unverified``), ``none``
    where it has none (the penalty baseline): the table's ``Fc_check``."""
    return result.Fc_check.status if result.Fc_check is not None else "none"


def _puncture(scene: Scene) -> tuple[dict, dict]:
    from ..experiments.puncture import run_puncture

    setup = _puncture_setup(scene)
    r = run_puncture(setup)
    row = {
        "Fc_star": r.Fc_star,
        "delta_c_star": r.delta_c_star,
        "load_x": float(r.load_point[0]),
        "load_y": float(r.load_point[1]),
        "tilt_deg_final": float(r.tilt_deg[-1]),
        "wc_star": float(r.w_star[-1]),
        "max_penetration": r.max_penetration,
        "n_increments": len(r.states) - 1,
        "qp_solves": r.qp_solves,
        "load_levels": r.load_levels,
        "branched": r.branch.branched,
        "Fc_check": check_status(r),
        "coupling": setup.coupling_factor,
        "Fc_N": force_from_star(r.Fc_star, E_S_PA, NU_S, L_M),
        "wc_mm": float(r.w_star[-1]) * L_M * 1e3,
    }
    if scene.rings == 0:
        from ..substrate import isolated_block

        row["K_phi_star"] = directional_rot_stiffness(isolated_block(scene.shape, NU_S), r.load_point)
        row["Fc_rigid_star"] = np.deg2rad(setup.phi_c_deg) * row["K_phi_star"] / r.delta_c_star
    data = {"w_star": r.w_star.tolist(), "F_star": r.F_star.tolist(), "q_final": r.states[-1].q.tolist()}
    if scene.rings > 0 and scene.interaction == "full" and scene.slant_deg == 0.0:
        data["effective_neighbours"] = effective_neighbours(scene)
        row["n_effective_neighbours"] = len(data["effective_neighbours"])
    return row, data


def paper_sibling(scene: Scene) -> Scene | None:
    """The puncture scene a patch scene starts from: the paper's patch of the same design at every
    vertex (the interaction study's full scene, or the slant study's); None for other kinds."""
    if scene.kind != "patch":
        return None
    from .paper_scenes import PAPER_RINGS

    study = "slant" if scene.slant_deg > 0.0 else "interaction"
    return replace(scene, study=study, kind="puncture", rings=PAPER_RINGS)


#: What a patch scene reads from its sibling's row instead of running the paper's patch again.
SIBLING_COLUMNS = ("Fc_star", "load_x", "load_y", "qp_solves", "Fc_check")


def _paper_patch(scene: Scene, sibling: dict | None) -> dict:
    """The paper's patch of a patch scene at its worst vertex (``SIBLING_COLUMNS``): read from its
    sibling's row when that run ended ok and recorded them all, run here otherwise.  The two are the
    same computation (the same set-up), so the patch scene's row does not depend on which."""
    from ..experiments.puncture import run_puncture
    from .paper_scenes import PAPER_RINGS

    if sibling is not None and sibling.get("status") == "ok":
        if all(sibling.get(c) is not None for c in SIBLING_COLUMNS):
            return {c: sibling[c] for c in SIBLING_COLUMNS}
    r = run_puncture(_puncture_setup(scene, PAPER_RINGS))
    return {
        "Fc_star": float(r.Fc_star),
        "load_x": float(r.load_point[0]),
        "load_y": float(r.load_point[1]),
        "qp_solves": int(r.qp_solves),
        "Fc_check": check_status(r),
    }


def _patch(scene: Scene, sibling: dict | None = None) -> tuple[dict, dict]:
    """The patch-size sequence of one design (formulations/puncture.md sec. 7, "The study's patch
    sequence"): the paper's patch at every vertex (``_paper_patch``: the sibling's row, ``sibling``,
    when given), then its worst vertex on the patches of 1, 2, ..., ``scene.rings`` rings, and what
    the sequence says about the skin (``patch_convergence.estimate``)."""
    from ..experiments.puncture import run_puncture
    from ..patch_convergence import estimate
    from .paper_scenes import PAPER_RINGS

    paper = _paper_patch(scene, sibling)
    point = (float(paper["load_x"]), float(paper["load_y"]))
    rings = list(range(1, scene.rings + 1))
    runs = {r: run_puncture(_puncture_setup(scene, r, point)) for r in rings if r != PAPER_RINGS}
    values = [float(paper["Fc_star"]) if r == PAPER_RINGS else float(runs[r].Fc_star) for r in rings]
    checks = [paper["Fc_check"], *map(check_status, runs.values())]
    widths = [2 * r + 1 for r in rings]
    est = estimate(widths, values)
    row = {
        "Fc_star": float(paper["Fc_star"]),
        "load_x": point[0],
        "load_y": point[1],
        **{f"Fc_r{r}": v for r, v in zip(rings, values)},
        "Fc_patch": est.value,
        "Fc_patch_err": est.error,
        "patch_verdict": est.verdict,
        "patch_change": est.change,
        "patch_note": est.note,
        "qp_solves": int(paper["qp_solves"]) + sum(int(x.qp_solves) for x in runs.values()),
        "unverified": sum(c != "verified" for c in checks),
    }
    data = {"rings": rings, "widths": widths, "Fc_star": values}
    return row, data


# Flexure scenes of the quick and smoke studies (mesh_h 1 L) keep the former one-element gaps and
# uniform layers: they check the chain in seconds; their covered compliances are several times too
# low (formulations/membrane.md sec. 9c), which the quick study's figures do not claim otherwise.
QUICK_MESH_H = 1.0


#: Element size along the gaps of the study's fitted meshes, in L (``FlexureSetup``'s default): the
#: honeycomb's reduction against its own isolated scale is the same to 0.01 point at 0.5, 0.25 and
#: 0.125 (formulations/membrane.md sec. 9e).
STUDY_ALONG = 0.5


def flexure_mesh(scene: Scene) -> str:
    """The study's mesh of a flexure scene: the footprint-fitted one where the design has oblique
    edges (triangle, trapezoid, dart, hexagon), which the tensor mesh cannot follow; the tensor
    mesh for the bare membrane, the square designs and the quick study (membrane.md sec. 9e)."""
    from ..experiments.flexure import oblique_edges

    if scene.flex_mode == "bare" or scene.mesh_h >= QUICK_MESH_H or scene.design.gap <= 0.0:
        return "tensor"
    return "fitted" if oblique_edges(scene.design) else "tensor"


def _flexure(scene: Scene) -> tuple[dict, dict]:
    from ..experiments.flexure import FlexureSetup, run_flexure
    from ..membrane import MembraneModel

    nz = max(2, int(round(1.5 / scene.mesh_h)))
    mesh = flexure_mesh(scene)
    setup = FlexureSetup(
        design=scene.design,
        mode=scene.flex_mode,
        load_line=scene.load_line,
        membrane=MembraneModel(nu=0.5, h=scene.mesh_h, nz=nz),
        increments=scene.increments,
        gap_elements=None if scene.mesh_h >= QUICK_MESH_H else FlexureSetup.gap_elements,
        mesh=mesh,
        along=STUDY_ALONG,
    )
    r = run_flexure(setup)
    # The membrane is solved with E_m = 1: forces are in E_m L^2.
    scale_N = E_M_PA * L_M**2
    row = {
        "Cf_star": r.Cf_star,
        "mesh": mesh,
        "C_f": r.C_f,
        "n_scales": r.n_scales,
        "max_penetration": r.max_penetration,
        "n_increments": len(r.deflection) - 1,
        "F_end_N": float(r.force[-1]) * scale_N,
        "deflection_end_mm": float(r.deflection[-1]) * L_M * 1e3,
    }
    data = {
        "deflection": r.deflection.tolist(),
        "force": r.force.tolist(),
        "deflection_mm": (r.deflection * L_M * 1e3).tolist(),
        "force_N": (r.force * scale_N).tolist(),
    }
    return row, data


#: The run of each kind of scene.
RUNNERS = {"puncture": _puncture, "flexure": _flexure, "patch": _patch}

#: The clock of a scene's time limit (``timelimit.time_limit``).
SCENE_CLOCK = "cpu"
#: A patch scene runs three puncture paths besides its sibling's, the largest on 3.2 times the
#: 5x5's scales: its limit is this many times a scene's (the 9x9 staggered triangle slanted 60 deg
#: towards 90 deg alone takes 672 s of CPU, the 5x5 at every vertex 175 s).
PATCH_LIMIT_FACTOR = 2.0


def scene_limit(scene: Scene, limit_s: float | None) -> float | None:
    """The CPU-time limit of ``scene`` in a study whose scene limit is ``limit_s``."""
    if limit_s is None or scene.kind != "patch":
        return limit_s
    return PATCH_LIMIT_FACTOR * limit_s


def run_scene(scene: Scene, limit_s: float | None = None, done: dict | None = None) -> tuple[dict, dict]:
    """Run one scene; return its table row (parameters, results, status) and its curve data.

    ``done`` maps scenes already run (here or in an earlier run) to their rows: a patch scene takes
    its sibling's (``paper_sibling``) from it.

    Failures are caught here so that a study carries on: ``status`` holds the solver's
    status (or the exception's class), ``error`` the message, and result columns stay empty.
    A scene still running after ``limit_s`` seconds of CPU time (a patch scene: ``scene_limit``) is
    abandoned with the status
    ``time_limit`` (CPU, not wall time: on a shared machine the load must not decide which scenes
    fail; ``cpu_s`` records the scene's CPU time beside ``wall_s``).
    """
    row = scene.as_dict()
    if scene.kind != "flexure":
        row["n_scales"] = scene.design.patch().n_scales
    t0, c0 = time.perf_counter(), time.thread_time()
    data: dict = {}
    try:
        with time_limit(scene_limit(scene, limit_s), clock=SCENE_CLOCK):
            if scene.kind == "patch":
                result, data = _patch(scene, (done or {}).get(paper_sibling(scene)))
            else:
                result, data = RUNNERS[scene.kind](scene)
        row.update(result)
        row["status"] = "ok"
    except TimeLimitReached as exc:
        row.update({"status": exc.status, "error": str(exc)})
    except SolverFailure as exc:
        row.update({"status": exc.status, "error": str(exc), "failed_increment": exc.increment})
    except QpscaleError as exc:
        row.update({"status": type(exc).__name__, "error": str(exc)})
    except Exception as exc:  # noqa: BLE001 - one broken scene must not stop the study
        log.error("scene %s crashed:\n%s", scene.key, traceback.format_exc())
        row.update({"status": f"crash:{type(exc).__name__}", "error": str(exc)})
    row["wall_s"] = time.perf_counter() - t0
    row["cpu_s"] = time.thread_time() - c0
    return row, data


def condensation_group(scene: Scene) -> Scene | None:
    """What a flexure scene shares with its siblings: the scene without its slant (and study).

    A slant keeps the base footprints, so the flexure scenes of one design and load line that
    differ only in slant have one condensation (formulations/membrane.md sec. 5, "Reuse"); run one
    after another in one process, all but the first reuse it.  None for a puncture scene (nothing
    to share).  Only the order of work depends on this: whether a condensation is reused is
    decided by comparing its inputs."""
    if scene.kind != "flexure":
        return None
    return replace(scene, study="flexure", slant_deg=0.0, slant_dir_deg=0.0)


def task_group(scene: Scene) -> Scene:
    """The scenes run one after another in one task share this: a flexure scene's condensation
    group (``condensation_group``), a patch scene's sibling (``paper_sibling``), else the scene."""
    return condensation_group(scene) or paper_sibling(scene) or scene


def run_scene_group(
    scenes: list[Scene], limit_s: float | None = None, done: dict | None = None
) -> list[tuple[dict, dict]]:
    """:func:`run_scene` on each of ``scenes`` in turn, in this process (each with its own limit);
    each sees the rows of ``done`` and of the scenes before it."""
    seen = dict(done or {})
    results = []
    for scene in scenes:
        results.append(run_scene(scene, limit_s, seen))
        seen[scene] = results[-1][0]
    return results
