"""Running a design sweep (:mod:`qpscale.studies.sweep`) on the engine and keeping its table.

Implements no formulation: this is plumbing.  Each design runs through :mod:`qpscale.api` (the
same path as ``qpscale puncture`` and ``qpscale flexure``) in one task of the
:class:`~qpscale.studies.engine.Engine`; its row holds the design's key and parameters, its
``status`` (``ok``, the solver's status word, ``time_limit``, ``invalid_design``, the error's class,
or ``KilledWorker`` for a task that killed its workers) with the message in ``error``, and the
results, which stay empty for a failure: a failed design is never a number.

The table is a Parquet file written as the rows arrive.  Each finished row is first appended to a
journal beside it (``.NAME.journal``, one JSON object per line), then the Parquet file is rewritten
through a temporary file and a rename, at most as often as keeps the rewriting a small part of the
run; the journal is removed once the table holds everything.  A run that is killed keeps every
finished row (in the table or its journal), and a rerun with the same ``--out`` reads both and skips
every design whose key is already there.
"""

from __future__ import annotations

import datetime
import json
import os
import socket
import time
import traceback
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import InvalidDesign, QpscaleError, SolverFailure
from ..timelimit import TimeLimitReached, time_limit
from .engine import Engine
from .sweep import DesignPoint, SweepSpec

# Leading columns of the table; the design's parameters follow, then status and results.
KEY_COLUMNS = ("key", "experiment")
STATUS_COLUMNS = ("status", "error")
PUNCTURE_RESULTS = (
    "Fc_star",
    "delta_c_star",
    "tilt_deg",
    "load_x",
    "load_y",
    "max_penetration",
    "increments",
    "qp_solves",
    "load_levels",
    "n_scales",
    "branched",
)
FLEXURE_RESULTS = ("Cf_star", "n_scales", "n_retained", "sqp_iterations", "max_penetration")
META_COLUMNS = ("wall_s", "host", "pid", "sweep_id", "finished_at", "version")
INVALID = "invalid_design"
# The table is rewritten at most once per this many times the duration of its last rewrite, so
# that rewriting a large table takes at most ~5 % of the run.
REWRITE_SPACING = 20.0


def _results(experiment: str, payload: Mapping[str, Any]) -> dict[str, Any]:
    if experiment == "flexure":
        return {k: payload[k] for k in FLEXURE_RESULTS}
    out = {k: payload[k] for k in PUNCTURE_RESULTS if k in payload}
    out["load_x"], out["load_y"] = payload["load_point"]
    out["branched"] = bool((payload.get("branch") or {}).get("branched", False))
    return out


def _call_api(point: DesignPoint) -> dict[str, Any]:
    """The design through :func:`qpscale.api.puncture` or ``flexure``; the JSON payload."""
    from .. import api

    p = dict(point.params)
    if point.experiment == "puncture":
        full = p["interaction"] == "full"
        return api.puncture(**{**p, "coupling_factor": None if full else p["coupling_factor"]}).to_dict()
    mode = p.pop("mode")
    return api.flexure(**p, isolated=mode == "isolated").to_dict()


def _plain_params(point: DesignPoint) -> dict[str, Any]:
    """The parameters as table cells (the accuracy is a word or a number: kept as text)."""
    p = dict(point.params)
    if "accuracy" in p and p["accuracy"] is not None:
        p["accuracy"] = str(p["accuracy"])
    return p


