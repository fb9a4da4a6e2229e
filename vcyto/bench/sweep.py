"""`vcyto bench sweep`: one sweep on local pools of several sizes (1 and 2 workers by default): whole-sweep
wall times and the speed-up."""

from __future__ import annotations

import statistics
import time


def bench_sweep(spec_path, worker_counts=(1, 2), repeats: int = 1, progress=None) -> dict:
    """The same sweep on a local pool of each size in ``worker_counts``, ``repeats`` times (sizes interleaved, so
    machine load falls on all alike); whole-sweep wall times (pool start, imports and plant builds included) and
    the speed-up over the first size. Each run starts from an empty table in a temporary directory."""
    import os
    import tempfile
    from pathlib import Path

    from .. import sweep
    plan = sweep.load_sweep(spec_path)
    walls = {workers: [] for workers in worker_counts}
    point_seconds = {workers: [] for workers in worker_counts}
    for repeat in range(repeats):
        for workers in worker_counts:
            if progress:
                progress.note(f"{len(plan.points)} points on {workers} worker(s) ({repeat + 1}/{repeats})")
            with tempfile.TemporaryDirectory() as directory:
                started = time.perf_counter()
                with sweep.executor(None, workers) as (pool, slots, _):
                    result = sweep.run_sweep(plan, Path(directory), pool, slots)
                walls[workers].append(time.perf_counter() - started)
            if result["failed"]:
                raise RuntimeError(f"{result['failed']} point(s) of the benchmark sweep failed")
            point_seconds[workers].append(sum(row["wall_time_s"] for row in result["rows"]))
    medians = {workers: statistics.median(times) for workers, times in walls.items()}
    first = worker_counts[0]
    return {"spec": str(spec_path), "points": len(plan.points),
            "models": sorted({p.settings.model for p in plan.points}),
            "repeats": repeats, "wall_s": walls, "median_wall_s": medians, "point_work_s": point_seconds,
            "speed_up": {workers: medians[first] / medians[workers] for workers in worker_counts},
            "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()}


def sweep_lines(result: dict) -> list[str]:
    first = next(iter(result["median_wall_s"]))
    lines = [f"{result['points']} points of {result['spec']} (model {', '.join(result['models'])}), "
             f"{result['repeats']} run(s) per pool size, {result['cpus']} CPUs; whole sweep, pool start included:"]
    for workers, median in result["median_wall_s"].items():
        runs = ", ".join(f"{t:.1f}" for t in result["wall_s"][workers])
        work = statistics.median(result["point_work_s"][workers])
        lines.append(f"  {workers} worker(s): median {median:.1f} s (runs {runs} s; points' own time {work:.1f} s), "
                     f"speed-up {result['speed_up'][workers]:.2f}x over {first}")
    return lines
