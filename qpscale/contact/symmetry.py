"""A mirror symmetry held on a loading path: the DOF modes it reverses and the separating planes' images.

Implements formulations/contact.md section 8, eqs. (25)-(28), used by formulations/puncture.md
section 4.  A reflection of the patch about a vertical plane through the punctured scale's
reference point maps every scale onto a scale, every convex piece onto a piece, and so every
separating plane of a piece pair onto the separating plane of the image pair.  Holding a path on
its symmetric branch means holding both: the configuration (the antisymmetric DOF modes vanish)
and the planes (each plane is the image of its partner).  Planes left free turn asymmetrically
about their hinges, and the rows that hold the configuration then carry the difference of the
contact forces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from ..geometry import Array
from ..tiling import Patch
from .placement import bodies_of

# Vertices of a piece and of its image must coincide to this, in L.
_MATCH_TOL = 1e-6
# Scales whose pieces are matched to their images at once (bounds the (chunk, P, P, V, V) array).
_CHUNK = 1024
# Singular values of a plane orbit's equality rows below this are dependent rows, dropped.
_RANK_TOL = 1e-9

PlaneKey = tuple[int, int, int, int]
# Slots of an orbit's columns in ascending rows (see ``Mirror._null_columns``).
_PAIR_ORDER = np.array([3, 4, 5, 0, 1, 2])
_OWN_ORDER = np.arange(3)


def map_dofs(q: np.ndarray, M: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """Image ``(n, 5)`` of the configuration q under the symmetry (M, perm)."""
    out = np.empty_like(q)
    out[perm, :2] = q[:, :2] @ M.T
    out[perm, 2] = q[:, 2]
    out[perm, 3:5] = np.linalg.det(M) * (q[:, 3:5] @ M.T)
    return out


def _scale_map(M: np.ndarray) -> Array:
    """S on one scale's DOFs ``(5, 5)``: (u_x, u_y) by M, u_z kept, (phi_x, phi_y) by det(M) M."""
    B = np.zeros((5, 5))
    B[:2, :2] = M
    B[2, 2] = 1.0
    B[3:5, 3:5] = np.linalg.det(M) * M
    return B


def _orbit_modes(n: int, M: np.ndarray, perm: np.ndarray, sign: float) -> sp.csr_matrix:
    """Rows ``(r, 5 n)`` (sparse, orthonormal) spanning the range of (I + sign S) / 2, orbit by orbit.

    For a pair of scales i -> p != i the five rows (e_ik + sign S e_ik) / sqrt 2 (orthonormal, as
    S e_ik lies on scale p); for a scale on the mirror (p = i) the eigenvectors of eigenvalue
    ``sign`` of its own 5 x 5 block.  At most ten entries a row: memory linear in n.
    """
    M = np.asarray(M, dtype=float)
    perm = np.asarray(perm, dtype=int)
    B = _scale_map(M)
    scales = np.arange(n)
    pairs = scales[perm > scales]
    w, V = np.linalg.eigh(0.5 * (B + B.T))
    own = V[:, sign * w > 0].T  # (k, 5): the modes of a scale mapped onto itself
    fixed = scales[perm == scales]
    # pair rows: e_ik / sqrt 2 on scale i, sign (B e_k) / sqrt 2 on scale p
    k = np.arange(5)
    pr = np.repeat(np.arange(5 * len(pairs)), 6)
    cols_i = 5 * pairs[:, None] + k  # (P, 5)
    cols_p = 5 * perm[pairs][:, None, None] + np.broadcast_to(k, (5, 5))  # (P, 5 (row k), 5)
    vals = np.concatenate(
        [np.ones((len(pairs), 5, 1)), sign * np.broadcast_to(B.T, (len(pairs), 5, 5))], axis=2
    ) / np.sqrt(2.0)
    cols = np.concatenate([cols_i[:, :, None], cols_p], axis=2)
    fr = 5 * len(pairs) + np.repeat(np.arange(len(own) * len(fixed)), 5)
    fcols = (5 * fixed[:, None, None] + np.broadcast_to(k, (len(own), 5))).reshape(-1)
    fvals = np.broadcast_to(own, (len(fixed), *own.shape)).reshape(-1)
    r = 5 * len(pairs) + len(own) * len(fixed)
    out = sp.csr_matrix(
        (np.r_[vals.ravel(), fvals], (np.r_[pr, fr], np.r_[cols.ravel(), fcols])), shape=(r, 5 * n)
    )
    out.eliminate_zeros()
    return out


