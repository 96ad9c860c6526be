"""The generic convex QP of one load increment, its solution record and its KKT checks.

Implements formulations/increment-qp.md: the problem (1), the Lagrangian and sign convention (2),
the KKT conditions (3)-(6), the residuals we measure ourselves (7)-(9) and the tolerance table
(section 5).  The contact-specific assembly (which rows are gaps, which is the loading constraint)
lives in ``increment.py``; here a QP is only ``P, q, G, h, A, b`` with row labels.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from .errors import InvalidDesign, QpscaleWarning

#: Absolute KKT tolerances of the named accuracies (qpbenchmark style), formulations eq. (10).
ACCURACY: dict[str, float] = {"high": 1e-9, "mid": 1e-6, "low": 1e-3}


def resolve_tolerance(accuracy: str | float) -> float:
    """Return the absolute KKT tolerance of a named accuracy or an explicit positive float.

    >>> resolve_tolerance("mid")
    1e-06
    """
    if isinstance(accuracy, str):
        if accuracy not in ACCURACY:
            raise InvalidDesign("accuracy", accuracy, "one of " + ", ".join(ACCURACY) + " or a float")
        return ACCURACY[accuracy]
    tol = float(accuracy)
    if not (0.0 < tol < 1.0):
        raise InvalidDesign("accuracy", accuracy, "(0, 1)")
    return tol


def _as_csc(name: str, M: Any, shape: tuple[int, int] | None = None) -> sp.csc_matrix:
    """Convert ``M`` to float CSC; dense input is accepted with a warning (STYLE.md section 2)."""
    if sp.issparse(M):
        out = sp.csc_matrix(M, dtype=float)
    else:
        arr = np.asarray(M, dtype=float)
        if arr.ndim != 2:
            raise InvalidDesign(name, f"array of shape {arr.shape}", "a 2-D matrix")
        warnings.warn(f"{name} given dense; converted to scipy.sparse CSC", QpscaleWarning, stacklevel=4)
        out = sp.csc_matrix(arr)
    if shape is not None and out.shape != shape:
        raise InvalidDesign(f"{name}.shape", out.shape, f"{shape}")
    if out.nnz and not np.all(np.isfinite(out.data)):
        raise InvalidDesign(name, "non-finite entries", "finite floats")
    return out


def _as_vector(name: str, v: Any, size: int) -> np.ndarray:
    arr = np.asarray(v, dtype=float).reshape(-1) if v is not None else np.zeros(0)
    if arr.shape != (size,):
        raise InvalidDesign(f"{name}.shape", arr.shape, f"({size},)")
    if not np.all(np.isfinite(arr)):
        raise InvalidDesign(name, "non-finite entries", "finite floats")
    return arr


def _labels(name: str, labels: Sequence[Any] | None, size: int, prefix: str) -> tuple[Any, ...]:
    if labels is None:
        return tuple(f"{prefix}{i}" for i in range(size))
    out = tuple(labels)
    if len(out) != size:
        raise InvalidDesign(f"len({name})", len(out), f"{size} (one label per row)")
    return out


@dataclass(frozen=True)
class IncrementQP:
    """Convex QP ``min 1/2 x'Px + q'x  s.t.  G x <= h,  A x = b`` (formulations/increment-qp.md eq. 1).

    Parameters
    ----------
    P : scipy.sparse CSC (n, n)
        Full symmetric positive semidefinite Hessian (both triangles stored); in the puncture
        problem the stiffness K in E* L units.
    q : ndarray (n,)
        Linear term.
    G, h : CSC (m, n), ndarray (m,)
        Inequality rows (linearised contact gaps written as ``-J dq <= g``); ``None`` means m = 0.
    A, b : CSC (p, n), ndarray (p,)
        Equality rows (the prescribed loading); ``None`` means p = 0.
    row_labels_G, row_labels_A : tuple
        One label per row (str or a small record) so multipliers map back to contact points and
        to the loading constraint; default ``"g0", "g1", ...`` and ``"a0", ...``.

    Raises
    ------
    InvalidDesign
        On inconsistent shapes, non-finite data or an asymmetric ``P``.

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> qp = IncrementQP(P=sp.identity(2, format="csc"), q=np.array([1.0, -1.0]))
    >>> qp.n, qp.m_ineq, qp.m_eq
    (2, 0, 0)
    """

    P: sp.csc_matrix
    q: np.ndarray
    G: sp.csc_matrix | None = None
    h: np.ndarray | None = None
    A: sp.csc_matrix | None = None
    b: np.ndarray | None = None
    row_labels_G: tuple[Any, ...] | None = None
    row_labels_A: tuple[Any, ...] | None = None

    def __post_init__(self) -> None:
        q = np.asarray(self.q, dtype=float).reshape(-1)
        n = q.size
        P = _as_csc("P", self.P, (n, n))
        asym = abs(P - P.T).max() if P.nnz else 0.0
        if asym > 1e-12 * max(1.0, abs(P).max() if P.nnz else 0.0):
            raise InvalidDesign("P", f"asymmetric (max |P - P'| = {asym:.3g})", "a symmetric matrix")
        set_ = object.__setattr__
        set_(self, "P", P)
        set_(self, "q", _as_vector("q", q, n))
        for M, v, lab, pre in (("G", "h", "row_labels_G", "g"), ("A", "b", "row_labels_A", "a")):
            mat = getattr(self, M)
            mat = sp.csc_matrix((0, n)) if mat is None else _as_csc(M, mat)
            if mat.shape[1] != n:
                raise InvalidDesign(f"{M}.shape[1]", mat.shape[1], f"{n} (= len(q))")
            set_(self, M, mat)
            set_(self, v, _as_vector(v, getattr(self, v), mat.shape[0]))
            set_(self, lab, _labels(lab, getattr(self, lab), mat.shape[0], pre))

    @classmethod
    def assembled(
        cls,
        P: sp.csc_matrix,
        q: np.ndarray,
        G: sp.csc_matrix,
        h: np.ndarray,
        A: sp.csc_matrix,
        b: np.ndarray,
        row_labels_A: tuple[Any, ...],
    ) -> IncrementQP:
        """A QP that qpscale assembled itself, without the checks of a user's input.

        The increment QP is built every iteration of every level from matrices whose shapes,
        symmetry and finiteness hold by construction (a CSC stiffness and diagonal, CSC rows);
        the checks of ``__post_init__`` (a transpose, a difference, a label per row) took a third
        of the assembly.  The solvers' residual checks still see every answer.  The rows of ``G``
        carry no labels (None): a contact row is named by its contact set.
        """
        qp = object.__new__(cls)
        set_ = object.__setattr__
        for name, value in (("P", P), ("q", q), ("G", G), ("h", h), ("A", A), ("b", b)):
            set_(qp, name, value)
        set_(qp, "row_labels_G", None)
        set_(qp, "row_labels_A", row_labels_A)
        return qp

    @property
    def n(self) -> int:
        """Number of variables."""
        return self.q.size

    @property
    def m_ineq(self) -> int:
        """Number of inequality rows of ``G``."""
        return self.rows()[1].size

    @property
    def m_eq(self) -> int:
        """Number of equality rows of ``A``."""
        return self.rows()[3].size

    def rows(self) -> tuple[sp.csc_matrix, np.ndarray, sp.csc_matrix, np.ndarray]:
        """``(G, h, A, b)``: never None once built (absent rows are empty matrices)."""
        G, h, A, b = self.G, self.h, self.A, self.b
        if G is None or h is None or A is None or b is None:  # only before __post_init__ ran
            raise InvalidDesign("G/h/A/b", None, "set by IncrementQP.__post_init__")
        return G, h, A, b

    def objective(self, x: np.ndarray) -> float:
        """``1/2 x'Px + q'x`` at ``x``."""
        return float(0.5 * x @ (self.P @ x) + self.q @ x)

    def residuals(self, x: np.ndarray, z: np.ndarray, y: np.ndarray) -> dict[str, float]:
        """KKT residuals (infinity norms) of a candidate ``(x, z, y)``; formulations eqs. (7)-(9).

        Returns
        -------
        dict
            ``primal``: largest violation of ``Gx <= h`` and ``Ax = b``; ``dual``: largest entry
            of ``Px + q + G'z + A'y`` or of ``max(-z, 0)``; ``complementarity``: largest
            ``|z_i (h - Gx)_i|``.  All absolute, in the units of ``q`` (respectively ``h``, ``q h``).
        """
        x, z, y = (np.asarray(v, dtype=float) for v in (x, z, y))
        G, h, A, b = self.rows()
        slack = h - G @ x
        parts_p = [np.maximum(-slack, 0.0), np.abs(A @ x - b)]
        stat = self.P @ x + self.q + transpose_times(G, z) + transpose_times(A, y)
        parts_d = [np.abs(stat), np.maximum(-z, 0.0)]
        return {
            "primal": float(max((p.max() for p in parts_p if p.size), default=0.0)),
            "dual": float(max((p.max() for p in parts_d if p.size), default=0.0)),
            "complementarity": float(np.abs(z * slack).max()) if z.size else 0.0,
        }


@dataclass(frozen=True)
class WarmStart:
    """A start for a backend that can use one (``solve_qp(warm_start=...)``): a point ``x`` and
    multipliers ``z`` (inequality rows) and ``y`` (equality rows) laid out as the QP it is handed
    with, e.g. the last answer's carried over to the next linearisation's rows by their labels."""

    x: np.ndarray
    z: np.ndarray
    y: np.ndarray


@dataclass(frozen=True)
class IncrementResult:
    """What every backend returns (formulations/increment-qp.md section 4).

    Parameters
    ----------
    x : ndarray (n,) or None
        Primal solution; ``None`` when ``found`` is False.
    z : ndarray (m_ineq,) or None
        Inequality multipliers in our convention (z >= 0, eq. 2); contact forces of the gap rows.
    y : ndarray (m_eq,) or None
        Equality multipliers in our convention; for the loading row, the reaction.
    found : bool
        True only when the backend reported success and our residuals pass the tolerance.
    status : str
        The backend's own status word (or ``"residuals"`` when our check rejected it).
    obj : float or None
        ``1/2 x'Px + q'x`` evaluated by our code.
    residuals : dict or None
        ``{"primal", "dual", "complementarity"}`` computed by :meth:`IncrementQP.residuals` from
        the problem data, never taken from the backend; None when the backend returned no point.
    build_s, solve_s : float
        Wall time to build the backend's problem object and to solve it, in seconds.
    iterations : int or None
        Backend iterations, when it reports them.
    extras : dict
        Backend-specific details (polish status, internal timings, rejected candidate ...).
    """

    x: np.ndarray | None
    z: np.ndarray | None
    y: np.ndarray | None
    found: bool
    status: str
    obj: float | None
    residuals: dict[str, float] | None
    build_s: float
    solve_s: float
    iterations: int | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.found and (self.x is None or self.z is None or self.y is None or self.residuals is None):
            raise InvalidDesign("found", True, "False when x, z, y or residuals are missing")
        if self.build_s < 0 or self.solve_s < 0:
            raise InvalidDesign("build_s/solve_s", (self.build_s, self.solve_s), "[0, inf)")

    def max_residual(self) -> float:
        """Largest of the three KKT residuals (inf when there is no candidate)."""
        return max(self.residuals.values()) if self.residuals else float("inf")


def _qpsolvers_opts(name: str, tol: float) -> dict[str, Any]:
    """Keyword options qpsolvers forwards to the named solver (formulations section 5)."""
    t = 0.1 * tol
    table: dict[str, dict[str, Any]] = {
        "clarabel": {"tol_gap_abs": t, "tol_gap_rel": 0.0, "tol_feas": t},
        "osqp": {"eps_abs": t, "eps_rel": 0.0, "max_iter": 100_000, "polishing": True},
        # ProxQP ignores complementarity unless asked to check the duality gap
        "proxqp": {
            "eps_abs": t,
            "eps_rel": 0.0,
            "check_duality_gap": True,
            "eps_duality_gap_abs": t,
            "eps_duality_gap_rel": 0.0,
        },
        # the KKT systems of held-symmetric paths (face contacts, planes held mirror-symmetric) are
        # ill-conditioned enough that PIQP's factorisation without refinement ran into NaN
        "piqp": {
            "eps_abs": t,
            "eps_rel": 0.0,
            "eps_duality_gap_abs": t,
            "eps_duality_gap_rel": 0.0,
            "iterative_refinement_always_enabled": True,
        },
        # DAQP's default primal tolerance (1e-6) let a row stay 9.7e-7 violated on the default scene;
        # its default cycle_tol (10 iterations without progress) declared cycling (exit -2) on a
        # degenerate QP of the default scene's asymmetric branch that 154 iterations solve
        "daqp": {"primal_tol": t, "dual_tol": t, "cycle_tol": 100},
        "qpalm": {"eps_abs": t, "eps_rel": 0.0},
        "scs": {"eps_abs": t, "eps_rel": 0.0},
        # CVXOPT stops on the absolute OR relative gap; the relative one scales with |objective|
        "cvxopt": {"abstol": t, "reltol": 1e-15, "feastol": t},
        "ecos": {"abstol": t, "reltol": t, "feastol": t},
        "highs": {"primal_feasibility_tolerance": t, "dual_feasibility_tolerance": t},
    }
    return dict(table.get(name, {}))


def backend_options(solver: str, tol: float) -> dict[str, Any]:
    """The tolerance table: settings handed to each backend for an absolute KKT target ``tol``.

    Every backend aims ten times below ``tol`` because most stop on residuals that are scaled
    (relative to the data norms) or measured on their own reformulation, while we check the
    unscaled residuals of eqs. (7)-(9); the margin absorbs that difference.  Reasons per row are
    in formulations/increment-qp.md, table 1.

    >>> backend_options("osqp", 1e-6)["eps_abs"]
    1e-07
    """
    t = 0.1 * tol
    if solver in ("clarabel", "cvxpy"):
        # Clarabel stops when the absolute OR the relative duality gap is small; the relative one scales
        # with |objective| and let max z_i s_i reach 2e-9 at tol_gap_rel=1e-10, so it is switched off.
        # Its feasibility residuals are relative to max(1, |q|, |b|...): absolute for our O(1) data.
        return {"tol_gap_abs": t, "tol_gap_rel": 0.0, "tol_feas": t, "max_iter": 200}
    if solver == "piqp":
        # Iterative refinement on every factorisation: without it one held-symmetric QP of the
        # default scene (face contacts, planes held mirror-symmetric) stopped at PIQP's iteration
        # limit with the dual residual at 10 (formulations table 1).  Up to 1000 iterations: on
        # the hinged planes of slanted arrays its last iterations stagnate at this tolerance (QPs
        # of a slanted 5x5 dart array needed 204-540; at 200 the path stopped), and aiming at
        # ``tol`` itself instead leaves dq noisy at the step test (more stalled levels).
        return {
            "eps_abs": t,
            "eps_rel": 0.0,
            "eps_duality_gap_abs": t,
            "eps_duality_gap_rel": 0.0,
            "iterative_refinement_always_enabled": True,
            "max_iter": 1000,
        }
    if solver == "osqp":
        # ADMM with polishing: the polished active-set solve is exact when it succeeds; eps_rel = 0 so the
        # unpolished fallback stops on absolute residuals; ADMM may need many iterations at 1e-9.
        return {"eps_abs": t, "eps_rel": 0.0, "max_iter": 100_000, "polishing": True, "polish_refine_iter": 5}
    if solver.startswith("qpsolvers:"):
        return _qpsolvers_opts(solver.split(":", 1)[1], tol)
    if solver == "active-set":
        # Exact once its rows settle: it stops when no row is violated, nor one carrying force
        # open, by more than t, and its point is stationary to t (formulations sec. 8).  A tenth
        # of the target, as every backend aims, not the exact check's 1e-12: a weak direction of
        # P (a plane's 1e-6) leaves rounding of ~1e-12 L.
        return {"tol": t}
    raise InvalidDesign("solver", solver, "a known backend key")


#: Clarabel's static regularisation on the retry (default 1e-8): on a degenerate QP (dependent
#: active rows on a hinge) the default stalls at complementarity ~1e-7 (formulations sec. 5).
RETRY_STATIC_REGULARIZATION = 1e-12


def retry_options(
    solver: str, tol: float, near_miss: bool, table: Callable[[str, float], dict[str, Any]] | None = None
) -> dict[str, Any] | None:
    """Settings of the one second attempt after a rejected answer (formulations section 5), or None.

    Every backend gets the tolerance table at ``tol`` (the caller passes 1/100 of the target)
    after a near miss; Clarabel (directly, through CVXPY or through qpsolvers) is also retried
    after any other rejection, with its static regularisation lowered.  ``table`` replaces
    :func:`backend_options` (the benchmark overrides it per method).

    >>> retry_options("clarabel", 1e-11, near_miss=False)["static_regularization_constant"]
    1e-12
    >>> retry_options("osqp", 1e-11, near_miss=False) is None
    True
    """
    base = (table or backend_options)(solver, tol)
    if solver in ("clarabel", "cvxpy", "qpsolvers:clarabel"):
        return {**base, "static_regularization_constant": RETRY_STATIC_REGULARIZATION}
    return base if near_miss else None


def candidate_result(
    qp: IncrementQP,
    x: np.ndarray | None,
    z: np.ndarray | None,
    y: np.ndarray | None,
    *,
    status: str,
    ok: bool,
    build_s: float,
    solve_s: float,
    iterations: int | None = None,
    extras: dict[str, Any] | None = None,
) -> IncrementResult:
    """Wrap a backend's answer, measuring its residuals with our own code (eqs. 7-9).

    ``ok`` is the backend's own verdict on its status; the tolerance check comes later, in
    :func:`accept`.  A backend that returned no point, or a point with non-finite entries, gives
    ``found=False`` and ``residuals=None``.
    """
    have = all(v is not None and np.all(np.isfinite(v)) for v in (x, z, y))
    if not have:
        return IncrementResult(
            None, None, None, False, status, None, None, build_s, solve_s, iterations, dict(extras or {})
        )
    x, z, y = (np.asarray(v, dtype=float).reshape(-1) for v in (x, z, y))
    res = qp.residuals(x, z, y)
    return IncrementResult(
        x, z, y, bool(ok), status, qp.objective(x), res, build_s, solve_s, iterations, dict(extras or {})
    )


def accept(result: IncrementResult, tol: float) -> IncrementResult:
    """Return ``result`` if it passed its status and ``tol``, else a copy with ``found=False``.

    The rejected point is kept in ``extras["rejected"]`` as ``(x, z, y)`` for diagnosis only;
    the numeric fields are cleared so a failed solve is never used as a number.
    """
    if result.found and result.max_residual() <= tol:
        return result
    extras = dict(result.extras)
    if result.x is not None:
        extras["rejected"] = (result.x, result.z, result.y)
    extras["rejected_by"] = "residuals" if result.found else "status"
    return IncrementResult(
        None,
        None,
        None,
        False,
        result.status,
        None,
        result.residuals,
        result.build_s,
        result.solve_s,
        result.iterations,
        extras,
    )


def transpose_times(M: sp.spmatrix, v: np.ndarray) -> np.ndarray:
    """``M.T @ v``, for a CSC ``M`` without forming ``M.T``: each column's products summed in
    its stored order from zero, as scipy's CSR product of the transpose sums them, so the result
    is the same to the bit (``M.T`` is a new matrix object, 60 us a call, most of the residual
    check's time on the small QPs of 3x3 patches).

    >>> M = sp.csc_matrix(np.array([[1.0, 2.0], [0.0, 3.0]]))
    >>> transpose_times(M, np.array([1.0, 1.0]))
    array([1., 5.])
    """
    if M.format != "csc":
        return np.asarray(M.T @ v)
    columns = np.repeat(np.arange(M.shape[1]), np.diff(M.indptr))
    return np.bincount(columns, weights=M.data * v[M.indices], minlength=M.shape[1])


def block_diagonal(X: sp.csc_matrix, Y: sp.csc_matrix) -> sp.csc_matrix:
    """``blockdiag(X, Y)`` of two CSC matrices, by appending Y's arrays to X's: the same arrays as
    scipy's ``block_diag`` of two canonical matrices (which took 0.4 ms a call)."""
    (r, c), (ry, cy) = X.shape, Y.shape
    indptr = np.concatenate([X.indptr, X.nnz + Y.indptr[1:]])
    indices = np.concatenate([X.indices, r + Y.indices])
    return sp.csc_matrix((np.concatenate([X.data, Y.data]), indices, indptr), shape=(r + ry, c + cy))
