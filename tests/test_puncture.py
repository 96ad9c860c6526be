"""Puncture path: formulations/puncture.md and formulations/increment.md."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from qpscale import Design
from qpscale.cli import app
from qpscale.contact import ContactSettings
from qpscale.contact.symmetry import map_dofs
from qpscale.errors import InvalidDesign
from qpscale.experiments.puncture import PunctureSetup, build_model, run_puncture, top_vertices
from qpscale.experiments.symmetry import mirror_through, vertex_orbits
from qpscale.geometry import tilt
from qpscale.increment import SQPSettings
from qpscale.solvers import available_solvers
from qpscale.substrate import SubstrateModel, isolated_block

from .cases import work_balance

PHI_C = np.deg2rad(13.0)
SMALL = Design(rings=1)  # 3x3 square array: contact and coupling at a tenth of the 5x5 cost


# The mid-edge load point (1, 0) of the 3x3 square: its symmetric path stays stable up to failure
# (no branch), so it is one equilibrium path that every step size samples.
EDGE = (1.0, 0.0)


def _run(design: Design = SMALL, **kw) -> object:
    kw.setdefault("probe", False)
    return run_puncture(PunctureSetup(design=design, **kw))


@pytest.mark.parametrize("shape", ["square", "hexagon", "triangle"])
def test_isolated_scale_obeys_finite_rotation_balance(shape):
    # F (delta_c cos phi + t sin phi) = K_phi phi at every converged state (puncture.md eq. 1): the
    # isolated block at nu = 0.5 has no translation-rotation coupling and K_phi isotropic for these
    # symmetric footprints.  Tolerance 1e-6: the sequential QP stops at |dq| <= 1e-8.
    result = _run(Design(shape=shape, rings=0))
    K = isolated_block(shape, 0.5)
    K_phi = 0.5 * (K[3, 3] + K[4, 4])
    dc, t = result.delta_c_star, 1.0
    for state in result.states[1:]:
        phi = tilt(state.q[0, 3:5])
        assert state.F * (dc * np.cos(phi) + t * np.sin(phi)) == pytest.approx(K_phi * phi, rel=1e-6)
    assert result.tilt_deg[-1] == pytest.approx(13.0, rel=1e-9)
    small_rotation = PHI_C * K_phi / dc
    assert result.Fc_star < small_rotation  # the t sin(phi) arm lowers F_c below the paper's estimate


def test_worst_vertex_of_isolated_square_is_a_corner():
    result = run_puncture(PunctureSetup(design=Design(rings=0)))
    assert result.delta_c_star == pytest.approx(np.sqrt(2.0), rel=1e-12)
    assert len(result.candidates) == 1  # the four corners form one symmetry orbit


@pytest.mark.parametrize(
    "design,orbits",
    [
        (Design(), 1),
        (Design(shape="hexagon"), 1),
        (Design(slant_deg=60.0), 2),
        (Design(slant_deg=60, slant_dir_deg=45), 3),
    ],
)
def test_vertex_orbits_follow_the_symmetry(design, orbits):
    patch = design.patch()
    assert len(vertex_orbits(patch, top_vertices(patch))) == orbits


def test_backends_agree_on_Fc():
    # PIQP (the default), Clarabel, the CVXPY formulation of the same QPs and PIQP through
    # qpsolvers: 1e-6 relative, the bar; each QP is solved to 1e-9 KKT and the SQP stops at
    # |dq| <= 1e-8.  The corner load branches (sec. 4), so this also checks that every backend
    # follows the same branch.
    solvers = ["piqp", "clarabel", "cvxpy"] + [s for s in available_solvers() if s == "qpsolvers:piqp"]
    values = {s: _run(load_point=(1.0, 1.0), probe=True, sqp=SQPSettings(solver=s)) for s in solvers}
    ref = values["piqp"]
    assert ref.branch.branched
    for solver, result in values.items():
        assert result.Fc_star == pytest.approx(ref.Fc_star, rel=1e-6), solver
        # The branch point is located where the smallest eigenvalue crosses -1e-6; on the held
        # branch (planes held symmetric) the eigenvalue is smooth and falls at ~3e-3 per L, so an
        # eigenvalue noise of 1e-9 (FD Hessian, states to |dq| <= 1e-8) moves the located depth
        # by ~3e-7 L: 1e-5 relative (measured 1.9e-7 between Clarabel and PIQP).
        assert result.branch.delta_branch[0] == pytest.approx(ref.branch.delta_branch[0], rel=1e-5)


def test_osqp_is_refused_on_the_plane_formulation_not_switched():
    # Every backend solves the formulation it is given: OSQP cannot solve the plane rows (it stops
    # at its iteration limit), so asking for it is an input error naming --solver, exit 2, and the
    # feature formulation must be asked for by name.  Nothing switches silently.
    with pytest.raises(InvalidDesign, match="solver"):
        PunctureSetup(design=Design(rings=1), sqp=SQPSettings(solver="osqp"))
    out = CliRunner().invoke(app, ["puncture", "--rings", "1", "--solver", "osqp", "--json"])
    assert out.exit_code == 2 and "--solver" in out.output and "formulation" in out.output
    # Without contact (the isolated scale) there are no plane rows and OSQP is fine.
    alone = PunctureSetup(design=Design(rings=0), sqp=SQPSettings(solver="osqp"))
    assert alone.contact.formulation == "plane"


def test_osqp_agrees_on_the_feature_formulation():
    # OSQP's polishing needs independent active rows; the plane rows of a face-to-face contact are
    # not (8 rows, 3 plane unknowns), so ADMM alone must reach 1e-9 and runs out of iterations.  On
    # the feature formulation (two-body rows) polished OSQP matches Clarabel to 1e-6.
    feature = ContactSettings(formulation="feature")
    values = {s: _run(contact=feature, sqp=SQPSettings(solver=s)).Fc_star for s in ("clarabel", "osqp")}
    assert values["osqp"] == pytest.approx(values["clarabel"], rel=1e-6)


def test_work_of_the_load_equals_stored_energy_except_at_located_snaps():
    # Frictionless, non-penetrating contact does no work, so int F dw = 1/2 q'Kq along a continuous
    # path.  The mid-edge path of the 3x3 square ends in a snap (a fold of its symmetric branch,
    # puncture.md sec. 2), which is the failure and not part of the curve: along the curve
    # work - energy changes per increment by the trapezoidal rule's error only, which the step
    # control keeps within SNAP_WORK (1e-3) of the increment's work, above the resolution of the
    # states' energies (each state is within ~10 step tolerances of the exact one, so its energy
    # within 10 * 1e-8 * |K q|_1): a short step at a small load has W ~ 1e-9 and noise R ~ 1e-11.
    setup = PunctureSetup(design=SMALL, increments=48, load_point=EDGE)
    _, K = build_model(setup)
    result = run_puncture(setup)
    w, F = result.w_star, result.F_star
    step_work = 0.5 * np.diff(w) * (F[1:] + F[:-1])
    energy = np.array([0.5 * s.q.ravel() @ (K @ s.q.ravel()) for s in result.states])
    resolution = 10 * setup.sqp.step_tol * np.array([np.abs(K @ s.q.ravel()).sum() for s in result.states])
    floor = resolution[1:] + resolution[:-1]
    assert np.all(np.abs(step_work - np.diff(energy)) <= 1e-3 * step_work + floor)
    # The floor matters only at the start: once the load is of order one, steps meet 1e-3 alone.
    late = step_work > 1e-4
    assert late.sum() >= 10 and np.all(np.abs(step_work - np.diff(energy))[late] <= 1e-3 * step_work[late])
    snaps = [e.to_dict() for e in result.events if e.kind == "snap"]
    assert snaps and all(e["energy_released"] > 1e-3 * energy[-1] for e in snaps)
    failure = next(e.to_dict() for e in result.events if e.kind == "failure")
    assert failure["by"] == "snap" and failure["tilt_deg"] < 13.0 < failure["tilt_deg_after"]
    assert result.Fc_star == pytest.approx(snaps[-1]["F_between"][0], rel=1e-15)


def test_corner_load_is_symmetric_about_the_diagonal_up_to_the_branch():
    # The corner-loaded 3x3 square loses stability on its symmetric path (formulations/puncture.md
    # sec. 4): symmetric (to the SQP's 1e-8 per DOF, times a few iterations: 1e-7) before the
    # reported branch point, clearly asymmetric at failure, and the asymmetric branch's energy
    # lies below the symmetric state it left.
    patch = SMALL.patch()
    corner = np.array([1.0, 1.0])
    M, perm = mirror_through(patch, corner)
    result = _run(load_point=(1.0, 1.0), probe=True)
    assert result.branch.branched
    lo, hi = result.branch.delta_branch
    assert 0.0 < lo < hi < result.states[-1].delta
    before = [s for s in result.states if s.delta <= lo]
    assert len(before) >= 3
    for state in before:
        assert np.max(np.abs(state.q - map_dofs(state.q, M, perm))) < 1e-7
    assert np.max(np.abs(result.states[-1].q - map_dofs(result.states[-1].q, M, perm))) > 1e-3
    assert any(e.kind == "branch" and e.energy_drop > 0 for e in result.events)


def test_second_variation_of_the_isolated_scale_matches_its_hessian(monkeypatch):
    # No contact: H = K + F d2w/dq2 restricted to a'dq = 0; the load term only touches the loaded
    # scale's rotations.  Independent value: the same reduced Hessian built from finite
    # differences of LoadPoint.gradient (step 1e-5, error ~1e-10) and scipy's null space.
    import scipy.linalg as la

    from qpscale.experiments.puncture import _load_point
    from qpscale.stability import second_variation

    result = _run(Design(rings=0))
    patch, K = build_model(PunctureSetup(design=Design(rings=0)))
    load = _load_point(patch, result.load_point)
    state = result.states[-1]
    sv = second_variation(patch, K, state, load)
    x, h = state.q.ravel(), 1e-5
    H = K.toarray().copy()
    for i in range(5):
        e = np.zeros(5)
        e[i] = h
        dg = load.gradient((x + e).reshape(1, 5)) - load.gradient((x - e).reshape(1, 5))
        H[:, i] += state.F * dg / (2 * h)
    Z = la.null_space(load.gradient(state.q).reshape(1, -1))
    expect = np.linalg.eigvalsh(Z.T @ (0.5 * (H + H.T)) @ Z)[0] / K.diagonal().max()
    assert sv.min_eigenvalue == pytest.approx(expect, rel=1e-6)
    assert sv.stable
    # LAPACK's gesdd failed to converge on a dart state; the gesvd fallback gives the same answer.
    import qpscale.stability as stability

    real = la.null_space

    def flaky(C, rcond=None, lapack_driver="gesdd", **kw):
        if lapack_driver == "gesdd":
            raise la.LinAlgError("SVD did not converge")
        return real(C, rcond=rcond, lapack_driver=lapack_driver, **kw)

    monkeypatch.setattr(stability.la, "null_space", flaky)
    again = second_variation(patch, K, state, load)
    assert again.min_eigenvalue == pytest.approx(sv.min_eigenvalue, rel=1e-10)


def test_contact_off_gives_no_contact_forces():
    result = _run(interaction="substrate")
    assert all(s.contacts is None and len(s.lam) == 0 for s in result.states)


def test_patch_size_convergence_of_the_substrate_coupling():
    # Contact off, F_c of the corner load converges with the number of rings: the substrate's
    # coupling between scales decays with distance (substrate.md).  Measured 0.43592, 0.42837,
    # 0.42705, 0.42690 for rings 1-4; successive differences must shrink and the last be < 0.1 %.
    # (With contact the chain of touching scales reaches the patch's edge and F_c keeps growing:
    # puncture.md sec. 7 reports that table; it is too slow for CI.)
    corner = (-1.0, -1.0)
    fc = [_run(Design(rings=r), interaction="substrate", load_point=corner).Fc_star for r in (1, 2, 3, 4)]
    steps = np.abs(np.diff(fc))
    assert steps[0] > steps[1] > steps[2]
    assert steps[2] < 1e-3 * fc[-1]


def test_coupling_zero_still_solves_and_contact_only_stiffens():
    isolated = _run(Design(rings=0)).Fc_star
    coupled = _run(interaction="contact", coupling=0.0).Fc_star
    assert coupled >= isolated * (1 - 1e-9)
    _, K = build_model(PunctureSetup(design=SMALL, interaction="contact", coupling=0.0))
    block = isolated_block("square", 0.5)
    assert np.allclose(K.toarray()[:5, :5], 0.5 * (block + block.T), atol=1e-12)
    assert abs(K.toarray()[:5, 5:]).max() == 0.0


def test_contact_sampling_does_not_change_Fc():
    # Completeness (SPEC "Contact"): extra points along every clipped edge must not move F_c (0.1 %).
    coarse = _run().Fc_star
    fine = _run(contact=ContactSettings(sampling=3)).Fc_star
    assert fine == pytest.approx(coarse, rel=1e-3)


def test_Fc_independent_of_increment_size():
    # The mid-edge path of the 3x3 square is continuous up to a fold of its symmetric branch, where
    # it snaps through phi_c (puncture.md secs. 2-3): the fold is located by bisection to 1e-7 of
    # its depth whatever the step, and F_c is the force just before it.  Near a fold F(delta) has
    # a square-root singularity, F ~ F_fold - c sqrt(delta_fold - delta): a state within 1e-7
    # delta (5e-8 L) of the fold is below it by up to c 2.2e-4, so F_c is reproducible to a few
    # 1e-5 only (measured spreads: 2e-6 with Clarabel before planes with violated rows kept their
    # steps, 1.8e-5 with PIQP after).
    a = _run(increments=6, load_point=EDGE, probe=True)
    b = _run(increments=30, load_point=EDGE, probe=True)
    assert not a.branch.branched and not b.branch.branched
    assert a.Fc_star == pytest.approx(b.Fc_star, rel=5e-5)


def test_corner_branch_point_independent_of_increment_size():
    # The corner load's symmetric path loses stability at a subcritical pitchfork.  With the
    # planes held symmetric (contact.md sec. 8) the held rows carry nothing and the smallest
    # eigenvalue is smooth along the branch, so the bisection locates the branch point to 1e-7
    # of its depth plus the eigenvalue's noise (~3e-7 L, see test_backends_agree_on_Fc): 1e-5.
    # The landing from it is then reproducible too; F_c at the 1e-6 (measured 4e-9 over
    # 6, 16, 30 and 40 increments; 0.3 % before the planes were held).
    a = _run(increments=16, load_point=(1.0, 1.0), probe=True)
    b = _run(increments=40, load_point=(1.0, 1.0), probe=True)
    assert a.branch.branched and b.branch.branched
    assert a.branch.delta_branch[0] == pytest.approx(b.branch.delta_branch[0], rel=1e-5)
    assert a.Fc_star == pytest.approx(b.Fc_star, rel=1e-6)


@pytest.mark.slow
def test_default_scene_independent_of_increment_size():
    # The paper's validation case (5x5 squares, worst vertex = a corner, branched): 12 and 40
    # target increments give the same branch point and F_c (measured 1.3104548 to 1.3e-8; before
    # the planes were held, 1.3100024 and 1.3110477 from different step sequences).
    a = run_puncture(PunctureSetup(increments=12))
    b = run_puncture(PunctureSetup(increments=40))
    assert a.branch.branched and b.branch.branched
    assert a.branch.delta_branch[0] == pytest.approx(b.branch.delta_branch[0], rel=1e-5)
    assert a.Fc_star == pytest.approx(b.Fc_star, rel=1e-6)


@pytest.mark.slow
def test_both_plane_updates_and_both_backends_give_one_Fc():
    # The 3x3 triangle array slanted 60 deg at 45 deg, at its worst vertex.  A level's converged
    # state is a fixed point of both plane updates (increment.md sec. 4b), so the damped and the
    # undamped paths are the same path, with PIQP and with Clarabel: F_c at the 1e-6
    # (measured within 5e-9).  Before planes with violated rows kept their steps on undamped paths
    # too (increment.md sec. 2), some level here failed with either update and the other one
    # rescued it (other_plane_update; that rescue's own test injects the fault, test_level.py).
    design = Design(shape="triangle", slant_deg=60.0, slant_dir_deg=45.0, rings=1)
    point = (2.744416242694774, 0.3473621960899268)
    runs = [
        run_puncture(
            PunctureSetup(design=design, load_point=point, sqp=SQPSettings(solver=s, plane_damping=damped))
        )
        for s in ("piqp", "clarabel")
        for damped in (False, True)
    ]
    for r in runs[1:]:
        assert r.Fc_star == pytest.approx(runs[0].Fc_star, rel=1e-6)


def test_array_beats_isolated_and_full_beats_partial():
    full, substrate = _run().Fc_star, _run(interaction="substrate").Fc_star
    isolated = _run(Design(rings=0)).Fc_star
    assert full > substrate > isolated


def test_stiffness_uses_substrate_model():
    setup = PunctureSetup(design=SMALL)
    patch, K = build_model(setup)
    assert K.shape == (5 * patch.n_scales,) * 2
    from qpscale.substrate import stiffness_matrix

    assert abs(K - stiffness_matrix(patch, SubstrateModel())).max() == 0.0


runner = CliRunner()


def test_cli_puncture_json_contract_and_newtons():
    result = runner.invoke(app, ["puncture", "--isolated", "--E-s", "150e3", "--L-mm", "2", "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    for key in (
        "Fc_star",
        "delta_c_star",
        "load_point",
        "tilt_deg",
        "max_penetration",
        "increments",
        "solver",
        "wall_s",
        "curve",
    ):
        assert key in data
    assert data["tilt_deg"] == pytest.approx(13.0)
    # E* L^2 = 150 kPa / 0.75 * (2 mm)^2 = 0.8 N
    assert data["Fc_N"] == pytest.approx(0.8 * data["Fc_star"], rel=1e-12)
    assert len(data["curve"]["w_star"]) == len(data["curve"]["F_star"]) == data["increments"] + 1


@pytest.mark.parametrize(
    "args,flag",
    [
        (["--interaction", "glue"], "--interaction"),
        (["--coupling-factor", "1.5"], "--coupling-factor"),
        (["--phi-c", "0"], "--phi-c"),
        (["--nu", "0.7"], "--nu"),
        (["--solver", "nope"], "--solver"),
        (["--slant", "95"], "--slant"),
    ],
)
def test_cli_puncture_bad_input_exits_2(args, flag):
    result = runner.invoke(app, ["puncture", "--isolated", *args])
    assert result.exit_code == 2
    assert result.stderr.strip().startswith(f"error: {flag}")


def test_vtk_series_loads_back(tmp_path):
    import meshio

    result = runner.invoke(app, ["puncture", "--rings", "1", "--no-probe", "--vtk", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    pvd = tmp_path / "puncture.pvd"
    assert pvd.exists()
    files = sorted(tmp_path.glob("puncture_scales_*.vtu"))
    mesh = meshio.read(files[-1])
    assert mesh.point_data["displacement"].shape == (mesh.points.shape[0], 3)
    assert set(np.unique(np.concatenate(mesh.cell_data["scale"]))) == set(range(9))
    contacts = meshio.read(sorted(tmp_path.glob("puncture_contacts_*.vtu"))[-1])
    assert contacts.point_data["force"].shape[1] == 3


@pytest.mark.slow
def test_paper_validation_scenes_run_and_report_newtons():
    for design in (Design(rings=0), Design(), Design(slant_deg=63.4)):
        result = run_puncture(PunctureSetup(design=design))
        assert 0.1 < result.Fc_star * 0.8 < 10.0  # F_c in newtons (E* L^2 = 0.8 N)
        assert result.max_penetration <= 1e-9


def test_a_step_that_gains_energy_is_flagged_like_one_that_releases_it():
    # R = trapezoidal work - change of stored energy (puncture.md sec. 2).  A state holding far
    # more energy than the load supplied (the SQP leapt into a higher basin: seen on the 5x5 dart,
    # a step of 1.4e-5 L to 150 times the stored energy) must be bisected like a release.
    import scipy.sparse as sp

    from qpscale.continuation import SNAP_WORK
    from qpscale.experiments.puncture import _load_point, puncture_path
    from qpscale.increment import Equilibrium

    setup = PunctureSetup(design=Design(rings=0))
    patch = setup.design.patch()
    path = puncture_path(setup, patch, sp.identity(5), _load_point(patch, (0.5, 0.5)))

    def state(delta, F, energy):
        q = np.zeros((1, 5))
        q[0, 2] = np.sqrt(2.0 * energy)  # 1/2 q'Kq = energy with K = I
        return Equilibrium(q, delta, F, None, np.zeros(0), 1, 0.0)

    a = state(0.1, 1.0, 0.05)
    work = 0.5 * (1.0 + 1.0) * 0.01
    for change, flagged in (
        (work, False),
        (work * (1 - 0.5 * SNAP_WORK), False),
        (0.5 * work, True),
        (150 * 0.05, True),
    ):
        assert path.snapped(a, state(0.11, 1.0, 0.05 + change)) is flagged, change


SLANTED_45 = {"slant_deg": 60.0, "slant_dir_deg": 45.0, "rings": 1}


@pytest.mark.parametrize(
    ("design", "point"),
    [
        # stopped at 9.2 deg after 400 increments when the step followed the iteration count
        (Design(shape="dart", **SLANTED_45), (3.2247448713915885, 0.7247448713915885)),
        # stopped at 0.04 deg when the energy balance flagged noise (puncture.md sec. 2)
        (Design(shape="hexagon", **SLANTED_45), (0.15017493956804673, 1.8451481107929881)),
        (Design(shape="triangle", tiling="staggered", **SLANTED_45), (2.744416242694774, 0.3473621960899268)),
    ],
    ids=["dart", "hexagon", "triangle-staggered"],
)
def test_slanted_arrays_reach_phi_c_and_their_work_balances(design, point):
    # The 3x3 variants of the hard slanted arrays (the 5x5 ones are slow tests), at vertices whose
    # paths stalled: each reaches phi_c.  Independent check, a conservation law: frictionless
    # contact that does not penetrate does no work, so the load's work (trapezoidal; the step
    # control keeps its error within 1e-3 of each step's work) equals the stored energy at failure
    # plus the energy released at located snaps.
    setup = PunctureSetup(design=design, probe=False, load_point=point)
    result = run_puncture(setup)
    assert result.tilt_deg[-1] == pytest.approx(13.0, rel=1e-6)
    work, balance = work_balance(setup, result)
    assert work == pytest.approx(balance, rel=2e-3)


def test_local_edges_need_the_boundary_element_substrate():
    # The local self blocks are boundary-element solves of each edge neighbourhood (substrate.md
    # eq. (18)): with the spring fidelity there is nothing to solve, so the setup refuses it by name.
    with pytest.raises(InvalidDesign, match="edges"):
        PunctureSetup(edges="local", fidelity="springs")
    with pytest.raises(InvalidDesign, match="edges"):
        PunctureSetup(edges="free")