def antisymmetric_rows(n: int, M: np.ndarray, perm: np.ndarray) -> sp.csr_matrix:
    """Rows ``(r, 5 n)`` (sparse, orthonormal) spanning the DOF modes the reflection (M, perm) reverses.

    A configuration is mirror-symmetric exactly when these rows annihilate it; imposed as
    equalities in the increment QP they hold a path on its symmetric branch.  The map S of
    :func:`map_dofs` is orthogonal and an involution, so the reversed modes are the range of
    (I - S) / 2, built orbit by orbit (eq. (25a), :func:`_orbit_modes`).
    """
    return _orbit_modes(n, M, perm, -1.0)


def symmetric_basis(n: int, M: np.ndarray, perm: np.ndarray) -> sp.csc_matrix:
    """Columns ``(5 n, k)`` (sparse, orthonormal) spanning the DOF modes the reflection keeps.

    The complement of :func:`antisymmetric_rows`: the range of (I + S) / 2, orbit by orbit.  A
    symmetric increment is ``dq = Z xi``: the held path's QP in the reduced unknowns xi
    (formulations/increment.md sec. 2, "Held symmetry").
    """
    return sp.csc_matrix(_orbit_modes(n, M, perm, 1.0).T)


def _piece_images(patch: Patch, M: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """``(n, P)``: the piece of scale ``perm[i]`` that piece ``p`` of scale ``i`` maps onto."""
    bodies = bodies_of(patch)
    n, n_pieces = bodies.verts.shape[:2]
    c0 = patch.centroids[0]
    placed = bodies.verts.copy()
    placed[..., :2] += (patch.centroids - c0)[:, None, None, :]
    image = placed.copy()
    image[..., :2] = image[..., :2] @ M.T
    out = np.empty((n, n_pieces), dtype=int)
    for lo in range(0, n, _CHUNK):  # scales in chunks: (chunk, P, P, V, V) distances at once
        i = np.arange(lo, min(lo + _CHUNK, n))
        target = placed[perm[i]]
        # distance from each image vertex to the nearest vertex of each candidate piece
        d = np.linalg.norm(image[i][:, :, None, :, None, :] - target[:, None, :, None, :, :], axis=-1)
        worst = d.min(axis=4).max(axis=3)  # (chunk, P, P)
        out[i] = np.argmin(worst, axis=2)
        best = np.take_along_axis(worst, out[i][:, :, None], axis=2)[..., 0]
        if np.any(best > _MATCH_TOL):
            k, p = np.argwhere(best > _MATCH_TOL)[0]
            raise ValueError(f"piece {p} of scale {i[k]} has no image under the reflection")
    return out


@dataclass(frozen=True)
class Mirror:
    """A reflection symmetry of a patch, as held on a symmetric path.

    Attributes
    ----------
    M : ndarray (2, 2)
        The reflection of the plane (det -1).
    perm : ndarray (n,) of int
        ``perm[i]``: the scale that scale ``i`` maps onto.
    pieces : ndarray (n, P) of int
        ``pieces[i, p]``: the piece of scale ``perm[i]`` that piece ``p`` of scale ``i`` maps onto.
    centre : ndarray (3,)
        A point of the mirror plane: scale 0's reference point, in L.
    dof_rows : scipy.sparse.csr_matrix (r, 5 n)
        Orthonormal rows spanning the antisymmetric DOF modes (at most ten entries a row).
    """

    M: Array
    perm: np.ndarray
    pieces: np.ndarray
    centre: Array
    dof_rows: sp.csr_matrix

    @classmethod
    def of(cls, patch: Patch, M: np.ndarray, perm: np.ndarray) -> Mirror:
        """The reflection ``(M, perm)`` of ``patch`` (from ``experiments.symmetry.mirror_through``)."""
        return cls(
            np.asarray(M, dtype=float),
            np.asarray(perm, dtype=int),
            _piece_images(patch, M, perm),
            np.r_[patch.centroids[0], 0.0],
            antisymmetric_rows(patch.n_scales, M, perm),
        )

    @cached_property
    def dof_basis(self) -> sp.csc_matrix:
        """Orthonormal columns ``(5 n, k)`` spanning the symmetric DOF modes (:func:`symmetric_basis`)."""
        return symmetric_basis(len(self.perm), self.M, self.perm)

    def reduced_stiffness(self, K: sp.csc_matrix) -> sp.csc_matrix:
        """``Zq' K Zq`` symmetrised, in CSC (``Zq`` = :attr:`dof_basis`): the DOF block of a held QP's
        Hessian (formulations/increment.md sec. 2, Held symmetry), kept for the last ``K`` asked for.

        K is the same along a path, so the product is formed once instead of in every held QP
        (it was a third of building one, 0.4 ms of 1.3 ms, on the default scene).  It is formed
        with the same sparse products, in the same order, as the whole ``Z' P Z`` of
        ``increment._held``, whose DOF block it is: the same sums, bit for bit.
        """
        cached = self.__dict__.get("_reduced_stiffness")
        if cached is not None and cached[0] is K:
            return cached[1]
        Z = self.dof_basis
        P = Z.T @ K @ Z
        out = sp.csc_matrix(0.5 * (P + P.T))
        self.__dict__["_reduced_stiffness"] = (K, out)
        return out

    @property
    def M3(self) -> Array:
        """The reflection in space: M on (x, y), z unchanged."""
        out = np.eye(3)
        out[:2, :2] = self.M
        return out

    def plane_images(self, keys: Sequence[PlaneKey]) -> tuple[np.ndarray, np.ndarray]:
        """Index of each plane's image among ``keys`` (-1 if absent) and its orientation s.

        The image of the pair (a, pa, b, pb) is the pair of the images; keys are ordered a < b,
        so when the images come in the other order the plane's normal (from a to b) maps onto
        minus the image's: s = -1, eq. (25).
        """
        keys = tuple(keys)
        cache: dict = self.__dict__.setdefault("_images", {})  # a path asks for the same set often
        if keys in cache:
            return cache[keys]
        P = len(keys)
        image = np.full(P, -1, dtype=int)
        sign = np.ones(P)
        if P:
            k = np.asarray(keys, dtype=np.int64).reshape(P, 4)
            ia, ib = self.perm[k[:, 0]], self.perm[k[:, 2]]
            ka, kb = self.pieces[k[:, 0], k[:, 1]], self.pieces[k[:, 2], k[:, 3]]
            swap = ~(ia < ib)  # as the tuples order them
            swapped, kept = np.stack([ib, kb, ia, ka], axis=1), np.stack([ia, ka, ib, kb], axis=1)
            img = np.where(swap[:, None], swapped, kept).astype(np.int64)
            sign[swap] = -1.0
            base = np.int64(max(len(self.perm), self.pieces.shape[1], 1))

            def code(x: np.ndarray) -> np.ndarray:  # one integer per key, in the order of the tuples
                return ((x[:, 0] * base + x[:, 1]) * base + x[:, 2]) * base + x[:, 3]

            own = code(k)
            order = np.argsort(own, kind="stable")
            at = np.searchsorted(own[order], code(img))
            found = at < P
            found[found] = own[order][at[found]] == code(img)[found]
            image[found] = order[at[found]]
        image.flags.writeable = sign.flags.writeable = False
        if len(cache) > 256:
            cache.clear()
        cache[keys] = (image, sign)
        return image, sign

    def symmetrise(self, keys: Sequence[PlaneKey], normal: Array, point: Array) -> tuple[Array, Array]:
        """Planes ``(P, 3)`` replaced by the mean of themselves and their partners' images, eq. (26).

        The result is exactly symmetric (the reflection is an involution).  A plane whose image
        is not among ``keys`` (its partner lies just outside the margin) is kept as it is.
        """
        image, sign = self.plane_images(keys)
        n, p = normal.copy(), point.copy()
        R, c = self.M3, self.centre
        js = np.flatnonzero(image >= 0)
        i = image[js]
        mean = 0.5 * (normal[js] + sign[i, None] * (normal[i] @ R.T))
        size = np.linalg.norm(mean, axis=1)
        ok = size >= 0.5  # else a plane and its image's image disagree by over 120 deg: keep it
        js, i = js[ok], i[ok]
        n[js] = mean[ok] / size[ok, None]
        p[js] = 0.5 * (point[js] + c + (point[i] - c) @ R.T)
        return n, p

    def _plane_orbits(
        self, keys: Sequence[PlaneKey], point: Array, basis: Array
    ) -> tuple[np.ndarray, np.ndarray, Array]:
        """One plane per orbit present in ``keys`` (``js``), its image (``i_``), and the orbit's
        equality block ``(k, 3, 6)`` of eq. (27) on the columns (t_i (2), sigma_i, t_j (2), sigma_j)."""
        image, sign = self.plane_images(keys)
        R, c = self.M3, self.centre
        P = len(keys)
        js = np.flatnonzero(image >= np.arange(P))
        i_, s = image[js], sign[js]
        A = s[:, None, None] * np.einsum("kai,ab,kbj->kij", basis[i_], R, basis[js])  # t_i = A t_j
        # offset about the centre o_k = n_k . (p_k - c), its increment sigma_k + (E_k t_k) . (p_k - c)
        lever_j = np.einsum("kaj,ka->kj", basis[js], point[js] - c)
        lever_i = np.einsum("kaj,ka->kj", basis[i_], point[i_] - c)
        local = np.zeros((len(js), 3, 6))
        local[:, :2, :2] = np.eye(2)
        local[:, :2, 3:5] = -A
        local[:, 2, 2] = 1.0
        local[:, 2, :2] = lever_i
        local[:, 2, 5] = -s
        local[:, 2, 3:5] = -s[:, None] * lever_j
        return js, i_, local

    @staticmethod
    def _orbit_svd(js: np.ndarray, i_: np.ndarray, local: Array, subset: np.ndarray, own: bool) -> tuple:
        """SVD of the orbits ``subset``: a pair's 3 x 6 block, or (``own``: planes that are their own
        images) the 3 x 3 block, both column sets being the same unknowns; with the orbits' columns."""
        block = local[subset, :, :3] + local[subset, :, 3:] if own else local[subset]
        _, sv, Vt = np.linalg.svd(block, full_matrices=True)
        base = 3 * js[subset, None] if own else np.stack([3 * i_[subset], 3 * js[subset]], axis=1)
        columns = (base[:, :, None] + np.arange(3)).reshape(len(base), -1)
        rank = sv > _RANK_TOL * np.maximum(1.0, sv[:, :1])
        return sv, Vt, columns, rank

    def plane_rows(
        self, keys: Sequence[PlaneKey], normal: Array, point: Array, basis: Array
    ) -> sp.csr_matrix:
        """Equality rows ``(r, 3 P)`` on the plane unknowns that keep symmetric planes symmetric
        (sparse: at most six entries a row).

        Eq. (27): the image of plane j's increment is plane j*'s increment, for the two rotations
        ``t`` and the shift ``sigma`` of each plane (order t1, t2, sigma).  One orbit (a pair of
        planes, or one plane that is its own image) gives its rows at once, reduced to an
        orthonormal independent set (a plane on the mirror keeps one rotation free).
        """
        P = len(keys)
        js, i_, local = self._plane_orbits(keys, point, basis)
        if not len(js):
            return sp.csr_matrix((0, 3 * P))
        own = i_ == js
        vals = np.zeros((len(js), 3, 6))
        cols = np.zeros((len(js), 3, 6), dtype=int)
        keep = np.zeros((len(js), 3), dtype=bool)
        for subset, is_own in ((~own, False), (own, True)):
            if not subset.any():
                continue
            sv, Vt, columns, rank = self._orbit_svd(js, i_, local, subset, is_own)
            width = columns.shape[1]
            vals[subset, :, :width] = Vt[:, :3]
            cols[subset, :, :width] = columns[:, None, :]
            keep[subset] = rank
        vals, cols = vals[keep], cols[keep]  # (r, 6), in orbit order
        rows = np.repeat(np.arange(len(vals)), 6)
        out = sp.csr_matrix((vals.ravel(), (rows, cols.ravel())), shape=(len(vals), 3 * P))
        out.eliminate_zeros()
        return out

    def _null_columns(
        self, keys: Sequence[PlaneKey], point: Array, basis: Array
    ) -> tuple[np.ndarray, Array, np.ndarray, np.ndarray]:
        """The columns of ``Zp`` (:meth:`plane_block`), each as six slots in ascending rows: its rows
        ``(k, 6)``, values ``(k, 6)`` (zero in unused slots) and the first column and column count
        of its orbit.

        Lone planes (image absent) give three unit columns, each its own orbit; then the pair
        orbits' null vectors, then those of the planes on the mirror: the columns' order of ``Zp``.
        """
        image, _ = self.plane_images(keys)
        js, i_, local = self._plane_orbits(keys, point, basis)
        own = i_ == js
        lone = np.flatnonzero(image < 0)
        n = 3 * len(lone)
        rows = [np.zeros((n, 6), dtype=int)]
        rows[0][:, 0] = (3 * lone[:, None] + np.arange(3)).ravel()
        vals = [np.zeros((n, 6))]
        vals[0][:, 0] = 1.0
        first, count = [np.arange(n)], [np.ones(n, dtype=int)]
        for subset, is_own in ((~own, False), (own, True)):
            if not subset.any():
                continue
            _, Vt, columns, rank = self._orbit_svd(js, i_, local, subset, is_own)
            width = columns.shape[1]
            free = np.ones((len(columns), width), dtype=bool)
            free[:, :3] = ~rank
            k, j = np.nonzero(free)  # orbit k's null vector Vt[k, j]
            # ascending rows: a pair's columns are (image's, own) and the image comes later (js < i_)
            order = _PAIR_ORDER if width == 6 else _OWN_ORDER
            r = np.zeros((len(k), 6), dtype=int)
            v = np.zeros((len(k), 6))
            r[:, :width] = columns[k][:, order]
            v[:, :width] = Vt[k, j][:, order]
            per = free.sum(axis=1)
            starts = n + np.cumsum(per) - per
            rows.append(r)
            vals.append(v)
            first.append(starts[k])
            count.append(per[k])
            n += len(k)
        return np.concatenate(rows), np.concatenate(vals), np.concatenate(first), np.concatenate(count)

    def plane_block(
        self, keys: Sequence[PlaneKey], point: Array, basis: Array, weight: Array
    ) -> tuple[sp.csc_matrix, sp.csc_matrix]:
        """``Zp`` and the plane block of a held QP's Hessian for the diagonal ``weight`` ``(3 P,)``:
        ``S = (H + H') / 2``, ``H = Zp' diag(weight) Zp`` (formulations/increment.md sec. 2, Held
        symmetry).  ``Zp``: columns ``(3 P, k)`` (sparse, orthonormal) spanning the plane
        increments that :meth:`plane_rows` allows, each orbit's null space (the right singular
        vectors of its block beyond its rank), and the three unknowns of a plane whose image is
        absent.

        Both in CSC, built from each column's six slots (scipy's triplet constructor and its
        sparse products took 0.7 ms a held QP on the default scene).  ``H`` is block diagonal by
        orbit; each entry is summed as scipy's ``(Zp.T @ W) @ Zp`` sums it (zero entries left
        out, the rows in descending order, ``0 +`` the first term), so ``S`` is, bit for bit, the
        plane block of the whole product ``increment._held`` formed before.
        """
        rows, vals, first, count = self._null_columns(keys, point, basis)
        # entries (c1, c2) of each orbit's block, column by column (CSC order)
        c2 = np.repeat(np.arange(len(rows)), count)
        c1 = first[c2] + np.arange(len(c2)) - np.repeat(np.cumsum(count) - count, count)
        scaled = vals * np.asarray(weight, dtype=float)[rows]
        t12 = (scaled[c1] * vals[c2]).T.copy()  # (6, entries): the terms, slot by slot
        t21 = (scaled[c2] * vals[c1]).T.copy()
        h12, h21 = np.zeros(len(c2)), np.zeros(len(c2))
        for t in range(5, -1, -1):
            h12 += t12[t]
            h21 += t21[t]
        total = h12 + h21
        keep = total != 0.0  # scipy's sum drops exact zeros
        indptr = np.zeros(len(rows) + 1, dtype=np.int32)
        np.cumsum(np.bincount(c2[keep], minlength=len(rows)), out=indptr[1:])
        S = sp.csc_matrix((0.5 * total[keep], c1[keep].astype(np.int32), indptr), shape=(len(rows),) * 2)
        return _slots_csc(rows, vals, 3 * len(keys)), S

    def orbit_any(self, keys: Sequence[PlaneKey], flags: np.ndarray) -> np.ndarray:
        """``flags`` (P,) or-ed with their partners': a decision made for a whole orbit."""
        image, _ = self.plane_images(keys)
        out = np.asarray(flags, dtype=bool).copy()
        has = image >= 0
        out[has] |= flags[image[has]]
        return out


def _slots_csc(rows: np.ndarray, vals: Array, n: int) -> sp.csc_matrix:
    """CSC ``(n, k)`` of k columns given as slots ``(k, s)`` in ascending rows, zero values left
    out (as ``eliminate_zeros`` left them out of the triplet-built matrix)."""
    on = vals != 0.0
    indptr = np.zeros(len(rows) + 1, dtype=np.int32)
    np.cumsum(on.sum(axis=1), out=indptr[1:])
    return sp.csc_matrix((vals[on], rows[on].astype(np.int32), indptr), shape=(n, len(rows)))
