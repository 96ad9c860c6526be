"""A time limit on one run (a scene of ``qpscale paper``, a method of ``qpscale bench``, a fuzz design).

Study plumbing, not mechanics: it implements no formulation, and no formulations/ file states it.

A study of many scenes must not wait on one that does not end: the scene is abandoned at its
limit and recorded with the status ``time_limit`` (the public QP benchmarks count such a run as a
failure at the limit).  The limit counts wall-clock time, or the process's CPU time where the
machine's load must not decide the outcome.  It is a POSIX interval timer whose signal raises
:class:`TimeLimitReached` in the running Python code; a solver's compiled call is not cut short,
the exception comes as soon as control returns to Python.

:class:`TimeLimitReached` derives from ``BaseException`` on purpose, like ``KeyboardInterrupt``:
the backends wrap their solver calls in ``except Exception`` (to turn a solver's own errors into
a ``SolverFailure``), and an interruption there must end the run, not be reported as a solver
status.  Where no interval timer exists (not the main thread, or no ``setitimer``), the limit is
not enforced and the run goes to its end.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

STATUS = "time_limit"


class TimeLimitReached(BaseException):
    """The run exceeded its time limit (seconds in ``limit``, on ``clock``: "wall" or "cpu")."""

    status = STATUS

    def __init__(self, limit: float, clock: str = "wall") -> None:
        self.limit, self.clock = limit, clock
        what = "wall-time" if clock == "wall" else "CPU-time"
        super().__init__(f"stopped at the {what} limit of {limit:g} s")


def enforceable() -> bool:
    """True where :func:`time_limit` can interrupt: POSIX interval timers, main thread."""
    return hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()


# Interval timer and its signal: wall-clock time, or the process's CPU time (user + system).
_CLOCKS = {"wall": ("ITIMER_REAL", "SIGALRM"), "cpu": ("ITIMER_PROF", "SIGPROF")}


@contextmanager
def time_limit(seconds: float | None, clock: str = "wall") -> Iterator[None]:
    """Raise :class:`TimeLimitReached` in the body once ``seconds`` have passed on ``clock``.

    ``clock="wall"`` counts elapsed time (a study's budget); ``"cpu"`` the process's CPU time,
    which a busy machine does not inflate (the fuzz grid, run beside other jobs).  ``None`` or a
    non-positive value sets no limit.  The previous handler and timer are restored on exit, so
    limits do not leak into the caller.

    >>> with time_limit(None):
    ...     1 + 1
    2
    """
    if clock not in _CLOCKS:
        raise ValueError(f"clock={clock!r} is outside {{wall, cpu}}")
    if seconds is None or seconds <= 0 or not enforceable():
        yield
        return
    timer, signum = (getattr(signal, name) for name in _CLOCKS[clock])

    def _raise(sig: int, frame: object) -> None:
        signal.setitimer(timer, 0.0)
        raise TimeLimitReached(float(seconds), clock)

    previous = signal.signal(signum, _raise)
    signal.setitimer(timer, float(seconds))
    try:
        yield
    finally:
        signal.setitimer(timer, 0.0)
        signal.signal(signum, previous)
