"""`vcyto paper`: the paper's scenario 1 (RBC, IDT off) or 2 (melanoma, IDT on)."""

from __future__ import annotations

from ..arguments import Quantity
from ..options import check_run_time, scenario_from, scenario_options, tolerance_options
from ..restored import restored_warning
from .common import (
    EXIT_SIGINT,
    EXIT_SIGTERM,
    RunStopped,
    emit,
    output_options,
    output_path,
    removed_unless_written,
    signals_seen,
)


def add_command(commands):
    paper = commands.add_parser("paper", help="run the paper's scenario 1 (RBC, IDT off) or 2 (melanoma, IDT on)")
    paper.add_argument("number", type=int, choices=(1, 2),
                       help="1: RBC, IDT off, dt 2.5 us; 2: melanoma, IDT on, dt 25 us")
    scenario_options(paper)
    tolerance_options(paper)
    paper.add_argument("--png", metavar="FILE",
                       help="where to save the path over the flow (default recordings/paperN.png)")
    paper.add_argument("--no-png", action="store_true", help="do not save a PNG")
    paper.add_argument("--allow-long", action="store_true", help="run even if estimated to take more than 24 h")
    paper.add_argument("--max-time", type=Quantity("time", "ms", low=0, low_open=True, high=3600.0), default="20",
                       metavar="TIME", help="give up (outlet 'lost') after this much simulated time (ms; default 20)")
    output_options(paper)
    paper.set_defaults(handler=command_paper)


def command_paper(args):
    from ..progress import Progress
    from ..recording import runfiles
    from ..studies.painter import Painter, core_idle
    # the PNG's helper process starts first where a core is idle: it imports matplotlib while this one imports the
    # plant and runs (vcyto.studies.painter); leaving this block (an error, Ctrl-C) stops it
    with Painter(start=not args.no_png and core_idle()) as painter:
        from ..studies import paper
        # with --tolerance the finest level is --dt or 2.5 us, the step the tolerance is stated against
        scenario = paper.paper_scenario(args.number, scenario_from(args, membrane="paper"),
                                        dt_given=args.dt is not None or args.tolerance is not None)
        check_run_time(args, scenario, args.max_time, "--dt/--max-time")
        png = None if args.no_png else output_path(args.png or f"recordings/paper{args.number}.png",
                                                   default=not args.png)
        progress = Progress(quiet=args.quiet or args.json)
        signals_seen.clear()
        with removed_unless_written(png), runfiles.signals_as_interrupt(signals_seen):
            try:
                result = paper.run_paper(args.number, scenario, args.max_time, progress)
            except paper.Interrupted as stop:
                progress.close()
                signal_name = signals_seen.get("last", "SIGINT")
                runfiles.say(f"interrupted by {signal_name} at step {stop.step} (t = {stop.time * 1e3:.3f} ms); an "
                             "unfinished paper run saves nothing")
                raise RunStopped(EXIT_SIGTERM if signal_name == "SIGTERM" else EXIT_SIGINT) from None
            finally:
                progress.close()
            lines = paper.report_lines(result)
            if png:
                paper.save_png(str(png), result, scenario, painter)
                result["png"] = str(png)
                lines.append(f"  saved {png}")
    if (warning := restored_warning(result["area_restored"])) is not None:
        runfiles.say(warning)
    emit(args, paper.public(result), lines)
