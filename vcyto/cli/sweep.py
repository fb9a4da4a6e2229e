"""`vcyto sweep`: a parameter sweep of the closed loop, locally or on a Dask cluster (``vcyto.sweep``)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from .. import outputs
from ..arguments import Integer
from ..options import wire_controller, wire_options
from ..outputs import strict_json
from .common import SMALL_FILES_BYTES, UsageError, emit, output_directory, output_options, signals_seen


def add_command(commands):
    sweep = commands.add_parser("sweep", help="a parameter sweep of the closed loop, locally or on a Dask cluster")
    sweep.add_argument("spec", metavar="SPEC", help="sweep spec (TOML): [base] run, [parameters], [sweep] metrics")
    sweep.add_argument("--output", metavar="DIR",
                       help="where results.csv, summary.png and sweep.json go; a re-run skips the points already "
                            "there (default recordings/sweeps/SPEC)")
    sweep.add_argument("--workers", type=Integer(low=1, high=1024), metavar="N",
                       help="worker processes (default: the CPU count)")
    sweep.add_argument("--scheduler", metavar="ADDRESS", help="run on the Dask scheduler at ADDRESS (e.g. "
                                                              "tcp://host:8786), or 'local' to start a LocalCluster")
    sweep.add_argument("--retry-failed", action="store_true", help="run the points recorded as failed again")
    sweep.add_argument("--keep-old-rows", action="store_true",
                       help="reuse rows computed by another vcyto version for the same inputs (by default an "
                            "upgrade recomputes every point; the summary counts the rows kept)")
    sweep.add_argument("--chunk", type=Integer(low=1), default="8", metavar="N",
                       help="points sharing a plant go to one worker N at a time (default 8)")
    wire_options(sweep, "every point's")
    output_options(sweep)
    sweep.set_defaults(handler=command_sweep)


def command_sweep(args):
    from .. import sweep
    from ..progress import Progress
    from ..recording import runfiles
    try:
        if args.scheduler is not None:
            sweep.check_scheduler(args.scheduler)
        spec = sweep.load_sweep(args.spec, wire_controller(args))
    except sweep.SweepError as error:
        raise UsageError(str(error)) from None
    output = output_directory(args.output or str(Path("recordings") / "sweeps" / Path(args.spec).stem),
                              min_free=SMALL_FILES_BYTES)
    workers = args.workers or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
    progress = Progress(quiet=args.quiet or args.json)
    try:
        with runfiles.signals_as_interrupt(signals_seen), \
                sweep.executor(args.scheduler, workers) as (pool, slots, where):
            progress.note(f"{len(spec.points)} points on {where}; results in {output / sweep.RESULTS}")
            result = sweep.run_sweep(spec, output, pool, slots, progress, retry_failed=args.retry_failed,
                                     chunk=args.chunk, keep_old_rows=args.keep_old_rows, where=where)
    except sweep.SweepError as error:
        raise UsageError(str(error)) from None
    except KeyboardInterrupt:
        progress.close()
        print(f"vcyto: interrupted; finished points are in {output / sweep.RESULTS}; the same command completes "
              "the sweep", file=sys.stderr)
        raise
    finally:
        progress.close()
    if result["ran"]:                   # this run computed points: its entry in the record names where
        result["executor"] = result["runs"][-1]["executor"] = where
    else:                               # nothing ran: the record keeps the executor of the run that computed them
        result["executor"] = next((run["executor"] for run in reversed(result["runs"]) if "executor" in run), None)
    if result["ok"]:
        sweep.save_plot(output / sweep.FIGURE, spec, result["rows"])
        result["files"]["figure"] = str(output / sweep.FIGURE)
    result["files"]["summary"] = str(output / sweep.SUMMARY)
    outputs.write_into(output / sweep.SUMMARY, strict_json(result) + "\n")
    emit(args, result, sweep.report_lines(result))
