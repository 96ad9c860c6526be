"""A path held symmetric: formulations/contact.md section 8 (qpscale/contact/symmetry.py)."""

from __future__ import annotations

import numpy as np
import pytest

from qpscale import Design
from qpscale.contact import detect_contacts
from qpscale.contact.symmetry import Mirror, map_dofs
from qpscale.continuation import predict
from qpscale.experiments.puncture import PunctureSetup, _load_point, build_model, puncture_path
from qpscale.experiments.symmetry import mirror_through, patch_symmetries
from qpscale.increment import PunctureLevel, SQPSettings

CORNER = np.array([1.0, 1.0])  # a corner of the 3x3 square's loaded scale: on the diagonal mirror


@pytest.fixture(scope="module")
def corner():
    setup = PunctureSetup(design=Design(rings=1), load_point=tuple(CORNER))
    patch, K = build_model(setup)
    M, perm = mirror_through(patch, CORNER)
    return setup, patch, K, Mirror.of(patch, M, perm)


def _symmetric_q(patch, mirror, seed=3):
    """A small mirror-symmetric configuration: the mean of a random one and its image."""
    q = 1e-3 * np.random.default_rng(seed).standard_normal((patch.n_scales, 5))
    return 0.5 * (q + map_dofs(q, mirror.M, mirror.perm))


def _asymmetry(mirror, planes) -> float:
    """Largest |nu_j* - s M nu_j| and offset mismatch over the planes whose image is present, eq. (25)."""
    image, sign = mirror.plane_images(planes.keys)
    R, c = mirror.M3, mirror.centre
    worst = 0.0
    for j in np.flatnonzero(image >= 0):
        i = image[j]
        worst = max(worst, float(np.max(np.abs(planes.normal[i] - sign[j] * R @ planes.normal[j]))))
        offset_j = planes.normal[j] @ (planes.point[j] - c)
        worst = max(worst, abs(planes.normal[i] @ (planes.point[i] - c) - sign[j] * offset_j))
    return worst


def test_plane_images_are_an_involution(corner):
    _, patch, _, mirror = corner
    cs = detect_contacts(patch, _symmetric_q(patch, mirror), mirror=mirror)
    image, sign = mirror.plane_images(cs.planes.keys)
    assert np.all(image >= 0)  # at a symmetric configuration every near pair's image is near too
    assert np.array_equal(image[image], np.arange(len(image)))
    assert np.array_equal(sign[image], sign)
    assert np.any(image == np.arange(len(image)))  # planes on the mirror (the diagonal neighbours)
    # eq. (26): the symmetrised linearisation is symmetric to round-off
    assert _asymmetry(mirror, cs.planes) < 1e-12


def test_unsymmetrised_planes_are_not_symmetric(corner):
    # The defect sec. 8 removes: without the mirror, planes start from best axes that tie on the
    # diagonal neighbours' corners and are not mirror images of each other.
    _, patch, _, mirror = corner
    q = _symmetric_q(patch, mirror)
    assert _asymmetry(mirror, detect_contacts(patch, q).planes) > 1e-3


def test_increments_obeying_the_rows_keep_the_planes_symmetric(corner):
    # Eq. (27) is exact, not only first order: with t_j* = s E_j*' M E_j t_j the new normals are
    # exact images, and the offsets follow with sigma_j* = s sigma_j.  Any increment in the null
    # space of the rows, applied by Planes.advanced (eq. (22)), keeps the planes symmetric.
    _, patch, _, mirror = corner
    planes = detect_contacts(patch, _symmetric_q(patch, mirror), mirror=mirror).planes
    rows = mirror.plane_rows(planes.keys, planes.normal, planes.point, planes.basis).toarray()
    assert np.allclose(rows @ rows.T, np.eye(len(rows)), atol=1e-12)  # orthonormal, independent
    z = 1e-2 * np.random.default_rng(0).standard_normal(3 * planes.count)
    z -= rows.T @ (rows @ z)
    moved = planes.advanced(z)
    keys = list(planes.keys)
    normal = np.array([moved[k][0] for k in keys])
    point = np.array([moved[k][1] for k in keys])
    assert _asymmetry(mirror, type(planes)(planes.keys, normal, point, planes.basis)) < 1e-12
    # and a generic increment does not (the rows are not vacuous)
    z = 1e-2 * np.random.default_rng(1).standard_normal(3 * planes.count)
    moved = planes.advanced(z)
    normal = np.array([moved[k][0] for k in keys])
    point = np.array([moved[k][1] for k in keys])
    assert _asymmetry(mirror, type(planes)(planes.keys, normal, point, planes.basis)) > 1e-4


