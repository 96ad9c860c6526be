"""Tests of qpscale.contact against hand-derived geometry and finite differences.

formulations/contact.md gives the equations; every expected number below is derived
independently of the module (by hand, or from geometry.rotation_matrix and finite differences).
"""

from __future__ import annotations

import numpy as np
import pytest

from qpscale import Design, InvalidDesign
from qpscale.contact import ContactSettings, contact_forces, detect_contacts, gap_jacobian, penetration
from qpscale.geometry import rotation_matrices as rotations
from qpscale.geometry import rotation_matrix, tangent_operator
from qpscale.geometry import tangent_operators as tangents

# These tests check the feature formulation's contact points (clipping, edge-edge closest points);
# the plane formulation (qpscale.contact.planes) has its own test module beside this one.
FEATURE = ContactSettings(formulation="feature")

S2 = np.sqrt(2.0)


def neighbour(patch, offset):
    """Index of the scale whose centroid is at centroid[0] + offset."""
    target = patch.centroids[0] + np.asarray(offset)
    k = int(np.argmin(np.linalg.norm(patch.centroids - target, axis=1)))
    assert np.linalg.norm(patch.centroids[k] - target) < 1e-9
    return k


def centres(patch, q):
    c = np.zeros((patch.n_scales, 3))
    c[:, :2] = patch.centroids
    return c + q[:, :3]


def material_gaps(cs, patch, q):
    """Exact gaps of the rows' material points at q; the normal turns with scale a.

    Independent of the Jacobian: uses geometry.rotation_matrix on the body-frame coordinates.
    """
    c0, c1 = centres(patch, cs.q), centres(patch, q)
    out = np.empty(cs.m)
    for k in range(cs.m):
        a, b = cs.a[k], cs.b[k]
        Ra0, Rb0 = rotation_matrix(cs.q[a, 3:]), rotation_matrix(cs.q[b, 3:])
        Ra1, Rb1 = rotation_matrix(q[a, 3:]), rotation_matrix(q[b, 3:])
        xa = c1[a] + Ra1 @ Ra0.T @ (cs.xa[k] - c0[a])
        xb = c1[b] + Rb1 @ Rb0.T @ (cs.xb[k] - c0[b])
        out[k] = (Ra1 @ Ra0.T @ cs.normal[k]) @ (xb - xa)
    return out


def fd_jacobian(cs, patch, q, h=1e-6):
    J = np.zeros((cs.m, q.size))
    for j in range(q.size):
        e = np.zeros(q.size)
        e[j] = h
        J[:, j] = material_gaps(cs, patch, q + e.reshape(q.shape)) - material_gaps(
            cs, patch, q - e.reshape(q.shape)
        )
        J[:, j] /= 2 * h
    return J


def test_vectorised_rotations_match_geometry():
    rng = np.random.default_rng(0)
    phi = np.vstack([rng.normal(scale=0.5, size=(6, 2)), [[0, 0], [1e-9, -2e-9], [3e-7, 1e-7]]])
    # Same formulas evaluated elementwise: agreement to round-off.
    assert np.allclose(rotations(phi), [rotation_matrix(p) for p in phi], atol=1e-15)
    # An independent implementation of the exponential map: SciPy's rotation-vector conversion.
    from scipy.spatial.transform import Rotation

    rotvec = np.column_stack([phi, np.zeros(len(phi))])
    assert np.allclose(rotations(phi), Rotation.from_rotvec(rotvec).as_matrix(), atol=1e-14)
    assert np.allclose(tangents(phi), [tangent_operator(p) for p in phi], atol=1e-15)


def test_cubes_face_to_face_four_points_and_jacobian():
    d = 0.02
    patch = Design(thickness=2.0, gap=d, rings=1).patch()
    k = neighbour(patch, (2.0 + d, 0.0))
    q = np.zeros((patch.n_scales, 5))
    cs = detect_contacts(patch, q, FEATURE, pairs=[(0, k)])
    assert cs.m == 4
    assert np.allclose(cs.gap, d, atol=1e-14)
    assert np.allclose(cs.normal, [1, 0, 0], atol=1e-14)
    corners = {(1.0, y, z) for y in (-1.0, 1.0) for z in (0.0, 2.0)}
    got = {tuple(np.round(x, 12) + 0.0) for x in cs.xa}
    assert got == corners
    assert set(cs.kind_names) == {"face-face"}
    # Central differences with h = 1e-6: truncation ~h^2 and round-off ~1e-16/h; 1e-8 covers both.
    J = gap_jacobian(cs, patch, q).toarray()
    assert np.allclose(J, fd_jacobian(cs, patch, q), atol=1e-8)
    # Face-face contact carries a moment: the rows span the normal translation and the tilt about y
    # (the moment about z has no DOF: phi_z is held at zero), so rank 2 > 1 of a single point.
    assert np.linalg.matrix_rank(J) == 2


