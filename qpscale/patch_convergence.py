"""Patch-size convergence of a patch result: grow the rings until it settles, and extrapolate.

Implements formulations/substrate.md sec. 10: the stopping rule |F(r) - F(r-1)| <= tol |F(r)| over
patches of r = start, start + 1, ... rings, and the fit F(n) = F_inf - a n^-p in the patch width
n = 2 r + 1 (in scales) with its error estimate, reported only where the sequence has that form;
and formulations/puncture.md sec. 7 ("The study's patch sequence"): what a fixed sequence of
patches says about the skin (``estimate``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import OptimizeWarning, curve_fit

# Fewest points for the three-parameter fit plus one to test it, and the points it uses (the last).
MIN_FIT_POINTS = 4
FIT_POINTS = 5
# Exponents outside this range are not a clear power-law tail (p -> 0 is a logarithm, large p a
# sequence that has already converged to its noise).
P_RANGE = (0.2, 8.0)


@dataclass(frozen=True)
class Extrapolation:
    """F_inf of the fit F(n) = F_inf - a n^-p (n the patch width in scales) and its error.

    ``error`` is the larger of the fit's standard error of F_inf and the change of F_inf when the
    earliest point of the fit is left out (the model error of assuming the tail already reached).
    """

    F_inf: float
    error: float
    a: float
    p: float
    points: int


@dataclass(frozen=True)
class RingsSequence:
    """The runs of a ``rings = auto`` puncture, in order."""

    tol: float
    rings: list[int] = field(default_factory=list)
    values: list[float] = field(default_factory=list)
    wall_s: list[float] = field(default_factory=list)
    converged: bool = False
    stop_reason: str = ""
    extrapolation: Extrapolation | None = None
    no_extrapolation: str = ""

    @property
    def changes(self) -> list[float | None]:
        """Relative change of each value from the previous patch's (None for the first)."""
        v = self.values
        return [None] + [abs(v[k] - v[k - 1]) / abs(v[k]) for k in range(1, len(v))]


def _model(n: np.ndarray, F_inf: float, a: float, p: float) -> np.ndarray:
    return F_inf - a * n ** (-p)


