"""Cerruti influence: tangential tractions, and the (1 - 2 nu) normal-tangential cross terms.

Implements formulations/substrate.md, sec. 1 (eq. (2)) with the panel integrals of
:mod:`qpscale.substrate.boussinesq`.  Normalised so that E* = E_s / (1 - nu^2) = 1.
"""

from __future__ import annotations

import numpy as np

from ..geometry import Array


def tangential_influence(ints: dict[str, Array], nu: float) -> Array:
    """In-plane displacement per unit tangential traction, ``(2M, 2T)`` ordered [x-block, y-block].

    Cerruti: ``u_a = Q_b / pi [delta_ab / r + nu/(1-nu) e_a e_b / r]`` on the surface (E* = 1).
    """
    w = nu / (1.0 - nu)
    gxx = (ints["1"] + w * ints["xx"]) / np.pi
    gyy = (ints["1"] + w * ints["yy"]) / np.pi
    gxy = w * ints["xy"] / np.pi
    return np.block([[gxx, gxy], [gxy, gyy]])


def cross_influence(ints: dict[str, Array], nu: float) -> tuple[Array, Array]:
    """The (1 - 2 nu) coupling blocks ``(G_tz (2M, T), G_zt (M, 2T))`` (eq. (2c)).

    An upward (tensile) normal traction moves surface points away from it: ``u_a = -c e_a / r``
    times the traction, ``c = (1 - 2 nu) / (2 pi (1 - nu))``, ``e`` pointing from the field
    point to the source; reciprocity gives ``u_z = +c e_a / r`` per unit tangential traction
    along ``a``.  Both vanish at nu = 0.5.
    """
    c = (1.0 - 2.0 * nu) / (2.0 * np.pi * (1.0 - nu))
    g_tz = np.vstack([-c * ints["x"], -c * ints["y"]])
    g_zt = np.hstack([c * ints["x"], c * ints["y"]])
    return g_tz, g_zt
