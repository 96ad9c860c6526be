"""Large-patch studies: the far field of the substrate coupling and the cost against patch size.

Implements the measurements of formulations/substrate.md secs. 9-10: the stiffness of a whole
patch from one boundary-element solve with every scale a source (the reference with every
coupling), the same matrix with the couplings below a threshold dropped, and the calibrated
translation-invariant assembly, compared through the compliance of the punctured scale and F_c*;
and the wall time and peak memory of a puncture run against the number of scales, each run in
its own subprocess so that peak memory is that run's.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..experiments.puncture import PunctureSetup, _one_point, top_vertices
from ..experiments.symmetry import vertex_orbits
from ..geometry import Array
from ..substrate import SubstrateModel, coupling_ratio, factor_stiffness, stiffness_matrix
from ..substrate.bem import extrapolated_blocks, shape_pieces
from ..threads import limited_blas
from ..tiling import Design, Patch


def full_patch_stiffness(patch: Patch, nu: float = 0.5, density: int = 3) -> Array:
    """Dense ``(5n, 5n)`` stiffness of a patch from one BEM solve with every scale a source.

    Every coupling is present (no truncation, no translation invariance), at a uniform panel
    density ``density`` with the Richardson step of eq. (11).  Cost grows like (n density^2)^3:
    a reference for patches up to about 11 x 11 at density 3.
    """
    feet = [shape_pieces(patch.design.shape, a, c) for a, c in zip(patch.angles, patch.centroids)]
    sources = tuple(range(patch.n_scales))
    K = extrapolated_blocks(feet, patch.centroids, nu, density, sources).K
    n = patch.n_scales
    K = K.transpose(0, 2, 1, 3).reshape(5 * n, 5 * n)
    return 0.5 * (K + K.T)


def truncated(K: Array, threshold: float) -> sp.csc_matrix:
    """``K`` with every off-diagonal 5 x 5 block whose ratio (eq. (14)) is below ``threshold`` dropped."""
    n = K.shape[0] // 5
    B = K.reshape(n, 5, n, 5).transpose(0, 2, 1, 3).copy()
    for s in range(n):
        for r in range(n):
            if r != s and coupling_ratio(B[r, s], B[s, s]) < threshold:
                B[r, s] = 0.0
    return sp.csc_matrix(B.transpose(0, 2, 1, 3).reshape(5 * n, 5 * n))


def centre_compliance(K: sp.spmatrix | Array) -> dict[str, float]:
    """Compliance of the punctured scale (index 0) under its own force and moment, the others free:
    the diagonal of K^-1 for u_z and phi_x (sparse LDL')."""
    solver, _ = factor_stiffness(sp.csc_matrix(K))
    out = {}
    for name, dof in (("c_z", 2), ("c_phi", 3)):
        e = np.zeros(K.shape[0])
        e[dof] = 1.0
        out[name] = float(solver.solve(e)[dof])
    return out


def block_count(K: sp.spmatrix) -> int:
    """Stored 5 x 5 blocks of K (pairs of scales with any non-zero entry)."""
    coo = sp.coo_matrix(K)
    n = K.shape[0] // 5
    return int(np.unique((coo.row // 5) * n + coo.col // 5).size)


def rigid_patch_kz(patch: Patch, K: sp.spmatrix) -> float:
    """Vertical stiffness of the whole patch moved down as one rigid body (every scale u_z = 1):
    the "locked patch as one large punch" of formulations/substrate.md sec. 10."""
    e = np.zeros(K.shape[0])
    e[2::5] = 1.0
    return float(e @ (K @ e))


def puncture_with_stiffness(setup: PunctureSetup, K: sp.spmatrix) -> float:
    """F_c* of ``setup`` with a given substrate stiffness (worst top-face vertex, as run_puncture)."""
    patch = setup.design.patch()
    K = sp.csc_matrix(K)
    verts = top_vertices(patch)
    with limited_blas():
        forces = [_one_point(setup, patch, K, verts[o[0]])[0][-1].F for o in vertex_orbits(patch, verts)]
    return float(min(forces))


@dataclass(frozen=True)
class FarFieldRow:
    """One stiffness of a patch against the reference with every coupling."""

    label: str
    couplings_per_scale: float
    c_z: float
    c_phi: float
    K_patch_z: float
    Fc_star: float | None


def far_field_study(
    rings: int = 4, density: int = 3, thresholds: tuple[float, ...] = (1e-2, 1e-3, 1e-4), fc: bool = True
) -> list[FarFieldRow]:
    """Truncation error of the coupling on a (2 rings + 1)^2 square-array patch (substrate.md sec. 9).

    Rows: the full BEM stiffness of the patch (reference), the same with couplings below each
    threshold dropped, and the calibrated assemblies (3x3 and 5x5 calibration patches) at the same
    refinement.  With ``fc`` every row also gets F_c* of the default puncture scene.
    """
    design = Design(rings=rings)
    patch = design.patch()
    setup = PunctureSetup(design=design)
    n = patch.n_scales
    K_full = full_patch_stiffness(patch, density=density)
    cases: list[tuple[str, sp.csc_matrix]] = [("full BEM (every coupling)", sp.csc_matrix(K_full))]
    cases += [(f"full BEM, drop < {t:g}", truncated(K_full, t)) for t in thresholds]
    for cr in (1, 2):
        model = SubstrateModel(refinement=density, calibration_rings=cr, threshold=0.0)
        cases.append((f"calibrated {2 * cr + 1}x{2 * cr + 1}", stiffness_matrix(patch, model)))
    rows = []
    for label, K in cases:
        comp = centre_compliance(K)
        F = puncture_with_stiffness(setup, K) if fc else None
        rows.append(
            FarFieldRow(
                label, block_count(K) / n - 1.0, comp["c_z"], comp["c_phi"], rigid_patch_kz(patch, K), F
            )
        )
    return rows


_COST_SCRIPT = """
import json, resource, sys, time
from qpscale.api import puncture
t0 = time.perf_counter()
r = puncture(rings=int(sys.argv[1]), probe=sys.argv[2] == "1", max_memory_gb=1e3, max_minutes=1e4)
use = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"Fc_star": r.payload["Fc_star"], "qp_solves": r.payload["qp_solves"],
                  "run_s": time.perf_counter() - t0, "cpu_s": use.ru_utime + use.ru_stime,
                  "maxrss_kb": use.ru_maxrss}))
"""


def run_cost(rings: int, probe: bool = True) -> dict[str, float]:
    """Wall time, CPU time (user + system: less sensitive than the wall time to other jobs on a
    shared machine) and peak resident memory (``ru_maxrss``) of one default puncture run on a patch
    of ``rings`` rings, in a fresh subprocess so that the peak is that run's alone."""
    cmd = [sys.executable, "-c", _COST_SCRIPT, str(rings), "1" if probe else "0"]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"puncture rings={rings} failed ({out.returncode}): {out.stderr.strip()[-400:]}")
    payload = json.loads(out.stdout.strip().splitlines()[-1])
    side = 2 * rings + 1
    return {
        "rings": rings,
        "n_scales": side * side,
        "wall_s": wall,
        "run_s": payload["run_s"],
        "cpu_s": payload["cpu_s"],
        "peak_gb": payload["maxrss_kb"] / 1e6,
        "Fc_star": payload["Fc_star"],
        "qp_solves": payload["qp_solves"],
    }


def fitted_exponent(n: list[float], y: list[float]) -> float:
    """Slope of log y against log n (least squares): the cost exponent of y ~ n^p."""
    return float(np.polyfit(np.log(n), np.log(y), 1)[0])


@dataclass(frozen=True)
class PatchMechanics:
    """Where the puncture load goes at failure, for one patch size (substrate.md sec. 10).

    ``vertical[k]``: net vertical substrate reaction under ring k, as a fraction of F (the rings
    add up to 1).  ``inplane[k]``: sum over ring k of the magnitudes of the in-plane substrate
    reactions, as a fraction of F (they cancel in the sum: the wedged patch is self-equilibrated in
    its plane).  ``chain``: scales connected to the punctured one through contacts carrying more
    than 1e-6 F (the locked group).
    """

    rings: int
    n_scales: int
    Fc_star: float
    vertical: list[float]
    inplane: list[float]
    chain: int
    contact_pairs: int


def patch_mechanics(rings: int) -> PatchMechanics:
    """Run the default puncture scene on ``rings`` rings and split the failure load by ring and
    by contact cluster."""
    from ..experiments.puncture import run_puncture

    design = Design(rings=rings)
    patch = design.patch()
    eq = run_puncture(PunctureSetup(design=design)).states[-1]
    K = stiffness_matrix(patch, SubstrateModel())
    reaction = -(K @ eq.q.ravel()).reshape(-1, 5)  # force of the substrate on each scale
    F = eq.F
    vertical = [float(reaction[patch.ring == k, 2].sum() / F) for k in range(rings + 1)]
    inplane = [float(np.hypot(*reaction[patch.ring == k, :2].T).sum() / F) for k in range(rings + 1)]
    cs, lam = eq.contacts, np.asarray(eq.lam)
    pairs: set[tuple[int, int]] = set()
    if cs is not None and cs.m:
        on = lam[: cs.m] > 1e-6 * F
        pairs = {(int(a), int(b)) for a, b in zip(cs.a[on], cs.b[on])}
    neighbours: dict[int, set[int]] = {}
    for a, b in pairs:
        neighbours.setdefault(a, set()).add(b)
        neighbours.setdefault(b, set()).add(a)
    cluster, frontier = {0}, [0]
    while frontier:
        for j in neighbours.get(frontier.pop(), set()) - cluster:
            cluster.add(j)
            frontier.append(j)
    return PatchMechanics(rings, patch.n_scales, float(F), vertical, inplane, len(cluster), len(pairs))


def draw_patch_size(
    sequences: dict[str, tuple[list[int], list[float]]], mechanics: list[PatchMechanics], out: str | Path
) -> list[Path]:
    """Figure of formulations/substrate.md sec. 10: (a) F_c* against patch width for each stiffness
    model in ``sequences`` (label -> (widths, F_c*)); (b) the in-plane substrate reaction by ring at
    failure for each patch of ``mechanics``.  Written as PNG and SVG into ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    for label, (widths, F) in sequences.items():
        ax.plot(widths, F, "o-", label=label)
    ax.set_xlabel("patch width n (scales)")
    ax.set_ylabel("F_c*")
    ax.set_title("(a) puncture resistance against patch size")
    ax.legend(fontsize=8)
    for m in mechanics:
        bx.plot(range(m.rings + 1), m.inplane, "o-", label=f"{2 * m.rings + 1}x{2 * m.rings + 1}")
    bx.set_xlabel("ring k (0: punctured scale)")
    bx.set_ylabel("sum |in-plane substrate reaction| / F")
    bx.set_title("(b) in-plane load carried by each ring at failure")
    bx.legend(fontsize=8)
    paths = [out / "patch_size.png", out / "patch_size.svg"]
    for p in paths:
        fig.savefig(p, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return paths


def cost_study(rings: list[int], probe: bool = True) -> dict[str, object]:
    """Wall time and peak memory of the default puncture scene against the number of scales, one
    subprocess per patch, with the fitted exponents of time and memory in n (substrate.md sec. 11)."""
    rows = [run_cost(r, probe) for r in rings]
    n = [float(r["n_scales"]) for r in rows]
    return {
        "rows": rows,
        "time_exponent": fitted_exponent(n, [float(r["run_s"]) for r in rows]) if len(rows) > 1 else None,
        "cpu_exponent": fitted_exponent(n, [float(r["cpu_s"]) for r in rows]) if len(rows) > 1 else None,
        "memory_exponent": fitted_exponent(n, [float(r["peak_gb"]) for r in rows]) if len(rows) > 1 else None,
    }


def local_edge_stiffness(patch: Patch, model: SubstrateModel | None = None) -> sp.csc_matrix:
    """K of a patch with the edge-aware self blocks of eq. (18) (ring-1 couplings as calibrated)."""
    return stiffness_matrix(patch, (model or SubstrateModel()).with_(edges="local"))


def patch_size_figure(out: str | Path, rings: tuple[int, ...] = (1, 2, 3)) -> list[Path]:
    """Compute and draw the figure of formulations/substrate.md sec. 10 for the default scene:
    F_c* of the default and the edge-aware (eq. (18)) models, and the in-plane load by ring."""
    mechanics = [patch_mechanics(r) for r in rings]
    widths = [2 * r + 1 for r in rings]
    local = []
    for r in rings:
        design = Design(rings=r)
        local.append(
            puncture_with_stiffness(PunctureSetup(design=design), local_edge_stiffness(design.patch()))
        )
    sequences = {
        "default: K0 on every scale": (widths, [m.Fc_star for m in mechanics]),
        "edge-aware self blocks (eq. 18)": (widths, local),
    }
    return draw_patch_size(sequences, mechanics, out)
