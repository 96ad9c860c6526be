"""The elastic membrane of the flexure test: hexahedral mesh, locking-free stiffness, condensation.

Implements formulations/membrane.md: the tensor-product hexahedral mesh whose grid lines follow
the supports and the plate (section 2), the selective reduced integration that keeps trilinear
hexahedra free of volumetric locking as nu_m -> 1/2 (section 3, eqs. (2)-(4); the closed form
(3b) on boxes), the linear tie of bonded top-face nodes to a scale's rigid motion (section 4,
eq. (5)) and the condensation of the membrane onto the retained degrees of freedom through one
sparse factorisation (section 5, eqs. (6)-(8d)), with held DOFs, their reactions (eqs. (10b)-(10c)) and
their release (eq. (8c)) from section 7.  Lengths in L, E_m = 1 unless given.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
from skfem import Basis, BilinearForm, ElementHex1, ElementVector, MeshHex
from skfem.helpers import ddot, div, sym_grad
from skfem.quadrature import get_quadrature
from skfem.refdom import RefHex

from .errors import InvalidDesign, SolverFailure
from .geometry import Array
from .units import check_nu

#: nu_m = 1/2 is taken as this value in the bulk modulus (formulations/membrane.md, eq. (4)).
NU_INCOMPRESSIBLE = 0.4999


@dataclass(frozen=True)
class MembraneModel:
    """A rectangular block ``[-a/2, a/2] x [-b/2, b/2] x [0, h]`` of linear elastic solid.

    Parameters
    ----------
    length, width, height : float
        Extent along x, y and z, in L (paper: 10, 10, 1.5).
    E : float
        Young's modulus E_m (1 in the solver).
    nu : float
        Poisson's ratio nu_m in [0, 0.5]; 0.5 is taken as ``NU_INCOMPRESSIBLE``.
    h : float
        Target element edge in the plane, in L (grid lines are forced at ``breaks``).
    nz : int
        Element layers through the thickness.
    h_min : float
        Element size at a graded line (a scale edge next to a gap), in L.
    growth : float
        Growth ratio of the element size away from graded lines, in (1, 4].
    top_h : float or None
        Layer thickness at the top face, in L: the layers are graded from it (growth ``growth``) up
        to ``height / nz``, resolving the membrane under the gaps between bonded scales (membrane.md
        sec. 9); None: ``nz`` uniform layers.
    integration : {"sri", "full"}
        Selective reduced integration (default), or full 2x2x2 integration of both parts (the
        locking element, kept to show what the default avoids).
    """

    length: float = 10.0
    width: float = 10.0
    height: float = 1.5
    E: float = 1.0
    nu: float = 0.5
    h: float = 0.5
    nz: int = 3
    h_min: float = 0.005
    growth: float = 1.5
    top_h: float | None = None
    integration: str = "sri"

    def __post_init__(self) -> None:
        check_nu(self.nu, "nu_m")
        if self.integration not in ("sri", "full"):
            raise InvalidDesign("integration", self.integration, "{sri, full}")
        for name, value in (
            ("length", self.length),
            ("width", self.width),
            ("height", self.height),
            ("E_m", self.E),
            ("h", self.h),
            ("h_min", self.h_min),
        ):
            if not (np.isfinite(value) and value > 0):
                raise InvalidDesign(name, value, "(0, inf)")
        if not (1 <= int(self.nz) == self.nz <= 64):
            raise InvalidDesign("nz", self.nz, "integers in [1, 64]")
        if not (1.0 < self.growth <= 4.0):
            raise InvalidDesign("growth", self.growth, "(1, 4]")
        if self.top_h is not None and not (0 < self.top_h <= self.height / self.nz):
            raise InvalidDesign("top_h", self.top_h, f"(0, height / nz = {self.height / self.nz}]")
        if self.h_min > self.h:
            raise InvalidDesign("h_min", self.h_min, f"(0, h = {self.h}]")
        if self.h > min(self.length, self.width):
            raise InvalidDesign("h", self.h, f"(0, {min(self.length, self.width)}]")

    @property
    def nu_eff(self) -> float:
        return min(self.nu, NU_INCOMPRESSIBLE)

    @property
    def lame(self) -> tuple[float, float]:
        """Shear modulus mu and bulk modulus kappa of eq. (2)."""
        nu = self.nu_eff
        return self.E / (2.0 * (1.0 + nu)), self.E / (3.0 * (1.0 - 2.0 * nu))


def graded_axis(
    lo: float,
    hi: float,
    h: float,
    breaks: tuple[float, ...] = (),
    fine: tuple[float, ...] = (),
    h_min: float = 0.005,
    growth: float = 1.5,
    fine_h: tuple[float, ...] | None = None,
) -> Array:
    """Grid coordinates on [lo, hi]: a line at each break and each fine line, spacing <= h.

    Away from ``fine`` the spacing is uniform per interval; towards a fine line the target size
    is ``s(x) = min(h, h_min + (growth - 1) dist(x, fine))``, a geometric grading (eq. (1)):
    the nodes of each interval between lines sit at equal steps of ``int dx / s``.  ``fine_h``
    gives each fine line its own smallest size instead of ``h_min`` (membrane.md sec. 2).
    """
    sizes = np.full(len(fine), h_min) if fine_h is None else np.asarray(fine_h, dtype=float)
    if len(sizes) != len(fine):
        raise InvalidDesign("fine_h", len(sizes), f"one size per fine line ({len(fine)})")
    keep = np.array([lo <= f <= hi for f in fine], dtype=bool)
    fine_in, sizes = np.asarray(fine, dtype=float)[keep], sizes[keep]
    pts = np.unique(np.round(np.r_[lo, hi, [b for b in breaks if lo < b < hi], fine_in], 12))
    out: list[Array] = [np.asarray(pts[:1], dtype=float)]
    for a, b in zip(pts[:-1], pts[1:]):
        if len(fine_in) == 0:
            n = max(1, int(np.ceil((b - a) / h - 1e-9)))
            out.append(np.linspace(a, b, n + 1)[1:])
            continue
        x = np.linspace(a, b, 4001)
        size = np.min(sizes[None, :] + (growth - 1.0) * np.abs(x[:, None] - fine_in[None, :]), axis=1)
        dens = 1.0 / np.minimum(h, size)
        cum = np.r_[0.0, np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(x))]
        n = max(1, int(np.ceil(cum[-1] - 1e-9)))
        out.append(np.interp(np.linspace(0.0, cum[-1], n + 1)[1:], cum, x))
    return np.concatenate(out)


def build_mesh(
    model: MembraneModel,
    xbreaks: tuple[float, ...] = (),
    ybreaks: tuple[float, ...] = (),
    xfine: tuple[float, ...] = (),
    yfine: tuple[float, ...] = (),
    xfine_h: tuple[float, ...] | None = None,
    yfine_h: tuple[float, ...] | None = None,
) -> MeshHex:
    """The tensor hexahedral mesh of the block; breaks become grid lines, graded towards ``*fine``
    (to ``model.h_min``, or to the per-line sizes ``*fine_h``)."""
    g = {"h_min": model.h_min, "growth": model.growth}
    x = graded_axis(-model.length / 2, model.length / 2, model.h, (0.0, *xbreaks), xfine, fine_h=xfine_h, **g)
    y = graded_axis(-model.width / 2, model.width / 2, model.h, (0.0, *ybreaks), yfine, fine_h=yfine_h, **g)
    return MeshHex.init_tensor(x, y, layers(model))


def layers(model: MembraneModel) -> Array:
    """The levels z of the element layers: ``nz`` uniform ones, or graded towards the top face
    from ``top_h`` (membrane.md sec. 9c)."""
    if model.top_h is None:
        return np.linspace(0.0, model.height, model.nz + 1)
    hz = model.height / model.nz
    return graded_axis(0.0, model.height, hz, (), (model.height,), h_min=model.top_h, growth=model.growth)


def _centre_quadrature() -> tuple[Array, Array]:
    return np.full((3, 1), 0.5), np.ones(1)


def assemble_stiffness(model: MembraneModel, mesh: MeshHex) -> sp.csr_matrix:
    """Stiffness ``(3N, 3N)`` by selective reduced integration, eqs. (2)-(3).

    The deviatoric energy is integrated with 2x2x2 Gauss points, the volumetric one at the
    element centre only (the mean-dilatation B-bar of trilinear hexahedra). DOF ordering is
    skfem's: node k has DOFs ``3k, 3k+1, 3k+2`` (x, y, z).  Meshes of axis-parallel boxes (every
    tensor mesh of ``build_mesh``) take the closed form of eq. (3b); others the same quadrature
    vectorised over the elements (``_assemble_hexahedra``, the fitted mesh of sec. 9d).
    """
    boxes = _box_layout(mesh)
    if boxes is not None:
        return _assemble_boxes(model, mesh, *boxes)
    return _assemble_hexahedra(model, mesh)


def assemble_stiffness_skfem(model: MembraneModel, mesh: MeshHex) -> sp.csr_matrix:
    """Eq. (3) by scikit-fem's form assembly (any hexahedral mesh)."""
    mu, kappa = model.lame
    element = ElementVector(ElementHex1())

    @BilinearForm
    def deviatoric(u, v, w):
        eu, ev = sym_grad(u), sym_grad(v)
        return 2.0 * mu * (ddot(eu, ev) - div(u) * div(v) / 3.0)

    @BilinearForm
    def volumetric(u, v, w):
        return kappa * div(u) * div(v)

    full = Basis(mesh, element, intorder=2)
    reduced = full if model.integration == "full" else Basis(mesh, element, quadrature=_centre_quadrature())
    K = deviatoric.assemble(full) + volumetric.assemble(reduced)
    return sp.csr_matrix(K)


