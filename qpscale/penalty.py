"""The penalty baseline: frictionless penalty contact and Newton iterations at one load level.

Implements formulations/penalty.md: the penalty stiffness relative to the substrate (eq. (1)),
the penalised energy and its stationarity (2)-(3), the Newton step on the sparse saddle system
(4), the merit function of the line search (5) and the acceptance rule (6).  Same loading,
contact points and exact rigid update as the sequential QP of ``increment.py``; only the
non-penetration constraints are replaced by contact forces k (-g)_+.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import level
from .contact import ContactSet, ContactSettings, detect_contacts, gap_jacobian, penetration
from .errors import InvalidDesign, SolverFailure
from .increment import Equilibrium, LoadPoint
from .level import LevelControls, LevelOutcome, Progress, Step
from .tiling import Patch

SOLVER = "penalty"


@dataclass(frozen=True)
class PenaltySettings:
    """Options of the penalty baseline (formulations/penalty.md).

    Parameters
    ----------
    k_pen : float
        Penalty stiffness per contact point relative to the substrate scale k_s of eq. (1) (the
        largest translational diagonal entry of K), dimensionless, in [1e-3, 1e14].
    tol : float
        Converged when the largest Newton update is below this (L or rad) and the penalised row set
        no longer changes, in (0, 1e-3].
    max_iter : int
        Newton iterations at one load level, in [1, 10000].
    line_search : bool
        Backtrack on the merit (5) when a plain step (row set changed) does not reduce it.
    """

    k_pen: float = 1e3
    tol: float = 1e-10
    max_iter: int = 50
    line_search: bool = True

    def __post_init__(self) -> None:
        if not (np.isfinite(self.k_pen) and 1e-3 <= self.k_pen <= 1e14):
            raise InvalidDesign("k_pen", self.k_pen, "[1e-3, 1e14] (relative to max translational K_ii)")
        if not (np.isfinite(self.tol) and 0.0 < self.tol <= 1e-3):
            raise InvalidDesign("tol", self.tol, "(0, 1e-3] (in L or rad)")
        if not (int(self.max_iter) == self.max_iter and 1 <= self.max_iter <= 10_000):
            raise InvalidDesign("max_iter", self.max_iter, "integers in [1, 10000]")


def substrate_scale(K: sp.spmatrix) -> float:
    """k_s of eq. (1): the largest translational diagonal entry of K (F*/L, i.e. K*).

    >>> float(substrate_scale(sp.diags([2.0, 3.0, 5.0, 1.0, 1.0])))
    5.0
    """
    d = np.asarray(K.diagonal()).reshape(-1, 5)
    return float(np.max(d[:, :3]))


@dataclass(frozen=True)
class _Lin:
    """Contact rows linearised at the configuration ``q``: the set, gaps, Jacobian, penalised rows."""

    q: np.ndarray
    cs: ContactSet | None
    g: np.ndarray
    J: sp.csr_matrix | None
    on: np.ndarray

    @property
    def key(self) -> tuple:
        labels = self.cs.labels if self.cs is not None else ()
        return tuple(lab for lab, flag in zip(labels, self.on) if flag)


def _linearise(
    patch: Patch, q: np.ndarray, contact: ContactSettings | None, previous: ContactSet | None
) -> _Lin:
    if contact is None:
        return _Lin(q, None, np.zeros(0), None, np.zeros(0, dtype=bool))
    # Penalty forces act between two scales at contact points: the feature formulation's rows.
    cs = detect_contacts(patch, q, replace(contact, formulation="feature"), previous=previous)
    if cs.m == 0:
        return _Lin(q, cs, np.zeros(0), None, np.zeros(0, dtype=bool))
    g = np.asarray(cs.gap, dtype=float)
    return _Lin(q, cs, g, gap_jacobian(cs, patch, q), g < 0.0)


def _energy_slope(K, k, x, lin, dq, p, s) -> float:
    """d/ds of the linearised penalised energy (3) at dq + s p along the direction p."""
    v = dq + s * p
    slope = p @ (K @ (x + v))
    if lin.J is not None:
        slope += k * np.minimum(lin.g + lin.J @ v, 0.0) @ (lin.J @ p)
    return float(slope)


def _line_search(K, k, x, lin, dq, p) -> float:
    """Step s in (0, 1] minimising the convex piecewise quadratic (3) along p: bisection, eq. (5)."""
    if _energy_slope(K, k, x, lin, dq, p, 1.0) <= 0.0:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _energy_slope(K, k, x, lin, dq, p, mid) < 0.0 else (lo, mid)
    return hi


def newton_step(
    K: sp.spmatrix, k: float, q: np.ndarray, lin: _Lin, load: LoadPoint, delta: float, on: np.ndarray
) -> tuple[np.ndarray, float]:
    """Eq. (4): solve [[K + k J_a'J_a, a], [a', 0]] [dq; F] = [-(K q + k J_a'g_a); -delta - w(q)].

    ``on`` marks the penalised rows a.  Returns the update ``(n, 5)`` and the load multiplier F
    (force pushing the point down, F*).
    """
    x = q.reshape(-1)
    H, rhs = K.tocsc(), -(K @ x)
    if lin.J is not None and on.any():
        Ja = lin.J[on]
        H = H + k * (Ja.T @ Ja)
        rhs = rhs - k * (Ja.T @ lin.g[on])
    a = sp.csc_matrix(load.gradient(q).reshape(1, -1))
    A = sp.bmat([[H, a.T], [a, None]], format="csc")
    sol = spla.spsolve(A, np.append(rhs, -delta - load.height_change(q)))
    if not np.all(np.isfinite(sol)):
        raise SolverFailure(SOLVER, "singular Newton system", detail=f"k = {k:.3g}")
    return sol[:-1].reshape(q.shape), float(sol[-1])


def solve_linearised(
    K: sp.spmatrix,
    k: float,
    q: np.ndarray,
    lin: _Lin,
    load: LoadPoint,
    delta: float,
    settings: PenaltySettings,
) -> tuple[np.ndarray, float, int]:
    """Semi-smooth Newton on the linearised penalised problem (3): returns (dq, F, Newton steps).

    The penalised rows are those with g + J dq < 0 at the current dq; the step towards the
    minimiser of that quadratic is damped by the exact line search (5) from the second step on
    (the first makes the linear load constraint hold).  Done when the rows no longer change, or
    when the step is below ``tol / 10`` (rows at round-off level flipping).
    """
    x, dq, on = q.reshape(-1), np.zeros(q.size), lin.on.copy()
    for it in range(1, settings.max_iter + 1):
        target, F = newton_step(K, k, q, lin, load, delta, on)
        p = target.reshape(-1) - dq
        s = _line_search(K, k, x, lin, dq, p) if settings.line_search and it > 1 else 1.0
        dq = dq + s * p
        new_on = (lin.g + lin.J @ dq < 0.0) if lin.J is not None else on
        # Rows whose linearised gap is at round-off level may flip forever; a step below tol/10 is converged.
        if (s == 1.0 and np.array_equal(new_on, on)) or np.max(np.abs(s * p)) <= 0.1 * settings.tol:
            return dq.reshape(q.shape), F, it
        on = new_on
    raise SolverFailure(
        SOLVER,
        "newton did not converge",
        None,
        f"penalised rows still changing after {settings.max_iter} Newton steps, k = {k:.3g}",
    )


@dataclass(frozen=True)
class _PenaltyLevel:
    """One penalty level as a :class:`qpscale.level.LevelProblem`: the contact rows linearised at
    the exact configuration, the penalised problem (3) solved by Newton, the exact update."""

    patch: Patch
    K: sp.spmatrix
    load: LoadPoint
    delta: float
    contact: ContactSettings | None
    settings: PenaltySettings
    increment: int | None
    k: float

    @property
    def controls(self) -> LevelControls:
        # The overlap is reported, not checked (eq. (7)); a direct solve has no tolerance to tighten.
        s = self.settings
        unconverged = "newton did not converge"
        return LevelControls(
            SOLVER, self.delta, self.increment, s.tol, np.inf, s.max_iter, 5, False, unconverged
        )

    def linearise(self, q: np.ndarray, rows: ContactSet | None, refresh: float | None) -> _Lin:
        return _linearise(self.patch, q, self.contact, rows)

    def solve(self, lin: _Lin, tightened: bool) -> Step[Equilibrium]:
        t0, k = time.perf_counter(), self.k
        try:
            dq, F, n = solve_linearised(self.K, k, lin.q, lin, self.load, self.delta, self.settings)
        except SolverFailure as exc:  # the Newton solve of one linearisation reports by raising
            return Step(failure=SolverFailure(SOLVER, exc.status, self.increment, exc.detail))
        # The rows' forces (6) at the configuration the step reaches, the exact one if it is the last.
        lam = k * np.maximum(0.0, -(lin.g + lin.J @ dq.reshape(-1))) if lin.J is not None else np.zeros(0)
        residuals = {"max_penalty_force": float(lam.max(initial=0.0)), "k": k}
        answer = Equilibrium(lin.q, self.delta, F, lin.cs, lam, 0, 0.0, residuals)
        return Step(answer, dx=dq, rows=lin.cs, labels=lin.key, seconds=time.perf_counter() - t0, work=n)

    def penetration(self, q: np.ndarray) -> float:
        return penetration(self.patch, q) if self.contact is not None else 0.0

    def state(self, q: np.ndarray, answer: Equilibrium, progress: Progress) -> Equilibrium:
        return replace(answer, q=q, **asdict(progress))


def penalty_level(
    patch: Patch,
    K: sp.spmatrix,
    q0: np.ndarray,
    load: LoadPoint,
    delta: float,
    contact: ContactSettings | None,
    settings: PenaltySettings,
    increment: int | None = None,
    previous: ContactSet | None = None,
) -> LevelOutcome[Equilibrium]:
    """Penalty contact and Newton iterations at a fixed load level, formulations/penalty.md.

    Same meaning and outcome as :meth:`qpscale.increment.PunctureLevel.solve`, by the same driver
    (:func:`qpscale.level.solve`): linearise the contact rows at the exact configuration, solve
    the penalised problem (3) by Newton, update exactly, repeat until the update is below
    ``settings.tol`` (Anderson-accelerated while the rows stay the same).  The rows' forces are
    ``lam = k (-g)_+`` with ``k = settings.k_pen * substrate_scale(K)``.  The exact penetration is
    reported, not checked: it is O(F / k) by design (eq. (7)).  A failed level has status
    ``qp failed`` (``"singular Newton system"``, a Newton solve that did not converge) or
    ``not converged`` (the linearisations did not settle); the penalty baseline has no rescues.
    ``penalty_level(...).unwrap()`` is the state, or the failure raised.
    """
    k = settings.k_pen * substrate_scale(K)
    problem = _PenaltyLevel(patch, K, load, delta, contact, settings, increment, k)
    return level.solve(problem, q0, previous)
