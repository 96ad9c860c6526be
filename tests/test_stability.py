"""Second variation: formulations/stability.md, the exact Hessian of eqs. (5)-(7)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import qpscale.continuation as continuation
import qpscale.experiments.puncture as puncture
from qpscale import Design
from qpscale.errors import SolverFailure
from qpscale.experiments.puncture import PunctureSetup, build_model, run_puncture
from qpscale.geometry import rotation_matrices, tangent_operators
from qpscale.stability import (
    _base_hessian,
    _hessian,
    _hessian_fd,
    _lifted,
    _second_variation_fd,
    rotated_point_derivatives,
    second_variation,
)

# Tolerances, each relative to max K_ii (the scale of the reported eigenvalue).
TOLERANCES = {
    # The reference differences exact gradients with step 1e-6: truncation ~1e-12, round-off
    # ~eps |grad| / h ~ 1e-10 (measured 8.5e-11 on the default 5x5 run's 88 states, 2e-11 to
    # 9e-11 on the picked 3x3 states, 2e-12 away from the state).
    "hessian": 1e-9,
    # mu_min moves by at most |dH| (Weyl), so the same bound plus a margin: 1e-8 (measured 5e-12).
    "eigenvalue": 1e-8,
    # An eigenvector moves by ~|dH| / (gap to the next eigenvalue): 1e-7 on the unstable states,
    # whose negative eigenvalue is simple (measured 1.4e-10).
    "mode": 1e-7,
}
PATH_TOL = continuation.STABILITY_TOL
SETUP = PunctureSetup(design=Design(rings=1), load_point=(1.0, 1.0))


@pytest.fixture(scope="module")
def corner_states():
    """Every state the 3x3 square's corner-loaded path tested (symmetric branch, the branch point's
    bisection, the asymmetric branch after it): the inputs of ``Path.stability`` as recorded."""
    seen = []
    real = continuation.Path.stability

    def record(self, eq):
        seen.append(eq)
        return real(self, eq)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(continuation.Path, "stability", record)
        run_puncture(SETUP)
    patch, K = build_model(SETUP)
    load = puncture._load_point(patch, SETUP.load_point)
    return patch, K, load, seen


def _pick(patch, K, load, states):
    """A few states of different kinds: no contact, hinged planes (a plane whose active rows lie
    on one line, free to turn about it), clearly unstable, and the asymmetric branch."""
    kinds = {}
    for eq in states:
        lifted = _lifted(patch, eq, load)
        mu = second_variation(patch, K, eq, load, PATH_TOL).min_eigenvalue
        if not len(lifted.rows):
            kinds.setdefault("free", eq)
        elif _hinged(lifted, eq) and mu > 1e-5:
            kinds.setdefault("hinged", eq)
        elif mu < -1e-5:
            kinds.setdefault("unstable", eq)
        elif eq.delta > 0.3:
            kinds.setdefault("branch", eq)
    assert set(kinds) == {"free", "hinged", "unstable", "branch"}
    return kinds


def _hinged(lifted, eq) -> bool:
    r = rotated_point_derivatives(eq.q[lifted.scale, 3:5], lifted.X)[0]
    x = lifted.ref[lifted.scale] + eq.q[lifted.scale, :3] + r
    for p in range(len(lifted.n0)):
        pts = x[lifted.plane == p]
        if len(pts) > 1 and np.linalg.svd(pts - pts.mean(0), compute_uv=False)[1] < 1e-6:
            return True
    return False


def test_rotated_point_derivatives_match_rodrigues_and_the_tangent_operator():
    # r against geometry.rotation_matrices (closed form / Taylor), dr against the spatial angular
    # velocity T dphi x r (contact.md eq. 2): round-off, 1e-12.  ddr against central differences
    # of dr (step 1e-5: truncation ~1e-10, round-off ~1e-11): 1e-9.  Angles from 0 through the
    # Taylor switch of rotation_matrices (1e-8) to 1.5 rad.
    rng = np.random.default_rng(7)
    size = np.repeat([0.0, 1e-9, 1e-7, 1e-3, 0.3, 1.5], 8)
    phi = rng.normal(size=(size.size, 2)) * size[:, None]
    X = rng.normal(size=(size.size, 3))
    r, dr, ddr = rotated_point_derivatives(phi, X)
    assert np.allclose(r, np.einsum("mij,mj->mi", rotation_matrices(phi), X), rtol=0, atol=1e-12)
    T = tangent_operators(phi)
    assert np.allclose(dr, np.cross(T.transpose(0, 2, 1), r[:, None]), rtol=0, atol=1e-12)
    h = 1e-5
    fd = np.stack(
        [
            (rotated_point_derivatives(phi + h * e, X)[1] - rotated_point_derivatives(phi - h * e, X)[1])
            / (2 * h)
            for e in np.eye(2)
        ],
        axis=2,
    )
    assert np.allclose(ddr, fd, rtol=0, atol=1e-9)


def test_hessian_matches_the_finite_difference_reference(corner_states):
    patch, K, load, states = corner_states
    scale = K.diagonal().max()
    for kind, eq in _pick(patch, K, load, states).items():
        lifted = _lifted(patch, eq, load)
        err = np.abs(_hessian(lifted, K) - _hessian_fd(lifted, K)).max()
        assert err < TOLERANCES["hessian"] * scale, kind


def test_hessian_away_from_the_state(corner_states):
    # At t = sigma = 0 several terms vanish (nu . d2nu/dt2 pieces, n0 . dnu/dt); away from it every
    # term of eq. (6) is live.  Independent value: central differences (step 1e-6) of the exact
    # constraint gradients _Lifted.force_gradient at a perturbed point, every unknown.
    patch, K, load, states = corner_states
    eq = _pick(patch, K, load, states)["hinged"]
    lifted = _lifted(patch, eq, load)
    rng = np.random.default_rng(3)
    z = lifted.z0 + 0.05 * rng.normal(size=lifted.size)
    H = _hessian(lifted, K, z)
    ref = np.zeros_like(H)
    h = 1e-6
    for i in range(lifted.size):
        e = np.zeros(lifted.size)
        e[i] = h
        ref[:, i] = -(lifted.force_gradient(z + e) - lifted.force_gradient(z - e)) / (2 * h)
    geometric = H - _base_hessian(lifted, K)
    assert np.abs(geometric - 0.5 * (ref + ref.T)).max() < TOLERANCES["hessian"] * K.diagonal().max()


def test_verdict_and_min_eigenvalue_agree_with_the_reference(corner_states):
    # mu_min to 1e-8 of max K_ii; the verdict wherever mu_min is farther than that from -tol (the
    # bisection of the branch point puts states within 1e-9 of it, where either verdict is right).
    patch, K, load, states = corner_states
    verdicts = set()
    for eq in states:
        new = second_variation(patch, K, eq, load, PATH_TOL)
        ref = _second_variation_fd(patch, K, eq, load, PATH_TOL)
        assert new.min_eigenvalue == pytest.approx(ref.min_eigenvalue, abs=TOLERANCES["eigenvalue"])
        if abs(ref.min_eigenvalue + PATH_TOL) > TOLERANCES["eigenvalue"]:
            assert new.stable == ref.stable
            verdicts.add(ref.stable)
        assert new.active == ref.active
        # The mode's sign follows round-off when two entries share the largest magnitude.
        gap = min(np.abs(new.mode - ref.mode).max(), np.abs(new.mode + ref.mode).max())
        if not ref.stable:
            assert gap < TOLERANCES["mode"]
    assert verdicts == {True, False}  # both verdicts were compared


def test_sparse_hessian_equals_the_dense_one(corner_states):
    # The same terms summed as triplets instead of into an N x N array: round-off (1e-13 of max K_ii).
    from qpscale.stability import _sparse_hessian

    patch, K, load, states = corner_states
    for kind, eq in _pick(patch, K, load, states).items():
        lifted = _lifted(patch, eq, load)
        err = np.abs(_sparse_hessian(lifted, K).toarray() - _hessian(lifted, K)).max()
        assert err < 1e-13 * K.diagonal().max(), kind


def test_sparse_test_agrees_with_the_dense_one(corner_states):
    # Second method: shift-invert Lanczos on the KKT pencil (stability.md sec. 8) against the
    # dense null space and eigensolver (sec. 3), on every state the 3x3 corner path tested
    # (59 states: free, hinged, unstable, both branches).  mu_min to 1e-9 of max K_ii (measured
    # 5.5e-11 here and 2.9e-11 on the 5x5 default path's 52 states; the KKT regularisation 1e-14
    # and the Lanczos tolerance 1e-12 bound it near 1e-10), the verdict wherever mu_min is farther
    # than that from -tol, the unstable modes to 1e-7 (measured 8e-13).
    from qpscale.stability import _sparse_reduced_minimum

    patch, K, load, states = corner_states
    verdicts = set()
    for eq in states:
        dense = second_variation(patch, K, eq, load, PATH_TOL)
        sparse = _sparse_reduced_minimum(patch, K, eq, load, PATH_TOL, _lifted(patch, eq, load))
        assert sparse.min_eigenvalue == pytest.approx(dense.min_eigenvalue, abs=1e-9)
        if abs(dense.min_eigenvalue + PATH_TOL) > 1e-9:
            assert sparse.stable == dense.stable
            verdicts.add(dense.stable)
        assert sparse.active == dense.active
        if not dense.stable:
            gap = min(np.abs(sparse.mode - dense.mode).max(), np.abs(sparse.mode + dense.mode).max())
            assert gap < TOLERANCES["mode"]
    assert verdicts == {True, False}


def test_sparse_verdict_over_the_multiplier_set_agrees_with_the_dense_one(monkeypatch):
    # stability.md sec. 7 evaluated two ways on every call the 3x3 corner path makes (the states
    # its own multipliers call unstable): the dense reduced tensors, and each member by the sparse
    # test with its subgradient from the eigenvector (multipliers._sparse_uniform, forced by a
    # zero byte budget).  mu* to 1e-9 (measured 5e-16), the same verdicts, modes to 1e-7.
    import qpscale.multipliers as multipliers

    calls = []
    real = continuation.uniform_second_variation

    def record(*args):
        calls.append(args)
        return real(*args)

    monkeypatch.setattr(continuation, "uniform_second_variation", record)
    run_puncture(SETUP)
    assert calls
    for args in calls:
        dense = real(*args)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(multipliers, "DENSE_BYTES", 0.0)
            sparse = real(*args)
        assert sparse.min_eigenvalue == pytest.approx(dense.min_eigenvalue, abs=1e-9)
        assert sparse.stable == dense.stable
        gap = min(np.abs(sparse.mode - dense.mode).max(), np.abs(sparse.mode + dense.mode).max())
        assert gap < TOLERANCES["mode"]


def test_null_space_of_a_tall_matrix_is_scipys_without_the_square_factor():
    # _null_space takes the thin SVD of a tall matrix (the multiplier set's B, one row per unknown)
    # instead of scipy's full one; the space must be the same: the projectors onto both bases
    # agree to round-off, here with two exact dependencies among 40 columns of 2,000 rows.
    import scipy.linalg as la

    from qpscale.stability import _null_space

    rng = np.random.default_rng(7)
    C = rng.standard_normal((2000, 40))
    C[:, 5] = C[:, 1] - 2 * C[:, 3]
    C[:, 17] = 0.5 * C[:, 9]
    Z, R = _null_space(C), la.null_space(C, rcond=1e-10)
    assert Z.shape == R.shape == (40, 2)
    np.testing.assert_allclose(Z @ Z.T, R @ R.T, atol=1e-12)
    np.testing.assert_allclose(Z.T @ Z, np.eye(2), atol=1e-12)


def _captured_pencil():
    """The scaled stiffness, geometric matrix and constraint rows of one state of the 9x9 staggered
    triangle array slanted 60 deg towards 45 deg (the study's patch scene), captured where the sparse
    test's second shift could not converge: its lowest eigenvalues on ker C are a cluster of the
    separating planes' own modes (six within 0.03 %, the lowest two 8e-9 apart)."""
    import scipy.sparse as sp

    d = np.load(Path(__file__).parent / "data" / "plane_cluster_stability.npz")

    def mat(k):
        return sp.coo_matrix((d[f"{k}_val"], (d[f"{k}_row"], d[f"{k}_col"])), shape=tuple(d[f"{k}_shape"]))

    return mat("Ks").tocsc(), mat("G").tocsc(), mat("C").tocsr()


def test_sparse_test_resolves_a_cluster_of_plane_modes(monkeypatch):
    # Second method: the dense null space of C (SVD, the dense test's threshold 1e-10) and every
    # eigenvalue of Z'HZ.  mu_min to 1e-10 of max K_ii (measured 1e-17; the sparse test's own bound
    # is near 1e-10, test above), the mode in ker C and its Rayleigh quotient mu.  With one shift
    # (the scheme before SHIFT_RUNS) the tight run does not converge here.
    import scipy.linalg as sla

    import qpscale.stability as stability

    Ks, G, C = _captured_pencil()
    mu, x = stability.smallest_on_null_space(Ks, G, C)
    Z = sla.null_space(C.toarray(), rcond=1e-10)
    H = (Ks + G).toarray()
    dense = np.linalg.eigvalsh(Z.T @ H @ Z)
    assert mu == pytest.approx(dense[0], abs=1e-10)
    assert dense[1] - dense[0] < 1e-8 and dense[5] < 1.001 * dense[0]  # the cluster
    assert np.linalg.norm(C @ x) < 1e-9 and x @ H @ x == pytest.approx(mu, abs=1e-10)
    monkeypatch.setattr(stability, "SHIFT_RUNS", 1)
    with pytest.raises(SolverFailure, match="Lanczos did not converge"):
        stability.smallest_on_null_space(Ks, G, C)
