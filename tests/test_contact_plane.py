"""Tests of the separating-plane contact formulation (formulations/contact.md sec. 7)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np
import pytest

from qpscale import Design
from qpscale.contact import ContactSettings, contact_forces, detect_contacts, gap_jacobian, penetration
from qpscale.contact.planes import tangent_basis
from qpscale.experiments.flexure import _take
from qpscale.experiments.puncture import PunctureSetup, _load_point, build_model, run_puncture
from qpscale.geometry import rotation_matrices
from qpscale.increment import PunctureLevel, SQPSettings, assemble_increment, map_labels
from qpscale.solvers import solve_qp
from qpscale.tiling import Patch

PLANE = ContactSettings()


class EdgePath(NamedTuple):
    """The 3x3 square array loaded at the top-face point (1, 0): its model and its converged path."""

    patch: Patch
    K: Any
    load: Any
    states: list


@pytest.fixture(scope="module")
def edge_path() -> EdgePath:
    setup = PunctureSetup(design=Design(rings=1), load_point=(1.0, 0.0), probe=False)
    patch, K = build_model(setup)
    return EdgePath(patch, K, _load_point(patch, np.array([1.0, 0.0])), run_puncture(setup).states)


def _level_near(path: EdgePath, delta: float) -> tuple:
    """The converged state of ``path`` nearest ``delta`` (chosen by depth, not by index) and the one
    before it."""
    i = int(np.argmin([abs(s.delta - delta) for s in path.states]))
    return path.states[i - 1], path.states[i]


def _tilted(patch, seed=0, size=0.02):
    return np.random.default_rng(seed).normal(scale=size, size=(patch.n_scales, 5))


def _gaps(patch, cs, q0, q, theta):
    """Gaps of the rows of ``cs`` (fixed vertices, planes moved by theta), from scratch: eq. (20)."""
    ref = np.zeros((patch.n_scales, 3))
    ref[:, :2] = patch.centroids
    scale = np.where(cs.side > 0, cs.b, cs.a)
    x0 = np.where((cs.side > 0)[:, None], cs.xb, cs.xa)
    R0, R = rotation_matrices(q0[:, 3:5]), rotation_matrices(q[:, 3:5])
    X = np.einsum("mji,mj->mi", R0[scale], x0 - (ref + q0[:, :3])[scale])
    x = (ref + q[:, :3])[scale] + np.einsum("mij,mj->mi", R[scale], X)
    th = theta.reshape(-1, 3)[cs.plane]
    n0, p0 = cs.planes.normal[cs.plane], cs.planes.point[cs.plane]
    v = n0 + np.einsum("mij,mj->mi", cs.planes.basis[cs.plane], th[:, :2])
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    return cs.side * np.einsum("mk,mk->m", n, x - p0 - th[:, 2:3] * n0)


def test_untilted_neighbours_are_split_by_the_mid_plane():
    # At q = 0 the square array's face neighbours are d = 0.005 apart: the start plane lies half-way,
    # so every row's gap is d/2 (exact geometry, 1e-12) and the plane normal is the face normal.
    patch = Design(rings=1).patch()
    cs = detect_contacts(patch, np.zeros((patch.n_scales, 5)), PLANE)
    face = [j for j, k in enumerate(cs.planes.keys) if k[:1] == (0,) and k[2] in (1, 2, 3, 4)]
    for j in face:
        rows = cs.plane == j
        assert np.allclose(cs.gap[rows].min(), 0.0025, atol=1e-12)
        assert np.isclose(np.abs(cs.planes.normal[j]).max(), 1.0, atol=1e-12)
    assert set(cs.kind_names) == {"vertex-plane"}


@pytest.mark.parametrize("shape", ["square", "dart"])
def test_jacobian_against_finite_differences(shape):
    # Columns for the DOFs and the plane unknowns against central differences of eq. (20) rebuilt
    # from scratch; h = 1e-6: truncation ~1e-12, round-off ~1e-10.
    design = Design(shape=shape, tiling="chevron" if shape == "dart" else "arrayed", rings=1)
    patch = design.patch()
    q = _tilted(patch)
    cs = detect_contacts(patch, q, PLANE)
    J = gap_jacobian(cs, patch, q).toarray()
    n_dof = 5 * patch.n_scales
    rng = np.random.default_rng(1)
    h = 1e-6
    for _ in range(3):
        d = rng.normal(size=n_dof + cs.n_extra)
        dq, dt = d[:n_dof].reshape(-1, 5), d[n_dof:]
        fd = (_gaps(patch, cs, q, q + h * dq, h * dt) - _gaps(patch, cs, q, q - h * dq, -h * dt)) / (2 * h)
        assert np.allclose(J @ d, fd, atol=1e-8)
    assert np.allclose(_gaps(patch, cs, q, q, np.zeros(cs.n_extra)), cs.gap, atol=1e-12)


def test_plane_rows_of_a_pair_sum_to_zero_force(edge_path):
    # Stationarity in each plane's unknowns (contact.md sec. 7): the forces its rows put on the two
    # scales are equal and opposite, so the contact forces of the whole patch sum to zero (Newton's
    # third law), to the QP's KKT tolerance 1e-9 summed over the ~30 active rows: 3e-8.
    # A state inside the path: the last one is the fold where the path snaps (puncture.md sec. 3).
    state = min(edge_path.states, key=lambda s: abs(s.delta - 0.4))
    Q = contact_forces(state.contacts, state.lam)
    assert np.abs(Q[:, :3].sum(axis=0)).max() < 3e-8
    assert np.abs(Q[:, :3]).max() > 0.1
    for j in range(state.contacts.planes.count):
        rows = state.contacts.plane == j
        assert abs(np.sum(state.lam[rows] * state.contacts.side[rows])) < 3e-8


def test_converged_state_does_not_depend_on_the_starting_planes(edge_path):
    # Path independence: the same load level solved from planes started on the best axes, and from
    # the same planes tilted by 0.05 rad, ends in the same state (SQP accuracy 1e-8 per DOF).
    patch, K, load, states = edge_path
    state = states[len(states) // 2]
    start = states[len(states) // 2 - 1]
    cs = start.contacts
    n = cs.planes.normal + 0.05 * tangent_basis(cs.planes.normal)[:, :, 0]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tilted = replace(cs, plane_memory={k: (n[j], cs.planes.point[j]) for j, k in enumerate(cs.planes.keys)})
    a = (
        PunctureLevel(patch, K, start.q, load, state.delta, PLANE, SQPSettings(), previous=cs)
        .iterate()
        .unwrap()
    )
    b = (
        PunctureLevel(patch, K, start.q, load, state.delta, PLANE, SQPSettings(), previous=tilted)
        .iterate()
        .unwrap()
    )
    assert np.abs(a.q - b.q).max() < 1e-7
    assert a.F == pytest.approx(b.F, rel=1e-7)
    assert penetration(patch, b.q) <= 1e-9


def test_plane_and_feature_formulations_agree_on_one_load_level(edge_path):
    # Two independent contact formulations of the same frictionless problem, one load level solved
    # from the same converged state (so both start in the same basin: the arrays have several
    # stable equilibria, formulations/puncture.md sec. 4): F and q agree to the feature
    # formulation's own accuracy (its clipped points carry ~1e-5 of sticky-axis error).
    patch, K, load, _ = edge_path
    # A level well inside the path (contact set settled).
    start, state = _level_near(edge_path, 0.2)
    feature = ContactSettings(formulation="feature")
    a = (
        PunctureLevel(patch, K, start.q, load, state.delta, PLANE, SQPSettings(), previous=start.contacts)
        .iterate()
        .unwrap()
    )
    b = PunctureLevel(patch, K, start.q, load, state.delta, feature, SQPSettings()).iterate().unwrap()
    assert a.F == pytest.approx(b.F, rel=1e-4)
    assert np.abs(a.q - b.q).max() < 1e-4


def test_invalid_formulation():
    with pytest.raises(Exception, match="formulation"):
        ContactSettings(formulation="penalty")


def test_a_stale_plane_restarts_from_the_best_axis_and_a_near_one_is_kept():
    # A remembered plane that separates its pieces worse than their best axis by more than the
    # margin cannot be turned far enough by one linearised step (the increment QP of the 5x5 dart
    # became infeasible with rows violated by 0.94 L); it restarts from the best axis.
    patch = Design(rings=1).patch()
    q = np.zeros((patch.n_scales, 5))
    fresh = detect_contacts(patch, q)
    key = fresh.planes.keys[0]
    n, p = fresh.plane_memory[key]
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 deg about z
    slight = np.array([[1.0, -1e-3, 0.0], [1e-3, 1.0, 0.0], [0.0, 0.0, 1.0]])
    for turn, kept in ((quarter, False), (slight, True)):
        m = turn @ n
        memory = {**fresh.plane_memory, key: (m / np.linalg.norm(m), p)}
        cs = detect_contacts(patch, q, previous=replace(fresh, plane_memory=memory))
        j = cs.planes.keys.index(key)
        expected = memory[key][0] if kept else n
        assert np.allclose(cs.planes.normal[j], expected, atol=1e-12)


def test_pieces_all_beyond_the_margin_give_no_plane_whatever_is_remembered():
    # Scales pushed apart by more than the margin have no near piece pair: the set is empty, the
    # remembered planes are dropped, and nothing fails on the empty selection.
    patch = Design(rings=1).patch()
    q = np.zeros((patch.n_scales, 5))
    fresh = detect_contacts(patch, q)
    apart = q.copy()
    apart[:, :2] = 0.5 * patch.centroids  # every gap grows by half a centre distance (>= 1 L)
    cs = detect_contacts(patch, apart, previous=fresh)
    assert cs.planes.count == 0 and len(cs.gap) == 0


def test_slack_rows_of_the_band_leave_the_map_and_its_labels_unchanged(edge_path):
    # Anderson's history restarts when the map changes (formulations/increment.md sec. 4,
    # "Restart on the planes"): a vertex entering or leaving a plane's margin band does not change
    # it.  The increment QP of a converged state inside the 3x3 path, solved with every row and
    # without the band's slack rows (gap above 1e-3 L, no force), has the same answer: dq to the
    # QP's accuracy (KKT 1e-9 over lambda_min(K) ~ 0.1: 1e-8), the contact forces on the scales to
    # 1e-7 (their split between a face's dependent rows is not unique, the resultants are); and
    # the two row sets have the same map labels (the planes' keys) but different row labels.
    patch, K, load, _ = edge_path
    start, state = _level_near(edge_path, 0.2)
    level = PunctureLevel(patch, K, start.q, load, state.delta, PLANE, SQPSettings(), previous=start.contacts)
    qp, cs = level.increment_qp()
    full = solve_qp(qp, solver="piqp")
    slack = (cs.gap > 1e-3) & (np.asarray(full.z) < 1e-12)
    assert 0 < slack.sum() < cs.m
    keep = ~slack
    fewer = _take(cs, keep)
    J = gap_jacobian(fewer, patch, start.q)
    part = solve_qp(assemble_increment(K, start.q, load, state.delta, fewer, J), solver="piqp")
    nq = start.q.size
    assert np.abs(np.asarray(part.x)[:nq] - np.asarray(full.x)[:nq]).max() < 1e-8
    forces = contact_forces(fewer, np.asarray(part.z)) - contact_forces(cs, np.asarray(full.z))
    assert np.abs(forces).max() < 1e-7
    assert map_labels(fewer) == map_labels(cs) == cs.planes.keys
    assert fewer.labels != cs.labels


def test_a_pressed_plane_that_separates_worse_than_the_best_axis_restarts_from_it():
    # contact.md sec. 7: a remembered plane that parts its pieces by more than STALE_PLANE_TOL less than
    # their best separating axis can press pieces that do not touch (flexure's staggered triangle array,
    # load line x: 4.6e-4 E_m L^2 across a distance of 1.5e-5 L, membrane.md sec. 8), so a pressed one
    # restarts from the best axis.  (Puncture's slanted staggered triangle drifts the same way, and its
    # accelerated iteration uses the rule too: increment.md sec. 4, "Stale pressed planes".)
    # Two triangles of the staggered array at rest, their vertical corner edges 0.005 L apart: the plane
    # turned by 0.1 rad about the vertical through its point parts them by 0.005 cos(0.1), 2.5e-5 L
    # less: above STALE_PLANE_TOL, far below the margin (0.1 L), whose test alone keeps it.
    from qpscale.contact.planes import STALE_PLANE_TOL

    patch = Design(shape="triangle", tiling="staggered", rings=1).patch()
    q = np.zeros((patch.n_scales, 5))
    cs = detect_contacts(patch, q, PLANE)
    turned, same = cs.planes.keys[0], cs.planes.keys[1]
    n, p = cs.plane_memory[turned]
    c, s = np.cos(0.1), np.sin(0.1)
    memory = dict(cs.plane_memory)
    memory[turned] = (np.array([c * n[0] - s * n[1], s * n[0] + c * n[1], n[2]]), p)
    rows = replace(cs, plane_memory=memory)

    def normal(out, key):
        return out.planes.normal[out.planes.keys.index(key)]

    # Not pressed: kept whatever it separates (an unpressed plane carries nothing).
    kept = detect_contacts(patch, q, PLANE, previous=rows)
    np.testing.assert_array_equal(normal(kept, turned), memory[turned][0])
    j = kept.planes.keys.index(turned)
    assert kept.gap[kept.plane == j].min() < cs.gap[cs.plane == 0].min() - 10 * STALE_PLANE_TOL
    # Pressed: restarted from the best axis, and its rows are those of the set at rest again; the
    # other pressed plane, the best axis itself, is kept.
    out = detect_contacts(patch, q, PLANE, previous=rows, pressed=frozenset({turned, same}))
    j = out.planes.keys.index(turned)
    np.testing.assert_allclose(normal(out, turned), n, atol=1e-12)
    np.testing.assert_allclose(out.gap[out.plane == j], cs.gap[cs.plane == 0], atol=1e-12)
    np.testing.assert_array_equal(normal(out, same), cs.plane_memory[same][0])
    # The best axis is never stale: with every plane pressed, the fresh set is its own next.
    fresh = detect_contacts(patch, q, PLANE, previous=cs, pressed=frozenset(cs.planes.keys))
    np.testing.assert_array_equal(fresh.planes.normal, cs.planes.normal)
    assert STALE_PLANE_TOL < 1e-3 * patch.design.gap


def test_the_accelerated_iteration_restarts_a_stale_pressed_plane_and_the_plain_one_keeps_it(edge_path):
    # increment.md sec. 4, "Stale pressed planes": in the accelerated iteration a plane the last QP
    # pressed restarts from its pieces' best axis once it parts them by more than STALE_PLANE_TOL less
    # than that axis; the plain iteration (a landing's descent) keeps its planes.  A converged state of
    # the 3x3 square with its most pressed plane turned by 1e-3 rad about its point: within the margin,
    # so the margin's test keeps it, but stale by about its rows' spread times 1e-3, far above 1e-6 L.
    from qpscale.increment import _SequentialQP

    _, state = _level_near(edge_path, 0.3)
    cs = state.contacts
    force = np.bincount(cs.plane[cs.side > 0], weights=state.lam[cs.side > 0], minlength=cs.planes.count)
    j = int(np.argmax(force))
    key = cs.planes.keys[j]
    n, p = cs.plane_memory[key]
    e = tangent_basis(n[None])[0][:, 0]
    turned = dict(cs.plane_memory)
    turned[key] = ((n + 1e-3 * e) / np.linalg.norm(n + 1e-3 * e), p)
    start = replace(cs, plane_memory=turned)
    args = (edge_path.patch, edge_path.K, state.q, edge_path.load, state.delta, PLANE)
    normals = {}
    for depth in (5, 0):
        sqp = _SequentialQP(PunctureLevel(*args, SQPSettings(anderson_depth=depth)))
        sqp.pressed = frozenset({key})  # as the attempt's last QP left it
        _, _, rows, _ = sqp.linearise(state.q, start, None)
        normals[depth] = rows.planes.normal[rows.planes.keys.index(key)]
    # Restarted: the best axis of two squares in face contact is the face normal, the converged
    # plane's own to the state's accuracy; kept: the turned normal, exactly.
    assert np.abs(normals[5] - n).max() < 1e-7
    np.testing.assert_array_equal(normals[0], turned[key][0])
