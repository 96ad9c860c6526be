"""Normalisations of the paper, stated in formulations/normalisation.md.

Lengths are in units of L (the square scale's base is 2L x 2L).  With
E* = E_s / (1 - nu_s^2):

* force            F*      = F (1 - nu_s^2) / (E_s L^2)     = F / (E* L^2)
* stiffness        K*      = K (1 - nu_s^2) / (E_s L)       = K / (E* L)
* rot. stiffness   K_phi*  = K_phi (1 - nu_s^2) / (E_s L^3) = K_phi / (E* L^3)
* compliance       C_f*    = C_f E_m I_m / L^3
"""

from __future__ import annotations

from .errors import InvalidDesign


def check_nu(nu: float, name: str = "nu") -> float:
    """Return ``nu`` if it is a Poisson's ratio of a stable isotropic solid we accept.

    >>> check_nu(0.5)
    0.5
    """
    nu = float(nu)
    if not (0.0 <= nu <= 0.5):
        raise InvalidDesign(name, nu, "[0, 0.5]")
    return nu


def e_star(E_s: float, nu_s: float) -> float:
    """Plane-strain modulus E* = E_s / (1 - nu_s^2).

    >>> e_star(1.0, 0.5)
    1.3333333333333333
    """
    if not E_s > 0:
        raise InvalidDesign("E_s", E_s, "(0, inf)")
    nu_s = check_nu(nu_s, "nu_s")
    return E_s / (1.0 - nu_s**2)


def force_star(F: float, E_s: float, nu_s: float, L: float) -> float:
    """F* = F (1 - nu_s^2) / (E_s L^2)."""
    return F / (e_star(E_s, nu_s) * L**2)


def force_from_star(F_star: float, E_s: float, nu_s: float, L: float) -> float:
    """Inverse of :func:`force_star`: the force in the units of E_s L^2."""
    return F_star * e_star(E_s, nu_s) * L**2


def stiffness_star(K: float, E_s: float, nu_s: float, L: float) -> float:
    """K* = K (1 - nu_s^2) / (E_s L)."""
    return K / (e_star(E_s, nu_s) * L)


def rot_stiffness_star(K_phi: float, E_s: float, nu_s: float, L: float) -> float:
    """K_phi* = K_phi (1 - nu_s^2) / (E_s L^3)."""
    return K_phi / (e_star(E_s, nu_s) * L**3)


def compliance_star(C_f: float, E_m: float, I_m: float, L: float) -> float:
    """C_f* = C_f E_m I_m / L^3 (C_f in length per force)."""
    return C_f * E_m * I_m / L**3