#: Elements per batch of ``_assemble_hexahedra``: its (batch, 8, 3, 8, 3) arrays stay near 100 MB.
_BATCH = 20_000


def _assemble_hexahedra(model: MembraneModel, mesh: MeshHex) -> sp.csr_matrix:
    """Eq. (3) on any hexahedral mesh, as ``assemble_stiffness_skfem`` does it, vectorised.

    With ``G`` the physical gradients of the eight trilinear shape functions at a quadrature point
    and ``w`` its weight times det J, the element matrix of u = N_i e_a, v = N_j e_b is
    ``mu (delta_ab G_i.G_j + G_ib G_ja - 2/3 G_ia G_jb)`` summed over the 2x2x2 points, plus the
    mean dilatation ``kappa V bbar_ia bbar_jb`` with ``bbar = (1/V) int G dV`` (eq. (3c); the full
    rule ``kappa G_ia G_jb`` at every point with ``integration="full"``).  On a box ``bbar`` is
    the centre point's gradient, so this is eq. (3b); on a distorted hexahedron the centre point
    alone would fail the patch test (membrane.md sec. 3).  On the isolated dart's fitted mesh (34k
    nodes) scikit-fem's form assembly took 9.1 s of CPU, this 3.4 s.
    """
    mu, kappa = model.lame
    element = ElementHex1()
    full_pts, full_w = get_quadrature(RefHex, 2)

    def reference(points: Array) -> Array:
        # (g, 8, 3): d N_i / d xi_k at each point.
        return np.stack([element.lbasis(points, i)[1].T for i in range(8)], axis=1)

    def gradients(X: Array, dref: Array, weights: Array) -> tuple[Array, Array]:
        # (e, g, 8, 3) physical gradients and (e, g) weights times |det J| of elements X (e, 8, 3).
        J = np.einsum("eia,gib->egab", X, dref)  # dx_a / dxi_b
        G = np.einsum("gib,egba->egia", dref, np.linalg.inv(J))
        return G, weights[None, :] * np.abs(np.linalg.det(J))

    d_full = reference(full_pts)
    parts = []
    for lo in range(0, mesh.t.shape[1], _BATCH):
        t = mesh.t[:, lo : lo + _BATCH]
        X = mesh.p[:, t].transpose(2, 1, 0)  # (e, 8, 3)
        G, w = gradients(X, d_full, full_w)
        GG = np.einsum("eg,egia,egjb->eiajb", w, G, G)
        Ke = mu * (GG.transpose(0, 1, 4, 3, 2) - (2.0 / 3.0) * GG)
        Ke += mu * np.einsum("eij,ab->eiajb", np.einsum("eiaja->eij", GG), np.eye(3))
        if model.integration == "full":
            Ke += kappa * GG
        else:  # the mean dilatation: the volume average of the divergence rows
            V = w.sum(axis=1)
            bbar = np.einsum("eg,egia->eia", w, G) / V[:, None, None]
            Ke += kappa * np.einsum("e,eia,ejb->eiajb", V, bbar, bbar)
        parts.append(Ke.reshape(t.shape[1], -1))
    return _summed(mesh, np.concatenate(parts))