def edge_edge_config(g):
    """Scale a tilted 45 deg about y (top edge along y), scale b 45 deg about x (bottom edge along x)."""
    patch = Design(thickness=2.0, rings=1).patch()
    k = neighbour(patch, (2.005, 0.0))
    q = np.zeros((patch.n_scales, 5))
    q[0, 4] = np.pi / 4
    C = patch.centroids
    # a's top edge: body vertex (-1, y, 2) -> (sqrt2/2, y, 3 sqrt2/2);
    # b's lowest edge: body (x, -1, 0) -> (x, -sqrt2/2, -sqrt2/2).
    q[k, :3] = [C[0, 0] + S2 / 2 + 0.2 - C[k, 0], C[0, 1] + 0.3 + S2 / 2 - C[k, 1], 2 * S2 + g]
    q[k, 3] = np.pi / 4
    xa = np.array([C[0, 0] + S2 / 2, C[0, 1] + 0.3, 1.5 * S2])
    return patch, k, q, xa


def test_edge_edge_gap_normal_points_by_hand():
    g = 0.03
    patch, k, q, xa = edge_edge_config(g)
    cs = detect_contacts(patch, q, FEATURE, pairs=[(0, k)])
    assert cs.m == 1 and cs.kind_names == ("edge-edge",)
    assert cs.gap[0] == pytest.approx(g, abs=1e-12)
    assert np.allclose(cs.normal[0], [0, 0, 1], atol=1e-12)
    assert np.allclose(cs.xa[0], xa, atol=1e-12)
    assert np.allclose(cs.xb[0], xa + [0, 0, g], atol=1e-12)
    # The incomplete node-to-surface set misses a crossing of two edges entirely.
    assert (
        detect_contacts(patch, q, ContactSettings(mode="vertex", formulation="feature"), pairs=[(0, k)]).m
        == 0
    )
    # Overlap of the crossing edges: depth is -g exactly.
    patch, k, q, _ = edge_edge_config(-0.02)
    assert penetration(patch, q, pairs=[(0, k)]) == pytest.approx(0.02, abs=1e-12)


def test_edge_edge_jacobian_matches_redetected_gap():
    patch, k, q, _ = edge_edge_config(0.03)
    cs = detect_contacts(patch, q, FEATURE, pairs=[(0, k)])
    J = gap_jacobian(cs, patch, q).toarray()
    rng = np.random.default_rng(1)
    h = 1e-5
    for _ in range(5):
        dq = np.zeros_like(q)
        dq[[0, k]] = rng.normal(size=(2, 5))
        gp = detect_contacts(patch, q + h * dq, FEATURE, pairs=[(0, k)]).gap[0]
        gm = detect_contacts(patch, q - h * dq, FEATURE, pairs=[(0, k)]).gap[0]
        # Re-detected edge-edge distance is smooth; central FD error ~h^2 |g''| ~ 1e-10.
        assert (gp - gm) / (2 * h) == pytest.approx(J[0] @ dq.ravel(), abs=1e-8)


def test_vertex_face_points_by_hand():
    g = 0.04
    patch = Design(rings=1).patch()
    k = neighbour(patch, (2.005, 0.0))
    q = np.zeros((patch.n_scales, 5))
    q[k, 3:] = [0.5, 0.3]
    R = rotation_matrix(q[k, 3:])
    body = patch.prism(k).vertices @ R.T
    low = body[np.argmin(body[:, 2])]
    # Put b's lowest vertex a height g above the point (0.1, -0.2) of a's top face (z = t = 1).
    target = np.array([0.1, -0.2, 1.0 + g])
    q[k, :3] = target - low - np.append(patch.centroids[k], 0.0)
    cs = detect_contacts(patch, q, FEATURE, pairs=[(0, k)])
    assert np.allclose(cs.normal, [0, 0, 1], atol=1e-12)
    i = int(np.argmin(cs.gap))
    assert cs.gap[i] == pytest.approx(g, abs=1e-12) and cs.kind_names[i] == "vertex-face"
    assert np.allclose(cs.xb[i], target, atol=1e-12)
    # Every row is a point of b above a's top face: gap = its height above z = 1, xa its foot.
    assert np.allclose(cs.gap, cs.xb[:, 2] - 1.0, atol=1e-12)
    assert np.allclose(cs.xa, np.column_stack([cs.xb[:, :2], np.ones(cs.m)]), atol=1e-12)