def test_a_held_state_is_an_equilibrium_of_the_free_problem(corner):
    # Symmetric criticality (eq. (28)): with the planes held symmetric, the rows holding the
    # configuration carry nothing, so the held state is an equilibrium without them.  Independent
    # check: the free sequential QP started from the held state (its planes included) must stop at
    # once on the same state.  Tolerances: F to 1e-8 relative, q to 1e-7 (step test |dq| <= 1e-8).
    # The depths lie before the branch point (0.0845): the held state is also stable there.
    setup, patch, K, mirror = corner
    load = _load_point(patch, CORNER)
    path = puncture_path(setup, patch, K, load, mirror=mirror)
    states = [path.origin()]
    for delta in (0.02, 0.04, 0.06, 0.08):
        states.append(path.solve(predict(states, delta), delta, len(states)).unwrap())
    for held in states[1:]:
        assert np.max(np.abs(held.q - map_dofs(held.q, mirror.M, mirror.perm))) < 1e-12
        free = (
            PunctureLevel(
                patch, K, held.q, load, held.delta, setup.contact, SQPSettings(), previous=held.contacts
            )
            .iterate()
            .unwrap()
        )
        assert free.iterations <= 2
        assert free.F == pytest.approx(held.F, rel=1e-8)
        assert np.max(np.abs(free.q - held.q)) < 1e-7


def test_reduced_held_qp_equals_the_qp_with_the_held_rows(corner):
    # Eq. (4h): solving the held equalities (x = x0 + Z xi) is the same QP as appending them.
    # Second method: the appended QP, solved by the same backend.  At a held state 0.06 deep and
    # at a depth step beyond it (planes and contacts pressed), the lifted answer must give the
    # same DOF increment (1e-8: both answers meet residuals of 1e-9 on a problem whose unknowns
    # are O(1e-2)) and the same load multiplier F (1e-8 relative), obey the held rows exactly
    # (round-off) and have about half the unknowns with the load as the only equality.
    from qpscale.increment import _SequentialQP
    from qpscale.solvers import solve_qp

    setup, patch, K, mirror = corner
    load = _load_point(patch, CORNER)
    path = puncture_path(setup, patch, K, load, mirror=mirror)
    states = [path.origin()]
    for delta in (0.03, 0.06):
        states.append(path.solve(predict(states, delta), delta, len(states)).unwrap())
    held = states[-1]
    for delta in (held.delta, held.delta + 0.01):
        level = PunctureLevel(
            patch, K, held.q, load, delta, setup.contact, SQPSettings(), previous=held.contacts, mirror=mirror
        )
        _, full, cs, none = _SequentialQP(level, reduced=False).linearise(held.q, held.contacts, None)
        _, small, _, basis = _SequentialQP(level).linearise(held.q, held.contacts, None)
        assert none is None and basis is not None and cs is not None and cs.planes.count
        assert small.m_eq == 1 and full.m_eq > 1 and small.n < 0.6 * full.n
        a, b = solve_qp(full, solver="piqp"), solve_qp(small, solver="piqp")
        x = basis.lift(np.asarray(b.x))
        nq = held.q.size
        assert np.max(np.abs(x[:nq] - np.asarray(a.x)[:nq])) < 1e-8
        assert float(b.y[0]) == pytest.approx(float(a.y[0]), rel=1e-8)
        assert np.max(np.abs(full.A[1:] @ x - full.b[1:])) < 1e-12