def _box_layout(mesh: MeshHex) -> tuple[Array, Array] | None:
    """Edge lengths ``(n_e, 3)`` and the common corner signs ``(8, 3)`` if every element is an
    axis-parallel box with the same local node order; else None."""
    X = mesh.p[:, mesh.t]  # (3, 8, n_e)
    lo, hi = X.min(axis=1), X.max(axis=1)
    size = hi - lo
    if not np.all(size > 0):
        return None
    signs = np.where(np.isclose(X, lo[:, None, :], rtol=0, atol=1e-12 * size.max()), -1.0, 1.0)
    on_corner = np.isclose(X, lo[:, None, :], rtol=0, atol=1e-12 * size.max()) | np.isclose(
        X, hi[:, None, :], rtol=0, atol=1e-12 * size.max()
    )
    if not on_corner.all() or not np.all(signs == signs[:, :, :1]):
        return None
    s = signs[:, :, 0].T  # (8, 3)
    if len(np.unique(s, axis=0)) != 8:
        return None
    return size.T, s


def _reference_gradients(s: Array, points: Array, weights: Array) -> Array:
    """``R[k, l, i, j] = sum_g w_g dN_i/dxi_k dN_j/dxi_l`` on [-1, 1]^3 for corner signs ``s``."""
    xi = 1.0 + s[None, :, :] * points[:, None, :]  # (g, 8, 3): 1 + s_ik xi_k
    dN = np.empty((len(points), 3, 8))
    for k in range(3):
        others = [m for m in range(3) if m != k]
        dN[:, k] = s[None, :, k] * xi[:, :, others[0]] * xi[:, :, others[1]] / 8.0
    return np.einsum("g,gki,glj->klij", weights, dN, dN)


