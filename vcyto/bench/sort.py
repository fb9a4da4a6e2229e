"""`vcyto bench sort`: long sorting runs on the ``rom`` plant, with and without recording, at growing lengths.

Each run is a fresh `vcyto stream` process (Poisson arrivals with the inlet's dead time, the shipped
controller in purity mode), so its peak memory is its own: the summary gives the peak resident memory after
the set-up and at the end. Reported per length: events, loop wall (run minus set-up), device time, the
loop's cost per event, the ratio of loop walls between lengths (linear cost: ratio of lengths), peak memory,
the sort report, and the sizes of the files written.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path


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
            if done.returncode != 0:
                raise RuntimeError(f"the {count}-cell stream failed: {done.stderr.strip()}")
            result = json.loads(done.stdout)
            sizes = {path.suffix: path.stat().st_size for path in Path(directory).iterdir()}
        loop = result["wall_time_s"] - result["setup_time_s"]
        stats = result["statistics"]
        rows.append({"offered": count, "events": stats["events"], "device_time_s": result["simulated_time_ms"] * 1e-3,
                     "loop_wall_s": loop, "setup_s": result["setup_time_s"], "steps": result["steps"],
                     "loop_us_per_event": loop / max(1, stats["events"]) * 1e6,
                     "real_time_factor": result["simulated_time_ms"] * 1e-3 / loop,
                     "memory_mb": result["memory_mb"], "file_bytes": sizes, "purity": stats["purity"],
                     "yield": stats["yield"], "yield_estimate": (result["yield_estimate"] or {}).get("yield"),
                     "aborts": stats["aborts"], "co_deflected": stats["co_deflected"],
                     "misclassified": stats["misclassified"]})
    for row in rows[1:]:
        row["loop_ratio_to_first"] = row["loop_wall_s"] / rows[0]["loop_wall_s"]
        row["events_ratio_to_first"] = row["events"] / rows[0]["events"]
    return {"model": "rom", "rate_offered_per_s": rate, "record": record, "rerun": record and rerun, "seed": seed,
            "rows": rows}


def _megabytes(memory: dict) -> str:
    """Peak resident MB at the loop's end / with the report built."""
    values = [memory.get(key) for key in ("after_loop", "peak")]
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
                 "MB: peak resident memory at the loop's end / with the per-cell report built")
    return lines
