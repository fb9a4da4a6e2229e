"""Running a sweep: the points not yet in the table, in chunks sharing a plant, on any concurrent.futures
executor; rows appended as chunks finish, a progress bar, and the summary (with the record of the runs that
computed the table, carried over from the ``sweep.json`` of the earlier runs).

Interrupts: the loop waits for chunks ``POLL_S`` at a time, so a SIGINT or SIGTERM takes effect within that
even when the operating system hands the signal to another thread than the one waiting (the Python handler
only runs on the main thread, once it wakes); no chunk is submitted after it, and a chunk's rows are appended
whole (``runfiles.interrupts_deferred``), then the interrupt goes on. Stopping the workers is the executor's
(``executors.executor``)."""

from __future__ import annotations

import json
import math
import time
from collections import OrderedDict
from concurrent.futures import FIRST_COMPLETED, BrokenExecutor, Future, wait
from datetime import datetime, timezone
from pathlib import Path

from ..outputs import strict_json, write_into
from .model import Point, Sweep, float_or_nan, one_line
from .table import RESULTS, SUMMARY, ResultTable
from .worker import evaluate

FAILURES_SHOWN = 5
POLL_S = 0.25                   # the longest the loop waits for a chunk before it looks at signals again
CHUNKS_PER_SLOT = 2             # chunks submitted ahead per worker slot: one running, one queued


def run_sweep(sweep: Sweep, output: Path, executor, slots: int = 1, progress=None, retry_failed: bool = False,
              simulator=None, chunk: int = 8, keep_old_rows: bool = False, where: str | None = None) -> dict:
    """Run the points of ``sweep`` not yet in ``output/results.csv`` on ``executor`` (``slots`` workers);
    a JSON-ready summary. Points sharing a plant go in chunks of up to ``chunk`` points, no more than an even
    share per worker. ``simulator(scenario, settings) -> run_stream result`` replaces the closed loop (tests).
    A row counts for a point when its id matches: same inputs and same code (vcyto version, schema); with
    ``keep_old_rows`` an ok row of the same inputs computed by other code counts too (the summary says how many).
    ``where`` names the executor in the record of this run. An interrupted run that finished points records itself in
    ``sweep.json`` (status "interrupted", its rows so far), so the run that completes the sweep counts its time."""
    started, began = time.perf_counter(), datetime.now(timezone.utc).isoformat(timespec="seconds")
    earlier = _earlier_runs(output / SUMMARY)
    table = ResultTable(output / RESULTS, sweep.columns)
    previous = table.load()
    if retry_failed and any(row["status"] != "ok" for row in previous.values()):
        previous = {key: row for key, row in previous.items() if row["status"] == "ok"}
        table.rewrite(previous.values())
    rows = dict(previous)
    kept = _old_rows(sweep, previous) if keep_old_rows else {}
    rows.update(kept)
    todo = [point for point in sweep.points if point.id not in rows]
    if sweep.points and len(todo) == len(sweep.points) and earlier:
        # none of the recorded runs' rows is here (the table was removed, or another spec used the directory):
        # their record goes now, so that a later run does not count them even if this one is interrupted
        (output / SUMMARY).unlink(missing_ok=True)
        earlier = []
    tracker = _Tracker(len(sweep.points), len(sweep.points) - len(todo), progress)
    try:                                 # on an interrupt the executor's owner (``executor``) stops the workers
        _run_chunks(executor, _chunks(todo, slots, chunk), max(1, slots) * CHUNKS_PER_SLOT, sweep, simulator,
                    table, rows, tracker)
    except KeyboardInterrupt:
        tracker.close()
        tracker.interrupted(output / RESULTS)
        ran = tracker.done - tracker.initial
        if ran:
            run = {"started": began, "ran": ran, "wall_time_s": time.perf_counter() - started, "workers": slots,
                   "interrupted": True, **({"executor": where} if where else {})}
            summary = _summary(sweep, output, rows, ran, table.repaired, run["wall_time_s"], earlier + [run])
            summary.update(status="interrupted", reason=f"interrupted after {ran} of the {len(todo)} points it had "
                                                        "to run; the same command completes the sweep",
                           executor=where, kept_old_rows=len(kept), stale_rows=summary["stale_rows"] - len(kept))
            summary["files"]["summary"] = str(output / SUMMARY)
            try:
                write_into(output / SUMMARY, strict_json(summary) + "\n")
            except OSError:             # the rows are in the table; only the record of this run's time is lost
                pass
        raise
    finally:
        tracker.close()
    order = {point.id: index for index, point in enumerate(sweep.points)}
    table.rewrite(sorted((row for key, row in rows.items() if key not in kept),
                         key=lambda row: order.get(row["point"], len(order))))
    wall = time.perf_counter() - started
    runs = earlier                       # rows from before: their runs count too
    if todo:
        runs = runs + [{"started": began, "ran": len(todo), "wall_time_s": wall, "workers": slots}]
    summary = _summary(sweep, output, {key: row for key, row in rows.items()}, len(todo), table.repaired, wall,
                       runs)
    summary["kept_old_rows"] = len(kept)
    summary["stale_rows"] -= len(kept)
    summary["status"] = "complete"
    return summary


