"""Large patches: sparse stiffness, far field, patch-size convergence (formulations/substrate.md
secs. 7, 9, 10)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from qpscale.errors import QpscaleError
from qpscale.substrate import (
    SubstrateModel,
    assemble,
    calibrate,
    check_positive_definite,
    coupling_ratio,
    factor_stiffness,
)
from qpscale.tiling import Design


def dense_reference(patch, cal, threshold, f):
    """Eq. (15)-(16) entry by entry: a loop over every ordered pair of scales (independent of the
    vectorised triplet assembly)."""
    n = patch.n_scales
    K = np.zeros((5 * n, 5 * n))
    sites = patch.sites.tolist()
    for s, (i, j, m) in enumerate(sites):
        K[5 * s : 5 * s + 5, 5 * s : 5 * s + 5] = (1 - f) * cal.K_iso + f * cal.K0[m]
        for c in cal.couplings:
            if c.source != m or coupling_ratio(c.K1, cal.K0[m]) < threshold:
                continue
            target = [i + c.site[0], j + c.site[1], c.receiver]
            if target in sites:
                r = sites.index(target)
                K[5 * r : 5 * r + 5, 5 * s : 5 * s + 5] += f * c.K1
    return K


@pytest.mark.parametrize(
    ("shape", "tiling", "cal_rings", "threshold"),
    [
        ("square", "arrayed", 2, 0.0),
        ("square", "arrayed", 2, 0.01),
        ("square", "staggered", 1, 0.01),
        ("triangle", None, 1, 0.01),
        ("hexagon", None, 1, 0.0),
    ],
)
def test_sparse_assembly_equals_dense_reference(shape, tiling, cal_rings, threshold):
    design = Design(shape=shape, tiling=tiling, rings=3)
    cal = calibrate(design, SubstrateModel(refinement=3, calibration_rings=cal_rings))
    patch = design.patch()
    for f in (1.0, 0.3):
        K = assemble(patch, cal, threshold, f)
        assert sp.issparse(K)
        ref = dense_reference(patch, cal, threshold, f)
        assert np.abs(K.toarray() - ref).max() <= 1e-13 * np.abs(ref).max()


def test_sparse_definiteness_check_agrees_with_dense_eigenvalues():
    rng = np.random.default_rng(3)
    cal = calibrate(Design(), SubstrateModel(refinement=3))
    K = assemble(Design(rings=3).patch(), cal, 0.0, 1.0)
    check_positive_definite(K)  # the stiffness: every LDL' pivot positive
    solver, D = factor_stiffness(K)
    b = rng.standard_normal(K.shape[0])
    assert np.abs(K @ solver.solve(b) - b).max() < 1e-10 * np.abs(b).max()
    lo = np.linalg.eigvalsh(K.toarray()).min()
    # Shifted past its smallest eigenvalue the matrix is indefinite, and the check says so.
    check_positive_definite(K - 0.5 * lo * sp.identity(K.shape[0]))
    with pytest.raises(QpscaleError, match="positive definite"):
        check_positive_definite(K - 1.01 * lo * sp.identity(K.shape[0]))


def test_sparse_path_equals_dense_path_on_the_3x3():
    """F_c* of the default scene with the vectorised sparse K and with the loop-built dense K."""
    from qpscale.experiments.puncture import PunctureSetup, run_puncture
    from qpscale.studies.large_patch import puncture_with_stiffness

    design = Design(rings=1)
    patch = design.patch()
    ref = dense_reference(patch, calibrate(design, SubstrateModel()), 0.01, 1.0)
    F_dense = puncture_with_stiffness(PunctureSetup(design=design), sp.csc_matrix(ref))
    F_sparse = run_puncture(PunctureSetup(design=design)).Fc_star
    assert abs(F_sparse - F_dense) <= 1e-9 * F_dense


def test_extrapolation_recovers_a_power_tail_and_refuses_other_forms():
    from qpscale.patch_convergence import extrapolate

    n = [3, 5, 7, 9, 11, 13]
    exact = [1.5 - 0.8 * k**-1.2 for k in n]
    e, why = extrapolate(n, exact)
    assert e is not None and abs(e.F_inf - 1.5) < 1e-8 and abs(e.p - 1.2) < 1e-6 and e.error < 1e-6
    # A perturbed tail: the stated error covers the true limit.
    noisy = [F + 2e-4 * (-1) ** k for k, F in enumerate(exact)]
    e, _ = extrapolate(n, noisy)
    assert e is not None and abs(e.F_inf - 1.5) <= e.error
    assert extrapolate(n, [1.0, 1.2, 1.1, 1.3, 1.25, 1.4])[0] is None  # not monotone
    assert "not monotone" in extrapolate(n, [1.0, 1.2, 1.1, 1.3, 1.25, 1.4])[1]
    assert extrapolate(n[:3], exact[:3])[0] is None  # too few patches


def test_rings_auto_stops_by_its_rule_and_matches_individual_runs():
    from qpscale.api import puncture

    cheap = {"interaction": "substrate", "probe": False}
    report = puncture(rings="auto", **cheap)
    auto = report.to_dict()["rings_auto"]
    seq = auto["sequence"]
    assert auto["converged"] and auto["tol"] == 0.005
    changes = [row["change"] for row in seq]
    assert changes[0] is None and changes[-1] <= 0.005 and all(c > 0.005 for c in changes[1:-1])
    for row in seq:
        single = puncture(rings=row["rings"], **cheap).Fc_star
        assert abs(row["Fc_star"] - single) <= 1e-12 * single
    assert report.Fc_star == seq[-1]["Fc_star"]
    assert report.to_dict()["n_scales"] == seq[-1]["n_scales"]
    # A looser tolerance stops earlier on the same sequence.
    loose = puncture(rings="auto", rings_tol=0.05, **cheap).to_dict()["rings_auto"]["sequence"]
    assert [r["Fc_star"] for r in loose] == [r["Fc_star"] for r in seq[: len(loose)]]
    assert len(loose) == 2


def test_rings_auto_runs_every_patch_with_the_edges_asked_for():
    # --rings auto --edges local: every patch of the sequence is the single run with local edge
    # blocks (to round-off), and differs from the clamped run of the same patch: with contact off
    # the softer edge blocks lower F_c* by 2.8 % on the 3x3 and 0.32 % on the 5x5 (bound 1e-4).
    from qpscale.api import puncture

    cheap = {"interaction": "substrate", "probe": False}
    report = puncture(rings="auto", rings_tol=0.5, edges="local", **cheap).to_dict()
    assert report["edges"] == "local"
    for row in report["rings_auto"]["sequence"]:
        local = puncture(rings=row["rings"], edges="local", **cheap).Fc_star
        clamped = puncture(rings=row["rings"], **cheap).Fc_star
        assert abs(row["Fc_star"] - local) <= 1e-12 * local
        assert abs(local - clamped) > 1e-4 * clamped


@pytest.mark.parametrize(
    "args,flag",
    [
        (["--rings", "abc"], "--rings"),
        (["--rings", "2.5"], "--rings"),
        (["--rings", "-1"], "--rings"),
        (["--rings", "auto", "--rings-tol", "0"], "--rings-tol"),
        (["--rings", "auto", "--rings-tol", "0.6"], "--rings-tol"),
        (["--rings", "2", "--rings-tol", "0.01"], "--rings-tol"),
        (["--rings", "auto", "--isolated"], "--isolated"),
    ],
)
def test_bad_rings_values_exit_2_naming_the_flag(args, flag):
    from typer.testing import CliRunner

    from qpscale.cli import app

    result = CliRunner().invoke(app, ["puncture", *args])
    assert result.exit_code == 2
    assert flag in result.output


def test_rings_auto_json_holds_the_documented_fields():
    import json
    import re
    from pathlib import Path

    from typer.testing import CliRunner

    from qpscale.cli import app

    doc = (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| `rings_auto`"))
    documented = set(re.findall(r"`([A-Za-z_]+)`", row)) - {"rings_auto", "rings"}
    args = ["puncture", "--rings", "auto", "--rings-tol", "0.05", "--interaction", "substrate", "--no-probe"]
    result = CliRunner().invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    auto = json.loads(result.stdout)["rings_auto"]
    present = set(auto) | set(auto["sequence"][0])
    assert documented - {"Fc_star_inf", "error", "a", "p", "points"} <= present


def test_full_patch_bem_reproduces_the_calibration_blocks_on_the_3x3():
    """The whole-patch solve (every scale a source, uniform mesh) against the calibration (only the
    centre a source, far edges coarsened by eq. (9c)): same blocks to the focus rule's 1e-3."""
    from qpscale.studies.large_patch import full_patch_stiffness, rigid_patch_kz, truncated

    design = Design(rings=1)
    patch = design.patch()
    K = full_patch_stiffness(patch, density=4)
    cal = calibrate(design, SubstrateModel(refinement=4))
    scale = np.abs(cal.K0[0]).max()
    assert np.abs(K[:5, :5] - cal.K0[0]).max() < 2e-3 * scale
    east = next(c for c in cal.couplings if c.source == 0 and c.site == (1, 0))
    k = next(i for i, s in enumerate(patch.sites.tolist()) if s == [1, 0, 0])
    assert np.abs(K[5 * k : 5 * k + 5, :5] - east.K1).max() < 2e-3 * scale
    # Dropping nothing keeps the matrix; dropping every coupling leaves the self blocks.
    assert np.array_equal(truncated(K, 0.0).toarray(), K)
    diag = truncated(K, 0.999).toarray()
    assert np.count_nonzero(diag[:5, 5:]) == 0 and np.array_equal(diag[:5, :5], K[:5, :5])
    # The rigid-patch vertical stiffness is the sum of every zz entry.
    assert abs(rigid_patch_kz(patch, sp.csc_matrix(K)) - K[2::5, 2::5].sum()) < 1e-12 * K[2::5, 2::5].sum()


