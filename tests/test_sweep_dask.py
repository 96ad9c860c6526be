"""Sweeps and the engine on a local Dask cluster over loopback (qpscale/studies/engine.py,
qpscale/studies/sweep_run.py): answers equal to the same designs run serially through
qpscale.api, resume that runs only the missing designs, a worker killed mid-task whose task is
run again, a task that kills every worker recorded as a status, and the per-design time limit
inside a worker's thread.

One cluster (two worker processes, one thread each) serves the whole module; the engine reaches
it by its address, the ``--scheduler`` path.  Its scheduler allows one worker death per task
(Dask's default is 3), so that the test of a task that kills every worker ends after two deaths.
"""

from __future__ import annotations

import json
import logging
import os
import signal
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from qpscale import api
from qpscale.cli import app
from qpscale.studies.engine import Engine
from qpscale.studies.sweep import parse_spec
from qpscale.studies.sweep_run import run_sweep

# Designs of a few tenths of a second each: isolated scales, square and hexagon, two slants.
GRID = {"time_limit_s": 120, "parameters": {"shape": ["square", "hexagon"], "slant_deg": [0, 30], "rings": 0}}
# Relative agreement of a Dask run with the serial API run: the same code on the same input with
# one BLAS thread; only round-off could differ.
RTOL = 1e-9


@pytest.fixture(scope="module")
def scheduler():
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        cluster = LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address="127.0.0.1:0",
            silence_logs=logging.ERROR,
        )
    with cluster:
        yield cluster.scheduler_address


def test_sweep_on_dask_equals_the_serial_api_runs(scheduler, tmp_path):
    spec = parse_spec(GRID)
    with Engine(scheduler=scheduler) as engine:
        result = run_sweep(spec, tmp_path / "r.parquet", engine)
    assert result.n_run == 4 and result.statuses == {"ok": 4}
    table = pd.read_parquet(tmp_path / "r.parquet").set_index("key")
    assert table["pid"].nunique() >= 1 and (table["host"] != "").all()
    for point in spec.designs:
        serial = api.puncture(**point.params)
        row = table.loc[point.key]
        assert row["Fc_star"] == pytest.approx(serial.Fc_star, rel=RTOL)
        assert row["delta_c_star"] == pytest.approx(serial["delta_c_star"], rel=RTOL)
        assert [row["load_x"], row["load_y"]] == pytest.approx(serial["load_point"], rel=RTOL, abs=1e-12)
        assert row["increments"] == serial["increments"]


def test_resume_runs_only_the_designs_not_in_the_table(scheduler, tmp_path):
    out = tmp_path / "r.parquet"
    first = parse_spec({"parameters": {"shape": ["square", "hexagon"], "rings": 0}})
    more = parse_spec({"parameters": {"shape": ["square", "hexagon", "triangle"], "rings": 0}})
    with Engine(scheduler=scheduler) as engine:
        a = run_sweep(first, out, engine)
        b = run_sweep(more, out, engine)
        c = run_sweep(more, out, engine)
    assert (a.n_run, b.n_run, b.n_skipped, c.n_run, c.n_skipped) == (2, 1, 2, 0, 3)
    # Each row carries the id of the sweep that computed it: two rows from the first, one from the
    # second, none from the third.
    runs = pd.read_parquet(out)["sweep_id"].value_counts().to_dict()
    assert runs == {a.sweep_id: 2, b.sweep_id: 1}


def _die_once(flag: str, value: int) -> tuple[int, int]:
    """Kill this worker process the first time (the flag file marks it); then answer."""
    path = Path(flag)
    if not path.exists():
        path.write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return 2 * value, os.getpid()


def _die_always(value: int) -> int:
    os.kill(os.getpid(), signal.SIGKILL)
    return value


def test_worker_killed_mid_task_is_retried(scheduler, tmp_path):
    flag, spared = tmp_path / "killed", tmp_path / "spared"
    spared.write_text("0")  # the second task finds its flag: it answers at once
    with Engine(scheduler=scheduler) as engine:
        out = engine.map(_die_once, [(str(flag), 21), (str(spared), 1)], name="die-once")
    assert flag.exists()  # the first attempt did run, and killed its worker
    (value, pid), (other, _) = out
    assert (value, other) == (42, 2) and pid != int(flag.read_text())  # answered by another worker process


def test_task_that_kills_every_worker_becomes_a_status(scheduler):
    with Engine(scheduler=scheduler) as engine:
        out = engine.map(_die_always, [(1,)], failure=lambda i, exc: type(exc).__name__, name="die-always")
        assert out == ["KilledWorker"]
        # The nannies restarted the workers: the cluster still works.
        assert engine.map(abs, [(-3,)]) == [3]


