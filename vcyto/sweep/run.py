"""Running a sweep: the points not yet in the table, in chunks sharing a plant, on any concurrent.futures
executor; rows appended as chunks finish, a progress bar, and the summary."""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from concurrent.futures import as_completed
from pathlib import Path

from .model import Point, Sweep, float_or_nan, one_line
from .table import RESULTS, ResultTable
from .worker import evaluate

FAILURES_SHOWN = 5


def run_sweep(sweep: Sweep, output: Path, executor, slots: int = 1, progress=None, retry_failed: bool = False,
              simulator=None, chunk: int = 8, keep_old_rows: bool = False) -> dict:
    """Run the points of ``sweep`` not yet in ``output/results.csv`` on ``executor`` (``slots`` workers);
    a JSON-ready summary. Points sharing a plant go in chunks of up to ``chunk`` points, no more than an even
    share per worker. ``simulator(scenario, settings) -> run_stream result`` replaces the closed loop (tests).
    A row counts for a point when its id matches: same inputs and same code (vcyto version, schema); with
    ``keep_old_rows`` an ok row of the same inputs computed by other code counts too (the summary says how many)."""
    started = time.perf_counter()
    table = ResultTable(output / RESULTS, sweep.columns)
    previous = table.load()
    if retry_failed and any(row["status"] != "ok" for row in previous.values()):
        previous = {key: row for key, row in previous.items() if row["status"] == "ok"}
        table.rewrite(previous.values())
    rows = dict(previous)
    kept = _old_rows(sweep, previous) if keep_old_rows else {}
    rows.update(kept)
    todo = [point for point in sweep.points if point.id not in rows]
    tracker = _Tracker(len(sweep.points), len(sweep.points) - len(todo), progress)
    futures = {executor.submit(evaluate, [(p.scenario, p.settings) for p in chunk_points], sweep.metrics, simulator):
               chunk_points for chunk_points in _chunks(todo, slots, chunk)}
    try:                                 # on Ctrl-C the executor's owner (``executor``) stops the workers
        for future in as_completed(futures):
            outcomes = zip(futures[future], _outcomes(future, futures))
            finished = [_row(point, outcome, sweep.columns) for point, outcome in outcomes]
            table.append(finished)
            rows.update((row["point"], row) for row in finished)
            tracker.finished(finished)
    finally:
        tracker.close()
    order = {point.id: index for index, point in enumerate(sweep.points)}
    table.rewrite(sorted((row for key, row in rows.items() if key not in kept),
                         key=lambda row: order.get(row["point"], len(order))))
    summary = _summary(sweep, output, {key: row for key, row in rows.items()}, len(todo), table.repaired,
                       time.perf_counter() - started)
    summary["kept_old_rows"] = len(kept)
    summary["stale_rows"] -= len(kept)
    return summary


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


def _outcomes(future, futures) -> list[dict]:
    try:
        return future.result()
    except Exception as error:  # noqa: BLE001 - the worker died (out of memory, killed): the chunk failed
        message = one_line(f"the worker running this point died: {type(error).__name__}: {error}")
        return [{"status": "failed", "error": message}] * len(futures[future])


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
        self.started, self.initial = time.perf_counter(), done
        if progress and done:
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
        if self.progress:
            self.progress.interval = 0.0
            self.progress.update(self.bar())
            self.progress.close()


def _summary(sweep: Sweep, output: Path, rows: dict, ran: int, repaired: int, wall: float) -> dict:
    current = [{**rows[point.id], **dict(point.values)} for point in sweep.points if point.id in rows]
    ok = [row for row in current if row["status"] == "ok"]
    scored = [row for row in ok if math.isfinite(float_or_nan(row.get(sweep.plot)))]
    best = max(scored, key=lambda row: float_or_nan(row[sweep.plot]), default=None)
    return {"spec": sweep.path, "sampling": sweep.sampling, "parameters": [p.name for p in sweep.parameters],
            "metrics": list(sweep.metrics), "plot_metric": sweep.plot, "points": len(sweep.points),
            "ok": len(ok), "failed": sum(row["status"] == "failed" for row in current),
            "truncated": sum(row["status"] == "truncated" for row in current), "ran": ran,
            "done_before": len(sweep.points) - ran,
            "repaired_rows": repaired, "stale_rows": len(rows) - len(current), "wall_time_s": wall,
            "highest": best,
            "files": {"table": str(output / RESULTS)}, "rows": current}


def report_lines(result: dict) -> list[str]:
    truncated = f"{result['truncated']} truncated" + (" (not results: raise max_time or drop it)"
                                                      if result["truncated"] else "")
    lines = [f"{result['points']} points: {result['ok']} ok, {result['failed']} failed, {truncated} "
             f"({result['ran']} run now, {result['done_before']} done before) in {result['wall_time_s']:.1f} s"]
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