def _assemble_boxes(model: MembraneModel, mesh: MeshHex, size: Array, s: Array) -> sp.csr_matrix:
    """Eq. (3b): on a box of edges (a_1, a_2, a_3) every term of eq. (3) is one of nine constant
    24x24 matrices times ``a_1 a_2 a_3 / (a_k a_l)``."""
    mu, kappa = model.lame
    g = 1.0 / np.sqrt(3.0)
    gauss = np.array([[x, y, z] for x in (-g, g) for y in (-g, g) for z in (-g, g)])
    Rf = _reference_gradients(s, gauss, np.ones(8))
    Rc = Rf if model.integration == "full" else _reference_gradients(s, np.zeros((1, 3)), np.full(1, 8.0))
    eye = np.eye(3)
    C = np.zeros((3, 3, 8, 3, 8, 3))  # (k, l, i, alpha, j, beta)
    for k in range(3):
        for l in range(3):
            C[k, l] += mu * (k == l) * np.einsum("ij,ab->iajb", Rf[k, l], eye)
            C[k, l] += mu * np.einsum("ij,a,b->iajb", Rf[k, l], eye[l], eye[k])
            vol_part = kappa * Rc[k, l] - (2.0 * mu / 3.0) * Rf[k, l]
            C[k, l] += np.einsum("ij,a,b->iajb", vol_part, eye[k], eye[l])
    vol = size.prod(axis=1)
    w = 0.5 * vol[:, None, None] / (size[:, :, None] * size[:, None, :])  # (n_e, 3, 3)
    Ke = w.reshape(-1, 9) @ C.reshape(9, -1)  # (n_e, 24 * 24), row-major per element
    return _summed(mesh, Ke)


def _summed(mesh: MeshHex, Ke: Array) -> sp.csr_matrix:
    """The global matrix of the element matrices ``Ke`` ``(n_e, 24 * 24)``, row-major per element
    in skfem's DOF order (node k: ``3k, 3k+1, 3k+2``).

    Triplets with 32-bit indices, converted by COO -> CSR (duplicates summed in the same order):
    the same matrix as from 64-bit broadcast triplets, 2-7x faster on the default scene's meshes.
    """
    n = 3 * mesh.p.shape[1]
    index = np.int32 if n < 2**31 else np.int64
    dofs = (3 * mesh.t.T[:, :, None] + np.arange(3)).reshape(-1, 24).astype(index)
    rows = np.repeat(dofs, 24, axis=1).ravel()
    cols = np.tile(dofs, (1, 24)).ravel()
    return sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()


def node_dofs(nodes: np.ndarray, comp: int | None = None) -> np.ndarray:
    """Global DOF indices of ``nodes``: one component, or all three interleaved."""
    nodes = np.asarray(nodes, dtype=int)
    if comp is not None:
        return 3 * nodes + comp
    return (3 * nodes[:, None] + np.arange(3)).ravel()


def tie_rows(node_xy: Array, centroid: Array) -> Array:
    """Linear map ``(3 k, 5)`` from a scale's DOFs to its bonded nodes' displacements, eq. (5).

    Node displacement = (u_x, u_y, u_z + phi_x (y - c_y) - phi_y (x - c_x)): the small-rotation
    rigid motion of points on the base plane z = 0 of the scale's body frame.
    """
    k = node_xy.shape[0]
    T = np.zeros((k, 3, 5))
    T[:, 0, 0] = 1.0
    T[:, 1, 1] = 1.0
    T[:, 2, 2] = 1.0
    T[:, 2, 3] = node_xy[:, 1] - centroid[1]
    T[:, 2, 4] = -(node_xy[:, 0] - centroid[0])
    return T.reshape(3 * k, 5)


