"""`vcyto tradeoff`: speed against accuracy of the plant models on fixed scenes (table, CSV, Pareto plot)."""

from __future__ import annotations

import dataclasses

from .. import outputs, units
from ..options import scenario_from, scenario_options
from ..recording import runfiles
from .common import (
    SMALL_FILES_BYTES,
    UsageError,
    emit,
    non_negative_list,
    output_directory,
    output_options,
    plain_number,
    positive_list,
    remove_if_empty,
    signals_seen,
)


def add_command(commands):
    tradeoff_parser = commands.add_parser("tradeoff", help="speed against accuracy of the plant models on fixed scenes "
                                                           "(table, CSV, Pareto plot)")
    tradeoff_parser.add_argument("--fast", action="store_true",
                                 help="the reduced set (coarse mesh, reference FE-IB at h = 6.67 um; a few minutes)")
    tradeoff_parser.add_argument("--output", default="recordings/tradeoff", metavar="DIR",
                                 help="where tradeoff.md, tradeoff.csv and tradeoff.png go "
                                      "(default recordings/tradeoff)")
    tradeoff_parser.add_argument("--coupling", metavar="LIST",
                                 help="add an auto level for each coupling factor, e.g. 2,2.5 (the default auto "
                                      "level has coupling 3)")
    tradeoff_parser.add_argument("--stiff-capillary", metavar="LIST",
                                 help="add an auto level for each stiff-cell capillary number, e.g. 0,100 (0 turns the "
                                      "stiff-cell rule off; the default auto level has 100)")
    tradeoff_parser.add_argument("--pair-gap", metavar="MS",
                                 help="add a close-pair scene for each gap (ms, below 2) between the melanoma and the "
                                      "RBC, e.g. 0.5,1.0 (the fixed scene's gap is 0.25)")
    tradeoff_parser.add_argument("--lone-rbc", metavar="MS",
                                 help="add a scene for each time (ms, below 2) with an RBC alone injected then under "
                                      "the pair scenes' 0.9-2.1 ms pulse, e.g. 0.565 (the pair's RBC without the "
                                      "melanoma)")
    scenario_options(tradeoff_parser)
    output_options(tradeoff_parser)
    tradeoff_parser.set_defaults(handler=command_tradeoff)


def _times_before_pulse_end(text: str, option: str, example: str, what: str) -> list[float]:
    """Times (bare numbers in ms; returned in s) for the extra tradeoff scenes: positive and below 2 ms."""
    times = positive_list(text, option, example, lambda part: units.parse_quantity(part, "time", "ms", option))
    if max(times) >= 2e-3:
        raise UsageError(f"{option}: takes {what} below 2 ms (the scenes' pulse ends at 2.1 ms; got {text})")
    return times


def command_tradeoff(args):
    from ..progress import Progress
    from ..studies import tradeoff
    scenario = scenario_from(args)
    made = []
    output = output_directory(args.output, min_free=SMALL_FILES_BYTES, made=made)
    progress = Progress(quiet=args.quiet or args.json)
    ladder, scenes = tradeoff.FAST_LADDER if args.fast else tradeoff.LADDER, tradeoff.SCENES
    base = next(level for level in ladder if level.model == "auto" and level.window is None)
    if args.coupling:
        values = positive_list(args.coupling, "--coupling", "2,2.5,3", plain_number("--coupling"))
        ladder += tuple(dataclasses.replace(base, coupling=value) for value in values)
    if args.stiff_capillary:
        values = non_negative_list(args.stiff_capillary, "--stiff-capillary", "0,100")
        ladder += tuple(dataclasses.replace(base, stiff=value) for value in values)
    if args.pair_gap:
        gaps = _times_before_pulse_end(args.pair_gap, "--pair-gap", "0.5,1.0", "gaps")
        scenes += tuple(tradeoff.pair_scene(gap) for gap in gaps)
    if args.lone_rbc:
        starts = _times_before_pulse_end(args.lone_rbc, "--lone-rbc", "0.5,0.565", "injection times")
        scenes += tuple(tradeoff.lone_rbc_scene(start) for start in starts)
    try:
        result = tradeoff.tradeoff(scenario, ladder, scenes, progress=progress)
    finally:
        progress.close()
    lines = tradeoff.table_lines(result)
    if result["interrupted"]:           # the finished rows are printed, marked PARTIAL; no file claims a whole table
        remove_if_empty(made)
        emit(args, result, lines)
        raise KeyboardInterrupt         # the exit is an interrupt's (130)
    interrupted = False
    if output is not None:
        # Ctrl-C or SIGTERM while the files are written waits for them: the table is finished
        with runfiles.interrupts_deferred(signals_seen) as saving:
            if (output / "tradeoff.md").exists():          # a run never overwrites another's files
                output = outputs.unique_directory(output)
            result["files"] = tradeoff.save(result, output)
        interrupted = saving.pending
        lines.append(f"saved {', '.join(result['files'].values())}")
    emit(args, result, lines)
    if interrupted:
        raise KeyboardInterrupt         # the files are whole and listed; the exit is an interrupt's (130)
