"""Tests of qpscale.membrane: patch test, tie, condensation, locking (formulations/membrane.md)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from skfem import MeshHex

from qpscale.errors import InvalidDesign, SolverFailure
from qpscale.membrane import (
    MembraneMesh,
    MembraneModel,
    build_mesh,
    condense,
    generalised_map,
    graded_axis,
    node_dofs,
    tie_rows,
)


def small(nu: float = 0.3, integration: str = "sri") -> MembraneMesh:
    model = MembraneModel(length=2.0, width=2.0, height=1.0, nu=nu, h=0.5, nz=2, integration=integration)
    return MembraneMesh(model, build_mesh(model))


def test_graded_axis_has_breaks_and_spacing():
    x = graded_axis(-5.0, 5.0, 0.5, (-4.25, 3.75, 0.1))
    assert np.all(np.diff(x) <= 0.5 + 1e-12)
    for b in (-5.0, -4.25, 0.1, 3.75, 5.0):
        assert np.min(np.abs(x - b)) < 1e-12


@pytest.mark.parametrize("nu", [0.3, 0.4999])
def test_patch_test_linear_field_is_in_equilibrium(nu):
    # A linear displacement field is reproduced exactly by trilinear hexahedra with either rule,
    # so the internal nodes carry no force: round-off level relative to the boundary forces.
    mm = small(nu)
    xyz = mm.nodes
    grad = np.array([[1e-2, 2e-3, -3e-3], [4e-3, -5e-3, 1e-3], [0.0, 7e-3, 2e-3]])
    u = (xyz @ grad.T).ravel()
    f = (mm.K @ u).reshape(-1, 3)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    inner = np.all((xyz > lo + 1e-9) & (xyz < hi - 1e-9), axis=1)
    assert inner.any()
    assert np.abs(f[inner]).max() < 1e-10 * np.abs(f).max()


def test_rigid_motions_carry_no_energy():
    # Translations and small rotations are in the kernel of K (to round-off).
    mm = small(0.4999)
    xyz = mm.nodes
    K = mm.K
    for w in np.eye(3):
        rot = np.cross(w, xyz).ravel()
        assert np.abs(K @ rot).max() < 1e-9 * abs(K).max()
    for k in range(3):
        t = np.zeros_like(xyz)
        t[:, k] = 1.0
        assert np.abs(K @ t.ravel()).max() < 1e-9 * abs(K).max()


def test_tie_rows_is_the_linearised_rigid_motion():
    # Eq. (5) against u + phi x r with r = (x - c, 0) and phi = (phi_x, phi_y, 0).
    rng = np.random.default_rng(1)
    xy = rng.normal(size=(7, 2))
    c = np.array([0.3, -0.2])
    q = rng.normal(size=5)
    u = (tie_rows(xy, c) @ q).reshape(-1, 3)
    r = np.column_stack([xy - c, np.zeros(len(xy))])
    expect = q[:3] + np.cross(np.array([q[3], q[4], 0.0]), r)
    assert np.allclose(u, expect, atol=1e-14)


def test_no_ties_gives_the_identity_map():
    # Removing every scale leaves the membrane itself: T is the identity on the unpinned DOFs.
    mm = small()
    T, gen_of = generalised_map(len(mm.nodes), [], np.array([0, 1]))
    assert T.shape == (3 * len(mm.nodes), 3 * len(mm.nodes) - 2)
    assert (gen_of[:2] == -1).all() and abs(T.T @ T - sp.identity(T.shape[1])).max() == 0


def test_node_bonded_twice_is_rejected():
    mm = small()
    nodes = np.array([3, 4])
    tie = (nodes, mm.nodes[nodes, :2], np.zeros(2))
    with pytest.raises(InvalidDesign):
        generalised_map(len(mm.nodes), [tie, tie], np.zeros(0, int))


def test_condensation_matches_a_direct_solve():
    # Schur complement against solving the full system with the retained DOFs prescribed.
    mm = small(0.45)
    bottom = mm.face_nodes(False)
    top = mm.face_nodes(True)
    tie = (top[:5], mm.nodes[top[:5], :2], mm.nodes[top[2], :2])
    T, gen_of = generalised_map(len(mm.nodes), [tie], node_dofs(bottom))
    n = T.shape[1]
    retained = np.r_[np.arange(n - 5, n), gen_of[3 * top[-3:] + 2]]
    cond = condense(mm.K, T, retained)
    zr = np.linspace(-1.0, 1.0, len(retained)) * 1e-2
    Kg = (T.T @ mm.K @ T).toarray()
    c = cond.condensed
    zc = np.linalg.solve(Kg[np.ix_(c, c)], -Kg[np.ix_(c, retained)] @ zr)
    z = np.zeros(n)
    z[retained], z[c] = zr, zc
    assert np.isclose(zr @ cond.S @ zr, z @ Kg @ z, rtol=1e-10)
    u = cond.displacement(zr)
    assert np.allclose(u[tie[0]], (tie_rows(tie[1], tie[2]) @ zr[:5]).reshape(-1, 3), atol=1e-14)


@pytest.mark.parametrize("schur", ["trailing", "forward"])
def test_schur_complement_entrywise_with_the_rigid_modes_bordered(schur):
    # No pins: the bordered DOFs (three top nodes in full, the bottom face's u_z held) carry all six
    # rigid modes, so S is singular and the factor's trailing block holds S + sigma I (eq. (8d)).
    # S against the dense Schur complement entry by entry, and S times a rigid translation and a
    # rotation about z, which must give no force.  Tolerance 1e-12 of S's largest entry (measured
    # 1e-14): on this small mesh K_bb is 2.4 times S's scale, so the cancellation of eq. (8a) and
    # the shift sigma lose little; a shift not taken off again would be off by sigma ~ K_bb.
    # Both ways: the trailing block of K_g's factor (8d) and the forward solve (8a).
    mm = small(0.45)
    bottom, top = mm.face_nodes(False), mm.face_nodes(True)
    T, gen_of = generalised_map(len(mm.nodes), [], np.zeros(0, dtype=int))
    corners = top[[0, len(top) // 2, -1]]
    retained = np.r_[node_dofs(corners), gen_of[3 * top[3:6] + 2]]
    held = gen_of[3 * bottom + 2]
    cond = condense(mm.K, T, retained, held, schur=schur)
    Kg = (T.T @ mm.K @ T).toarray()
    b, c = cond.bordered, cond.condensed
    dense = Kg[np.ix_(b, b)] - Kg[np.ix_(b, c)] @ np.linalg.solve(Kg[np.ix_(c, c)], Kg[np.ix_(c, b)])
    scale = np.abs(dense).max()
    assert np.abs(cond.S_bordered - dense).max() <= 1e-12 * scale
    xyz = np.repeat(mm.nodes, 3, axis=0)[b]
    axis = np.tile([0, 1, 2], len(mm.nodes))[b]
    translation = (axis == 0).astype(float)
    rotation = np.where(axis == 0, -xyz[:, 1], np.where(axis == 1, xyz[:, 0], 0.0))
    for mode in (translation, rotation):
        assert np.abs(cond.S_bordered @ mode).max() <= 1e-12 * scale * np.abs(mode).max()


@pytest.mark.parametrize("schur", ["trailing", "forward"])
def test_rigid_modes_left_in_the_condensed_dofs_are_reported(schur):
    # No pins and one retained DOF: five rigid modes live in the condensed DOFs alone, so K_cc (and
    # K_g shifted on the bordered DOFs) is singular.  CHOLMOD meets a non-positive pivot and the
    # condensation fails with its status instead of returning a Schur complement of round-off.
    mm = small(0.45)
    T, gen_of = generalised_map(len(mm.nodes), [], np.zeros(0, dtype=int))
    with pytest.raises(SolverFailure, match="singular membrane stiffness"):
        condense(mm.K, T, gen_of[3 * mm.face_nodes(True)[:1] + 2], schur=schur)


def test_condense_refuses_an_unknown_schur_method():
    mm = small(0.45)
    T, gen_of = generalised_map(len(mm.nodes), [], node_dofs(mm.face_nodes(False)))
    with pytest.raises(InvalidDesign, match="schur"):
        condense(mm.K, T, gen_of[3 * mm.face_nodes(True)[:3] + 2], schur="dense")


def test_release_is_the_condensation_with_those_dofs_retained():
    # A held DOF released into the retained set (eq. (8c), read from the bordered Schur complement)
    # against condensing again with it retained from the start; and the held DOFs' reactions
    # against K_g g of the full generalised field.  Both are the same algebra by two routes, so
    # round-off (1e-10 of the stiffness scale) is the tolerance.
    mm = small(0.45)
    bottom = mm.face_nodes(False)
    top = mm.face_nodes(True)
    T, gen_of = generalised_map(len(mm.nodes), [], node_dofs(bottom[:2]))
    retained = gen_of[3 * top[:4] + 2]
    held = gen_of[3 * bottom[2:8] + 2]
    cond = condense(mm.K, T, retained, held)
    freed = cond.released(held[[4, 1]])
    direct = condense(mm.K, T, np.r_[retained, held[[4, 1]]], np.delete(held, [4, 1]))
    scale = np.max(np.abs(direct.S))
    assert np.max(np.abs(freed.S - direct.S)) <= 1e-10 * scale
    assert set(freed.held.tolist()) == set(direct.held.tolist())
    zr = np.linspace(-1.0, 1.0, len(retained)) * 1e-2
    Kg = (T.T @ mm.K @ T).toarray()
    g = cond.generalised(zr)
    assert np.allclose(cond.reactions(zr), (Kg @ g)[held], rtol=0, atol=1e-10 * scale * 1e-2)
    assert np.max(np.abs((Kg @ g)[cond.condensed])) <= 1e-10 * scale * 1e-2
    # After the release the reactions are read from other blocks of the bordered S (eq. (10c)):
    # against K_g g of the released model's own field, the released DOFs now carrying values.
    zf = np.r_[zr, 3e-3, -2e-3]
    gf = freed.generalised(zf)
    assert np.allclose(freed.reactions(zf), (Kg @ gf)[freed.held], rtol=0, atol=1e-10 * scale * 1e-2)


def test_model_validation():
    with pytest.raises(InvalidDesign, match="nu_m"):
        MembraneModel(nu=0.6)
    with pytest.raises(InvalidDesign, match="integration"):
        MembraneModel(integration="bbar?")
    assert MembraneModel(nu=0.5).nu_eff == pytest.approx(0.4999)


def test_graded_axis_grows_geometrically_from_the_fine_lines():
    # Eq. (1): both edges of a gap of 0.005 are lines, the gap is one element, the sizes grow by at
    # most the ratio gamma (plus 10 %: each interval is stretched to a whole number of elements) and never
    # exceed h.
    fine = (0.9975, 1.0025)
    x = graded_axis(-5.0, 5.0, 0.5, (0.0,), fine, h_min=0.005, growth=1.5)
    dx = np.diff(x)
    for f in fine:
        assert np.min(np.abs(x - f)) < 1e-12
    k = int(np.argmin(np.abs(x - 0.9975)))
    assert dx[k] == pytest.approx(0.005, rel=1e-9)
    assert dx.max() <= 0.5 + 1e-12
    assert np.all(dx[1:] / dx[:-1] < 1.5 * 1.1) and np.all(dx[:-1] / dx[1:] < 1.5 * 1.1)
    assert len(x) < 60


@pytest.mark.parametrize("integration", ["sri", "full"])
def test_box_assembly_matches_scikit_fem(integration):
    # Eq. (3b), the closed form on axis-parallel boxes, against scikit-fem's quadrature of eq. (3) on a
    # graded mesh with unequal edges: the same numbers up to round-off (1e-13 of the largest entry).
    from qpscale.membrane import assemble_stiffness, assemble_stiffness_skfem

    model = MembraneModel(length=3.0, width=2.0, height=1.0, nu=0.45, h=0.5, nz=2, integration=integration)
    mesh = build_mesh(model, xbreaks=(0.3,), yfine=(0.2475, 0.2525))
    K1, K2 = assemble_stiffness(model, mesh), assemble_stiffness_skfem(model, mesh)
    assert abs(K1 - K2).max() < 1e-13 * abs(K2).max()


def _distorted(integration: str) -> tuple[MembraneModel, MeshHex]:
    """A tensor mesh whose inner nodes are moved at random by up to ~0.1 of an element (every
    element distorted, none inverted)."""
    from qpscale.membrane import _box_layout

    model = MembraneModel(length=2.0, width=1.0, height=0.5, nu=0.4999, h=0.34, nz=3, integration=integration)
    mesh = MeshHex.init_tensor(np.linspace(0, 2, 7), np.linspace(0, 1, 5), np.linspace(0, 0.5, 4))
    p = mesh.p.copy()
    inner = np.all((p > 1e-9) & (p < np.array([[2.0], [1.0], [0.5]]) - 1e-9), axis=0)
    p[:, inner] += 0.02 * np.random.default_rng(0).standard_normal((3, int(inner.sum())))
    mesh = MeshHex(p, mesh.t)
    assert _box_layout(mesh) is None
    return model, mesh


def test_general_hexahedra_assembly_matches_scikit_fem_with_the_full_rule():
    # The vectorised quadrature of eq. (3) for hexahedra that are not boxes (the fitted mesh, sec. 9d)
    # against scikit-fem's assembly of the same forms: round-off.
    from qpscale.membrane import assemble_stiffness, assemble_stiffness_skfem

    model, mesh = _distorted("full")
    K1, K2 = assemble_stiffness(model, mesh), assemble_stiffness_skfem(model, mesh)
    assert abs(K1 - K2).max() < 1e-13 * abs(K2).max()


def test_general_hexahedra_assembly_is_the_closed_form_on_boxes():
    # The mean dilatation of eq. (3c) is the centre point's divergence on a box: the general path
    # on a graded tensor mesh equals the closed form of eq. (3b) to round-off.
    from qpscale.membrane import _assemble_boxes, _assemble_hexahedra, _box_layout

    model = MembraneModel(length=3.0, width=2.0, height=1.0, nu=0.45, h=0.5, nz=2)
    mesh = build_mesh(model, xbreaks=(0.3,), yfine=(0.2475, 0.2525))
    K1, K2 = _assemble_hexahedra(model, mesh), _assemble_boxes(model, mesh, *_box_layout(mesh))
    assert abs(K1 - K2).max() < 1e-13 * abs(K2).max()


def test_mean_dilatation_passes_the_patch_test_on_distorted_hexahedra():
    # A uniform dilatation u = e x: the exact stress is a pressure, so the inner nodes carry no
    # force.  The mean dilatation (eq. (3c)) integrates each divergence row exactly and passes;
    # the centre point alone (scikit-fem's reduced rule here) does not on distorted elements.
    from qpscale.membrane import assemble_stiffness, assemble_stiffness_skfem

    model, mesh = _distorted("sri")
    xyz = mesh.p.T
    u = (1e-2 * xyz).ravel()
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    inner = np.all((xyz > lo + 1e-9) & (xyz < hi - 1e-9), axis=1)
    f = (assemble_stiffness(model, mesh) @ u).reshape(-1, 3)
    assert np.abs(f[inner]).max() < 1e-10 * np.abs(f).max()
    f_centre = (assemble_stiffness_skfem(model, mesh) @ u).reshape(-1, 3)
    assert np.abs(f_centre[inner]).max() > 1e-3 * np.abs(f_centre).max()


def test_condensed_displacement_matches_a_direct_solve_with_pins_and_ties():
    # The factorisation kept by `condense` recovers the condensed DOFs (eq. (7)) of the full solve with
    # the retained DOFs prescribed, to 1e-10 relative (round-off of two different direct solvers).
    mm = small(0.4999)
    bottom, top = mm.face_nodes(False), mm.face_nodes(True)
    tie = (top[:4], mm.nodes[top[:4], :2], mm.nodes[top[1], :2])
    T, gen_of = generalised_map(
        len(mm.nodes), [tie], np.array([3 * bottom[0], 3 * bottom[0] + 1, 3 * bottom[3] + 1])
    )
    n = T.shape[1]
    retained = np.r_[np.arange(n - 5, n), gen_of[3 * bottom + 2]]
    cond = condense(mm.K, T, retained)
    zr = np.cos(np.arange(len(retained))) * 1e-2
    Kg = (T.T @ mm.K @ T).toarray()
    c = cond.condensed
    zc = np.linalg.solve(Kg[np.ix_(c, c)], -Kg[np.ix_(c, retained)] @ zr)
    z = np.zeros(n)
    z[retained], z[c] = zr, zc
    assert np.allclose(cond.displacement(zr), (T @ z).reshape(-1, 3), rtol=0, atol=1e-10 * np.abs(zc).max())


def test_top_graded_layers():
    # top_h: the top layer has about that thickness (the equal steps of int dz / s place it within 25 %:
    # 0.024 here; a gap between two fine lines is exact, test above), layers grow towards the bottom by at
    # most the growth ratio (plus 10 %) and never exceed height / nz.
    model = MembraneModel(h=1.0, nz=3, top_h=0.02, growth=1.5)
    z = np.unique(np.round(build_mesh(model).p[2], 12))
    dz = np.diff(z)
    assert dz[-1] == pytest.approx(0.02, rel=0.25)
    assert dz.max() <= 0.5 + 1e-12 and np.all(dz[:-1] / dz[1:] < 1.5 * 1.1)
    with pytest.raises(InvalidDesign, match="top_h"):
        MembraneModel(nz=3, top_h=0.6)


def _factor_nonzeros(A: sp.spmatrix, order: np.ndarray) -> int:
    """Nonzeros of CHOLMOD's factor of ``A`` in exactly ``order`` (its AMD comparison switched off)."""
    from qpscale.membrane import _cholmod, _lower

    L = _lower(A)
    with _cholmod(nmethods=1) as (cvxopt, cholmod):
        F = cholmod.symbolic(L, p=cvxopt.matrix(np.asarray(order, dtype=np.int64)), uplo="L")
        cholmod.numeric(L, F)
        return len(cholmod.getfactor(F).V)