def _fit(n: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    slope = (F[-1] - F[-2]) / (n[-1] - n[-2])
    p0 = 1.0
    a0 = slope * n[-1] ** (p0 + 1) / p0
    guess = [F[-1] + a0 * n[-1] ** -p0, a0, p0]
    lo = [-np.inf, -np.inf, P_RANGE[0] / 2]
    hi = [np.inf, np.inf, 2 * P_RANGE[1]]
    with warnings.catch_warnings():
        # Four points leave one degree of freedom: a covariance that cannot be estimated is
        # reported as inf and the error then rests on the leave-one-out change (``extrapolate``).
        warnings.simplefilter("ignore", OptimizeWarning)
        popt, pcov = curve_fit(_model, n, F, p0=guess, bounds=(lo, hi), maxfev=20000)
    return popt, pcov


def extrapolate(widths: list[int], values: list[float]) -> tuple[Extrapolation | None, str]:
    """Fit the last points of a sequence by F_inf - a n^-p; None and the reason where it has no
    clear form of that kind.

    >>> n = [3, 5, 7, 9, 11]
    >>> e, _ = extrapolate(n, [2.0 - 0.5 * k**-1.5 for k in n])
    >>> round(e.F_inf, 9), round(e.p, 6)
    (2.0, 1.5)
    """
    if len(values) < MIN_FIT_POINTS:
        return None, f"fewer than {MIN_FIT_POINTS} patches"
    n = np.asarray(widths[-FIT_POINTS:], dtype=float)
    F = np.asarray(values[-FIT_POINTS:], dtype=float)
    steps = np.diff(F)
    if not (np.all(steps > 0) or np.all(steps < 0)):
        return None, "the sequence is not monotone"
    if np.any(np.abs(steps[1:]) > np.abs(steps[:-1]) * (n[2:] - n[1:-1]) / (n[1:-1] - n[:-2])):
        return None, "the steps do not shrink"
    try:
        popt, pcov = _fit(n, F)
        drop, _ = _fit(n[1:], F[1:]) if len(n) > MIN_FIT_POINTS else _fit(n[:-1], F[:-1])
    except (RuntimeError, ValueError) as exc:
        return None, f"the fit failed ({exc})"
    F_inf, a, p = (float(x) for x in popt)
    if not P_RANGE[0] <= p <= P_RANGE[1]:
        return None, f"fitted exponent p = {p:.3g} outside [{P_RANGE[0]}, {P_RANGE[1]}]"
    stderr = float(np.sqrt(max(pcov[0, 0], 0.0))) if np.all(np.isfinite(pcov)) else 0.0
    error = max(stderr, abs(F_inf - float(drop[0])))
    if not math.isfinite(error) or error > abs(F_inf - F[-1]):
        return None, f"the extrapolated value is less certain (+-{error:.3g}) than its distance to the last"
    return Extrapolation(F_inf, error, a, p, len(n)), ""


def grow_patch(
    run: Callable[[int], float],
    tol: float,
    start: int,
    max_rings: int,
    on_step: Callable[[int, float, float], None] | None = None,
    stop: Callable[[int], str] | None = None,
) -> RingsSequence:
    """Run ``run(rings)`` for rings = start, start + 1, ... until the relative change is at most
    ``tol``, ``max_rings`` is reached, or ``stop(rings)`` names a reason not to run that patch
    (a resource limit); then fit the tail.  ``on_step(rings, value, wall_s)`` reports each run."""
    import time

    seq = RingsSequence(tol)
    reason = f"reached rings = {max_rings} without meeting the tolerance"
    converged = False
    for rings in range(start, max_rings + 1):
        why = stop(rings) if stop is not None and rings > start else ""
        if why:
            reason = f"stopped before rings = {rings}: {why}"
            break
        t0 = time.perf_counter()
        value = run(rings)
        seq.rings.append(rings)
        seq.values.append(value)
        seq.wall_s.append(time.perf_counter() - t0)
        if on_step is not None:
            on_step(rings, value, seq.wall_s[-1])
        change = seq.changes[-1]
        if change is not None and change <= tol:
            converged, reason = True, f"relative change {change:.3g} <= {tol:g}"
            break
    widths = [2 * r + 1 for r in seq.rings]
    ext, why_not = extrapolate(widths, seq.values)
    return RingsSequence(tol, seq.rings, seq.values, seq.wall_s, converged, reason, ext, why_not)


#: Relative change between the two largest patches below which a sequence counts as converged
#: (``qpscale puncture --rings auto``'s default tolerance).
DEFAULT_TOL = 0.005


@dataclass(frozen=True)
class PatchEstimate:
    """What a fixed sequence of patches says about the skin (formulations/puncture.md sec. 7).

    ``verdict``: ``converged`` (the last change is within ``tol``: ``value`` is the largest patch's,
    ``error`` that change), ``extrapolated`` (``value`` is F_inf of :func:`extrapolate`, ``error``
    its error) or ``not converged`` (``value`` is the largest patch's, ``error`` NaN, ``note`` why
    no limit is claimed).  ``change``: the relative change between the two largest patches.
    """

    value: float
    error: float
    verdict: str
    change: float
    note: str = ""


def estimate(widths: list[int], values: list[float], tol: float = DEFAULT_TOL) -> PatchEstimate:
    """The skin's value from the results on patches of ``widths`` scales (ascending, at least two).

    >>> estimate([3, 5, 7], [1.0, 1.2, 1.201]).verdict
    'converged'
    >>> n = [3, 5, 7, 9]
    >>> e = estimate(n, [2.0 - k**-0.8 for k in n])
    >>> e.verdict, round(e.value, 6)
    ('extrapolated', 2.0)
    >>> estimate(n, [1.0, 1.1, 1.05, 1.1]).verdict
    'not converged'
    """
    if len(values) < 2 or len(widths) != len(values):
        raise ValueError("estimate needs at least two patches and one width per value")
    last, before = float(values[-1]), float(values[-2])
    change = abs(last - before) / abs(last)
    if change <= tol:
        return PatchEstimate(last, abs(last - before), "converged", change)
    ext, why = extrapolate(list(widths), list(values))
    if ext is not None:
        return PatchEstimate(ext.F_inf, ext.error, "extrapolated", change)
    return PatchEstimate(last, math.nan, "not converged", change, why)
