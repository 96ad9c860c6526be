"""The linearised contact rows of a contact set: gap Jacobian and generalised contact forces.

Implements formulations/contact.md section 4, eqs. (14)-(17): the Jacobian J of the gaps g + J dq
of every row of a :class:`~qpscale.contact.detection.ContactSet` with respect to the DOFs, with
the columns of the separating planes' unknowns of section 7, eq. (21); and section 5, eq. (18):
the generalised forces J' lam of the rows' multipliers.  Signs as in
:mod:`qpscale.contact.detection`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import InvalidDesign
from ..geometry import Array, cross, tangent_operators
from ..tiling import Patch
from .detection import ContactSet, _check_q


def _dof_rows(cs: ContactSet, q: Array, centre: Array) -> tuple[Array, Array]:
    """dg/dq_b and dg/dq_a, each ``(m, 5)``: eq. (16).

    A plane row moves only its own vertex (eq. (21)): the other scale's block is zero.
    """
    T = tangent_operators(q[:, 3:5])
    n = cs.normal
    rb = cross(cs.xb - centre[cs.b], n)
    ra = cross(cs.xa - centre[cs.a], n)
    wb = np.hstack([n, np.einsum("mji,mj->mi", T[cs.b], rb)])
    wa = np.hstack([n, np.einsum("mji,mj->mi", T[cs.a], ra)])
    wb[cs.side < 0] = 0.0
    wa[cs.side > 0] = 0.0
    return wb, -wa


def gap_jacobian(cs: ContactSet, patch: Patch, q: Array) -> sp.csr_matrix:
    """Jacobian ``(m, 5 n + cs.n_extra)`` of the gaps: eqs. (14)-(17) and (21).

    Columns follow scale-major DOF order [u_x, u_y, u_z, phi_x, phi_y] per scale, then the
    three unknowns (two normal rotations, one shift) of every separating plane.  Each row has
    13 slots in ascending columns (the lower-numbered scale's five, the other's, its plane's
    three); the CSR arrays are those slots without their zeros (a plane row's other-scale block,
    a feature row's plane), the canonical matrix that the triplet constructor and
    ``eliminate_zeros`` gave at 0.3 ms a call.
    """
    q = _check_q(patch, q)
    centre = np.zeros((patch.n_scales, 3))
    centre[:, :2] = patch.centroids
    centre += q[:, :3]
    wb, wa = _dof_rows(cs, q, centre)
    n_dof = 5 * patch.n_scales
    m = cs.m
    cols = np.zeros((m, 13), dtype=np.int32)
    vals = np.zeros((m, 13))
    b_first = (cs.b < cs.a)[:, None]
    k = np.arange(5)
    cols[:, :5] = 5 * np.where(b_first, cs.b[:, None], cs.a[:, None]) + k
    cols[:, 5:10] = 5 * np.where(b_first, cs.a[:, None], cs.b[:, None]) + k
    vals[:, :5] = np.where(b_first, wb, wa)
    vals[:, 5:10] = np.where(b_first, wa, wb)
    if cs.planes is not None and cs.planes.count:
        on = np.flatnonzero(cs.side != 0)
        j, s = cs.plane[on], cs.side[on].astype(float)
        x = np.where((cs.side[on] > 0)[:, None], cs.xb[on], cs.xa[on])
        lever = np.einsum("mki,mk->mi", cs.planes.basis[j], x - cs.planes.point[j])
        cols[on, 10:] = n_dof + 3 * j[:, None] + np.arange(3)
        vals[on, 10:12] = s[:, None] * lever
        vals[on, 12] = -s
    keep = vals != 0.0
    indptr = np.zeros(m + 1, dtype=np.int32)
    np.cumsum(np.count_nonzero(keep, axis=1), out=indptr[1:])
    return sp.csr_matrix((vals[keep], cols[keep], indptr), shape=(m, n_dof + cs.n_extra))


def contact_forces(cs: ContactSet, lam: Array) -> Array:
    """Generalised contact forces ``(n, 5)`` of multipliers ``lam`` (m,), eq. (18): J' lam.

    Row i holds the force on scale i and the work-conjugate of its rotation increments,
    T_i' (sum of r x F), at the configuration the set was detected at.
    """
    lam = np.asarray(lam, dtype=float)
    if lam.shape != (cs.m,):
        raise InvalidDesign("lam", lam.shape, f"shape ({cs.m},)")
    wb, wa = _dof_rows(cs, cs.q, cs.centre)
    out = np.zeros((cs.n_scales, 5))
    np.add.at(out, cs.b, lam[:, None] * wb)
    np.add.at(out, cs.a, lam[:, None] * wa)
    return out