def _run_chunks(executor, chunks: list[list[Point]], ahead: int, sweep: Sweep, simulator, table: ResultTable,
                rows: dict, tracker: _Tracker):
    """Run ``chunks`` on ``executor``, at most ``ahead`` submitted at a time, appending each chunk's rows as it
    finishes. Waits ``POLL_S`` at a time: an interrupt stops the loop within that, and nothing more is
    submitted."""
    waiting = iter(chunks)
    running: dict = {}
    while True:
        while len(running) < ahead and (piece := next(waiting, None)) is not None:
            jobs = [(point.scenario, point.settings) for point in piece]
            running[_submit(executor, evaluate, jobs, sweep.metrics, simulator)] = piece
        if not running:
            return
        finished_futures, _ = wait(running, timeout=POLL_S, return_when=FIRST_COMPLETED)
        for future in finished_futures:
            piece = running.pop(future)
            outcomes = zip(piece, _outcomes(future, len(piece)))
            _append_whole(table, [_row(point, outcome, sweep.columns) for point, outcome in outcomes], rows,
                          tracker)


def _submit(executor, *call) -> Future:
    """``executor.submit(*call)``; an executor that can take no more work (a process pool whose worker died:
    ``BrokenExecutor``) gives a future holding that error, so the chunk's points become failed rows as any
    point whose worker died, and the sweep goes on to its summary."""
    try:
        return executor.submit(*call)
    except BrokenExecutor as error:
        failed: Future = Future()
        failed.set_exception(error)
        return failed


def _append_whole(table: ResultTable, finished: list[dict], rows: dict, tracker: _Tracker):
    """Append ``finished`` (a chunk's rows) to the table whole: a SIGINT or SIGTERM meanwhile waits until they
    are written, then is raised again for the handler outside (the command line's: exit 130 or 143)."""
    from ..recording.runfiles import signals_held
    with signals_held():
        table.append(finished)
        rows.update((row["point"], row) for row in finished)
        tracker.finished(finished)


def _earlier_runs(path: Path) -> list[dict]:
    """The runs recorded in the ``sweep.json`` at ``path`` (the earlier runs into the same directory): its
    ``runs`` list, or, from a vcyto that wrote none, the one run it describes; [] without a readable one."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    if not isinstance(record, dict):
        return []
    runs = record.get("runs")
    if isinstance(runs, list):
        runs = [dict(run) for run in runs if isinstance(run, dict)]
    elif isinstance(record.get("ran"), int) and record["ran"] > 0 and _seconds(record.get("wall_time_s")):
        runs = [{"ran": record["ran"], "wall_time_s": record["wall_time_s"]}]
    else:
        return []
    if runs and isinstance(record.get("ran"), int) and record["ran"] > 0 and isinstance(record.get("executor"), str):
        runs[-1].setdefault("executor", record["executor"])    # the run that wrote it computed the last entry
    return [run for run in runs if _seconds(run.get("wall_time_s"))]


def _seconds(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0


def _old_rows(sweep: Sweep, previous: dict) -> dict:
    """Rows of other code (another vcyto version or schema) whose inputs equal those of a point of ``sweep``
    that has no row of its own, by that point's id."""
    by_inputs = {row.get("inputs"): row for row in previous.values() if row.get("status") == "ok"}
    return {point.id: {**by_inputs[point.inputs], "point": point.id} for point in sweep.points
            if point.id not in previous and point.inputs in by_inputs}


def _chunks(points, slots: int, chunk: int) -> list[list[Point]]:
    """Points grouped by plant, in spec order, each group cut in pieces of at most ``chunk`` points and at most
    an even share of the group per worker (so a small sweep still uses every worker)."""
    groups = OrderedDict()
    for point in points:
        groups.setdefault(point.plant_key, []).append(point)
    pieces = []
    for group in groups.values():
        size = max(1, min(chunk, math.ceil(len(group) / max(1, slots))))
        pieces += [group[start:start + size] for start in range(0, len(group), size)]
    return pieces


def _outcomes(future, points: int) -> list[dict]:
    try:
        return future.result()
    except Exception as error:  # noqa: BLE001 - the worker died (out of memory, killed): the chunk failed
        message = one_line(f"the worker running this point died: {type(error).__name__}: {error}")
        return [{"status": "failed", "error": message}] * points


def _row(point: Point, outcome: dict, columns: list[str]) -> dict:
    """The table row of ``point``: every column in table order (None where the outcome has no value), as a
    re-run reads it back from the table."""
    from .. import __version__
    row = {"point": point.id, **dict(point.values), "seed": point.settings.seed, **outcome, "inputs": point.inputs,
           "vcyto": __version__}
    return {column: row.get(column) for column in columns}