@dataclass(frozen=True)
class Condensed:
    """The membrane condensed onto its retained generalised DOFs z_r, eqs. (6)-(8).

    Generalised DOFs are retained (the QP's unknowns), held (fixed at zero, e.g. support DOFs
    assumed closed; their reactions are checked and they can be released into the retained set)
    or condensed (eliminated through the factorisation of ``K_cc``).

    Attributes
    ----------
    S : ndarray (m, m)
        Schur complement: the membrane energy is ``1/2 z_r' S z_r``.
    T : csr_matrix (3N, n_gen)
        Full nodal displacements from the generalised DOFs (ties and Dirichlet pins applied).
    retained, held, condensed : ndarray of int
        Indices into the generalised DOFs.
    K_g : csc_matrix (n_gen, n_gen)
        ``T' K T``.
    factor : cvxopt CHOLMOD factor
        The supernodal Cholesky factorisation ``P K_cc P' = L L'``, kept for eq. (7).
    bordered : ndarray of int
        The DOFs that were retained or held at the condensation, in that order.
    S_bordered : ndarray (len(bordered), len(bordered))
        The Schur complement onto all of them (eq. (8) with held DOFs free); ``S`` and every
        release (eq. (8c)) are blocks of it.
    """

    S: Array
    T: sp.csr_matrix
    retained: np.ndarray
    held: np.ndarray
    condensed: np.ndarray
    K_g: sp.csc_matrix
    factor: Any
    bordered: np.ndarray
    S_bordered: Array

    @cached_property
    def K_c(self) -> sp.csc_matrix:
        """Rows of ``K_g`` of the condensed DOFs ``(n_condensed, n_gen)``."""
        return sp.csc_matrix(sp.csr_matrix(self.K_g)[self.condensed])

    def solve_cc(self, rhs: Array) -> Array:
        """``K_cc^{-1} rhs`` for ``rhs`` of shape (n_condensed,) or (n_condensed, k)."""
        with _cholmod() as (cvxopt, cholmod):
            B = cvxopt.matrix(np.array(rhs, dtype=float).reshape(len(rhs), -1))
            cholmod.solve(self.factor, B)
        return np.array(B).reshape(np.shape(rhs))

    def generalised(self, z_r: Array) -> Array:
        """All generalised DOFs for retained values ``z_r``: held at zero, condensed by eq. (7)."""
        z = np.zeros(self.T.shape[1])
        z[self.retained] = z_r
        z[self.condensed] = -self.solve_cc(self.K_c[:, self.retained] @ z_r)
        return z

    def displacement(self, z_r: Array) -> Array:
        """Nodal displacements ``(N, 3)`` of the whole membrane for retained values ``z_r``, eq. (7)."""
        return (self.T @ self.generalised(z_r)).reshape(-1, 3)

    def _bordered_at(self, dofs: np.ndarray) -> np.ndarray:
        """Positions of ``dofs`` (retained or held) in ``bordered``, the rows of ``S_bordered``."""
        order = np.argsort(self.bordered)
        return order[np.searchsorted(self.bordered, dofs, sorter=order)]

    def reactions(self, z_r: Array) -> Array:
        """Forces ``(len(held),)`` the held DOFs need to stay at zero: ``(K_g g)`` on them, eq. (10b).

        Read from the bordered Schur complement, ``S_hr z_r`` (eq. (10c)): the condensed DOFs are in
        equilibrium, so the force on every bordered DOF is ``S_bordered`` times their values, the
        held ones zero.  Nothing is solved: eq. (7) and the product with ``K_g`` took 0.09 s a call
        on the square array's mesh, five calls and 13 % of a curve's time.
        """
        h, r = self._bordered_at(self.held), self._bordered_at(self.retained)
        return self.S_bordered[np.ix_(h, r)] @ np.asarray(z_r, dtype=float)

    def released(self, dofs: np.ndarray) -> Condensed:
        """The held ``dofs`` appended to the retained ones, ``S`` bordered by their columns (eq. (8c)).

        The bordered block is read from ``S_bordered``: nothing is solved or refactorised.
        """
        dofs = np.asarray(dofs, dtype=int)
        if not np.all(np.isin(dofs, self.held)) or len(np.unique(dofs)) != len(dofs):
            raise InvalidDesign("dofs", dofs.tolist(), "distinct held DOFs")
        retained = np.r_[self.retained, dofs]
        at = self._bordered_at(retained)
        held = self.held[~np.isin(self.held, dofs)]
        return replace(self, S=self.S_bordered[np.ix_(at, at)], retained=retained, held=held)


