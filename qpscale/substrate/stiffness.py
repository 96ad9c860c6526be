"""Substrate model, calibration entry point and the sparse stiffness of a patch.

Implements formulations/substrate.md, sec. 5-7 (eqs. (14)-(17)): coupling truncation by the
threshold, assembly of K_multi from the calibrated blocks by translation invariance of the
tiling, the interpolation K(f) = K_iso + f (K_multi - K_iso), and the positive-definiteness
check.  Every stiffness is normalised (L = 1, E* = 1).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from ..errors import InvalidDesign, QpscaleError
from ..geometry import Array
from ..tiling import Design, Patch
from ..units import check_nu, e_star
from .bem import isolated_block
from .cache import cache_key, cached
from .calibration import Calibration, solve_calibration
from .springs import spring_calibration

FIDELITIES = ("bem", "springs")
_MATRIX_CACHE: dict[tuple, sp.csc_matrix] = {}


@dataclass(frozen=True)
class SubstrateModel:
    """How the substrate is modelled.

    Parameters
    ----------
    nu : float
        Poisson's ratio of the half-space, [0, 0.5].
    fidelity : str
        ``"bem"`` (full 5 x 5 blocks) or ``"springs"`` (the paper's diagonal springs, nearest
        neighbours).
    threshold : float
        Couplings with max |K1_ab| / sqrt(K0_aa K0_bb) below this are dropped, [0, 1).
    coupling : float
        Coupling factor f of K(f) = K_iso + f (K_multi - K_iso), [0, 1].
    refinement : int
        Panel strips per fan triangle of each footprint, [2, 16].
    calibration_rings : int
        Rings of clamped neighbours in the calibration solve, 1 or 2.
    cross_terms : bool
        Include the (1 - 2 nu) normal-tangential coupling of the half-space.

    >>> SubstrateModel(coupling=0.04).coupling
    0.04
    """

    nu: float = 0.5
    fidelity: str = "bem"
    threshold: float = 0.01
    coupling: float = 1.0
    refinement: int = 6
    calibration_rings: int = 1
    cross_terms: bool = True

    def __post_init__(self) -> None:
        check_nu(self.nu)
        checks = [
            ("fidelity", self.fidelity, self.fidelity in FIDELITIES, "{bem, springs}"),
            ("threshold", self.threshold, 0.0 <= self.threshold < 1.0, "[0, 1)"),
            ("coupling", self.coupling, 0.0 <= self.coupling <= 1.0, "[0, 1]"),
            (
                "refinement",
                self.refinement,
                int(self.refinement) == self.refinement and 2 <= self.refinement <= 16,
                "integers in [2, 16]",
            ),
            ("calibration_rings", self.calibration_rings, self.calibration_rings in (1, 2), "{1, 2}"),
        ]
        for name, value, ok, allowed in checks:
            if not ok:
                raise InvalidDesign(name, value, allowed)

    def with_(self, **changes: object) -> SubstrateModel:
        return replace(self, **changes)  # type: ignore[arg-type]


def calibrate(design: Design, model: SubstrateModel | None = None) -> Calibration:
    """Blocks of a design (cached in memory and on disk), at the model's fidelity, untruncated.

    Only shape, tiling and gap of ``design`` matter (slant and thickness do not touch the
    footprint).  With ``fidelity="springs"`` the blocks are diagonal and nearest-neighbour.
    """
    model = model or SubstrateModel()
    params = {
        "shape": design.shape,
        "tiling": design.tiling,
        "gap": float(design.gap),
        "nu": float(model.nu),
        "refinement": int(model.refinement),
        "rings": int(model.calibration_rings),
        "cross_terms": bool(model.cross_terms and model.nu < 0.5),
    }
    cal = cached(
        cache_key(**params),
        lambda: solve_calibration(
            design.shape,
            design.tiling or "",
            design.gap,
            model.nu,
            model.refinement,
            model.calibration_rings,
            params["cross_terms"],
        ),
    )
    if model.fidelity == "springs":
        cal = spring_calibration(cal, design.shape, design.tiling or "", design.gap)
    return cal


def coupling_ratio(K1: Array, K0: Array) -> float:
    """max_ab |K1_ab| / sqrt(K0_aa K0_bb): the size of a coupling relative to the self block."""
    d = np.sqrt(np.diag(K0))
    return float(np.max(np.abs(K1) / np.outer(d, d)))


def _triplets(blocks: list[tuple[int, int, Array]], n: int) -> sp.csc_matrix:
    rows, cols, vals = [], [], []
    r5, c5 = np.meshgrid(np.arange(5), np.arange(5), indexing="ij")
    for i, j, B in blocks:
        rows.append((5 * i + r5).ravel())
        cols.append((5 * j + c5).ravel())
        vals.append(B.ravel())
    coo = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(5 * n, 5 * n)
    )
    K = coo.tocsc()
    K.eliminate_zeros()
    return K


def assemble(patch: Patch, cal: Calibration, threshold: float, coupling: float) -> sp.csc_matrix:
    """K(f) = K_iso + f (K_multi - K_iso) of a patch from calibrated blocks (eqs. (15)-(16))."""
    n = patch.n_scales
    members = patch.sites[:, 2]
    blocks = [(k, k, (1.0 - coupling) * cal.K_iso + coupling * cal.K0[m]) for k, m in enumerate(members)]
    if n > 1 and coupling > 0.0:
        index = {tuple(s): k for k, s in enumerate(patch.sites.tolist())}
        kept = [c for c in cal.couplings if coupling_ratio(c.K1, cal.K0[c.source]) >= threshold]
        by_source: dict[int, list] = {}
        for c in kept:
            by_source.setdefault(c.source, []).append(c)
        for k, (i, j, m) in enumerate(patch.sites.tolist()):
            for c in by_source.get(m, []):
                r = index.get((i + c.site[0], j + c.site[1], c.receiver))
                if r is not None:
                    blocks.append((r, k, coupling * c.K1))
    return _triplets(blocks, n)


def check_positive_definite(K: sp.spmatrix) -> None:
    """Raise QpscaleError unless K is symmetric positive definite (dense Cholesky)."""
    dense = K.toarray()
    if not np.allclose(dense, dense.T, rtol=0.0, atol=1e-12 * np.abs(dense).max()):
        raise QpscaleError("substrate stiffness is not symmetric")
    try:
        np.linalg.cholesky(dense)
    except np.linalg.LinAlgError as exc:
        raise QpscaleError(
            "substrate stiffness is not positive definite (lower the threshold or raise the refinement)"
        ) from exc


def stiffness_matrix(patch: Patch, model: SubstrateModel | None = None) -> sp.csc_matrix:
    """Normalised substrate stiffness ``(5n, 5n)`` of a patch, DOFs [u_x, u_y, u_z, phi_x, phi_y] per scale.

    A one-scale patch gets the isolated single-punch block.  The result is cached per
    (design, sites, model); the matrix is symmetric and checked positive definite.

    >>> K = stiffness_matrix(Design(rings=1).patch(), SubstrateModel(refinement=3))
    >>> K.shape
    (45, 45)
    """
    model = model or SubstrateModel()
    d = patch.design
    key = (d.shape, d.tiling, d.gap, patch.sites.tobytes(), model)
    if key not in _MATRIX_CACHE:
        if patch.n_scales == 1:
            K_iso = isolated_block(d.shape, model.nu, model.refinement, model.cross_terms)
            K_iso = 0.5 * (K_iso + K_iso.T)
            K = sp.csc_matrix(np.diag(np.diag(K_iso)) if model.fidelity == "springs" else K_iso)
        else:
            K = assemble(patch, calibrate(d, model), model.threshold, model.coupling)
        check_positive_definite(K)
        _MATRIX_CACHE[key] = K
    return _MATRIX_CACHE[key].copy()


def dimensional_stiffness(K_star: sp.spmatrix, E_s: float, nu: float, L: float) -> sp.csc_matrix:
    """Physical stiffness from the normalised one: translations E* L K*, rotations E* L^3 K_phi*."""
    if not L > 0:
        raise InvalidDesign("L", L, "(0, inf)")
    scale = np.tile([1.0, 1.0, 1.0, L, L], K_star.shape[0] // 5)
    S = sp.diags(scale)
    return (e_star(E_s, nu) * L * (S @ K_star @ S)).tocsc()
