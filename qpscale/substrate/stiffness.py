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
from .calibration import R180, Calibration, local_self_block, ring1_offsets, solve_calibration
from .springs import spring_calibration

FIDELITIES = ("bem", "springs")
EDGES = ("clamped", "local")
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
    edges : str
        Self blocks of scales with missing ring-1 neighbours: ``"clamped"`` (the default: K0 on
        every scale, as if the absent neighbours were present and clamped) or ``"local"`` (the
        block of the scale's own neighbourhood, formulations/substrate.md eq. (18)); ``bem`` only.

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
    edges: str = "clamped"

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
            ("edges", self.edges, self.edges in EDGES, "{clamped, local}"),
        ]
        for name, value, ok, allowed in checks:
            if not ok:
                raise InvalidDesign(name, value, allowed)
        if self.edges == "local" and self.fidelity != "bem":
            raise InvalidDesign("edges", self.edges, "{clamped} with fidelity springs (local needs bem)")

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
            bool(params["cross_terms"]),
        ),
    )
    if model.fidelity == "springs":
        cal = spring_calibration(cal, design.shape, design.tiling or "", design.gap)
    return cal


def coupling_ratio(K1: Array, K0: Array) -> float:
    """max_ab |K1_ab| / sqrt(K0_aa K0_bb): the size of a coupling relative to the self block."""
    d = np.sqrt(np.diag(K0))
    return float(np.max(np.abs(K1) / np.outer(d, d)))


def _kept_couplings(cal: Calibration, threshold: float) -> list:
    return [c for c in cal.couplings if coupling_ratio(c.K1, cal.K0[c.source]) >= threshold]


def _block_triplets(rows: np.ndarray, cols: np.ndarray, blocks: Array, n: int) -> sp.csc_matrix:
    """Sparse ``(5n, 5n)`` matrix of 5 x 5 ``blocks (b, 5, 5)`` at block positions (rows, cols)."""
    r5, c5 = np.meshgrid(np.arange(5), np.arange(5), indexing="ij")
    i = (5 * rows[:, None, None] + r5).ravel()
    j = (5 * cols[:, None, None] + c5).ravel()
    K = sp.coo_matrix((blocks.ravel(), (i, j)), shape=(5 * n, 5 * n)).tocsc()
    K.eliminate_zeros()
    return K


def assemble(
    patch: Patch,
    cal: Calibration,
    threshold: float,
    coupling: float,
    self_blocks: Array | None = None,
) -> sp.csc_matrix:
    """K(f) = K_iso + f (K_multi - K_iso) of a patch from calibrated blocks (eqs. (15)-(16)).

    Built from triplets, vectorised per kept coupling offset: memory and time are linear in the
    number of scales (about 25 (1 + kept couplings) stored entries per scale), no dense matrix.
    ``self_blocks (n, 5, 5)`` replaces the translation-invariant K0 of each scale (eq. (18)).
    """
    n = patch.n_scales
    members = patch.sites[:, 2]
    rows, cols = [np.arange(n)], [np.arange(n)]
    own = cal.K0[members] if self_blocks is None else self_blocks
    blocks = [(1.0 - coupling) * cal.K_iso[None] + coupling * own]
    if n > 1 and coupling > 0.0:
        # Sites (i, j, member) -> scale index through a sorted integer key (no Python loop per scale).
        span = (
            int(np.abs(patch.sites[:, :2]).max())
            + 1
            + max((max(abs(c.site[0]), abs(c.site[1])) for c in cal.couplings), default=0)
        )
        width = 2 * span + 1
        n_members = 1 + max(int(members.max()), *(c.receiver for c in cal.couplings))

        def key(ij: np.ndarray, m: np.ndarray) -> np.ndarray:
            return ((ij[:, 0] + span) * width + (ij[:, 1] + span)) * n_members + m

        site_key = key(patch.sites[:, :2], members)
        order = np.argsort(site_key)
        sorted_key = site_key[order]
        for c in _kept_couplings(cal, threshold):
            src = np.flatnonzero(members == c.source)
            target = key(patch.sites[src, :2] + np.asarray(c.site), np.full(len(src), c.receiver))
            pos = np.minimum(np.searchsorted(sorted_key, target), n - 1)
            hit = sorted_key[pos] == target
            rows.append(order[pos[hit]])
            cols.append(src[hit])
            blocks.append(np.broadcast_to(coupling * c.K1, (int(hit.sum()), 5, 5)))
    return _block_triplets(np.concatenate(rows), np.concatenate(cols), np.concatenate(blocks), n)