@pytest.mark.parametrize("shape", ["square", "triangle"])
def test_local_self_blocks_match_the_whole_patch_solve_on_the_edge(shape):
    """Eq. (18): a scale with missing neighbours gets the self block of its own neighbourhood; on
    the 3x3 (every scale but the centre on the edge) these equal the whole-patch BEM's diagonal
    blocks to the focus rule's 1e-3, where the translation-invariant K0 is off by a third."""
    from qpscale.studies.large_patch import full_patch_stiffness
    from qpscale.substrate.stiffness import local_self_blocks

    design = Design(shape=shape, rings=1)
    patch = design.patch()
    model = SubstrateModel(refinement=4)
    local = local_self_blocks(patch, model)
    K = full_patch_stiffness(patch, density=4)
    K0 = calibrate(design, model).K0
    scale = np.abs(K0[0]).max()
    for k in range(patch.n_scales):
        own = K[5 * k : 5 * k + 5, 5 * k : 5 * k + 5]
        assert np.abs(own - local[k]).max() < 3e-3 * scale
    edge = [k for k in range(patch.n_scales) if patch.ring[k] == 1]
    assert max(np.abs(K0[patch.sites[k, 2]] - local[k]).max() for k in edge) > 0.2 * scale
    assert np.array_equal(local[0], K0[0])  # the centre has every neighbour


