"""Where the studies' independent tasks run: this process, or a Dask cluster (local or remote).

Implements no formulation: this is plumbing, shared by ``qpscale sweep``, ``qpscale paper`` and
``qpscale bench``.  One worker and no scheduler address run the tasks here, one after another,
in the main thread (the serial baseline; no cluster to start).  Otherwise a Dask distributed
cluster runs them: a :class:`distributed.LocalCluster` on the loopback interface by default
(``workers`` processes, one thread each, so that a task runs alone in its process and its wall
time means what it means in a serial run as long as ``workers`` does not exceed the cores), or
the cluster whose scheduler is at ``scheduler``.  Every task runs with one BLAS thread
(:func:`qpscale.threads.limited_blas`).  A worker that dies mid-task (killed, out of memory) is
replaced by its nanny and the scheduler gives its task to another worker, up to
:data:`ALLOWED_FAILURES` deaths per task (``distributed.scheduler.allowed-failures``); after that
the task fails with ``KilledWorker``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import signal
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from ..errors import InvalidDesign

T = TypeVar("T")

log = logging.getLogger(__name__)

# Worker deaths a task may cause before it is given up (the local cluster's scheduler; an external
# scheduler keeps its own setting).  Dask's default, stated here so that the value is visible.
ALLOWED_FAILURES = 3
DASHBOARD_EXTRA = "pip install 'qpscale[dashboard]'"


def check_workers(workers: object) -> int:
    """``workers`` as given, or :class:`InvalidDesign` naming the allowed range (1 to the cores).

    >>> check_workers(1)
    1
    """
    cores = os.cpu_count() or 1
    if not isinstance(workers, int) or isinstance(workers, bool) or not 1 <= workers <= cores:
        raise InvalidDesign("workers", workers, f"an integer from 1 to {cores} (this machine's cores)")
    return workers


def run_task(fn: Callable[..., T], args: tuple[Any, ...]) -> T:
    """``fn(*args)`` with one BLAS thread: what a worker runs for each task."""
    from ..threads import limited_blas

    with limited_blas():
        return fn(*args)


def dask_setup(worker: Any) -> None:
    """Dask's preload hook, run in every worker process of the local cluster as it starts.

    Ctrl-C in a terminal reaches the whole process group: the workers ignore SIGINT and leave it
    to the parent, which closes the cluster (and with it the workers) instead of each printing a
    traceback.  Workers started with the cluster have SIGINT blocked from the start
    (:func:`_starting`); this covers those a nanny starts later, after a worker died.
    """
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("distributed.worker").addFilter(_closing_heartbeat)


#: What a worker logs, with a traceback, when a heartbeat is in flight as the connection to the
#: scheduler closes (dask/distributed issues 7105 and 9032: a race inside ``Worker.close``).
HEARTBEAT_RACE = "Failed to communicate with scheduler during heartbeat."


def _closing_heartbeat(record: logging.LogRecord) -> bool:
    """Drop the heartbeat-race record of :data:`HEARTBEAT_RACE` (a logging filter).

    The local cluster's scheduler runs in the parent process, over loopback: its connection closes
    only as the parent closes the cluster (the run ended, or Ctrl-C/SIGTERM).  Dask does not act on
    the failed heartbeat (the worker goes on; its scheduler stream decides), so the record says
    nothing a user can act on, and it printed a traceback under the parent's clean exit message.
    """
    return record.getMessage() != HEARTBEAT_RACE


@contextlib.contextmanager
def _starting() -> Iterator[None]:
    """While the local cluster starts, SIGINT is blocked in this thread and SIGTERM held back.

    Every thread the cluster starts meanwhile (its event loop, the threads that spawn the worker
    processes) inherits the blocked SIGINT, and so do the worker processes (a signal mask survives
    ``exec``): a Ctrl-C sent to the whole process group never reaches them, not even while they
    import.  In this process a Ctrl-C or SIGTERM that comes during the start stays pending and is
    delivered when the start is over and the cluster assigned, so that the caller's handlers end
    it cleanly (:meth:`Engine.close`).
    """
    main = threading.current_thread() is threading.main_thread()
    masks = hasattr(signal, "pthread_sigmask")  # POSIX
    held: list[int] = []
    old_term = signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum)) if main else None
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if masks else None
    try:
        yield
    finally:
        if old_mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # a pending Ctrl-C is delivered here
        if main:
            signal.signal(signal.SIGTERM, old_term)
            if held:
                os.kill(os.getpid(), signal.SIGTERM)


def bokeh_installed() -> bool:
    """Whether the Dask dashboard can be served (it is drawn with bokeh, an optional extra)."""
    return importlib.util.find_spec("bokeh") is not None


class Engine:
    """Runs tasks here (``workers == 1`` and no ``scheduler``) or on a Dask cluster.

    Use it as a context manager: the cluster is started (or connected to) when the first tasks
    come, so that nothing starts for a run with nothing left to do, and it is closed on exit (the
    local cluster's worker processes ended, also on Ctrl-C or an exception).

    Parameters
    ----------
    workers : int
        Worker processes of the local cluster, 1 to the core count (1: this process, no cluster).
    scheduler : str or None
        Address of an existing Dask scheduler (``tcp://host:8786``); its workers run the tasks and
        ``workers`` is not used.
    local_cluster : bool
        Start a local cluster even for one worker (``qpscale sweep`` always runs on Dask).
    announce : callable or None
        Called with :meth:`describe` once the cluster is up (where it runs, the dashboard).
    """

    def __init__(
        self,
        workers: int = 1,
        scheduler: str | None = None,
        local_cluster: bool = False,
        announce: Callable[[str], None] | None = None,
    ) -> None:
        self.workers = check_workers(workers)
        if scheduler is not None and (not isinstance(scheduler, str) or not scheduler.strip()):
            raise InvalidDesign("scheduler", scheduler, "a Dask scheduler address such as tcp://host:8786")
        self.scheduler = scheduler
        self.distributed = scheduler is not None or workers > 1 or local_cluster
        self.announce = announce
        self.started: str | None = None  # describe() when the cluster came up (kept after close)
        self.client: Any = None
        self.cluster: Any = None

    # -- lifecycle ---------------------------------------------------------------------------
    def __enter__(self) -> Engine:
        return self

    def start(self) -> None:
        """Start the local cluster or connect to the scheduler (once; nothing for this process)."""
        if not self.distributed or self.client is not None:
            return
        self._connect()
        self.started = self.describe()
        if self.announce is not None:
            self.announce(self.started)

    def _connect(self) -> None:
        if self.scheduler is not None:
            from distributed import Client

            try:
                self.client = Client(self.scheduler, timeout="10s", set_as_default=False)
            except (OSError, TimeoutError, ValueError) as exc:
                raise InvalidDesign(
                    "scheduler", self.scheduler, "the address of a running Dask scheduler", str(exc)
                ) from None
            return
        # multiprocessing starts its resource tracker with SIGINT blocked and then *unblocks* it in
        # the calling thread, which would undo _starting(): start it first, outside.
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
        try:
            with _starting():
                # Imported here: importing distributed starts a helper thread, which must inherit
                # the blocked SIGINT too, since the worker processes are spawned from its threads.
                import dask
                from distributed import Client, LocalCluster

                with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES}):
                    self.cluster = LocalCluster(
                        n_workers=self.workers,
                        threads_per_worker=1,
                        processes=True,
                        host="127.0.0.1",
                        # Loopback and a free port: the scheduler's HTTP server always starts (without
                        # bokeh it serves a page saying so), and it must not listen on every interface.
                        dashboard_address="127.0.0.1:0",
                        silence_logs=logging.ERROR,
                        preload=[__name__],
                    )
                self.client = Client(self.cluster, set_as_default=False)
        except BaseException:  # a signal held back during the start lands here, once assigned
            self.close()
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Disconnect from the scheduler and stop the local cluster (idempotent)."""
        client, cluster = self.client, self.cluster
        self.client = self.cluster = None
        for part in (client, cluster):
            if part is not None:
                try:
                    part.close()
                except Exception as exc:  # noqa: BLE001 - closing must not hide the run's own error
                    log.warning("closing %s failed: %s: %s", type(part).__name__, type(exc).__name__, exc)

    # -- information ---------------------------------------------------------------------------
    @property
    def dashboard(self) -> str | None:
        """The Dask dashboard's address, or None (no cluster, or no dashboard served)."""
        if self.client is None or (self.cluster is not None and not bokeh_installed()):
            return None
        services = self.client.scheduler_info().get("services", {})
        port = services.get("dashboard")
        if port is None:
            return None
        host = self.client.scheduler.address.split("://")[-1].rsplit(":", 1)[0]
        return f"http://{host}:{port}/status"

    def describe(self) -> str:
        """One line: where the tasks run and where the dashboard is (or why there is none)."""
        if not self.distributed:
            return "engine: this process (one worker)"
        if self.scheduler is not None:
            where = f"engine: Dask scheduler {self.scheduler}"
        else:
            where = f"engine: local Dask cluster, {self.workers} worker process" + "es" * (self.workers > 1)
        link = self.dashboard
        if link is not None:
            return f"{where}; dashboard {link}"
        if not bokeh_installed():
            return f"{where}; no dashboard (bokeh is not installed: {DASHBOARD_EXTRA})"
        return f"{where}; the scheduler serves no dashboard"

    # -- running -------------------------------------------------------------------------------
    def map(
        self,
        fn: Callable[..., T],
        tasks: Sequence[tuple[Any, ...]],
        *,
        on_done: Callable[[int, T], None] | None = None,
        failure: Callable[[int, BaseException], T] | None = None,
        progress: Callable[[str], None] | None = None,
        label: Callable[[tuple[Any, ...]], str] | None = None,
        name: str = "task",
    ) -> list[T]:
        """``[fn(*task) for task in tasks]``, order kept; ``on_done(i, result)`` as each ends.

        ``fn`` must be a module-level function (workers import it).  A task whose call raises, or
        that killed its workers :data:`ALLOWED_FAILURES` + 1 times, becomes ``failure(i, exc)``
        when ``failure`` is given; otherwise the exception is raised here and the remaining tasks
        are cancelled.  ``progress`` is called with ``"done/total label"`` as each task ends.
        """
        if not tasks:
            return []
        self.start()
        results: list[Any] = [None] * len(tasks)
        count = [0]

        def finish(i: int, value: Any) -> None:
            results[i] = value
            count[0] += 1
            if on_done is not None:
                on_done(i, value)
            if progress is not None:
                progress(f"{count[0]}/{len(tasks)} " + (label(tasks[i]) if label else ""))

        if not self.distributed:
            for i, task in enumerate(tasks):
                try:
                    value = run_task(fn, task)
                except Exception as exc:
                    if failure is None:
                        raise
                    value = failure(i, exc)
                finish(i, value)
            return results
        self._map_dask(fn, tasks, finish, failure, name)
        return results

    def _map_dask(
        self,
        fn: Callable[..., Any],
        tasks: Sequence[tuple[Any, ...]],
        finish: Callable[[int, Any], None],
        failure: Callable[[int, BaseException], Any] | None,
        name: str,
    ) -> None:
        from distributed import as_completed

        run = uuid.uuid4().hex[:8]
        # Earlier tasks first (higher priority), each under its own key: nothing is deduplicated
        # against an earlier run on the same cluster, and no task is retried on its own exception
        # (the tasks catch their errors and report a status; a lost worker is the scheduler's).
        futures = {
            self.client.submit(run_task, fn, task, key=f"{name}-{run}-{i}", priority=-i, pure=False): i
            for i, task in enumerate(tasks)
        }
        try:
            for fut in as_completed(futures, loop=self.client.loop):
                i = futures.pop(fut)
                try:
                    value = fut.result()
                except Exception as exc:
                    if failure is None:
                        raise
                    value = failure(i, exc)
                fut.release()
                finish(i, value)
        finally:
            if futures:  # interrupted, or a task's error: nothing may go on computing for nobody
                self.client.cancel(list(futures), force=True)


def map_tasks(
    fn: Callable[..., T],
    tasks: Sequence[tuple[Any, ...]],
    workers: int = 1,
    engine: Engine | None = None,
    progress: Callable[[str], None] | None = None,
    label: Callable[[tuple[Any, ...]], str] | None = None,
    name: str = "task",
) -> list[T]:
    """``[fn(*task) for task in tasks]`` on ``engine`` (entered), or on an engine of ``workers``
    processes opened for this call (1, or a single task: this process); order kept, a task's
    exception raised here."""
    if engine is not None:
        return engine.map(fn, tasks, progress=progress, label=label, name=name)
    with Engine(check_workers(workers) if len(tasks) > 1 else 1) as own:
        return own.map(fn, tasks, progress=progress, label=label, name=name)