class _Tracker:
    """The progress bar on stderr: points done of all, failures as they come, time left."""

    def __init__(self, total: int, done: int, progress):
        self.total, self.done, self.failed, self.truncated, self.progress = total, done, 0, 0, progress
        self.started, self.initial, self.closed = time.perf_counter(), done, False
        if progress and done == total:
            progress.note(f"all {total} points are already in the table: nothing to run")
        elif progress and done:
            progress.note(f"{done} of {total} points already in the table; running the other {total - done}")

    def finished(self, rows):
        self.done += len(rows)
        for row in rows:
            if row["status"] != "ok":       # truncated (not a result: max_time) or failed
                if row["status"] == "truncated":
                    self.truncated += 1
                else:
                    self.failed += 1
                shown = self.failed + self.truncated
                if self.progress and shown <= FAILURES_SHOWN:
                    more = " (further failures are only counted)" if shown == FAILURES_SHOWN else ""
                    self.progress.note(f"point {row['point']} {row['status']}: {row['error']}{more}")
        if self.progress:
            self.progress.update(self.bar())

    def bar(self, width: int = 30) -> str:
        elapsed = time.perf_counter() - self.started
        ran = self.done - self.initial
        left = elapsed / ran * (self.total - self.done) if ran else float("nan")
        filled = int(width * self.done / max(1, self.total))
        truncated = f"{self.truncated} truncated, " if self.truncated else ""
        return (f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} points, {self.failed} failed, "
                f"{truncated}{elapsed:.0f} s" + (f", ~{left:.0f} s left" if math.isfinite(left) else ""))

    def close(self):
        if self.progress and not self.closed:
            self.progress.interval = 0.0
            self.progress.update(self.bar())
            self.progress.close()
        self.closed = True

    def interrupted(self, table: Path):
        """Say what an interrupted run keeps: every row appended before the interrupt, each whole."""
        if self.progress:
            self.progress.note(f"interrupted: {table} holds {self.done} of the {self.total} points "
                               f"({self.done - self.initial} finished in this run)")


def _summary(sweep: Sweep, output: Path, rows: dict, ran: int, repaired: int, wall: float, runs: list) -> dict:
    """The JSON-ready summary. ``wall_time_s`` is the wall time of the recorded ``runs`` that computed the table
    (this one included if it computed a point; None if none is recorded); ``run_wall_time_s`` this run's."""
    current = [{**rows[point.id], **dict(point.values)} for point in sweep.points if point.id in rows]
    ok = [row for row in current if row["status"] == "ok"]
    scored = [row for row in ok if math.isfinite(float_or_nan(row.get(sweep.plot)))]
    best = max(scored, key=lambda row: float_or_nan(row[sweep.plot]), default=None)
    return {"spec": sweep.path, "sampling": sweep.sampling, "parameters": [p.name for p in sweep.parameters],
            "metrics": list(sweep.metrics), "plot_metric": sweep.plot, "points": len(sweep.points),
            "ok": len(ok), "failed": sum(row["status"] == "failed" for row in current),
            "truncated": sum(row["status"] == "truncated" for row in current), "ran": ran,
            "done_before": len(sweep.points) - ran,
            "already_done": ran == 0, "repaired_rows": repaired, "stale_rows": len(rows) - len(current),
            "wall_time_s": sum(run["wall_time_s"] for run in runs) if runs else None, "run_wall_time_s": wall,
            "runs": runs, "highest": best,
            "files": {"table": str(output / RESULTS)}, "rows": current}


def report_lines(result: dict) -> list[str]:
    truncated = f"{result['truncated']} truncated" + (" (not results: raise max_time or drop it)"
                                                      if result["truncated"] else "")
    counts = f"{result['points']} points: {result['ok']} ok, {result['failed']} failed, {truncated}"
    total, runs = result["wall_time_s"], result.get("runs", [])
    if result["ran"] == 0:
        record = f" (computed in {total:.1f} s over {_runs(len(runs))})" if total is not None else \
            " (the runs that computed them left no record)"
        lines = [f"{counts}; every point was already done: nothing ran{record}"]
    else:
        run = result.get("run_wall_time_s", total)
        earlier = f"; {total:.1f} s over {_runs(len(runs))} in all" if len(runs) > 1 else ""
        lines = [f"{counts} ({result['ran']} run now, {result['done_before']} done before) in {run:.1f} s{earlier}"]
    if result["repaired_rows"]:
        lines.append(f"  {result['repaired_rows']} torn row(s) of an interrupted run dropped; those points ran again")
    if result.get("kept_old_rows"):
        lines.append(f"  {result['kept_old_rows']} row(s) computed by another vcyto version reused (--keep-old-rows)")
    if result["stale_rows"]:
        lines.append(f"  {result['stale_rows']} row(s) of the table belong to no point of this spec or were computed "
                     "by another vcyto version (kept in the table, ignored; --keep-old-rows reuses the latter)")
    best = result["highest"]
    if best:
        where = ", ".join(f"{name}={best[name]}" for name in result["parameters"])
        lines.append(f"  highest {result['plot_metric']} = {best[result['plot_metric']]} at {where}")
    for row in [row for row in result["rows"] if row["status"] != "ok"][:5]:
        lines.append(f"  {row['status']}: {', '.join(f'{n}={row[n]}' for n in result['parameters'])}: {row['error']}")
    lines += [f"  {kind}: {path}" for kind, path in result["files"].items()]
    return lines


def _runs(count: int) -> str:
    return f"{count} run{'s' if count != 1 else ''}"
