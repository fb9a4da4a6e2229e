"""`vcyto bench sort`: long sorting runs on the ``rom`` plant, with and without recording, at growing lengths.

Each run is a fresh `vcyto stream` process (Poisson arrivals with the inlet's dead time, the shipped
controller in purity mode), so its peak memory is its own: the summary gives the peak resident memory after
the set-up and at the end. Reported per length: events, loop wall (run minus set-up), device time, the
loop's cost per event, the ratio of loop walls between lengths (linear cost: ratio of lengths), peak memory,
the sort report, and the sizes of the files written.

Checks (``checks``): every admitted cell has its row in the per-cell table and the summary's counts equal those
recomputed from the table (``vcyto.sortreport.statistics_of``); the peak memory of the longest run is within
``MEMORY_GROWTH`` of the shortest's when they differ tenfold or more; and the targets: at most ``TARGET_S_PER_1E5``
s of loop wall per 10^5 events with MCAP + Rerun, a peak of at most ``TARGET_PEAK_MB``.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

MEMORY_GROWTH = 0.10          # peak of the longest run over the shortest's, minus 1 (runs 10x apart or more)
TARGET_S_PER_1E5 = 20.0       # loop wall per 10^5 events with MCAP + Rerun (5x real time at 1,000 events/s)
TARGET_PEAK_MB = 1024.0
# counts the table's rows reproduce exactly (offered, rejected and yield also count the cells turned away)
_RECOUNTED = ("cells", "events", "sorted", "purity", "purity_of_sorting", "abort_rate", "aborts", "co_deflected",
              "misclassified", "undetected", "not_injected", "outlets", "outcomes")


def bench_sort(counts=(1_000, 10_000), rate: float = 2000.0, record: bool = True, rerun: bool = True,
               seed: int = 3, progress=lambda message: None) -> dict:
    """Run one stream per count (cells offered at ``rate``/s; the dead time admits about rate / (1 + rate d))."""
    rows = []
    for count in counts:
        progress(f"{count} cells offered at {rate:g}/s, recording {'on' if record else 'off'}")
        with tempfile.TemporaryDirectory() as directory:
            args = [sys.executable, "-m", "vcyto.cli", "stream", "--model", "rom", "--count", str(count),
                    "--rate", str(rate), "--arrivals", "poisson", "--mix", "RBC:0.9,melanoma:0.1", "--seed", str(seed),
                    "--json", "--quiet", "--output", directory if record else ""]
            if not (record and rerun):
                args.append("--no-viewer")
            else:
                args += ["--save", str(Path(directory) / "run.rrd")]
            done = subprocess.run(args, capture_output=True, text=True)
            # the process's peak, files included (the summary's is taken before the files are written): the
            # largest of the children so far, so runs in increasing length give each its own
            process_peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
            if done.returncode != 0:
                raise RuntimeError(f"the {count}-cell stream failed: {done.stderr.strip()}")
            result = json.loads(done.stdout)
            sizes = {path.suffix: path.stat().st_size for path in Path(directory).iterdir()}
            table_check = _table_check(result) if record else None
        result["memory_mb"]["process_peak"] = process_peak
        loop = result["wall_time_s"] - result["setup_time_s"]
        stats = result["statistics"]
        rows.append({"offered": count, "events": stats["events"], "device_time_s": result["simulated_time_ms"] * 1e-3,
                     "loop_wall_s": loop, "setup_s": result["setup_time_s"], "steps": result["steps"],
                     "loop_us_per_event": loop / max(1, stats["events"]) * 1e6,
                     "real_time_factor": result["simulated_time_ms"] * 1e-3 / loop,
                     "memory_mb": result["memory_mb"], "file_bytes": sizes, "purity": stats["purity"],
                     "yield": stats["yield"], "yield_estimate": (result["yield_estimate"] or {}).get("yield"),
                     "aborts": stats["aborts"], "co_deflected": stats["co_deflected"],
                     "misclassified": stats["misclassified"], "rare_cell": stats.get("rare_cell"),
                     "table": table_check})
    for row in rows[1:]:
        row["loop_ratio_to_first"] = row["loop_wall_s"] / rows[0]["loop_wall_s"]
        row["events_ratio_to_first"] = row["events"] / rows[0]["events"]
    result = {"model": "rom", "rate_offered_per_s": rate, "record": record, "rerun": record and rerun, "seed": seed,
              "rows": rows}
    result["checks"] = checks(result)
    return result


def _table_check(result: dict) -> dict:
    """Rows of the per-cell table against the cells counted, and the counts recomputed from it."""
    from ..celltable import records
    from ..sortreport import Tally
    tally = Tally()
    for record in records(result["cell_table"]["path"]):       # a row group at a time
        tally.add(record)
    recounted = tally.statistics(result["simulated_time_ms"] * 1e-3)
    stats = result["statistics"]
    differ = [key for key in _RECOUNTED if recounted[key] != stats[key]]
    return {"rows": result["cell_table"]["rows"], "cells": stats["cells"], "differ": differ,
            "holds": result["cell_table"]["rows"] == stats["cells"] and not differ}


def checks(result: dict) -> list[dict]:
    """The bench's verdicts (module docstring): name, figure, limit, whether it holds."""
    rows, verdicts = result["rows"], []
    for row in rows:
        if row.get("table") is not None:
            verdicts.append({"name": f"{row['offered']} offered: every cell's row in the table, counts equal",
                             "figure": row["table"]["rows"], "limit": row["table"]["cells"],
                             "holds": row["table"]["holds"]})
        peak = row["memory_mb"].get("process_peak")
        if peak is not None:
            verdicts.append({"name": f"{row['offered']} offered: peak memory (MB)", "figure": peak,
                             "limit": TARGET_PEAK_MB, "holds": peak <= TARGET_PEAK_MB})
        if result["record"] and result["rerun"] and row["events"] >= 10_000:
            per = row["loop_wall_s"] / row["events"] * 1e5
            verdicts.append({"name": f"{row['offered']} offered: loop wall per 10^5 events, MCAP + Rerun (s)",
                             "figure": per, "limit": TARGET_S_PER_1E5, "holds": per <= TARGET_S_PER_1E5})
    first, last = rows[0], rows[-1]
    peaks = first["memory_mb"].get("process_peak"), last["memory_mb"].get("process_peak")
    if last["offered"] >= 10 * first["offered"] and None not in peaks:
        growth = peaks[1] / peaks[0] - 1
        verdicts.append({"name": f"peak memory growth from {first['offered']} to {last['offered']} offered",
                         "figure": growth, "limit": MEMORY_GROWTH, "holds": growth <= MEMORY_GROWTH})
    return verdicts