def generalised_map(
    n_nodes: int,
    ties: list[tuple[np.ndarray, Array, Array]],
    pinned: np.ndarray,
    slaves: Slaves | None = None,
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Map ``T`` from generalised DOFs to the 3N nodal DOFs, eq. (5).

    Generalised DOFs: first the free nodal DOFs (neither tied, pinned nor slaved), then 5 per
    scale in the order of ``ties`` (each ``(nodes, node_xy (k, 2), centroid (2,))``).  ``slaves``
    (the interface of a two-slab mesh, eq. (5c)) follow the free DOFs of their masters.  Returns
    ``T`` and, for every nodal DOF, its generalised index (-1 if tied, pinned or slaved).
    """
    tied = np.concatenate([node_dofs(t[0]) for t in ties]) if ties else np.zeros(0, int)
    if len(np.unique(tied)) != len(tied):
        raise InvalidDesign("ties", "a node bonded to two scales", "disjoint footprints")
    slaved = node_dofs(slaves.nodes) if slaves is not None else np.zeros(0, int)
    if len(np.intersect1d(slaved, tied)):
        raise InvalidDesign("slaves", "a slaved node bonded to a scale", "nodes below the top face")
    free = np.setdiff1d(np.arange(3 * n_nodes), np.r_[tied, pinned, slaved].astype(int))
    gen_of = np.full(3 * n_nodes, -1)
    gen_of[free] = np.arange(len(free))
    rows, cols, vals = [free], [np.arange(len(free))], [np.ones(len(free))]
    if slaves is not None:
        W = sp.coo_matrix(slaves.weights)
        for k in range(3):
            master = gen_of[3 * W.col + k]
            if (master < 0).any():
                raise InvalidDesign("slaves", "a master node tied, pinned or slaved", "free masters")
            rows.append(3 * slaves.nodes[W.row] + k)
            cols.append(master)
            vals.append(W.data)
    base = len(free)
    for s, (nodes, xy, centroid) in enumerate(ties):
        Ts = tie_rows(xy, centroid)
        r, c = np.nonzero(Ts)
        rows.append(node_dofs(nodes)[r])
        cols.append(base + 5 * s + c)
        vals.append(Ts[r, c])
    T = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(3 * n_nodes, base + 5 * len(ties)),
    )
    return T, gen_of


# CHOLMOD's options are one dictionary for the whole module; every use sets them under this lock.
_CHOLMOD_LOCK = threading.RLock()


@contextmanager
def _cholmod(**options: Any) -> Iterator[tuple[Any, Any]]:
    """cvxopt and its CHOLMOD (imported on first use: only flexure condenses), supernodal ``L L'``,
    with ``options`` (``nmethods``, ``postorder``...) set for the block and restored after it."""
    import cvxopt
    import cvxopt.cholmod as cholmod

    with _CHOLMOD_LOCK:
        saved = dict(cholmod.options)
        cholmod.options.clear()
        cholmod.options.update({"supernodal": 2, **options})
        try:
            yield cvxopt, cholmod
        finally:
            cholmod.options.clear()
            cholmod.options.update(saved)


def _cvx(M: sp.spmatrix) -> Any:
    """``M`` as a cvxopt sparse matrix."""
    import cvxopt

    C = sp.coo_matrix(M)
    return cvxopt.spmatrix(C.data, C.row.astype(int), C.col.astype(int), size=C.shape)


def _lower(M: sp.spmatrix) -> Any:
    """The lower triangle of symmetric ``M`` as a cvxopt sparse matrix."""
    return _cvx(sp.tril(M))


def _amd(pattern: sp.spmatrix) -> np.ndarray:
    """Approximate-minimum-degree order of a symmetric pattern (CHOLMOD's, on a graph Laplacian + I)."""
    A = sp.csr_matrix(pattern, copy=True)
    A.data[:] = -1.0
    A.setdiag(0.0)
    A.eliminate_zeros()
    A = A + sp.diags(1.0 - np.asarray(A.sum(axis=1)).ravel())
    L = _lower(A)
    with _cholmod() as (_, cholmod):
        F = cholmod.symbolic(L, uplo="L")
        cholmod.numeric(L, F)
        return _factor_order(F, A.shape[0])


def _factor_order(F: Any, n: int) -> np.ndarray:
    """The order a CHOLMOD factor of an ``n x n`` matrix eliminates in (P applied to 0..n-1)."""
    with _cholmod() as (cvxopt, cholmod):
        order = cvxopt.matrix(np.arange(n, dtype=float))
        cholmod.solve(F, order, sys=7)
    return np.rint(np.array(order).ravel()).astype(int)


def _nested_dissection(graph: sp.spmatrix) -> np.ndarray:
    """METIS's nested-dissection order of a symmetric graph given by its pattern (diagonal ignored).

    Entry ``k`` is the vertex eliminated ``k``-th.  METIS's default options fix its random seed,
    so the order is the same from run to run.
    """
    import pymetis

    A = sp.csr_matrix(graph, copy=True)
    A.setdiag(0.0)
    A.eliminate_zeros()
    A.sort_indices()
    order, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(A.indptr, A.indices))
    return np.asarray(order, dtype=np.int64)


def _fill_reducing_order(
    K: sp.spmatrix, T: sp.csr_matrix, condensed: np.ndarray, Kcc: sp.spmatrix
) -> np.ndarray:
    """Order of the condensed DOFs for the factorisation of ``K_cc`` (membrane.md sec. 5).

    When every condensed DOF is a plain nodal DOF (ties and pins are retained or removed), the
    order is METIS's nested dissection of the node graph with each node's DOFs kept together:
    exact zeros in box elements (e.g. some u_x-u_y couplings) break the 3x3 blocks of the DOF
    graph, and an order of that broken pattern fills 1.5-4 times more; nested dissection fills
    18-40 % less than minimum degree on the study's meshes.  Otherwise AMD on the pattern of
    ``K_cc`` itself.  CHOLMOD keeps the order given only if it fills less than its own AMD.
    """
    Tc = sp.csc_matrix(T[:, condensed])
    if not np.all(np.diff(Tc.indptr) == 1):
        return _grouped_order(T, Tc, Kcc)
    dof = Tc.indices
    n_nodes = K.shape[0] // 3
    R = sp.kron(sp.identity(n_nodes, format="csr"), np.ones((1, 3)), format="csr")
    Kn = R @ abs(sp.csr_matrix(K)) @ R.T
    rank = np.empty(n_nodes, dtype=int)
    rank[_nested_dissection(Kn)] = np.arange(n_nodes)
    return np.lexsort((dof % 3, rank[dof // 3]))


def _grouped_order(T: sp.csr_matrix, Tc: sp.csc_matrix, Kcc: sp.spmatrix) -> np.ndarray:
    """Nested dissection of ``K_cc``'s graph with each node's DOFs kept together, where some
    condensed DOFs also carry other nodes' (a slaved interface, eq. (5c)); AMD if a condensed
    DOF is no node's own.

    A condensed DOF's node is that of its own row: the nodal DOF it is alone on with weight 1
    (a slave at a master's position has such a row too; its three DOFs name it together, so the
    grouping is consistent either way).
    """
    alone = np.diff(sp.csr_matrix(T).indptr) == 1
    column = np.repeat(np.arange(Tc.shape[1]), np.diff(Tc.indptr))
    mine = alone[Tc.indices] & (Tc.data == 1.0)
    first = np.full(Tc.shape[1], T.shape[0])
    np.minimum.at(first, column[mine], Tc.indices[mine])
    if (first == T.shape[0]).any():
        return _amd(Kcc)
    own = first // 3
    label, group = np.unique(own, return_inverse=True)
    P = sp.csr_matrix((np.ones(len(group)), (np.arange(len(group)), group)), shape=(len(group), len(label)))
    G = P.T @ abs(sp.csr_matrix(Kcc)) @ P
    rank = np.empty(len(label), dtype=int)
    rank[_nested_dissection(G)] = np.arange(len(label))
    return np.lexsort((np.arange(len(group)), rank[group]))


#: Largest K_g (generalised DOFs) whose Schur complement is read from the trailing block of its
#: factor (``_trailing_schur``): cvxopt hands the factor out as a copy, so that read holds about
#: 32 bytes per nonzero of L at its peak against the forward solve's 9 (membrane.md sec. 5).  At
#: this bound the default ``qpscale flexure`` keeps its peak memory: its mesh (102k DOFs) is read
#: from the factor, its finer companion (155k, 4.5 GB that way) by the forward solve.
TRAILING_MAX_DOFS = 120_000


def condense(
    K: sp.spmatrix,
    T: sp.csr_matrix,
    retained: np.ndarray,
    held: np.ndarray | None = None,
    schur: str = "auto",
) -> Condensed:
    """Schur complement of ``T' K T`` onto ``retained`` by sparse factorisation, eqs. (6)-(8).

    ``held`` generalised DOFs are fixed at zero (neither retained nor condensed).  ``K_cc`` is
    ordered by nested dissection of the node graph (``_fill_reducing_order``) and factorised by
    CHOLMOD (supernodal, ``P K_cc P' = L L'``) for the solves of eq. (7).  The Schur complement
    onto the retained and held DOFs together is ``schur``:

    - ``"trailing"``: the trailing block of the factor of the whole ``K_g`` with those DOFs
      ordered last (``_trailing_schur``, eq. (8d));
    - ``"forward"``: ``K_bb - Y'Y`` with ``Y = L^{-1} P K_cb``, one forward solve whose right-hand
      sides are sparse (eq. (8a));
    - ``"auto"``: trailing up to ``TRAILING_MAX_DOFS`` generalised DOFs, forward above.

    Both are the same algebra (formulations/membrane.md sec. 5); the trailing read is 1.2-2.3
    times faster on the study's meshes and holds more memory at its peak.
    """
    if schur not in ("auto", "trailing", "forward"):
        raise InvalidDesign("schur", schur, "'auto', 'trailing' or 'forward'")
    Kg = sp.csc_matrix(T.T @ K @ T)
    n = Kg.shape[0]
    retained = np.asarray(retained, dtype=int)
    held = np.zeros(0, dtype=int) if held is None else np.asarray(held, dtype=int)
    if len(np.intersect1d(retained, held)) or len(np.unique(retained)) != len(retained):
        raise InvalidDesign("retained", "repeated or held DOFs", "distinct DOFs, none of them held")
    bordered = np.r_[retained, held]
    condensed = np.setdiff1d(np.arange(n), bordered)
    Kr = sp.csr_matrix(Kg)
    rows = Kr[condensed]
    Kcc = sp.csc_matrix(rows[:, condensed])
    perm = _fill_reducing_order(K, T, condensed, Kcc)
    trailing = schur == "trailing" or (schur == "auto" and n <= TRAILING_MAX_DOFS)
    # The trailing read first: cvxopt's copy of that factor is freed before K_cc's is made.
    S_b = _trailing_schur(Kg, condensed[perm], bordered) if trailing else None
    A = _lower(Kcc)
    with _cholmod() as (cvxopt, cholmod):
        try:
            factor = cholmod.symbolic(A, p=cvxopt.matrix(perm.astype(int)), uplo="L")
            cholmod.numeric(A, factor)
        except ArithmeticError as exc:  # not positive definite: a rigid mode not removed by supports or pins
            raise SolverFailure("cholmod", "singular membrane stiffness", detail=str(exc)) from exc
        if S_b is None:
            Y = cholmod.spsolve(factor, cholmod.spsolve(factor, _cvx(rows[:, bordered]), sys=7), sys=4)
            IJ = (np.array(Y.I).ravel(), np.array(Y.J).ravel())
            Ys = sp.csc_matrix((np.array(Y.V).ravel(), IJ), shape=Y.size)
            S_b = Kr[bordered][:, bordered].toarray() - (Ys.T @ Ys).toarray()
            S_b = 0.5 * (S_b + S_b.T)
    if not np.all(np.isfinite(S_b)):
        raise SolverFailure("cholmod", "non-finite condensation")
    m = len(retained)
    return Condensed(S_b[:m, :m], sp.csr_matrix(T), retained, held, condensed, Kg, factor, bordered, S_b)


def _trailing_schur(Kg: sp.csc_matrix, first: np.ndarray, last: np.ndarray) -> Array:
    """Schur complement of symmetric ``Kg`` onto the DOFs ``last``, the others eliminated in the
    order ``first`` (formulations/membrane.md eq. (8d)).

    CHOLMOD factorises ``P (Kg + sigma E_last) P' = L L'`` in exactly the order ``[first, last]``
    (its comparison with AMD and its postordering switched off), so the trailing block of ``L``
    is the Cholesky factor of ``S + sigma I``.  The shift ``sigma = max diag(Kg_last)`` makes that
    block positive definite although ``S`` keeps the rigid modes the held DOFs remove; it is of
    the size of the entries the elimination cancels anyway (``K_bb`` against ``K_bc K_cc^-1 K_cb``),
    so it adds round-off of the same order.
    """
    n, m = Kg.shape[0], len(last)
    sigma = float(Kg.diagonal()[last].max())
    shift = np.zeros(n)
    shift[last] = sigma
    A = _lower(Kg + sp.diags(shift))
    order = np.r_[first, last]
    with _cholmod(nmethods=1, postorder=False) as (cvxopt, cholmod):
        try:
            F = cholmod.symbolic(A, p=cvxopt.matrix(order.astype(int)), uplo="L")
            cholmod.numeric(A, F)
        except ArithmeticError as exc:  # not positive definite: a rigid mode not removed by supports or pins
            raise SolverFailure("cholmod", "singular membrane stiffness", detail=str(exc)) from exc
        if not np.array_equal(_factor_order(F, n)[n - m :], last):
            raise SolverFailure("cholmod", "the bordered DOFs were not eliminated last")
        L = cholmod.getfactor(F)  # moves the values out: F is left symbolic
        del F
        L22 = np.array(cvxopt.matrix(L[n - m :, n - m :]))
    del L
    S = L22 @ L22.T
    S[np.diag_indices(m)] -= sigma
    return 0.5 * (S + S.T)


@dataclass(frozen=True)
class Slaves:
    """Nodes whose displacement is a weighted sum of other nodes' (eq. (5c)): ``nodes (k,)`` and
    ``weights (k, N)`` (sparse; row ``i`` gives slave ``nodes[i]`` from the mesh's N nodes), each
    row summing to 1."""

    nodes: np.ndarray
    weights: sp.csr_matrix


@dataclass(frozen=True)
class MembraneMesh:
    """A meshed membrane with its stiffness: node coordinates and face node sets.

    ``slaves``: a mesh of two slabs that do not share their interface's nodes (the fitted top
    slab over a tensor one, sec. 9e) ties the upper slab's interface nodes to the lower's face.
    """

    model: MembraneModel
    mesh: MeshHex
    slaves: Slaves | None = None

    @cached_property
    def K(self) -> sp.csr_matrix:
        return assemble_stiffness(self.model, self.mesh)

    @property
    def nodes(self) -> Array:
        """Node coordinates ``(N, 3)``."""
        return self.mesh.p.T

    def face_nodes(self, top: bool) -> np.ndarray:
        z = self.model.height if top else 0.0
        return np.flatnonzero(np.isclose(self.nodes[:, 2], z))
