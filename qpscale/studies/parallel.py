"""Run independent study tasks on several processes (``qpscale bench --workers``).

Implements no formulation: this is plumbing.  Each task runs whole in one worker process (its
own interpreter, started by ``spawn`` so that no lock held by the parent's progress-bar thread is
copied into a child), and a worker runs one task at a time, so a per-task time limit
(:mod:`qpscale.timelimit`, a POSIX timer of the worker's main thread) and a measured wall time
mean what they mean in a serial run as long as ``workers`` does not exceed the machine's cores.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TypeVar

from ..errors import InvalidDesign

T = TypeVar("T")


def check_workers(workers: int) -> int:
    """``workers`` as given, or :class:`InvalidDesign` naming the allowed range (1 to the core count)."""
    cores = os.cpu_count() or 1
    if not isinstance(workers, int) or not 1 <= workers <= max(cores, 1):
        raise InvalidDesign("workers", workers, f"an integer from 1 to {cores} (this machine's cores)")
    return workers


def pmap(
    fn: Callable[..., T],
    tasks: Sequence[tuple[Any, ...]],
    workers: int = 1,
    progress: Callable[[str], None] | None = None,
    label: Callable[[tuple[Any, ...]], str] | None = None,
) -> list[T]:
    """``[fn(*task) for task in tasks]``, on ``workers`` processes when ``workers > 1``; order kept.

    ``fn`` must be a module-level function (the workers import it).  ``progress`` is called with
    ``label(task)`` when a task starts (serial) or ends (parallel).  An exception in a task is
    raised here, as in the serial loop.
    """
    check_workers(workers)
    if workers == 1 or len(tasks) <= 1:
        out = []
        for task in tasks:
            if progress and label:
                progress(label(task))
            out.append(fn(*task))
        return out
    results: list[Any] = [None] * len(tasks)
    ctx = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=worker_init)
    try:
        futures = {pool.submit(fn, *task): i for i, task in enumerate(tasks)}
        for done, fut in enumerate(as_completed(futures), start=1):
            i = futures[fut]
            results[i] = fut.result()
            if progress:
                progress(f"{done}/{len(tasks)} " + (label(tasks[i]) if label else ""))
    except BaseException:
        # Ctrl-C, SIGTERM (the CLI raises it as an interrupt) or a task's error: no worker may
        # keep computing a task whose result nobody will read.
        terminate_pool(pool)
        raise
    pool.shutdown(wait=True)
    return results


def terminate_pool(pool: ProcessPoolExecutor, timeout_s: float = 5.0) -> None:
    """Stop a process pool now: pending tasks cancelled, running workers terminated and reaped."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for proc in processes:
        with contextlib.suppress(Exception):
            proc.terminate()
    for proc in processes:
        with contextlib.suppress(Exception):
            proc.join(timeout_s)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout_s)
    # With every worker reaped, the pool's manager thread sees them gone and ends; joining it here
    # (wait=True) matters: left running, the interpreter's exit hook for process pools woke it
    # through a closed pipe (a traceback on stderr) or waited on it (a Ctrl-C'd paper run that
    # never exited, seen under load in CI).
    pool.shutdown(wait=True, cancel_futures=True)


def worker_init() -> None:
    """Initializer of every worker process of the studies.

    Ctrl-C in a terminal reaches the whole process group: the workers ignore SIGINT and leave it to
    the parent, which terminates them (:func:`terminate_pool`) instead of each printing a
    traceback.  On Linux the kernel also sends a worker SIGTERM when its parent dies, so a parent
    killed without a chance to clean up (SIGKILL) leaves no orphan computing for minutes.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # A forked worker inherits the parent's handlers; the command line's SIGTERM handler turns the
    # signal into an exception, but a worker must simply end when the parent terminates it.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            import ctypes

            PR_SET_PDEATHSIG = 1
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
