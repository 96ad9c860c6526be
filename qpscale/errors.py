"""Exception and warning classes of qpscale.

Every error a user can provoke is a :class:`QpscaleError`.  Invalid input is an
:class:`InvalidDesign` (also a ``ValueError``) that names the parameter, its value and
the allowed range; the command line maps it to exit status 2.  A solver that fails or
answers inaccurately raises :class:`SolverFailure` carrying the solver's own status: a
failed solve is never turned into a number.
"""

from __future__ import annotations


class QpscaleError(Exception):
    """Base class of every qpscale error."""


class InvalidDesign(QpscaleError, ValueError):
    """An input parameter outside its allowed range.

    Parameters
    ----------
    parameter : str
        Name of the offending parameter, as the user spells it.
    value : object
        The value given.
    allowed : str
        Human description of the allowed values, e.g. ``"[0, 90)"``.
    """

    def __init__(self, parameter: str, value: object, allowed: str, detail: str = "") -> None:
        self.parameter = parameter
        self.value = value
        self.allowed = allowed
        message = f"{parameter}={value!r} is outside {allowed}" if allowed else f"{parameter}={value!r}"
        if detail:
            message = f"{message}: {detail}"
        super().__init__(message)


class SolverUnavailable(QpscaleError):
    """The requested solver backend is not installed or not known."""


class SolverFailure(QpscaleError):
    """A solve failed or returned an answer that did not pass the accuracy checks.

    Parameters
    ----------
    solver : str
        Backend key, e.g. ``"clarabel"``.
    status : str
        The backend's own status word, or the name of the check that failed.
    increment : int or None
        Index of the load increment, when the failure happened inside a path.
    detail : str
        Residuals or any other diagnostic.
    """

    def __init__(self, solver: str, status: str, increment: int | None = None, detail: str = "") -> None:
        self.solver = solver
        self.status = status
        self.increment = increment
        self.detail = detail
        where = f" at increment {increment}" if increment is not None else ""
        extra = f" ({detail})" if detail else ""
        super().__init__(f"solver {solver!r} failed{where}: status {status!r}{extra}")


class QpscaleWarning(UserWarning):
    """A recoverable event worth knowing about (coupling truncated, dense input converted)."""


class OutputNotWritten(QpscaleWarning):
    """An optional output (a drawing, a ParaView series) could not be written; the result that was
    computed is returned anyway and lists the failure in ``output_errors``."""