def _megabytes(memory: dict) -> str:
    """Peak resident MB at the loop's end / with the report built."""
    values = [memory.get(key) for key in ("after_loop", "process_peak")]
    return " / ".join("-" if value is None else f"{value:.0f}" for value in values)


def report_lines(result: dict) -> list[str]:
    recording = ("MCAP + Rerun .rrd" if result["rerun"] else "MCAP") if result["record"] else "no recording"
    lines = [f"rom, Poisson offered at {result['rate_offered_per_s']:g}/s, {recording}",
             f"{'offered':>8} {'events':>7} {'device s':>9} {'loop s':>8} {'us/event':>9} {'x real time':>11} "
             f"{'loop ratio':>10} {'MB loop/end':>11} {'purity':>7} {'yield (est.)':>14} files"]
    for row in result["rows"]:
        ratio = (f"{row['loop_ratio_to_first']:.1f} / {row['events_ratio_to_first']:.1f}"
                 if "loop_ratio_to_first" in row else "-")
        files = ", ".join(f"{suffix} {size / 1e6:.1f} MB" for suffix, size in sorted(row["file_bytes"].items()))
        lines.append(f"{row['offered']:>8} {row['events']:>7} {row['device_time_s']:>9.2f} {row['loop_wall_s']:>8.2f} "
                     f"{row['loop_us_per_event']:>9.0f} {row['real_time_factor']:>11.2f} {ratio:>10} "
                     f"{_megabytes(row['memory_mb']):>11} {100 * row['purity']:>6.1f}% "
                     f"{100 * row['yield']:>5.1f}% ({100 * (row['yield_estimate'] or float('nan')):.1f}%) {files}")
    lines.append("loop ratio: loop wall over the first row's / events over the first row's (linear cost: equal); "
                 "MB: peak resident memory at the loop's end / with the report and files written")
    for verdict in result.get("checks", ()):
        figure, limit = verdict["figure"], verdict["limit"]
        mark = "ok    " if verdict["holds"] else "MISSED"
        lines.append(f"  {mark} {verdict['name']}: {figure:.4g} (limit {limit:.4g})")
    return lines