def test_time_limit_holds_inside_a_worker(scheduler, tmp_path):
    # A 3x3 array with the stability probe takes seconds; 0.3 s stops it in the worker's thread.
    spec = parse_spec({"time_limit_s": 0.3, "parameters": {"rings": 1}})
    with Engine(scheduler=scheduler) as engine:
        result = run_sweep(spec, tmp_path / "r.parquet", engine)
    row = pd.read_parquet(tmp_path / "r.parquet").iloc[0]
    assert result.statuses == {"time_limit": 1} and row["status"] == "time_limit"
    assert pd.isna(row["Fc_star"]) and "limit of 0.3 s" in row["error"] and row["wall_s"] < 3.0


def test_cli_sweep_on_a_scheduler_prints_the_documented_json(scheduler, tmp_path):
    from tests.test_docs import _documented_fields

    grid = tmp_path / "grid.toml"
    grid.write_text('experiment = "puncture"\n[parameters]\nshape = ["square", "hexagon"]\nrings = 0\n')
    out = tmp_path / "r.parquet"
    args = ["sweep", str(grid), "--out", str(out), "--scheduler", scheduler, "--json"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    always, _ = _documented_fields("sweep")
    assert always <= set(payload), always - set(payload)
    assert (payload["n_run"], payload["n_failed"], payload["statuses"]) == (2, 0, {"ok": 2})
    again = json.loads(CliRunner().invoke(app, args).stdout)
    assert (again["n_run"], again["n_skipped"]) == (0, 2)
    assert len(pd.read_parquet(out)) == 2


def _blas_threads() -> list[int]:
    import numpy  # noqa: F401 - loads its BLAS, so that threadpoolctl sees it
    from threadpoolctl import threadpool_info

    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_engine_starts_its_own_loopback_cluster_with_one_blas_thread_per_task():
    from qpscale.studies.engine import bokeh_installed

    lines: list[str] = []
    with Engine(2, announce=lines.append) as engine:
        assert engine.client is None  # nothing started before there is work
        engine.start()
        (line,) = lines
        assert engine.client.scheduler.address.startswith("tcp://127.0.0.1:")
        threads = engine.map(_blas_threads, [()] * 2)
    assert line.startswith("engine: local Dask cluster, 2 worker processes")
    assert (
        ("dashboard http://127.0.0.1:" in line) if bokeh_installed() else ("bokeh is not installed" in line)
    )
    assert all(t and set(t) == {1} for t in threads), threads
    assert engine.client is None and engine.cluster is None  # closed on exit


def test_paper_scenes_run_on_the_scheduler_as_in_this_process(scheduler):
    # qpscale paper --scheduler: the same rows as the serial run (1e-12: deterministic, one BLAS
    # thread in both).
    from qpscale.studies.paper import run_scenes
    from qpscale.studies.paper_scenes import Scene

    scenes = [
        Scene("isolated", "puncture", "square", rings=0, increments=4),
        Scene("isolated", "puncture", "hexagon", rings=0, increments=4),
    ]
    with Engine(scheduler=scheduler) as engine:
        rows, data = run_scenes(scenes, engine=engine)
    serial, _ = run_scenes(scenes, workers=1)
    assert [r["status"] for r in rows] == ["ok", "ok"] and set(data) == {s.key for s in scenes}
    for r, s in zip(rows, serial):
        assert r["Fc_star"] == pytest.approx(s["Fc_star"], rel=1e-12)


def test_workers_drop_only_the_heartbeat_race_of_a_closing_cluster():
    """The record a worker logs when its heartbeat meets the closing connection (a race inside
    Dask's ``Worker.close``, which printed a traceback under a clean Ctrl-C/SIGTERM exit) is
    dropped by the preload; every other record of the worker's logger passes.  The message is
    compared with the installed Dask's source, so that a rewording there fails here."""
    import inspect
    import threading

    from distributed import worker

    from qpscale.studies import engine

    assert engine.HEARTBEAT_RACE in inspect.getsource(worker.Worker.heartbeat)
    logger = logging.getLogger("distributed.worker")
    # The preload as a worker runs it, but off the main thread: this process keeps its SIGINT.
    thread = threading.Thread(target=engine.dask_setup, args=(None,))
    thread.start()
    thread.join()
    try:

        def passes(msg: str) -> bool:
            return logger.filter(logging.LogRecord(logger.name, logging.ERROR, __file__, 1, msg, None, None))

        assert not passes(engine.HEARTBEAT_RACE)
        assert passes("Unexpected exception during heartbeat. Closing worker.")
        assert passes("Worker stream died during communication: %s")
    finally:
        logger.removeFilter(engine._closing_heartbeat)