def test_piece_images_swap_the_darts_pieces():
    # The dart is cut along its own axis into two convex pieces (geometry.md): the mirror through
    # the loaded dart's axis maps each of its pieces onto the other, and the image of a piece's
    # vertices under M is the other piece's vertex set (checked here directly, without the map).
    patch = Design(shape="dart", rings=1).patch()
    mirrors = [(M, perm) for M, perm in patch_symmetries(patch) if np.linalg.det(M) < 0]
    assert mirrors, "the flat dart array has a mirror through the loaded scale"
    mirror = Mirror.of(patch, *mirrors[0])
    assert mirror.pieces[0].tolist() == [1, 0]
    a, b = (p.vertices for p in patch.convex_prisms(0))
    image = a.copy()
    image[:, :2] = a[:, :2] @ mirror.M.T
    assert np.max(np.min(np.linalg.norm(image[:, None] - b[None], axis=2), axis=1)) < 1e-12


@pytest.mark.parametrize(("rings", "point"), [(1, (1.0, 1.0)), (2, (1.0, 1.0)), (2, (0.0, 1.0))])
def test_sparse_antisymmetric_rows_span_the_reversed_modes(rings, point):
    # Independent value: the eigenvectors of eigenvalue -1 of the dense 5n x 5n map S (built column
    # by column from map_dofs, then a symmetric eigensolver).  The sparse rows must be orthonormal,
    # have the same projector (round-off, 1e-14) and hold at most ten entries a row (two scales).
    from qpscale.contact.symmetry import antisymmetric_rows

    patch = Design(rings=rings).patch()
    n = patch.n_scales
    M, perm = mirror_through(patch, np.array(point))
    D = antisymmetric_rows(n, M, perm)
    assert np.diff(D.indptr).max() <= 10
    S = np.column_stack([map_dofs(e.reshape(n, 5), M, perm).ravel() for e in np.eye(5 * n)])
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    ref = V[:, w < 0]
    Dd = D.toarray()
    assert np.abs(Dd @ Dd.T - np.eye(len(Dd))).max() < 1e-14
    assert np.abs(Dd.T @ Dd - ref @ ref.T).max() < 1e-14


@pytest.mark.parametrize(("rings", "point"), [(1, (1.0, 1.0)), (2, (0.0, 1.0))])
def test_symmetric_basis_spans_the_kept_modes(rings, point):
    # Independent value: the eigenvectors of eigenvalue +1 of the dense map S (as above).  The
    # sparse columns must be orthonormal and give the same projector, I - D'D (round-off).
    from qpscale.contact.symmetry import symmetric_basis

    patch = Design(rings=rings).patch()
    n = patch.n_scales
    M, perm = mirror_through(patch, np.array(point))
    Z = symmetric_basis(n, M, perm).toarray()
    S = np.column_stack([map_dofs(e.reshape(n, 5), M, perm).ravel() for e in np.eye(5 * n)])
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    ref = V[:, w > 0]
    assert np.abs(Z.T @ Z - np.eye(Z.shape[1])).max() < 1e-14
    assert np.abs(Z @ Z.T - ref @ ref.T).max() < 1e-14


