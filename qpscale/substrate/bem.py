"""Rigid multi-punch boundary-element solve: blocks of generalised forces per unit motion.

Implements formulations/substrate.md, sec. 3-4 (eqs. (7)-(11)): constant tractions on the
panels of :mod:`qpscale.substrate.panels`, collocation at the panel centroids, the rigid-body
displacement of each footprint imposed there; the tractions are integrated into forces and
moments about each footprint's reference point.  Normalised units: L = 1, E* = 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from shapely.geometry import Polygon
from shapely.ops import unary_union

from ..errors import InvalidDesign, QpscaleError
from ..geometry import Array, convex_pieces, rotate2d
from ..units import check_nu
from .boussinesq import normal_influence, panel_integrals
from .cerruti import cross_influence, tangential_influence
from .panels import Panels, mesh_footprints

# Two footprints may touch (gap 0) but not overlap by more than this area, in L^2.
OVERLAP_TOL = 1e-9
# Error exponent q of the blocks in the density N, K(N) = K* - C N^-q, used to extrapolate from the
# densities N and 2N/3 (formulations/substrate.md, eq. (11)); measured 2.5 between N = 4 and 6.
RICHARDSON_RATE = 2.5
# Edges of other footprints farther than this (in L) from the footprint under study get half the
# panel density (formulations/substrate.md, eq. (9c)).
FOCUS_REACH = 0.5
# Mixed-precision solve: relative residual to reach, and the refinement steps allowed (eq. (7b)).
REFINE_TOL = 1e-12
REFINE_STEPS = 4


@dataclass(frozen=True)
class PunchBlocks:
    """Blocks ``K[r, s]`` (5 x 5): generalised force on footprint r per unit DOF of source s.

    Attributes
    ----------
    K : ndarray (n_footprints, n_sources, 5, 5)
        Normalised stiffness blocks (K*, K_phi*, mixed terms in units of E* L^2).
    sources : tuple of int
        Footprint index of each source.
    n_panels : int
    """

    K: Array
    sources: tuple[int, ...]
    n_panels: int


def check_no_overlap(footprints: list[list[Array]]) -> None:
    """Raise InvalidDesign if two footprints overlap (touching is allowed)."""
    polys = [unary_union([Polygon(p) for p in pieces]) for pieces in footprints]
    for i, p in enumerate(polys):
        for j in range(i + 1, len(polys)):
            area = p.intersection(polys[j]).area
            if area > OVERLAP_TOL:
                raise InvalidDesign(
                    "footprints", f"{i} and {j}", "non-overlapping polygons", f"overlap area {area:.3g} L^2"
                )


def rigid_map(panels: Panels, centres: Array) -> Array:
    """Kinematic matrix ``(3P, 5F)``: panel displacements [x; y; z] from the DOFs of every footprint.

    u = theta x r with theta = (phi_x, phi_y, 0) gives u_z = y phi_x - x phi_y (eq. (7)).
    """
    P, F = panels.n, len(centres)
    B = np.zeros((3 * P, 5 * F))
    rel = panels.centroids - centres[panels.owner]
    cols = 5 * panels.owner
    rows = np.arange(P)
    B[rows, cols] = 1.0
    B[P + rows, cols + 1] = 1.0
    B[2 * P + rows, cols + 2] = 1.0
    B[2 * P + rows, cols + 3] = rel[:, 1]
    B[2 * P + rows, cols + 4] = -rel[:, 0]
    return B


def dense_solve(G: Array, rhs: Array) -> Array:
    """Solve ``G x = rhs``: LU in single precision, refined with double-precision residuals (eq. (7b)).

    Columns of ``rhs`` that are zero are skipped.  If the refinement does not reach a relative
    residual of ``REFINE_TOL`` in ``REFINE_STEPS`` steps, a double-precision LU is used instead.
    """
    x = np.zeros_like(rhs)
    cols = np.flatnonzero(np.abs(rhs).max(axis=0) > 0.0)
    b = rhs[:, cols]
    if b.size == 0:
        return x
    lu = sla.lu_factor(G.astype(np.float32), check_finite=False)
    y = sla.lu_solve(lu, b.astype(np.float32), check_finite=False).astype(float)
    target = REFINE_TOL * np.abs(b).max()
    for _ in range(REFINE_STEPS):
        r = b - G @ y
        if np.abs(r).max() <= target:
            break
        y += sla.lu_solve(lu, r.astype(np.float32), check_finite=False)
    else:
        y = sla.solve(G, b, check_finite=False)
    x[:, cols] = y
    return x


def _solve_tractions(panels: Panels, nu: float, cross_terms: bool, rhs: Array) -> Array:
    """Tractions ``(3P, k)`` [x; y; z] that produce the panel displacements ``rhs (3P, k)``."""
    P = panels.n
    coupled = cross_terms and nu < 0.5
    keys = ("1", "x", "y", "xx", "xy", "yy") if coupled else ("1", "xx", "xy", "yy")
    ints = panel_integrals(panels.centroids, panels.tris, keys)
    g_zz = normal_influence(ints)
    g_tt = tangential_influence(ints, nu)
    del ints["xx"], ints["xy"], ints["yy"]
    try:
        if coupled:
            g_tz, g_zt = cross_influence(ints, nu)
            return dense_solve(np.block([[g_tt, g_tz], [g_zt, g_zz]]), rhs)
        t_tan = dense_solve(g_tt, rhs[: 2 * P])
        t_nrm = dense_solve(g_zz, rhs[2 * P :])
    except (sla.LinAlgError, ValueError) as exc:
        raise QpscaleError(f"boundary-element system is singular: {exc}") from exc
    return np.vstack([t_tan, t_nrm])


def punch_blocks(
    footprints: list[list[Array]],
    centres: Array,
    nu: float,
    density: list[int] | int,
    sources: tuple[int, ...] = (0,),
    cross_terms: bool = True,
    focus: int | None = None,
) -> PunchBlocks:
    """Stiffness blocks of rigid punches on a half-space, each source moved alone (eq. (10)).

    Parameters
    ----------
    footprints : list of list of ndarray (nv, 2)
        Convex pieces of each footprint, world frame, in L.
    centres : ndarray (n_footprints, 2)
        Reference point of each footprint, in L.
    nu : float
        Poisson's ratio of the half-space, in [0, 0.5].
    density : int or list of int
        Panel strips per fan triangle (see :func:`mesh_footprints`).
    sources : tuple of int
        Footprints given unit motions (all others held fixed).
    cross_terms : bool
        Include the (1 - 2 nu) normal-tangential coupling.
    focus : int, optional
        Footprint under study; edges of the others far from it get half the density (eq. (9c)).

    >>> sq = [convex_pieces("square")]
    >>> K = punch_blocks(sq, np.zeros((1, 2)), 0.5, 4).K[0, 0]
    >>> bool(abs(K[2, 2] / 2.257 - 1) < 0.03)  # close to the circle of equal area, 2 a = 2.257
    True
    """
    nu = check_nu(nu)
    centres = np.asarray(centres, dtype=float).reshape(-1, 2)
    check_no_overlap(footprints)
    panels = mesh_footprints(footprints, density, focus, FOCUS_REACH)
    B = rigid_map(panels, centres)
    cols = np.concatenate([np.arange(5 * s, 5 * s + 5) for s in sources])
    t = _solve_tractions(panels, nu, cross_terms, B[:, cols])
    area3 = np.tile(panels.areas, 3)[:, None]
    K = (B * area3).T @ t
    K = K.reshape(len(centres), 5, len(sources), 5).transpose(0, 2, 1, 3)
    return PunchBlocks(K, tuple(sources), panels.n)


def coarse_density(n: int) -> int:
    """The coarser density 2N/3 (rounded down, at least 1) of the Richardson pair (eq. (11))."""
    return max(1, (2 * int(n)) // 3)


def extrapolated_blocks(
    footprints: list[list[Array]],
    centres: Array,
    nu: float,
    density: list[int] | int,
    sources: tuple[int, ...] = (0,),
    cross_terms: bool = True,
    focus: int | None = None,
) -> PunchBlocks:
    """Blocks extrapolated from two panel densities, N and 2N/3 (eq. (11)).

    Same arguments as :func:`punch_blocks`; ``density`` (or its first entry) is the reference
    density N whose ratio to the coarse one sets the Richardson weight.
    """
    dens = [density] * len(footprints) if isinstance(density, int) else list(density)
    n = int(dens[0])
    n_c = coarse_density(n)
    fine = punch_blocks(footprints, centres, nu, dens, sources, cross_terms, focus)
    coarse_dens = [coarse_density(d) for d in dens]
    coarse = punch_blocks(footprints, centres, nu, coarse_dens, sources, cross_terms, focus)
    q = RICHARDSON_RATE
    w = n**-q / (n_c**-q - n**-q) if n_c < n else 0.0
    return PunchBlocks(fine.K + w * (fine.K - coarse.K), fine.sources, fine.n_panels)


def shape_pieces(shape: str, angle: float = 0.0, centre: Array | None = None) -> list[Array]:
    """Convex pieces of a base shape rotated by ``angle`` and placed at ``centre``."""
    c = np.zeros(2) if centre is None else np.asarray(centre, dtype=float)
    return [rotate2d(p, angle) + c for p in convex_pieces(shape)]


def isolated_block(shape: str, nu: float = 0.5, density: int = 6, cross_terms: bool = True) -> Array:
    """Self block ``(5, 5)`` of one scale alone on the half-space (single rigid punch).

    Extrapolated from the densities ``density`` and 2/3 of it (eq. (11)); at the default 6 every
    diagonal entry of the five shapes is within 0.1 % of its converged value.

    >>> bool(abs(isolated_block("square", 0.5, 3)[2, 2] / 2.3046 - 1) < 0.005)
    True
    """
    feet = [shape_pieces(shape)]
    return extrapolated_blocks(feet, np.zeros((1, 2)), nu, density, (0,), cross_terms).K[0, 0]