def test_nested_dissection_order_of_the_condensed_dofs():
    # The order condense() factorises K_cc in: a permutation of the condensed DOFs with each node's
    # three DOFs consecutive, and a factor with fewer nonzeros than in the tensor mesh's own
    # lexicographic order (a banded fill, set by the mesh alone and not by METIS; measured 0.24 of it
    # here, so the bound 0.5 leaves room for METIS versions but fails an order that does nothing).
    from qpscale.membrane import _fill_reducing_order

    model = MembraneModel(length=4.0, width=4.0, height=1.0, nu=0.3, h=0.25, nz=4)
    mm = MembraneMesh(model, build_mesh(model))
    T, _ = generalised_map(len(mm.nodes), [], node_dofs(mm.face_nodes(False)))
    condensed = np.arange(T.shape[1])
    Kcc = sp.csc_matrix(T.T @ mm.K @ T)
    order = _fill_reducing_order(mm.K, T, condensed, Kcc)
    assert np.array_equal(np.sort(order), condensed)
    node = sp.csc_matrix(T).indices[order] // 3  # each condensed DOF is one nodal DOF here
    assert np.all(node[0::3] == node[1::3]) and np.all(node[0::3] == node[2::3])
    assert _factor_nonzeros(Kcc, order) < 0.5 * _factor_nonzeros(Kcc, condensed)


