"""Calibration of a design: isolated block, self blocks K0 and coupling blocks K1 by offset.

Implements formulations/substrate.md, sec. 4-5 (eqs. (10)-(14)): one boundary-element solve on
a calibration patch (the scale of motif member 0 and its rings of neighbours, all clamped),
symmetrised by reciprocity; the blocks of motif member 1 follow from the point symmetry of every
two-member tiling (x -> c - x swaps the members), so only member 0 is ever solved.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..geometry import Array
from ..tiling import Design
from .bem import extrapolated_blocks, isolated_block, shape_pieces

# DOF signs under a 180-degree rotation about z: u_x, u_y, phi_x, phi_y change sign (eq. (13)).
R180 = np.diag([-1.0, -1.0, 1.0, -1.0, -1.0])


@dataclass(frozen=True)
class Coupling:
    """Block K1 ``(5, 5)``: force on the receiver per unit DOF of the source (normalised).

    ``source`` and ``receiver`` are motif members; ``site`` = (di, dj) the lattice offset of the
    receiver's cell; ``offset`` = (dx, dy) the vector between reference points, in L.
    """

    source: int
    receiver: int
    site: tuple[int, int]
    offset: tuple[float, float]
    K1: Array


@dataclass(frozen=True)
class Calibration:
    """Substrate blocks of one (shape, tiling, gap, nu, discretisation).

    Attributes
    ----------
    K_iso : ndarray (5, 5)
        Isolated single-punch block.
    K0 : ndarray (n_motif, 5, 5)
        Self block of each motif member with all neighbours clamped.
    couplings : tuple of Coupling
        Every (source member, receiver site) block, both directions, symmetrised.
    asymmetry : float
        max ||K_ij - K_ji^T||_F / ||K0||_F over the reciprocal pairs of one solve: the
        discretisation error of the collocation (eq. (12)).
    n_panels : int
    wall_s : float
    """

    K_iso: Array
    K0: Array
    couplings: tuple[Coupling, ...]
    asymmetry: float
    n_panels: int
    wall_s: float


def _calibration_patch(design: Design, rings: int):
    return design.with_(rings=rings, slant_deg=0.0, thickness=1.0).patch()


def solve_calibration(
    shape: str, tiling: str, gap: float, nu: float, refinement: int, rings: int, cross_terms: bool = True
) -> Calibration:
    """Run the boundary-element solves of one calibration (see module notes)."""
    t0 = time.perf_counter()
    patch = _calibration_patch(Design(shape=shape, tiling=tiling, gap=gap), rings)
    feet = [shape_pieces(shape, a, c) for a, c in zip(patch.angles, patch.centroids)]
    # Far rings carry small couplings: a coarser mesh there keeps the dense solve small.
    density = [refinement if r <= 1 else max(2, refinement // 2) for r in patch.ring]
    ring1 = tuple(int(k) for k in np.flatnonzero(patch.ring == 1))
    blocks = extrapolated_blocks(feet, patch.centroids, nu, density, (0, *ring1), cross_terms, focus=0)
    K = blocks.K
    K00 = K[0, 0]
    asym = [np.linalg.norm(K00 - K00.T)]
    asym += [np.linalg.norm(K[j, 0] - K[0, 1 + n].T) for n, j in enumerate(ring1)]
    K0 = 0.5 * (K00 + K00.T)
    couplings = _coupling_table(patch, K[:, 0], K0)
    K_iso = isolated_block(shape, nu, refinement, cross_terms)
    return Calibration(
        0.5 * (K_iso + K_iso.T),
        np.array([K0, R180 @ K0 @ R180][: design_members(patch)]),
        couplings,
        float(max(asym) / np.linalg.norm(K0)),
        blocks.n_panels,
        time.perf_counter() - t0,
    )


def design_members(patch) -> int:
    return int(patch.sites[:, 2].max()) + 1 if len(patch.sites) > 1 else patch.design.n_motif


def _coupling_table(patch, K_from0: Array, K0: Array) -> tuple[Coupling, ...]:
    """Symmetrised blocks for every receiver of source member 0, and their images (eq. (13))."""
    sites = {tuple(s): n for n, s in enumerate(patch.sites.tolist())}
    c = patch.centroids
    table: dict[tuple[int, int, int, int], tuple[Array, tuple[float, float]]] = {}
    for n in range(1, patch.n_scales):
        di, dj, m = (int(v) for v in patch.sites[n])
        raw = K_from0[n]
        if m == 0:
            partner = sites.get((-di, -dj, 0))
            S = 0.5 * (raw + K_from0[partner].T) if partner is not None else raw
        else:
            S = 0.5 * (raw + R180 @ raw.T @ R180)
        off = (float(c[n, 0] - c[0, 0]), float(c[n, 1] - c[0, 1]))
        neg = (-off[0], -off[1])
        table[(0, di, dj, m)] = (S, off)
        table[(m, -di, -dj, 0)] = (S.T, neg)
        if patch.design.n_motif == 2:
            table[(1, -di, -dj, 1 - m)] = (R180 @ S @ R180, neg)
            table[(1 - m, di, dj, 1)] = (R180 @ S.T @ R180, off)
    return tuple(Coupling(k[0], k[3], (k[1], k[2]), v[1], v[0]) for k, v in sorted(table.items()))


def ring1_offsets(shape: str, tiling: str, gap: float) -> tuple[tuple[int, int, int], ...]:
    """Lattice offsets (di, dj, member) of the ring-1 neighbours of a member-0 scale."""
    patch = _calibration_patch(Design(shape=shape, tiling=tiling, gap=gap), 1)
    return tuple(tuple(int(v) for v in patch.sites[k]) for k in np.flatnonzero(patch.ring == 1))  # type: ignore[misc]


def local_self_block(
    shape: str,
    tiling: str,
    gap: float,
    nu: float,
    refinement: int,
    present: tuple[tuple[int, int, int], ...],
    cross_terms: bool = True,
) -> Array:
    """Self block of a member-0 scale whose ring-1 neighbours are only ``present`` (offsets), all
    clamped: the self stiffness of a scale on the edge or corner of a patch (formulations/
    substrate.md sec. 9, eq. (18)).  Same mesh rules and extrapolation as the calibration."""
    patch = _calibration_patch(Design(shape=shape, tiling=tiling, gap=gap), 1)
    sites = [tuple(int(v) for v in s) for s in patch.sites]
    keep = [0] + [k for k, site in enumerate(sites) if k and site in set(present)]
    feet = [shape_pieces(shape, patch.angles[k], patch.centroids[k]) for k in keep]
    blocks = extrapolated_blocks(feet, patch.centroids[keep], nu, refinement, (0,), cross_terms, focus=0)
    K00 = blocks.K[0, 0]
    return 0.5 * (K00 + K00.T)
