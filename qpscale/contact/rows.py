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
from ..geometry import Array, tangent_operators
from ..tiling import Patch
from .detection import ContactSet, _check_q


def _dof_rows(cs: ContactSet, q: Array, centre: Array) -> tuple[Array, Array]:
    """dg/dq_b and dg/dq_a, each ``(m, 5)``: eq. (16).

    A plane row moves only its own vertex (eq. (21)): the other scale's block is zero.
    """
    T = tangent_operators(q[:, 3:5])
    n = cs.normal
    rb = np.cross(cs.xb - centre[cs.b], n)
    ra = np.cross(cs.xa - centre[cs.a], n)
    wb = np.hstack([n, np.einsum("mji,mj->mi", T[cs.b], rb)])
    wa = np.hstack([n, np.einsum("mji,mj->mi", T[cs.a], ra)])
    wb[cs.side < 0] = 0.0
    wa[cs.side > 0] = 0.0
    return wb, -wa


def gap_jacobian(cs: ContactSet, patch: Patch, q: Array) -> sp.csr_matrix:
    """Jacobian ``(m, 5 n + cs.n_extra)`` of the gaps: eqs. (14)-(17) and (21).

    Columns follow scale-major DOF order [u_x, u_y, u_z, phi_x, phi_y] per scale, then the
    three unknowns (two normal rotations, one shift) of every separating plane.  Built from
    triplets (10 entries per row, 13 for plane rows).
    """
    q = _check_q(patch, q)
    centre = np.zeros((patch.n_scales, 3))
    centre[:, :2] = patch.centroids
    centre += q[:, :3]
    wb, wa = _dof_rows(cs, q, centre)
    rows = np.repeat(np.arange(cs.m), 10)
    cols = np.hstack([5 * cs.b[:, None] + np.arange(5), 5 * cs.a[:, None] + np.arange(5)]).ravel()
    vals = np.hstack([wb, wa]).ravel()
    n_dof = 5 * patch.n_scales
    if cs.planes is not None and cs.planes.count:
        on = np.flatnonzero(cs.side != 0)
        j, s = cs.plane[on], cs.side[on].astype(float)
        x = np.where((cs.side[on] > 0)[:, None], cs.xb[on], cs.xa[on])
        lever = np.einsum("mki,mk->mi", cs.planes.basis[j], x - cs.planes.point[j])
        extra = np.hstack([s[:, None] * lever, -s[:, None]])
        rows = np.r_[rows, np.repeat(on, 3)]
        cols = np.r_[cols, (n_dof + 3 * j[:, None] + np.arange(3)).ravel()]
        vals = np.r_[vals, extra.ravel()]
    J = sp.csr_matrix((vals, (rows, cols)), shape=(cs.m, n_dof + cs.n_extra))
    J.eliminate_zeros()  # a plane row's other-scale block
    return J


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