def _two_slabs(nu: float = 0.45):
    """A 2 x 2 x 1 block in two slabs meeting at z = 0.5 whose grids do not match: 4 x 4
    elements below, 5 x 3 above (the upper slab's bottom nodes slaved to the lower's top face)."""
    from qpscale.fitted_mesh import grid_quads, slabs

    model = MembraneModel(length=2.0, width=2.0, height=1.0, nu=nu, h=0.5, nz=2)
    xy, quads = grid_quads(np.linspace(-1.0, 1.0, 6), np.linspace(-1.0, 1.0, 4))
    g = np.linspace(-1.0, 1.0, 5)
    mesh, slaves = slabs(xy, quads, g, g, np.array([0.0, 0.25, 0.5, 0.75, 1.0]), 2)
    return MembraneMesh(model, mesh, slaves)


def test_two_slabs_pass_the_patch_test():
    # A uniaxial stress along z (u = e (-nu x, -nu y, z)) loads only the top and bottom faces;
    # both slabs' elements reproduce it, and the mortar weights reproduce it across the
    # non-matching interface (rows: a linear field; columns: every grid node's exact share of the
    # uniform traction), so every generalised DOF off those faces carries no force.  Collocating
    # the slaves on the grid's bilinear field (the first try) leaves 14 % of the largest nodal
    # force on the interface here (5 x 3 over 4 x 4 elements).  Round-off tolerances.
    mm = _two_slabs(0.3)
    xyz = mm.nodes
    assert len(mm.slaves.nodes) == 24 and np.isclose(xyz[mm.slaves.nodes, 2], 0.5).all()
    T, gen_of = generalised_map(len(xyz), [], np.zeros(0, int), mm.slaves)
    nu = mm.model.nu_eff
    u = 1e-2 * np.column_stack([-nu * xyz[:, 0], -nu * xyz[:, 1], xyz[:, 2]]).ravel()
    free = np.flatnonzero(gen_of >= 0)
    g = np.empty(T.shape[1])
    g[gen_of[free]] = u[free]
    assert np.abs(T @ g - u).max() < 1e-15
    r = T.T @ (mm.K @ u)
    faces = np.isclose(xyz[:, 2], 0.0) | np.isclose(xyz[:, 2], 1.0)
    loaded = gen_of[node_dofs(np.flatnonzero(faces))]
    rest = np.setdiff1d(np.arange(T.shape[1]), loaded[loaded >= 0])
    assert len(rest) > 3 * 25  # the lower slab's 25 interface nodes among them
    assert np.abs(r[rest]).max() < 1e-13 * np.abs(r).max()


def test_condensation_of_two_slabs_matches_a_dense_schur_complement():
    # The slaved interface makes the condensed DOFs carry other nodes' (T's columns are not unit
    # vectors), so they are ordered by node groups of K_cc's own graph (``_grouped_order``); the
    # Schur complement against the dense one, to round-off.
    mm = _two_slabs()
    top, bottom = mm.face_nodes(True), mm.face_nodes(False)
    T, gen_of = generalised_map(len(mm.nodes), [], node_dofs(bottom[:2]), mm.slaves)
    retained = gen_of[3 * top[::3] + 2]
    cond = condense(mm.K, T, retained, schur="forward")
    Kg = (T.T @ mm.K @ T).toarray()
    c = np.setdiff1d(np.arange(Kg.shape[0]), retained)
    S = Kg[np.ix_(retained, retained)] - Kg[np.ix_(retained, c)] @ np.linalg.solve(
        Kg[np.ix_(c, c)], Kg[np.ix_(c, retained)]
    )
    assert np.abs(cond.S - S).max() < 1e-10 * np.abs(S).max()
