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
status.  Where neither mechanism exists (no ``setitimer`` in the main thread; not CPython, or no
per-thread CPU clock, elsewhere), the limit is not enforced and the run goes to its end.
"""

from __future__ import annotations

import ctypes
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

STATUS = "time_limit"


class TimeLimitReached(BaseException):
    """The run exceeded its time limit (seconds in ``limit``, on ``clock``: "wall" or "cpu")."""

    status = STATUS

    def __init__(self, limit: float, clock: str = "wall") -> None:
        self.limit, self.clock = limit, clock
        what = "wall-time" if clock == "wall" else "CPU-time"
        super().__init__(f"stopped at the {what} limit of {limit:g} s")


def enforceable(clock: str = "wall") -> bool:
    """True where :func:`time_limit` can interrupt the calling thread on ``clock``: POSIX interval
    timers in the main thread, a watchdog thread elsewhere (CPython; a per-thread CPU clock)."""
    if threading.current_thread() is threading.main_thread():
        return hasattr(signal, "setitimer")
    has_async = hasattr(ctypes, "pythonapi") and hasattr(ctypes.pythonapi, "PyThreadState_SetAsyncExc")
    return has_async and (clock == "wall" or hasattr(time, "pthread_getcpuclockid"))


# Poll period of the watchdog on the CPU clock, seconds: the limit is met within this (and the
# next Python bytecode); a wall-clock watchdog waits the whole remaining time in one call.  Also
# the period at which a limit that has fired is raised again until its body is left.
CPU_POLL_S = 0.05

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
    if seconds is None or seconds <= 0 or not enforceable(clock):
        yield
        return
    if threading.current_thread() is not threading.main_thread():
        with _watchdog(float(seconds), clock):
            yield
        return
    timer, signum = (getattr(signal, name) for name in _CLOCKS[clock])

    def _raise(sig: int, frame: object) -> None:
        raise TimeLimitReached(float(seconds), clock)

    # The timer repeats every CPU_POLL_S until the body is left: a raise that lands where the
    # interpreter ignores errors (see ``_watchdog``) is followed by the next.
    previous = signal.signal(signum, _raise)
    signal.setitimer(timer, float(seconds), CPU_POLL_S)
    try:
        yield
    finally:
        signal.setitimer(timer, 0.0)
        signal.signal(signum, previous)


def _thread_clock(clock: str) -> Callable[[], float]:
    """The calling thread's clock: monotonic wall time, or this thread's own CPU time."""
    if clock == "wall":
        return time.monotonic
    clk = time.pthread_getcpuclockid(threading.get_ident())
    return lambda: time.clock_gettime(clk)


def _set_async(ident: int, exc: type[BaseException] | None) -> None:
    """Raise ``exc`` in thread ``ident`` at its next bytecode (None: cancel a pending one)."""
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(ident), ctypes.py_object(exc) if exc else None)


@contextmanager
def _watchdog(seconds: float, clock: str) -> Iterator[None]:
    """The limit outside the main thread: a daemon thread that raises :class:`TimeLimitReached` in
    this one once ``seconds`` have passed on ``clock``.

    The asynchronous exception is a class raised without arguments, so a subclass carries the
    limit; it is raised again every ``CPU_POLL_S`` until the body ends (one can be swallowed where
    the interpreter ignores errors).  A lock orders the two ends: once the body is done the
    watchdog cannot fire, and an exception it set that the body had no time to see is withdrawn.
    """
    ident = threading.get_ident()
    now = _thread_clock(clock)
    t_end = now() + seconds
    lock = threading.Lock()
    done = threading.Event()
    fired = []

    class _Reached(TimeLimitReached):
        def __init__(self) -> None:
            super().__init__(seconds, clock)

    _Reached.__name__ = _Reached.__qualname__ = "TimeLimitReached"

    def watch() -> None:
        while not done.wait(max(t_end - now(), 0.0) if clock == "wall" else CPU_POLL_S):
            if now() >= t_end:
                break
        # Raised again every CPU_POLL_S until the body is done: an asynchronous exception that
        # arrives inside a callback whose errors the interpreter ignores (a garbage-collection
        # callback of Dask's worker printed "Exception ignored" and the run went on to its end)
        # is lost, and the next one stops the run.
        while True:
            with lock:
                if done.is_set():
                    return
                _set_async(ident, _Reached)
                fired.append(True)
            if done.wait(CPU_POLL_S):
                return

    watcher = threading.Thread(target=watch, name="qpscale-time-limit", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        with lock:
            done.set()
            if fired:
                _set_async(ident, None)
        watcher.join()
