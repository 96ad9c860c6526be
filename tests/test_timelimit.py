"""The wall-time limit of one run (qpscale/timelimit.py): it stops, it is not swallowed, it leaves
no timer behind, and the studies record it as a status.  Tolerances: the limit is checked
against the clock with 0.5 s of slack (the signal comes at the next Python bytecode)."""

from __future__ import annotations

import signal
import time

import pytest

from qpscale.studies.bench import Method, run_method
from qpscale.studies.bench import Scene as BenchScene
from qpscale.studies.paper_run import run_scene
from qpscale.studies.paper_scenes import Scene
from qpscale.tiling import Design
from qpscale.timelimit import STATUS, TimeLimitReached, enforceable, time_limit

pytestmark = pytest.mark.skipif(not enforceable(), reason="no POSIX interval timer here")


def _spin(seconds: float) -> None:
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        pass


def test_limit_stops_a_busy_loop_near_the_limit():
    t0 = time.perf_counter()
    with pytest.raises(TimeLimitReached) as info, time_limit(0.2):
        _spin(5.0)
    assert 0.2 <= time.perf_counter() - t0 < 0.7
    assert info.value.status == STATUS and info.value.limit == 0.2


def test_limit_passes_through_except_exception_and_restores_the_handler():
    before = signal.getsignal(signal.SIGALRM)
    with pytest.raises(TimeLimitReached), time_limit(0.1):
        try:
            _spin(5.0)
        except Exception:  # what a solver wrapper does around its call  # noqa: BLE001
            pytest.fail("the limit was caught as an ordinary exception")
    assert signal.getsignal(signal.SIGALRM) is before
    assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)


def test_no_limit_and_a_finished_body_leave_no_timer():
    with time_limit(None):
        _spin(0.01)
    with time_limit(10.0):
        _spin(0.01)
    assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)


def test_paper_scene_over_its_limit_is_a_status_without_results():
    # A 5x5 array at 16 increments takes tens of seconds; 0.5 s stops it mid-path.
    scene = Scene("interaction", "puncture", "square", "arrayed", increments=16)
    row, data = run_scene(scene, limit_s=0.5)
    assert row["status"] == STATUS and "Fc_star" not in row and data == {}
    assert row["wall_s"] < 5.0


def test_bench_run_over_its_limit_is_a_failure_at_the_limit():
    scene = BenchScene("square5", Design(rings=2))
    run = run_method(scene, Method("clarabel", "clarabel"), None, time_limit=0.5)
    assert not run.success and run.failure == "time limit" and run.status == STATUS
    assert run.wall_s == 0.5 and run.Fc_star is None


def test_cpu_clock_counts_cpu_not_sleep():
    # A sleeping body uses no CPU: a 0.2 s CPU limit does not stop 0.5 s of sleep, and a busy
    # loop is stopped after about 0.2 s of CPU.
    with time_limit(0.2, clock="cpu"):
        time.sleep(0.5)
    t0 = time.process_time()
    with pytest.raises(TimeLimitReached) as info, time_limit(0.2, clock="cpu"):
        _spin(5.0)
    assert 0.15 <= time.process_time() - t0 < 0.7 and "CPU-time" in str(info.value)
    assert signal.getitimer(signal.ITIMER_PROF) == (0.0, 0.0)
    with pytest.raises(ValueError, match="clock"), time_limit(1.0, clock="moon"):
        pass


def _in_thread(fn):
    """Run ``fn()`` in a new thread (as a Dask worker runs its tasks); its result or exception."""
    import threading

    out: list = []

    def body():
        try:
            out.append(fn())
        except BaseException as exc:  # noqa: BLE001 - handed back to the test
            out.append(exc)

    t = threading.Thread(target=body)
    t.start()
    t.join()
    return out[0]


@pytest.mark.parametrize("clock", ["wall", "cpu"])
def test_limit_stops_a_busy_loop_in_another_thread(clock):
    # Outside the main thread a watchdog sets the exception asynchronously; 0.5 s of slack as above
    # (the CPU clock is polled every 0.05 s), on the clock limited: this thread's CPU time for
    # "cpu" (on a loaded machine its wall time runs ahead).
    now = time.perf_counter if clock == "wall" else time.thread_time

    def run():
        t0 = now()
        try:
            with time_limit(0.2, clock):
                try:
                    _spin(5.0)
                except Exception:  # noqa: BLE001 - a solver wrapper must not swallow it
                    return "swallowed"
        except TimeLimitReached as exc:
            return exc, now() - t0
        return "not stopped"

    exc, elapsed = _in_thread(run)
    assert isinstance(exc, TimeLimitReached) and exc.status == STATUS and exc.limit == 0.2
    assert exc.clock == clock and 0.2 <= elapsed < 0.7


def test_finished_body_in_another_thread_is_not_interrupted_later():
    def run():
        with time_limit(0.3):
            _spin(0.05)
        _spin(0.6)  # past the limit: the watchdog must be gone
        with time_limit(0.2, "cpu"):
            time.sleep(0.4)  # sleeping costs no CPU time
        return "done"

    assert _in_thread(run) == "done"


@pytest.mark.parametrize("thread", ["other", "main"])
def test_limit_swallowed_once_is_raised_again(thread):
    # An asynchronous exception that lands where errors are ignored (Dask's GC callback printed
    # "Exception ignored" and a sweep ran to its end) is lost; outside the main thread the
    # watchdog raises it again every CPU_POLL_S, in the main thread the interval timer repeats.
    # Here the body swallows the first one itself and spins on: the second stops it.
    def run():
        t0 = time.perf_counter()
        caught = 0
        try:
            with time_limit(0.2):
                try:
                    _spin(5.0)
                except TimeLimitReached:
                    caught += 1
                    _spin(5.0)
        except TimeLimitReached:
            return caught, time.perf_counter() - t0
        return caught, None

    caught, elapsed = _in_thread(run) if thread == "other" else run()
    assert caught == 1 and elapsed is not None and 0.2 <= elapsed < 0.8