def run_design(point: DesignPoint, limit_s: float | None, sweep_id: str) -> dict[str, Any]:
    """One design's row (an engine task): parameters, status, results, where and when it ran.

    Errors are caught so that the sweep carries on: ``status`` is the solver's status, the time
    limit's, or the exception's class, ``error`` the message, and the result columns stay empty.
    """
    from .. import __version__

    row: dict[str, Any] = {"key": point.key, "experiment": point.experiment, **_plain_params(point)}
    t0 = time.perf_counter()
    try:
        with time_limit(limit_s):
            payload = _call_api(point)
        row.update(_results(point.experiment, payload))
        row["status"], row["error"] = "ok", None
    except TimeLimitReached as exc:
        row.update(status=exc.status, error=str(exc))
    except SolverFailure as exc:
        row.update(status=str(exc.status), error=str(exc))
    except QpscaleError as exc:
        row.update(status=type(exc).__name__, error=str(exc))
    except Exception as exc:  # noqa: BLE001 - one broken design must not stop the sweep
        row.update(status=f"crash:{type(exc).__name__}", error=f"{exc}\n{traceback.format_exc()}")
    row.update(
        wall_s=time.perf_counter() - t0,
        host=socket.gethostname(),
        pid=os.getpid(),
        sweep_id=sweep_id,
        finished_at=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        version=__version__,
    )
    return row


def failed_row(point: DesignPoint, status: str, error: str, sweep_id: str) -> dict[str, Any]:
    """The row of a design that did not run: not a design, or a task the cluster gave up."""
    from .. import __version__

    return {
        "key": point.key,
        "experiment": point.experiment,
        **_plain_params(point),
        "status": status,
        "error": error,
        "sweep_id": sweep_id,
        "finished_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "version": __version__,
    }


class ResultTable:
    """The sweep's Parquet table, kept up to date as rows arrive (see the module's notes).

    ``rows`` maps each design key to its row; rows of an earlier run (table and journal) are
    read on construction and the table rewritten with them, so that a killed run's journal is
    folded in at once.  ``rewrite_spacing``: the table is rewritten when the time since its last
    rewrite is at least this many times that rewrite's duration (0: at every row).
    """

    def __init__(self, path: Path, rewrite_spacing: float = REWRITE_SPACING) -> None:
        self.path = path
        self.rewrite_spacing = rewrite_spacing
        self.journal = path.with_name(f".{path.name}.journal")
        self.rows: dict[str, dict[str, Any]] = {}
        self._last_write = 0.0
        self._write_s = 0.0
        self._dirty = False
        self._load()
        self.write()
        self._write_s = 0.0  # that first rewrite also imported pyarrow: no measure of the next ones

    def _load(self) -> None:
        import pandas as pd

        if self.path.exists():
            try:
                table = pd.read_parquet(self.path)
            except (OSError, ValueError) as exc:
                raise InvalidDesign(
                    "out", str(self.path), "a table written by qpscale sweep", str(exc)
                ) from None
            if "key" not in table:
                raise InvalidDesign(
                    "out", str(self.path), "a table written by qpscale sweep", "it has no column 'key'"
                )
            for row in table.to_dict("records"):
                self.rows[str(row["key"])] = {k: _cell(x) for k, x in row.items()}
        if self.journal.exists():
            for line in self.journal.read_text().splitlines():
                try:
                    row = json.loads(line)
                except ValueError:  # the line a kill cut short
                    continue
                if isinstance(row, dict) and "key" in row:
                    self.rows[str(row["key"])] = row

    def add(self, row: dict[str, Any]) -> None:
        """Record a finished row: journal at once, table when due."""
        self.rows[row["key"]] = row
        with self.journal.open("a") as f:
            f.write(json.dumps(row, allow_nan=False, default=str) + "\n")
        self._dirty = True
        if time.monotonic() - self._last_write >= self.rewrite_spacing * self._write_s:
            self.write()

    def write(self) -> None:
        """Rewrite the table (atomically) with every row, then drop the journal it now holds."""
        t0 = time.monotonic()
        frame = self.frame()
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            frame.to_parquet(tmp, index=False)
            os.replace(tmp, self.path)
        finally:
            tmp.unlink(missing_ok=True)
        self.journal.unlink(missing_ok=True)
        self._dirty = False
        self._last_write = time.monotonic()
        self._write_s = self._last_write - t0

    def close(self) -> None:
        if self._dirty:
            self.write()

    def frame(self) -> Any:
        """Every row as a DataFrame, columns in a stable order."""
        import pandas as pd

        frame = pd.DataFrame(list(self.rows.values()))
        # Every result column of the experiments present, empty where no design ended ok.
        kinds = set(frame["experiment"]) if len(frame) else set()
        wanted = (PUNCTURE_RESULTS if "puncture" in kinds else ()) + (
            FLEXURE_RESULTS if "flexure" in kinds else ()
        )
        for column in (*STATUS_COLUMNS, *wanted):
            if column not in frame:
                frame[column] = None
        first = [c for c in (*KEY_COLUMNS,) if c in frame]
        last = [c for c in (*STATUS_COLUMNS, *PUNCTURE_RESULTS, *FLEXURE_RESULTS) if c in frame]
        meta = [c for c in META_COLUMNS if c in frame]
        middle = [c for c in frame.columns if c not in {*first, *last, *meta}]
        return frame[first + middle + list(dict.fromkeys(last)) + meta]