def test_plane_basis_is_the_null_space_of_the_plane_rows(corner):
    # The reduced unknowns of a held QP (``Zp`` of ``Mirror.plane_block``): the columns must be
    # orthonormal, obey the rows (eq. (27)) and, with the rows, span every plane increment (rank
    # 3 P).  A plane of a pair is dropped from the set so that one whose image is absent (three
    # free unknowns) is covered too.  The block summed slot by slot equals Zp' diag(w) Zp (for
    # weights spread over six decades, as the damping's are) to round-off of its largest entry.
    _, patch, _, mirror = corner
    planes = detect_contacts(patch, _symmetric_q(patch, mirror), mirror=mirror).planes
    image, _ = mirror.plane_images(planes.keys)
    paired = int(np.flatnonzero(image != np.arange(planes.count))[0])
    for keep in (np.arange(planes.count), np.delete(np.arange(planes.count), paired)):
        keys = [planes.keys[k] for k in keep]
        assert (mirror.plane_images(keys)[0] < 0).sum() == (len(keep) < planes.count)
        point, basis = planes.point[keep], planes.basis[keep]
        rows = mirror.plane_rows(keys, planes.normal[keep], point, basis).toarray()
        weight = 10.0 ** np.random.default_rng(len(keys)).uniform(-6.0, 0.0, 3 * len(keys))
        Zp, S = mirror.plane_block(keys, point, basis, weight)
        Z = Zp.toarray()
        H = Z.T @ (weight[:, None] * Z)
        assert np.abs(S.toarray() - 0.5 * (H + H.T)).max() < 1e-14 * np.abs(H).max()
        assert np.abs(Z.T @ Z - np.eye(Z.shape[1])).max() < 1e-14
        assert np.abs(rows @ Z).max() < 1e-14
        assert len(rows) + Z.shape[1] == 3 * len(keys)
        assert np.linalg.matrix_rank(np.vstack([rows, Z.T]), tol=1e-10) == 3 * len(keys)


def test_plane_images_match_a_key_by_key_reference(corner):
    # The vectorised look-up against the definition, one key at a time: the image of (a, pa, b, pb)
    # is the pair of the images, reordered (with s = -1) when the images come in the other order.
    _, patch, _, mirror = corner
    keys = detect_contacts(patch, _symmetric_q(patch, mirror), mirror=mirror).planes.keys
    index = {k: j for j, k in enumerate(keys)}
    image, sign = mirror.plane_images(keys)
    for j, (a, pa, b, pb) in enumerate(keys):
        ia, ib = int(mirror.perm[a]), int(mirror.perm[b])
        ka, kb = int(mirror.pieces[a, pa]), int(mirror.pieces[b, pb])
        key, s = ((ia, ka, ib, kb), 1.0) if ia < ib else ((ib, kb, ia, ka), -1.0)
        assert image[j] == index.get(key, -1)
        assert sign[j] == s
    # a key whose image is absent maps to -1
    image, _ = mirror.plane_images(keys[:1])
    assert image[0] in (-1, 0)


@pytest.mark.parametrize("shape", ["square", "triangle", "hexagon"])
def test_held_planes_at_the_unloaded_state_separate_every_pair_by_half_the_gap(shape):
    # q = 0: every near pair stands d = 0.005 L apart along its shared edge (farther at a corner:
    # d sqrt(2) across a square's diagonal), so a plane half-way between its pieces leaves each
    # row's vertex at least d/2 from it, and at most d here (a plane turned by the mean keeps half
    # the corners' clearance: d/sqrt(2) for the square, d sqrt(3)/2 for the triangle).  The held path's
    # planes are the means of a plane and its partner's image (eq. (26)); a diagonal pair of the
    # 5x5 square on the mirror line has axes x and y for the two, and with the planes' points at
    # the feet of the origin their mean plane lay 2.1 L on the wrong side of the pair.
    from qpscale.contact import ContactSettings
    from qpscale.experiments.puncture import top_vertices

    patch = Design(shape=shape, rings=2).patch()
    q = np.zeros((patch.n_scales, 5))
    lines = [mirror_through(patch, np.asarray(v[:2])) for v in top_vertices(patch)]
    assert any(m is not None for m in lines)
    for m in filter(None, lines):
        cs = detect_contacts(patch, q, ContactSettings(), mirror=Mirror.of(patch, *m))
        gap = np.asarray(cs.gap)
        assert gap.min() >= 0.0025 - 1e-12 and gap.max() <= 0.005, (gap.min(), gap.max())