def test_patch_size_figure_and_load_split(tmp_path):
    from qpscale.studies.large_patch import draw_patch_size, patch_mechanics

    m = patch_mechanics(1)
    # Vertical equilibrium: the substrate reactions of the rings carry F exactly.
    assert abs(sum(m.vertical) - 1.0) < 1e-6
    assert m.chain <= m.n_scales and m.Fc_star == pytest.approx(1.2249934, rel=1e-6)
    paths = draw_patch_size({"default": ([3], [m.Fc_star])}, [m], tmp_path)
    assert all(p.exists() and p.stat().st_size > 1000 for p in paths)


def test_cost_study_runs_each_patch_in_its_own_process():
    from qpscale.api import puncture
    from qpscale.studies.large_patch import cost_study, fitted_exponent

    study = cost_study([0, 1], probe=False)
    rows = study["rows"]
    assert [r["n_scales"] for r in rows] == [1, 9]
    for r in rows:
        assert r["Fc_star"] == pytest.approx(puncture(rings=r["rings"], probe=False).Fc_star, rel=1e-12)
        assert 0.0 < r["peak_gb"] < 4.0 and 0.0 < r["run_s"] <= r["wall_s"] and r["cpu_s"] > 0.0
    assert all(np.isfinite(study[k]) for k in ("time_exponent", "cpu_exponent", "memory_exponent"))
    assert fitted_exponent([1.0, 10.0, 100.0], [3.0, 300.0, 30000.0]) == pytest.approx(2.0)


def test_edges_option_of_the_substrate_model():
    from qpscale.errors import InvalidDesign
    from qpscale.substrate import stiffness_matrix
    from qpscale.substrate.stiffness import local_self_blocks

    patch = Design(rings=2).patch()
    model = SubstrateModel(refinement=3)
    K = stiffness_matrix(patch, model.with_(edges="local")).toarray()
    own = local_self_blocks(patch, model)
    ref = assemble(patch, calibrate(patch.design, model), model.threshold, model.coupling, own).toarray()
    assert np.array_equal(K, ref)
    default = stiffness_matrix(patch, model).toarray()
    inner = [k for k in range(patch.n_scales) if patch.ring[k] < 2]  # every neighbour present
    for k in inner:
        assert np.array_equal(
            K[5 * k : 5 * k + 5, 5 * k : 5 * k + 5], default[5 * k : 5 * k + 5, 5 * k : 5 * k + 5]
        )
    assert np.array_equal(K - np.diag(np.diag(K)) != 0, default - np.diag(np.diag(default)) != 0)
    with pytest.raises(InvalidDesign, match="edges"):
        SubstrateModel(edges="free")
    with pytest.raises(InvalidDesign, match="edges"):
        SubstrateModel(fidelity="springs", edges="local")