def _cell(x: Any) -> Any:
    """A table cell read back as plain Python (NaN read from a null number: None)."""
    if hasattr(x, "item"):
        x = x.item()
    if isinstance(x, float) and x != x:
        return None
    return x


@dataclass
class SweepResult:
    """What :func:`run_sweep` did: designs in the file, skipped (already in the table), run now,
    and the statuses of the whole table."""

    out: Path
    n_designs: int
    n_skipped: int
    n_run: int
    statuses: dict[str, int] = field(default_factory=dict)
    failed: list[dict[str, str]] = field(default_factory=list)
    sweep_id: str = ""
    wall_s: float = 0.0


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    engine: Engine,
    retry_failed: bool = False,
    on_start: Callable[[int, int], None] | None = None,
    on_done: Callable[[dict[str, Any]], None] | None = None,
) -> SweepResult:
    """Run every design of ``spec`` not yet in ``out`` on ``engine`` (entered); rows as they end.

    ``retry_failed`` also reruns the designs whose row has a status other than ``ok`` (after a
    larger time limit, say).  ``on_start(to_run, skipped)`` is called once before the run and
    ``on_done(row)`` as each design ends.  Designs that are not a design are recorded with the
    status ``invalid_design`` and not sent to the workers.
    """
    t0 = time.perf_counter()
    table = ResultTable(Path(out))
    sweep_id = uuid.uuid4().hex[:12]

    def finished(point: DesignPoint) -> bool:
        row = table.rows.get(point.key)
        return row is not None and not (retry_failed and row.get("status") != "ok")

    todo = [d for d in spec.designs if not finished(d)]
    skipped = len(spec.designs) - len(todo)
    if on_start is not None:
        on_start(len(todo), skipped)
    try:
        for point in (d for d in todo if d.invalid):
            table.add(failed_row(point, INVALID, point.invalid, sweep_id))
            if on_done is not None:
                on_done(table.rows[point.key])
        runnable = [d for d in todo if not d.invalid]

        def done(i: int, row: dict[str, Any]) -> None:
            table.add(row)
            if on_done is not None:
                on_done(row)

        def lost(i: int, exc: BaseException) -> dict[str, Any]:
            return failed_row(runnable[i], type(exc).__name__, str(exc), sweep_id)

        engine.map(
            run_design,
            [(d, spec.time_limit_s, sweep_id) for d in runnable],
            on_done=done,
            failure=lost,
            name="design",
        )
    finally:
        table.close()
    statuses: dict[str, int] = {}
    for row in table.rows.values():
        statuses[str(row["status"])] = statuses.get(str(row["status"]), 0) + 1
    failed = [
        {"key": k, "status": str(r["status"]), "error": str(r.get("error") or "")[:500]}
        for k, r in table.rows.items()
        if r["status"] != "ok"
    ]
    return SweepResult(
        Path(out), len(spec.designs), skipped, len(todo), statuses, failed, sweep_id, time.perf_counter() - t0
    )