_LOCAL_BLOCKS: dict[tuple, Array] = {}


def local_self_blocks(patch: Patch, model: SubstrateModel | None = None) -> Array:
    """Self block ``(n, 5, 5)`` of every scale with only the ring-1 neighbours the patch has
    (eq. (18)): K0 inside, the block of a scale with missing neighbours on the edge.

    One boundary-element solve per distinct neighbourhood (a square patch has 8: four edges, four
    corners), cached in memory.  Member-1 scales use the point reflection of eq. (13).
    """
    model = model or SubstrateModel()
    d = patch.design
    tiling = d.tiling or ""
    cal = calibrate(d, model)
    ring1 = ring1_offsets(d.shape, tiling, d.gap)
    index = {tuple(s) for s in patch.sites.tolist()}
    cross = bool(model.cross_terms and model.nu < 0.5)
    out = np.empty((patch.n_scales, 5, 5))
    for k, (i, j, m) in enumerate(patch.sites.tolist()):
        # A member-1 scale sees its neighbourhood point-reflected onto a member-0 one.
        offsets = ring1 if m == 0 else tuple((-a, -b, 1 - c) for a, b, c in ring1)
        present = tuple(o for o in offsets if (i + o[0], j + o[1], o[2]) in index)
        if len(present) == len(offsets):
            out[k] = cal.K0[m]
            continue
        as0 = present if m == 0 else tuple((-a, -b, 1 - c) for a, b, c in present)
        key = (d.shape, tiling, d.gap, model.nu, model.refinement, cross, as0)
        if key not in _LOCAL_BLOCKS:
            _LOCAL_BLOCKS[key] = local_self_block(
                d.shape, tiling, d.gap, model.nu, model.refinement, as0, cross
            )
        out[k] = _LOCAL_BLOCKS[key] if m == 0 else R180 @ _LOCAL_BLOCKS[key] @ R180
    return out


def factor_stiffness(K: sp.spmatrix):
    """Sparse LDL' factorisation of a symmetric K (qdldl, approximate minimum degree ordering).

    Returns the qdldl solver (``.solve(b)`` gives K^-1 b) and the pivots D; fill-in for the
    banded-like stiffness of a patch grows like n^1.5 in the number of scales, never n^2.
    Raises QpscaleError if a pivot is exactly zero.
    """
    import qdldl

    try:
        solver = qdldl.Solver(sp.csc_matrix(K))
    except (RuntimeError, ValueError) as exc:
        raise QpscaleError(f"substrate stiffness is singular ({exc})") from exc
    return solver, np.asarray(solver.factors()[1])


def check_positive_definite(K: sp.spmatrix) -> None:
    """Raise QpscaleError unless K is symmetric positive definite.

    Sparse: symmetry from K - K' (stored entries only), definiteness from the signs of the LDL'
    pivots (Sylvester's law of inertia: K is positive definite iff every pivot is positive).
    """
    K = sp.csc_matrix(K)
    big = float(abs(K).max()) if K.nnz else 0.0
    skew = abs(K - K.T)
    if skew.nnz and float(skew.max()) > 1e-12 * big:
        raise QpscaleError("substrate stiffness is not symmetric")
    bad = QpscaleError(
        "substrate stiffness is not positive definite (lower the threshold or raise the refinement)"
    )
    try:
        _, D = factor_stiffness(K)
    except QpscaleError as exc:
        raise bad from exc
    if not np.all(D > 0.0):
        raise bad


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
            own = local_self_blocks(patch, model) if model.edges == "local" else None
            K = assemble(patch, calibrate(d, model), model.threshold, model.coupling, own)
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