def random_state(patch, seed, rot=0.03, disp=0.003):
    rng = np.random.default_rng(seed)
    q = np.zeros((patch.n_scales, 5))
    q[:, :3] = rng.normal(scale=disp, size=(patch.n_scales, 3))
    q[:, 3:] = rng.normal(scale=rot, size=(patch.n_scales, 2))
    return q


@pytest.mark.parametrize("shape", ["square", "dart", "hexagon"])
def test_jacobian_against_finite_differences(shape):
    patch = Design(shape=shape, rings=1, slant_deg=30.0 if shape == "square" else 0.0).patch()
    q = random_state(patch, 3)
    cs = detect_contacts(patch, q, FEATURE)
    assert cs.m > 10
    # Central differences, h = 1e-6: truncation h^2 |g''| ~ 1e-12, round-off 1e-16/h ~ 1e-10.
    J = gap_jacobian(cs, patch, q)
    assert J.format == "csr" and J.nnz <= 10 * cs.m
    assert np.allclose(J.toarray(), fd_jacobian(cs, patch, q), atol=1e-7)
    # Generalised forces are J' lam (virtual work of lam_k n_k at xb_k and -lam_k n_k at xa_k).
    lam = np.random.default_rng(4).uniform(size=cs.m)
    assert np.allclose(contact_forces(cs, lam).ravel(), J.T @ lam, atol=1e-13)


def test_contact_forces_balance_for_a_pair():
    patch = Design(rings=1).patch()
    q = random_state(patch, 5)
    q[:, 3:] = 0.0
    cs = detect_contacts(patch, q, FEATURE)
    F = contact_forces(cs, np.ones(cs.m))
    # Equal and opposite forces: the total force vanishes (Newton's third law).
    assert np.allclose(F[:, :3].sum(axis=0), 0.0, atol=1e-13)


def reflect_index(patch):
    sw = patch.centroids[:, ::-1] - patch.centroids[0, ::-1] + patch.centroids[0]
    d = np.linalg.norm(patch.centroids[None, :, :] - sw[:, None, :], axis=2)
    assert np.all(d.min(axis=1) < 1e-9)
    return d.argmin(axis=1)


def canonical_rows(cs, perm=None):
    """Rows as (a, b, n, xa, xb) tuples with a < b, optionally reflected x <-> y."""
    out = []
    for k in range(cs.m):
        a, b, n, xa, xb = cs.a[k], cs.b[k], cs.normal[k], cs.xa[k], cs.xb[k]
        if perm is not None:
            a, b = perm[a], perm[b]
            n, xa, xb = n[[1, 0, 2]], xa[[1, 0, 2]], xb[[1, 0, 2]]
        if a > b:
            a, b, n, xa, xb = b, a, -n, xb, xa
        out.append(np.concatenate([[a, b], n, xa, xb]))
    return np.array(out)


def test_symmetric_tilt_gives_symmetric_contact_set():
    patch = Design().patch()
    q = np.zeros((patch.n_scales, 5))
    q[0, 3:] = 0.06 * np.array([1.0, -1.0]) / S2
    cs = detect_contacts(patch, q, FEATURE)
    rows, mirrored = canonical_rows(cs), canonical_rows(cs, reflect_index(patch))
    # Every row has its mirror image among the rows (round-off of the rotation only, 1e-9).
    d = np.abs(rows[:, None, :] - mirrored[None, :, :]).max(axis=2)
    assert len(rows) == len(mirrored) and np.all(d.min(axis=1) < 1e-9) and np.all(d.min(axis=0) < 1e-9)
    assert cs.gap.min() < 0.0


