"""Solver registry and the one entry point :func:`solve_qp` (formulations/increment-qp.md section 4).

Backends are imported when first used: a missing optional package removes its keys from the
registry instead of breaking ``import qpscale``, and a run imports only the backend it calls.
Keys: ``"clarabel"``, ``"piqp"``, ``"osqp"``, ``"cvxpy"``, ``"active-set"`` (the package's own
exact method, ``qpscale.active_set``) and ``"qpsolvers:<name>"`` for every solver qpsolvers reports
installed.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import sys
from collections.abc import Callable, Iterator, MutableMapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from ..errors import SolverFailure, SolverUnavailable

if TYPE_CHECKING:  # the QP record imports scipy.sparse: not needed to read DEFAULT_SOLVER (the CLI)
    from ..qp import IncrementQP, IncrementResult

logger = logging.getLogger(__name__)

#: Default backend: the fastest one that meets "high" accuracy on our problems (see the benchmark):
#: PIQP, 2.4x faster per QP than Clarabel on the default scene and exact to 1e-8 against DAQP's
#: active-set solutions where Clarabel's accepted points differ by up to 2e-6 (formulations 3.2a).
DEFAULT_SOLVER = "piqp"

Backend = Callable[["IncrementQP", dict, Any], "IncrementResult"]

#: A rejected answer is solved once more (formulations/increment-qp.md sec. 5): after a near miss
#: (residuals within NEAR_MISS x tolerance) any backend, aiming RETRY_TIGHTEN x lower; after any
#: rejection Clarabel, also with a lower static regularisation (``qp.retry_options``).
NEAR_MISS = 100.0
RETRY_TIGHTEN = 1e-2


def _load(module: str) -> Any | None:
    try:
        return importlib.import_module(f"{__name__}.{module}")
    except ImportError as exc:  # the optional third-party package is missing
        logger.debug("backend %s unavailable: %s", module, exc)
        return None


def _installed(package: str) -> bool:
    """Whether ``package`` can be imported, without importing it (cvxpy alone takes 0.75 s)."""
    if package in sys.modules:
        return sys.modules[package] is not None
    try:
        return importlib.util.find_spec(package) is not None
    except (ImportError, ValueError):
        return False


class _Registry(MutableMapping[str, Backend]):
    """Backend key -> solve function, each backend imported on first use.

    A run imports only the backend it calls: importing every backend at start-up cost 0.9 s of
    the default scene's 7 s (cvxpy, osqp and qpsolvers, none of them used by the default run).
    The keys of qpsolvers' solvers are listed only when asked for (listing imports qpsolvers).
    Assigning a key (tests inject faulty backends that way) overrides it.
    """

    DIRECT = ("clarabel", "piqp", "osqp", "cvxpy", "active-set")
    #: Backends of the package itself: always installed (no third-party package to look for).
    OWN = ("active-set",)

    def __init__(self) -> None:
        self._loaded: dict[str, Backend] = {}
        self._removed: set[str] = set()
        self._qpsolvers: list[str] | None = None

    def _qpsolvers_names(self) -> list[str]:
        if self._qpsolvers is None:
            mod = _load("qpsolvers_") if _installed("qpsolvers") else None
            self._qpsolvers = [f"qpsolvers:{n}" for n in mod.installed()] if mod is not None else []
        return self._qpsolvers

    def _known(self, key: str) -> bool:
        if key in self._removed:
            return False
        if key in self._loaded or key in self.OWN or (key in self.DIRECT and _installed(key)):
            return True
        return key.startswith("qpsolvers:") and key in self._qpsolvers_names()

    def __contains__(self, key: object) -> bool:
        return isinstance(key, str) and self._known(key)

    def __getitem__(self, key: str) -> Backend:
        if key in self._loaded and key not in self._removed:
            return self._loaded[key]
        if not self._known(key):
            raise KeyError(key)
        if key.startswith("qpsolvers:"):
            qps = _load("qpsolvers_")
            name = key.split(":", 1)[1]
            backend: Backend | None = None
            if qps is not None:
                backend = lambda qp, opts, ws: qps.solve(qp, name, opts, ws)  # noqa: E731
        else:
            mod = _load(f"{key.replace('-', '_')}_")
            backend = mod.solve if mod is not None else None
        if backend is None:
            self._removed.add(key)
            raise KeyError(key)
        self._loaded[key] = backend
        return backend

    def __setitem__(self, key: str, value: Backend) -> None:
        self._removed.discard(key)
        self._loaded[key] = value

    def __delitem__(self, key: str) -> None:
        self._loaded.pop(key, None)
        self._removed.add(key)

    def __iter__(self) -> Iterator[str]:
        direct = [k for k in self.DIRECT if self._known(k)]
        extra = [k for k in self._loaded if k not in self.DIRECT and not k.startswith("qpsolvers:")]
        qps = [k for k in self._qpsolvers_names() if k not in self._removed]
        return iter([*direct, *qps, *(k for k in extra if k not in self._removed)])

    def __len__(self) -> int:
        return sum(1 for _ in self)


_REGISTRY = _Registry()


def available_solvers() -> list[str]:
    """Keys of the installed backends, direct ones first.

    >>> "clarabel" in available_solvers()
    True
    """
    return list(_REGISTRY)


def is_available(solver: str) -> bool:
    """Whether the backend key ``solver`` is installed, importing as little as possible.

    >>> is_available("clarabel"), is_available("no-such-solver")
    (True, False)
    """
    return solver in _REGISTRY


def solve_qp(
    qp: IncrementQP,
    solver: str = DEFAULT_SOLVER,
    accuracy: str | float = "high",
    check: bool = True,
    warm_start: Any = None,
    options: dict[str, Any] | None = None,
) -> IncrementResult:
    """Solve ``qp`` with the backend ``solver`` and verify the answer with our KKT residuals.

    Parameters
    ----------
    qp : IncrementQP
        The problem.
    solver : str
        A key of :func:`available_solvers`.
    accuracy : {"high", "mid", "low"} or float
        Absolute tolerance on every KKT residual: 1e-9, 1e-6, 1e-3, or the float given.
    check : bool
        If True a failed status or a residual above the tolerance raises; if False the result
        comes back with ``found=False`` and the reason in ``extras["detail"]``.
    warm_start : IncrementResult or ndarray (n,), optional
        A previous solution; used by backends that can (OSQP, some qpsolvers), ignored otherwise.
    options : dict, optional
        Backend settings overriding the tolerance table (e.g. ``{"polishing": False}`` for OSQP).

    A backend stops on its own, scaled criteria; when the point it returns misses our unscaled
    residual check by less than ``NEAR_MISS`` x ``tol``, it is solved once more with the tolerance
    table at ``RETRY_TIGHTEN`` x ``tol``; Clarabel is retried after any rejection, with its static
    regularisation lowered as well (``extras["retried"]`` is then True, ``extras["first_status"]``
    the first status).  The answer must still pass the check at ``tol``: a retry never loosens
    anything, and the time of both attempts is counted.

    Returns
    -------
    IncrementResult

    Raises
    ------
    SolverUnavailable
        Unknown or uninstalled backend; the message lists the available ones.
    SolverFailure
        With ``check=True``: the backend's status was not a success, or a residual exceeded the
        tolerance (the residuals are in ``detail``).
    """
    from ..qp import accept, backend_options, resolve_tolerance, retry_options

    if solver not in _REGISTRY:
        raise SolverUnavailable(f"solver {solver!r} is not available; choose one of {available_solvers()}")
    tol = resolve_tolerance(accuracy)
    opts = {**backend_options(solver, tol), **(options or {})}
    raw = _REGISTRY[solver](qp, opts, warm_start)
    result = accept(raw, tol)
    if not result.found:
        near = result.residuals is not None and result.max_residual() <= NEAR_MISS * tol
        again = retry_options(solver, RETRY_TIGHTEN * tol, near, backend_options)
        tighter = {**again, **(options or {})} if again is not None else opts
        if tighter != opts:
            second = accept(_REGISTRY[solver](qp, tighter, warm_start), tol)
            extras = {**second.extras, "retried": True, "first_status": raw.status}
            # The time of both attempts is the cost of this solve.
            build_s, solve_s = raw.build_s + second.build_s, raw.solve_s + second.solve_s
            result = replace(second, build_s=build_s, solve_s=solve_s, extras=extras)
    if not result.found:
        res = result.residuals
        detail = "no solution returned" if res is None else ", ".join(f"{k}={v:.3g}" for k, v in res.items())
        detail = f"{detail}; tolerance {tol:g}; rejected by {result.extras.get('rejected_by')}"
        result = replace(result, extras={**result.extras, "detail": detail})
        if check:
            raise SolverFailure(solver, result.status, detail=detail)
    return result


__all__ = ["DEFAULT_SOLVER", "available_solvers", "is_available", "solve_qp"]
