"""`vcyto flow`: the steady flow with the IDT off and on, where the injection streamline leaves."""

from __future__ import annotations

from ..options import scenario_from, scenario_options
from .common import UsageError, emit, output_options, output_path, stderr_progress


def add_command(commands):
    flow = commands.add_parser("flow",
                               help="steady flow with the IDT off and on; where the injection streamline leaves")
    scenario_options(flow)
    flow.add_argument("--png", metavar="FILE", help="save the speed field with the streamlines as a PNG")
    flow.add_argument("--calibrate-streaming", action="store_true",
                      help="find the streaming force that deflects the streamline as far as the paper's jet")
    output_options(flow)
    flow.set_defaults(handler=command_flow)


def command_flow(args):
    from ..studies import flowtool
    scenario = scenario_from(args)
    if args.calibrate_streaming and args.png:
        raise UsageError("--png: --calibrate-streaming draws no figure; drop --png (or run vcyto flow without "
                         "--calibrate-streaming for the streamlines' figure)")
    png = output_path(args.png)
    progress = stderr_progress(args.quiet or args.json)
    if args.calibrate_streaming:
        result = flowtool.calibrate(scenario, progress)
        emit(args, result, [f"streaming force {result['streaming_force']:.4g} N/m^3 puts the injection streamline "
                             f"at y = {result['exit_y_um']:.1f} um ({result['iterations']} bisection steps, "
                             f"{result['wall_time_s']:.0f} s); set it with --set saw.streaming_force=..."])
        return
    paths, flows, solver = flowtool.solve_paths(scenario, progress)
    result = flowtool.summary(scenario, paths, solver)
    if png:
        flowtool.save_png(str(png), scenario, solver, flows, paths)
        result["png"] = str(png)
    lines = flowtool.report_lines(result) + ([f"  saved {png}"] if png else [])
    emit(args, result, lines)
