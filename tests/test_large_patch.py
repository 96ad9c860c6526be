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
