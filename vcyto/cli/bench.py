"""`vcyto bench TARGET`: the benchmarks (``vcyto.bench``), one parser and one run per target, dispatched by
the table ``TARGETS``."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Callable, NamedTuple

from .. import arguments as limits
from ..arguments import Integer, Quantity
from ..options import check_cells_fit, length_value, parse_mix, scenario_from, scenario_options
from .common import EXIT_NUMERICAL, RunStopped, UsageError, emit, output_options, positive_list, stderr_progress

EXAMPLES = Path(__file__).resolve().parent.parent.parent / "examples"


def _tolerance_parser(targets):
    tolerance = targets.add_parser("tolerance", help="the paper scenarios with --tolerance levels against fixed "
                                   "steps: outlets, path distance, steps per level")
    scenario_options(tolerance)
    tolerance.add_argument("--tolerances", default="1um,3um", metavar="LIST", help="tolerances (default 1um,3um)")
    tolerance.add_argument("--numbers", type=int, nargs="+", choices=(1, 2), default=[1, 2], metavar="N",
                           help="paper scenarios (default 1 2)")
    output_options(tolerance)
    tolerance.set_defaults(handler=command_bench)


def _fluid_parser(targets):
    fluid = targets.add_parser("fluid", help="set-up and per-step cost of the fluid solver, per convection treatment")
    scenario_options(fluid)
    fluid.add_argument("--repeats", type=Integer(low=2, high=100_000), default="40",
                       help="timed repetitions per median of the other treatments and back-ends, >= 2 (default 40)")
    fluid.add_argument("--rounds", type=Integer(low=1, high=10_000), default="8",
                       help="rounds of 0.5 s blocks (the fastest back-solves, the default back-solve, the default "
                            "step) behind the ratios, >= 1 (default 8)")
    output_options(fluid)
    fluid.set_defaults(handler=command_bench)


def _treatments_parser(targets):
    treatments = targets.add_parser("treatments", help="how far imex, oseen and stokes steps differ from implicit ones")
    scenario_options(treatments)
    treatments.add_argument("--steps", type=Integer(low=1, high=1_000_000), default="20",
                            help="steps after switching the IDT on (default 20)")
    output_options(treatments)
    treatments.set_defaults(handler=command_bench)


def _paper_parser(targets):
    paper_bench = targets.add_parser("paper", help="a paper scenario with imex and with implicit convection: "
                                                   "outlet, exit time and path differences")
    paper_bench.add_argument("number", type=int, choices=(1, 2))
    scenario_options(paper_bench)
    output_options(paper_bench)
    paper_bench.set_defaults(handler=command_bench)


def _auto_parser(targets):
    auto_bench = targets.add_parser("auto",
                                    help="a mixed stream with --model auto and with feib: outcomes and wall time")
    auto_bench.add_argument("--count", type=Integer(low=1), default="100", help="cells (default 100)")
    auto_bench.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="500",
                            help="Poisson arrival rate, cells/s (default 500)")
    auto_bench.add_argument("--mix", default="RBC:0.8,melanoma:0.2", help="type mix (default RBC:0.8,melanoma:0.2)")
    auto_bench.add_argument("--seed", type=Integer(low=0, high=2**63 - 1), default="0", help="random seed (default 0)")
    scenario_options(auto_bench)
    output_options(auto_bench)
    auto_bench.set_defaults(handler=command_bench)


def _membrane_parser(targets):
    membrane_bench = targets.add_parser("membrane", help="the paper's literal membrane method against the conserving "
                                                         "ones (conserving, multiplier): area kept, area restored by "
                                                         "the projection, point spacing, outlets, cost per step")
    membrane_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="2",
                                help="interleaved runs per scenario (default 2)")
    scenario_options(membrane_bench)
    output_options(membrane_bench)
    membrane_bench.set_defaults(handler=command_bench)


def _recording_parser(targets):
    recording_bench = targets.add_parser("recording",
                                         help="wall-time overhead of recording (MCAP + Rerun) an FE-IB stream")
    recording_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="3",
                                 help="interleaved pairs without/with (default 3)")
    scenario_options(recording_bench)
    output_options(recording_bench)
    recording_bench.set_defaults(handler=command_bench)


def _sweep_parser(targets):
    sweep_bench = targets.add_parser("sweep", help="one sweep on 1 and on 2 local workers: the speed-up")
    sweep_bench.add_argument("spec", nargs="?", metavar="SPEC",
                             help="sweep spec (default examples/sweeps/bench-rom.toml: 8 rom plants, 200 cells each)")
    sweep_bench.add_argument("--workers", default="1,2", metavar="N,M", help="pool sizes to compare (default 1,2)")
    sweep_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="1",
                             help="runs per pool size; medians (default 1)")
    output_options(sweep_bench)
    sweep_bench.set_defaults(handler=command_bench)


def _process_parser(targets):
    process_bench = targets.add_parser("process", help="whole vcyto processes with a warm set-up cache: the start, "
                                                       "paper 1 and 2, the README's stream at fixed steps and at "
                                                       "--tolerance 1um (the speed-up per round), against their "
                                                       "targets")
    process_bench.add_argument("--rounds", type=Integer(low=1, high=100), default="3",
                               help="timed rounds, each running every command once and then the floor probe "
                                    "(default 3; a round takes about 2 min on 2 cores)")
    process_bench.add_argument("--no-warm-up", action="store_true",
                               help="time from the first round (default: one untimed round fills the set-up cache)")
    output_options(process_bench)
    process_bench.set_defaults(handler=command_bench)


def _sort_stream_options(parser):
    """The offered rate and the seed of `bench sort`'s stream (Poisson, the inlet's dead time)."""
    parser.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="2000",
                        help="offered rate, cells/s (default 2000: about 1000 events/s after the dead time)")
    parser.add_argument("--seed", type=Integer(low=0, high=2**63 - 1), default="3", help="random seed (default 3)")


def _sort_parser(targets):
    sort_bench = targets.add_parser("sort", help="long rom sorting runs with recording: loop cost per event, "
                                                 "linearity in run length, peak memory, file sizes")
    scenario_options(sort_bench)
    sort_bench.add_argument("--counts", default="1000,10000", help="cells offered per run (default 1000,10000)")
    _sort_stream_options(sort_bench)
    sort_bench.add_argument("--no-record", action="store_true", help="no MCAP and no Rerun")
    sort_bench.add_argument("--no-rerun", action="store_true", help="MCAP only")
    output_options(sort_bench)
    sort_bench.set_defaults(handler=command_bench)


def _recorders_parser(targets):
    recorders_bench = targets.add_parser("recorders", help="where a recorded event's time goes on rom: the loop, "
                                                           "the loop shown to a recording, the MCAP and Rerun "
                                                           "recorders, each as CPU time per event")
    scenario_options(recorders_bench)
    recorders_bench.add_argument("--count", type=Integer(low=1, high=10_000_000), default="20000",
                                 help="cells offered (default 20000: about 10,000 events)")
    recorders_bench.add_argument("--repeats", type=Integer(low=1, high=100), default="3",
                                 help="runs of each part; the median (default 3)")
    _sort_stream_options(recorders_bench)
    output_options(recorders_bench)
    recorders_bench.set_defaults(handler=command_bench)


def _poisson_stream_options(parser, mix: str, duration_help: str):
    """The options of a benchmark that runs the rom loop on a Poisson stream: rate, duration, mix, repeats, seed."""
    parser.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="1000",
                        help="arrival rate in cells/s (default 1000; e.g. 1kHz)")
    parser.add_argument("--duration", type=Quantity("time", "s", low=0, low_open=True), default="1s", metavar="TIME",
                        help=duration_help)
    parser.add_argument("--mix", default=mix, help=f"type mix (default {mix})")
    parser.add_argument("--repeats", type=Integer(low=1, high=1000), default="3",
                        help="runs of the same stream (default 3; the median is reported)")
    parser.add_argument("--seed", type=Integer(low=0, high=2**63 - 1), default="0", help="random seed (default 0)")


def _realtime_parser(targets):
    realtime_bench = targets.add_parser("realtime", help="real-time factor of the closed loop with the rom plant: "
                                                         "a Poisson stream, detector and controller, no recording")
    scenario_options(realtime_bench)
    _poisson_stream_options(realtime_bench, "RBC:0.9,melanoma:0.1",
                            "device time of arrivals (s); count = rate x duration (default 1s)")
    realtime_bench.add_argument("--control-period", type=Quantity("time", "s", low=0, low_open=True, high=1.0),
                                metavar="TIME", help="control period (s; default: the plant's, 20us)")
    output_options(realtime_bench)
    realtime_bench.set_defaults(handler=command_bench)


def _wire_parser(targets):
    wire_bench = targets.add_parser("wire", help="the loop with its controller in another process (rom): lock-step "
                                                 "real-time factor, and missed decisions and lag in paced real time")
    scenario_options(wire_bench)
    _poisson_stream_options(wire_bench, "RBC:0.7,melanoma:0.3", "device time of each lock-step run (default 1 s)")
    wire_bench.add_argument("--realtime-duration", type=Quantity("time", "s", low=0, low_open=True, high=3600),
                            default="100s", metavar="TIME",
                            help="device time of the paced real-time run at 1x (default 100 s: as long in wall time)")
    wire_bench.add_argument("--min-spacing", type=Quantity("time", "ms", low=0), default="0.1", metavar="TIME",
                            help="dead time of the inlet (ms; default 0.1: coincidences and aborts occur)")
    wire_bench.add_argument("--client", metavar="CMD",
                            help="the controller to time, started as by vcyto stream --controller-exec (default: "
                                 "the built-in controller served by python -m vcyto.wire.serve --once)")
    output_options(wire_bench)
    wire_bench.set_defaults(handler=command_bench)


def _gym_parser(targets):
    gym_bench = targets.add_parser("gym", help="environment steps/s of the Gymnasium environment (vcyto/Sort-v0) "
                                               "on rom, against the loop itself (needs the extra rl)")
    scenario_options(gym_bench)
    gym_bench.add_argument("--count", type=Integer(low=1, high=1_000_000), default="2000",
                           help="cells offered per episode (default 2000)")
    gym_bench.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="1111.1",
                           help="offered Poisson rate, cells/s (default 1111.1: 1,000 events/s after the dead time)")
    gym_bench.add_argument("--min-spacing", type=Quantity("time", "ms", low=0), default="0.1", metavar="TIME",
                           help="the inlet's dead time (ms; default 0.1)")
    gym_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="5",
                           help="episodes timed; the median (default 5)")
    gym_bench.add_argument("--seed", type=Integer(low=0, high=2**63 - 1), default="0", help="reset seed (default 0)")
    output_options(gym_bench)
    gym_bench.set_defaults(handler=command_bench)


def _controller_parser(targets):
    controller_bench = targets.add_parser("controller", help="decision latency of the sorting controller")
    controller_bench.add_argument("--events", type=Integer(low=1, high=10_000_000), default="20000",
                                  help="synthetic events (default 20000)")
    output_options(controller_bench)
    controller_bench.set_defaults(handler=command_bench)



def _tolerance(args, scenario, progress):
    from ..bench import tolerance
    tolerances = positive_list(args.tolerances, "--tolerances", "1um,3um", length_value)
    result = tolerance.bench_tolerance(scenario, tuple(args.numbers), tuple(tolerances), progress)
    return result, tolerance.tolerance_lines(result)


def _fluid(args, scenario, progress):
    from ..bench import fluid
    result = fluid.bench_fluid(scenario, args.repeats, progress, rounds=args.rounds)
    return result, fluid.report_lines(result)


def _treatments(args, scenario, progress):
    from ..bench import treatments
    result = treatments.bench_treatments(scenario, args.steps, progress)
    return result, treatments.treatment_lines(result)


def _paper(args, scenario, progress):
    from ..bench import treatments
    from ..progress import Progress
    result = treatments.bench_paper_treatments(args.number, scenario, progress=Progress(quiet=args.quiet or args.json))
    return result, treatments.paper_treatment_lines(result)


def _coupling_parser(targets):
    coupling_bench = targets.add_parser("coupling", help="the explicit membrane coupling against the implicit one in "
                                                         "Scenario II: cost per step, largest step, path error")
    coupling_bench.add_argument("--steps", default="5us,10us,25us,50us,100us", metavar="LIST",
                                help="the ladder of steps each coupling runs Scenario II at (default "
                                     "5us,10us,25us,50us,100us); the reference is the explicit run at --dt")
    coupling_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="3",
                                help="interleaved runs of the cost per step (default 3)")
    scenario_options(coupling_bench)
    output_options(coupling_bench)
    coupling_bench.set_defaults(handler=command_bench)


def _coupling(args, scenario, progress):
    from .. import units
    from ..bench import coupling
    steps = positive_list(args.steps, "--steps", "5us,25us,100us",
                          lambda part: units.parse_quantity(part, "time", "s", "--steps"))
    if max(steps) > 1e-3:
        raise UsageError(f"--steps: takes steps of at most 1 ms, e.g. 5us,25us,100us (got {args.steps})")
    result = coupling.bench_coupling(scenario, steps, args.repeats, progress=progress)
    return result, coupling.coupling_lines(result)


def _auto(args, scenario, progress):
    from ..bench import auto
    from ..progress import Progress
    limits.check_cells(args.count)
    result = auto.bench_auto(scenario, args.count, args.rate, parse_mix(args.mix), args.seed,
                             progress=Progress(quiet=args.quiet or args.json))
    return result, auto.auto_lines(result)


def _membrane(args, scenario, progress):
    from ..bench import membrane
    from ..progress import Progress
    result = membrane.bench_membrane(scenario, args.repeats, progress=Progress(quiet=args.quiet or args.json))
    return result, membrane.membrane_lines(result)


def _recording(args, scenario, progress):
    from ..bench import recording
    from ..progress import Progress
    result = recording.bench_recording(scenario, repeats=args.repeats, progress=Progress(quiet=args.quiet or args.json))
    return result, recording.recording_lines(result)


def _sweep(args, scenario, progress):
    from .. import sweep
    from ..bench import sweep as sweep_bench
    from ..progress import Progress
    try:
        counts = tuple(int(part) for part in args.workers.split(","))
    except ValueError:
        raise UsageError(f"--workers: wants pool sizes such as 1,2 (got {args.workers!r})") from None
    if args.repeats < 1 or not counts or min(counts) < 1 or max(counts) > 1024:
        raise UsageError("--repeats/--workers: the repeats and every pool size must be at least 1 (pool sizes at "
                         "most 1024, as vcyto sweep's --workers)")
    spec = args.spec or str(EXAMPLES / "sweeps" / "bench-rom.toml")
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = sweep_bench.bench_sweep(spec, counts, args.repeats, progress)
    except sweep.SweepError as error:
        raise UsageError(str(error)) from None
    finally:
        progress.close()
    return result, sweep_bench.sweep_lines(result)


def _process(args, scenario, progress):
    from ..bench import process
    from ..cache import cache_enabled
    if not cache_enabled():
        raise UsageError("bench process times commands with a warm set-up cache, which VCYTO_CACHE=off turns off: "
                         "unset VCYTO_CACHE")
    try:
        result = process.bench_process(args.rounds, warm_up=not args.no_warm_up, progress=progress)
    except process.CommandFailed as failure:
        print(f"vcyto: bench process: {failure}", file=sys.stderr)
        raise RunStopped(EXIT_NUMERICAL) from failure
    return result, process.process_lines(result)


def _recorders(args, scenario, progress):
    from ..bench import recorders
    check_cells_fit(scenario, ["RBC", "melanoma"])
    result = recorders.bench_recorders(scenario, args.count, args.rate, args.repeats, args.seed, progress)
    return result, recorders.report_lines(result)


def _sort(args, scenario, progress):
    from sim.model.arrivals import MAX_COUNT

    from ..bench import sort
    try:
        counts = [int(v) for v in args.counts.split(",") if v.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1 or max(counts) > MAX_COUNT:
        raise UsageError(f"--counts: wants positive cell counts (at most {MAX_COUNT:,}) such as 1000,10000 "
                         f"(got {args.counts!r})")
    result = sort.bench_sort(counts, args.rate, not args.no_record, not args.no_rerun, args.seed, progress)
    return result, sort.report_lines(result)


def _realtime(args, scenario, progress):
    from ..bench import realtime
    mix = parse_mix(args.mix)
    check_cells_fit(scenario, [name for name, _ in mix])
    limits.check_cells(math.ceil(args.rate * args.duration), "--rate x --duration")
    result = realtime.bench_realtime(scenario, args.rate, args.duration, mix, args.repeats, args.control_period,
                                     args.seed, progress)
    return result, realtime.realtime_lines(result)


def _wire(args, scenario, progress):
    from ..bench import wire
    mix = parse_mix(args.mix)
    check_cells_fit(scenario, [name for name, _ in mix])
    limits.check_cells(math.ceil(args.rate * max(args.duration, args.realtime_duration)),
                       "--rate x --duration/--realtime-duration")
    result = wire.bench_wire(scenario, args.rate, args.duration, args.realtime_duration, mix, args.min_spacing,
                             args.repeats, args.seed, client=args.client, progress=progress)
    return result, wire.wire_lines(result)


def _gym(args, scenario, progress):
    try:
        import gymnasium  # noqa: F401
    except ImportError:
        raise UsageError("bench gym: needs Gymnasium, the optional extra rl: pip install 'vcyto[rl]'") from None
    from ..bench import gym
    check_cells_fit(scenario, ["RBC", "melanoma"])
    result = gym.bench_gym(scenario, args.count, args.rate, args.min_spacing, repeats=args.repeats, seed=args.seed,
                           progress=progress)
    return result, gym.gym_lines(result)


def _controller(args, scenario, progress):
    from ..bench import controller
    result = controller.bench_controller(args.events)
    return result, controller.controller_lines(result)


class Target(NamedTuple):
    """A benchmark of `vcyto bench`: its parser, its run ``(args, scenario, progress) -> (result, lines)``, and
    whether it takes a scenario (read from the scenario options before it runs)."""
    parser: Callable
    run: Callable
    scenario: bool = True


# in the order of `vcyto bench --help`
TARGETS = {
    "tolerance": Target(_tolerance_parser, _tolerance),
    "fluid": Target(_fluid_parser, _fluid),
    "treatments": Target(_treatments_parser, _treatments),
    "paper": Target(_paper_parser, _paper),
    "auto": Target(_auto_parser, _auto),
    "membrane": Target(_membrane_parser, _membrane),
    "coupling": Target(_coupling_parser, _coupling),
    "recording": Target(_recording_parser, _recording),
    "sweep": Target(_sweep_parser, _sweep, scenario=False),
    "process": Target(_process_parser, _process, scenario=False),
    "sort": Target(_sort_parser, _sort),
    "recorders": Target(_recorders_parser, _recorders),
    "realtime": Target(_realtime_parser, _realtime),
    "wire": Target(_wire_parser, _wire),
    "controller": Target(_controller_parser, _controller, scenario=False),
    "gym": Target(_gym_parser, _gym),
}


def add_command(commands):
    bench = commands.add_parser("bench", help="benchmarks")
    targets = bench.add_subparsers(dest="target", required=True, metavar="TARGET")
    for target in TARGETS.values():
        target.parser(targets)


CONVECTION_BENCHES = ("fluid", "treatments", "paper")     # they switch the convection treatment themselves


def command_bench(args):
    target = TARGETS[args.target]
    progress = stderr_progress(args.quiet or args.json)
    if args.target in CONVECTION_BENCHES and getattr(args, "time_scheme", None) not in (None, "auto"):
        raise UsageError(f"--time-scheme: bench {args.target} compares convection treatments with the paper's "
                         "step; drop --time-scheme (bench tolerance measures bdf2)")
    scenario = scenario_from(args) if target.scenario else None
    result, lines = target.run(args, scenario, progress)
    emit(args, result, lines)