def test_sampling_never_finds_a_smaller_gap():
    patch = Design().patch()
    q = random_state(patch, 7, rot=0.05)
    base = detect_contacts(patch, q, FEATURE)
    fine = detect_contacts(patch, q, ContactSettings(sampling=7, formulation="feature"))
    assert fine.m > base.m and "sample" in fine.kind_names
    for a, b in {(int(x), int(y)) for x, y in zip(base.a, base.b)}:
        g0 = base.gap[(base.a == a) & (base.b == b)].min()
        g1 = fine.gap[(fine.a == a) & (fine.b == b)].min()
        # Gaps are linear along a clipped edge: samples lie between its vertices' gaps.
        assert g1 >= g0 - 1e-12
    # The manifold's own points are all kept.
    assert np.allclose(base.gap, fine.gap[[fine.labels.index(lab) for lab in base.labels]])


def test_penetration_of_overlapping_boxes_by_hand():
    d = 0.005
    patch = Design(rings=1).patch()
    k = neighbour(patch, (2.0 + d, 0.0))
    q = np.zeros((patch.n_scales, 5))
    assert penetration(patch, q) == 0.0
    q[k, :2] = [-(d + 0.03), 0.5]
    assert penetration(patch, q, pairs=[(0, k)]) == pytest.approx(0.03, abs=1e-13)
    # a tilted by theta about y: its top-right edge reaches x = cos + t sin; b's face is at 1 + d.
    theta = 0.1
    q = np.zeros((patch.n_scales, 5))
    q[0, 4] = theta
    depth = np.cos(theta) + np.sin(theta) - 1.0 - d
    assert penetration(patch, q, pairs=[(0, k)]) == pytest.approx(depth, abs=1e-13)


def test_slanted_faces_gap_is_d_cos_alpha():
    d, alpha = 0.005, np.deg2rad(60.0)
    patch = Design(slant_deg=60.0).patch()
    q = np.zeros((patch.n_scales, 5))
    assert penetration(patch, q) == 0.0
    cs = detect_contacts(patch, q, FEATURE)
    assert cs.gap.min() >= 0.0
    kx, ky = neighbour(patch, (2 + d, 0)), neighbour(patch, (0, 2 + d))
    # Parallel planes leaning by alpha, offset d along x: distance d |n_x| = d cos(alpha).
    rows = (cs.a == 0) & (cs.b == kx)
    assert rows.sum() == 4 and np.allclose(cs.gap[rows], d * np.cos(alpha), atol=1e-14)
    assert np.allclose(cs.normal[rows], [np.cos(alpha), 0, -np.sin(alpha)], atol=1e-14)
    # Faces normal to y are not slanted (the slant runs along them): gap d.
    rows = (cs.a == 0) & (cs.b == ky)
    assert rows.sum() == 4 and np.allclose(cs.gap[rows], d, atol=1e-14)


def test_dart_pieces_touch_at_the_gap():
    patch = Design(shape="dart").patch()
    q = np.zeros((patch.n_scales, 5))
    assert penetration(patch, q) == 0.0
    cs = detect_contacts(patch, q, FEATURE)
    # Parallel base edges stand d apart in every tiling; pieces of one dart are never paired.
    assert cs.gap.min() == pytest.approx(0.005, abs=1e-12)
    assert np.all(cs.a != cs.b)


def test_vertex_mode_is_a_subset():
    patch = Design().patch()
    q = random_state(patch, 11, rot=0.05)
    full = detect_contacts(patch, q, FEATURE)
    vert = detect_contacts(patch, q, ContactSettings(mode="vertex", formulation="feature"))
    assert set(vert.labels) <= set(full.labels)
    assert set(vert.kind_names) <= {"vertex-face", "face-face"}
    assert "edge-crossing" in full.kind_names


@pytest.mark.parametrize(
    "kwargs", [{"margin": 0.0}, {"tie_tol": -1.0}, {"sampling": -1}, {"sampling": 1.5}, {"mode": "nodes"}]
)
def test_invalid_settings(kwargs):
    with pytest.raises(InvalidDesign):
        ContactSettings(**kwargs)


def test_invalid_inputs():
    patch = Design(rings=1).patch()
    with pytest.raises(InvalidDesign, match="q="):
        detect_contacts(patch, np.zeros((2, 5)))
    with pytest.raises(InvalidDesign, match="pairs="):
        penetration(patch, np.zeros((patch.n_scales, 5)), pairs=[(0, 0)])
    cs = detect_contacts(patch, np.zeros((patch.n_scales, 5)), FEATURE)
    with pytest.raises(InvalidDesign, match="lam="):
        contact_forces(cs, np.ones(cs.m + 1))
