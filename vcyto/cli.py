"""The `vcyto` command line. Bad input ends with one line on stderr and exit status 2; a numerical
failure with one line and status 1; never a traceback (set VCYTO_DEBUG=1 to see one)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from controller.sorter import MODES
from sim import plants
from sim.fluid import NumericalBlowUp
from sim.linalg import SolverError
from sim.scenario import CONVECTIONS, MEMBRANE_METHODS, SAW_MODELS, ScenarioError

from . import arguments as limits
from . import outputs, units
from .arguments import Integer, Number, Parser, Quantity
from .cache import install_default as install_cache
from .config import load_scenario
from .outputs import strict_json
from .stream import StreamStopped

EXIT_INPUT = 2
EXIT_NUMERICAL = 1
EXIT_INTERNAL = 3
EXIT_SIGINT = 130           # 128 + SIGINT, as shells report it
EXIT_SIGTERM = 143          # 128 + SIGTERM
MIN_FREE_BYTES = 100e6


class UsageError(ValueError):
    """Bad command-line input that is not a scenario field."""


class RunStopped(Exception):
    """A run that stopped early and has said so (files written, paths printed); ``status`` is the exit status."""

    def __init__(self, status: int):
        super().__init__(status)
        self.status = status


_signals_seen: dict[str, str] = {}      # "last": the name of the last signal turned into KeyboardInterrupt


def _progress(quiet: bool):
    def report(message: str):
        if not quiet:
            print(f"  .. {message}", file=sys.stderr, flush=True)
    return report


def _scenario_options(parser: argparse.ArgumentParser):
    group = parser.add_argument_group("scenario (SI units; values may carry units such as 3.33um or 25us)")
    group.add_argument("--scenario", metavar="FILE", help="TOML scenario file (default: the paper's device)")
    group.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                       help="override one field, e.g. --set fluid.viscosity=1e-3 (repeatable)")
    group.add_argument("--mesh-h", metavar="LENGTH", help="mesh size (default 3.33um, the paper's 54,243 DOFs)")
    group.add_argument("--dt", metavar="TIME",
                       help="time step (default 2.5us; vcyto paper: the paper's step for the scenario)")
    group.add_argument("--convection", choices=CONVECTIONS, help="convection treatment (default imex)")
    group.add_argument("--saw-model", choices=SAW_MODELS, help="SAW model (default paper)")
    group.add_argument("--solver", choices=("auto", "pardiso", "superlu"), help="linear solver (default auto)")
    group.add_argument("--membrane", choices=tuple(MEMBRANE_METHODS),
                       help="membrane method: conserving (area constraint + point redistribution; the default) or "
                            "paper (the paper's literal method, which leaks area; the default of vcyto paper)")


def _output_options(parser: argparse.ArgumentParser):
    parser.add_argument("--json", action="store_true", help="print a machine-readable result on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress messages on stderr")


def _scenario(args, membrane: str | None = None):
    """The scenario of the options; ``membrane`` is the command's default membrane method (--membrane wins,
    and --set of single fields refines either)."""
    method = getattr(args, "membrane", None) or membrane
    overrides = [f"numerics.{field}={str(value).lower()}" for field, value in MEMBRANE_METHODS[method].items()] \
        if method else []
    overrides += list(args.overrides) + _tolerance_override(args)
    for option, field in (("mesh_h", "numerics.mesh_h"), ("dt", "numerics.dt"), ("convection", "numerics.convection"),
                          ("saw_model", "saw.model"), ("solver", "numerics.linear_solver")):
        value = getattr(args, option, None)
        if value is not None:
            overrides.append(f"{field}={value}")
    scenario = load_scenario(args.scenario, overrides)
    limits.check_mesh(scenario.channel.length, scenario.channel.height, scenario.numerics.mesh_h)
    return scenario


LENGTH_UNITS = ("", "m", "mm", "um", "nm")


def _tolerance_options(parser: argparse.ArgumentParser):
    group = parser.add_argument_group("time steps chosen by a tolerance (README: 'Fast at the limit')")
    group.add_argument("--tolerance", metavar="LENGTH",
                       help="pick each FE-IB step from dt, 2dt, 4dt, 8dt (dt = --dt, default 2.5us) by an error "
                            "estimate on the membranes, for at most this centroid path error per transit against "
                            "fixed steps of dt, e.g. 1um; never above the cells' stability limit (default: fixed dt)")


def _length_value(text: str) -> float:
    """A positive length (m, mm, um or nm); ValueError otherwise."""
    from .config import _QUANTITY, parse_quantity
    match = _QUANTITY.fullmatch(text)
    value = parse_quantity(text)
    if (" ".join(match.group(2).split()) if match else "") not in LENGTH_UNITS:
        raise ValueError(f"{text!r} is not a length")
    return value


def _tolerance_bench_command(targets):
    tolerance = targets.add_parser("tolerance", help="the paper scenarios with --tolerance levels against fixed "
                                   "steps: outlets, path distance, steps per level")
    _scenario_options(tolerance)
    tolerance.add_argument("--tolerances", default="1um,3um", metavar="LIST", help="tolerances (default 1um,3um)")
    tolerance.add_argument("--numbers", type=int, nargs="+", choices=(1, 2), default=[1, 2], metavar="N",
                           help="paper scenarios (default 1 2)")
    _output_options(tolerance)
    tolerance.set_defaults(handler=command_bench)


def _tolerance_override(args) -> list[str]:
    """``--tolerance LENGTH`` as the override numerics.tolerance=VALUE (a length: m, mm, um or nm)."""
    text = getattr(args, "tolerance", None)
    if text is None:
        return []
    from .config import _QUANTITY, parse_quantity
    match = _QUANTITY.fullmatch(text)
    unit = " ".join(match.group(2).split()) if match else ""
    try:
        value = parse_quantity(text)
    except ValueError as error:
        raise UsageError(f"--tolerance: {error}") from None
    if unit not in LENGTH_UNITS or not (math.isfinite(value) and value > 0):
        raise UsageError(f"--tolerance: must be a positive length such as 1um or 0.5um (got {text!r})")
    if getattr(args, "model", None) not in (None, "feib"):
        raise UsageError(f"--tolerance: picks the steps of the feib model only; drop it or use --model feib "
                         f"(got --model {args.model})")
    return [f"numerics.tolerance={value!r}"]


def _output_path(path: str | None, default: bool = False) -> Path | None:
    """Check before any work that an output file can be written, and reserve it: a file that exists is never
    overwritten (a default name becomes NAME-2, NAME-3, ...; a name the user gave is refused)."""
    if path is None:
        return None
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    if default:
        directory.mkdir(parents=True, exist_ok=True)
    if not directory.is_dir():
        raise UsageError(f"cannot write {path}: directory {directory} does not exist")
    if not os.access(directory, os.W_OK):
        raise UsageError(f"cannot write {path}: directory {directory} is not writable")
    if default:
        return outputs.unique_path(target)
    if target.exists():
        raise UsageError(f"{path} exists: a run never overwrites a file; choose another name or remove it")
    return target


def _emit(args, result: dict, lines: list[str]):
    if args.json:
        print(strict_json(result))
    else:
        print("\n".join(lines))


def command_flow(args):
    from . import flowtool
    scenario = _scenario(args)
    png = _output_path(args.png)
    progress = _progress(args.quiet or args.json)
    if args.calibrate_streaming:
        result = flowtool.calibrate(scenario, progress)
        _emit(args, result, [f"streaming force {result['streaming_force']:.4g} N/m^3 puts the injection streamline "
                             f"at y = {result['exit_y_um']:.1f} um ({result['iterations']} bisection steps, "
                             f"{result['wall_time_s']:.0f} s); set it with --set saw.streaming_force=..."])
        return
    paths, flows, solver = flowtool.solve_paths(scenario, progress)
    result = flowtool.summary(scenario, paths, solver)
    if png:
        flowtool.save_png(str(png), scenario, solver, flows, paths)
        result["png"] = str(png)
    lines = flowtool.report_lines(result) + ([f"  saved {png}"] if png else [])
    _emit(args, result, lines)


def command_bench(args):
    from . import bench
    progress = _progress(args.quiet or args.json)
    if args.target == "controller":
        result = bench.bench_controller(args.events)
        _emit(args, result, bench.controller_lines(result))
        return
    if args.target == "sweep":
        _bench_sweep(args, bench)
        return
    scenario = _scenario(args)
    if args.target == "sort":
        from . import benchsort
        try:
            counts = [int(v) for v in args.counts.split(",") if v.strip()]
        except ValueError:
            counts = []
        if not counts or min(counts) < 1 or max(counts) > 10**7:
            raise UsageError(f"--counts wants positive cell counts such as 1000,10000 (got {args.counts!r})")
        result = benchsort.bench_sort(counts, args.rate, not args.no_record, not args.no_rerun, args.seed, progress)
        _emit(args, result, benchsort.report_lines(result))
        return
    if args.target == "realtime":
        _bench_realtime(args, bench, scenario, progress)
        return
    if args.target == "recording":
        from .progress import Progress
        result = bench.bench_recording(scenario, repeats=args.repeats, progress=Progress(quiet=args.quiet or args.json))
        _emit(args, result, bench.recording_lines(result))
        return
    if args.target == "auto":
        from .progress import Progress
        limits.check_cells(args.count)
        result = bench.bench_auto(scenario, args.count, args.rate, _mix(args.mix), args.seed,
                                  progress=Progress(quiet=args.quiet or args.json))
        _emit(args, result, bench.auto_lines(result))
        return
    if args.target == "membrane":
        from .progress import Progress
        result = bench.bench_membrane(scenario, args.repeats, progress=Progress(quiet=args.quiet or args.json))
        _emit(args, result, bench.membrane_lines(result))
        return
    if args.target == "tolerance":
        from .tolerancebench import bench_tolerance, tolerance_lines
        tolerances = _positive_list(args.tolerances, "--tolerances", "1um,3um", _length_value)
        result = bench_tolerance(scenario, tuple(args.numbers), tuple(tolerances), progress)
        _emit(args, result, tolerance_lines(result))
        return
    if args.target == "paper":
        from .progress import Progress
        result = bench.bench_paper_treatments(args.number, scenario, progress=Progress(quiet=args.quiet or args.json))
        _emit(args, result, bench.paper_treatment_lines(result))
        return
    if args.target == "treatments":
        result = bench.bench_treatments(scenario, args.steps, progress)
        _emit(args, result, bench.treatment_lines(result))
        return
    result = bench.bench_fluid(scenario, args.repeats, progress)
    _emit(args, result, bench.report_lines(result))


def _bench_realtime(args, bench, scenario, progress):
    mix = _mix(args.mix)
    _check_cells_fit(scenario, [name for name, _ in mix])
    limits.check_cells(math.ceil(args.rate * args.duration), "--rate x --duration")
    result = bench.bench_realtime(scenario, args.rate, args.duration, mix, args.repeats, args.control_period,
                                  args.seed, progress)
    _emit(args, result, bench.realtime_lines(result))


def _bench_sweep(args, bench):
    from . import sweep
    from .progress import Progress
    try:
        counts = tuple(int(part) for part in args.workers.split(","))
    except ValueError:
        raise UsageError(f"--workers wants pool sizes such as 1,2 (got {args.workers!r})") from None
    if args.repeats < 1 or not counts or min(counts) < 1:
        raise UsageError("--repeats and every pool size in --workers must be at least 1")
    spec = args.spec or str(Path(__file__).resolve().parent.parent / "examples" / "sweeps" / "bench-rom.toml")
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = bench.bench_sweep(spec, counts, args.repeats, progress)
    except sweep.SweepError as error:
        raise UsageError(str(error)) from None
    finally:
        progress.close()
    _emit(args, result, bench.sweep_lines(result))


def command_paper(args):
    from . import paper
    from .progress import Progress
    # with --tolerance the finest level is --dt or 2.5 us, the step the tolerance is stated against
    scenario = paper.paper_scenario(args.number, _scenario(args, membrane="paper"),
                                    dt_given=args.dt is not None or args.tolerance is not None)
    _check_run_time(args, scenario, args.max_time, "--dt/--max-time")
    png = None if args.no_png else _output_path(args.png or f"recordings/paper{args.number}.png", default=not args.png)
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = paper.run_paper(args.number, scenario, args.max_time, progress)
    finally:
        progress.close()
    lines = paper.report_lines(result)
    if png:
        paper.save_png(str(png), result, scenario)
        result["png"] = str(png)
        lines.append(f"  saved {png}")
    _emit(args, paper.public(result), lines)


def _lengths(text: str) -> list[float]:
    values = units.parse_list(text, "length", field="--mesh-sizes")
    if not values or any(v <= 0 for v in values):
        raise UsageError(f"--mesh-sizes: needs positive lengths such as 6.67um,3.33um (got {text!r})")
    return values


def command_stability(args):
    from . import stabilitymap
    from .progress import Progress
    scenario = _scenario(args)
    cells = [name.strip() for name in args.cells.split(",") if name.strip()]
    if not cells:
        raise UsageError("--cells needs at least one cell type, e.g. --cells RBC,melanoma")
    for name in cells:
        scenario.cell_type(name)
    sizes = _lengths(args.mesh_sizes)
    for h in sizes:
        scenario.with_numerics(mesh_h=h)          # validates that each mesh resolves the inlets
        limits.check_mesh(scenario.channel.length, scenario.channel.height, h, "--mesh-sizes")
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = stabilitymap.stability_map(scenario, cells, sizes, progress)
    finally:
        progress.close()
    _emit(args, result, stabilitymap.report_lines(result))


def _positive_list(text: str, option: str, example: str, parse) -> list[float]:
    return _number_list(text, option, example, parse, lambda v: v > 0, "positive")


def _non_negative_list(text: str, option: str, example: str) -> list[float]:
    return _number_list(text, option, example, _plain_number(option), lambda v: v >= 0, "non-negative")


def _plain_number(option: str):
    return lambda part: units.parse_quantity(part, "dimensionless", field=option)


def _number_list(text: str, option: str, example: str, parse, valid, kind: str) -> list[float]:
    try:
        values = [parse(part) for part in text.split(",")]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) and valid(v) for v in values):
        raise UsageError(f"{option}: needs {kind} numbers separated by commas, such as {example} (got {text!r})")
    return values


def _times_before_pulse_end(text: str, option: str, example: str, what: str) -> list[float]:
    """Times (bare numbers in ms; returned in s) for the extra tradeoff scenes: positive and below 2 ms."""
    times = _positive_list(text, option, example, lambda part: units.parse_quantity(part, "time", "ms", option))
    if max(times) >= 2e-3:
        raise UsageError(f"{option} takes {what} below 2 ms (the scenes' pulse ends at 2.1 ms; got {text})")
    return times


def command_tradeoff(args):
    from . import tradeoff
    from .progress import Progress
    scenario = _scenario(args)
    output = _output_directory(args.output)
    progress = Progress(quiet=args.quiet or args.json)
    ladder, scenes = tradeoff.FAST_LADDER if args.fast else tradeoff.LADDER, tradeoff.SCENES
    base = next(level for level in ladder if level.model == "auto" and level.window is None)
    if args.coupling:
        values = _positive_list(args.coupling, "--coupling", "2,2.5,3", _plain_number("--coupling"))
        ladder += tuple(dataclasses.replace(base, coupling=value) for value in values)
    if args.stiff_capillary:
        values = _non_negative_list(args.stiff_capillary, "--stiff-capillary", "0,100")
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
    if output is not None:
        if (output / "tradeoff.md").exists():              # a run never overwrites another's files
            output = outputs.unique_directory(output)
        result["files"] = tradeoff.save(result, output)
        lines.append(f"saved {', '.join(result['files'].values())}")
    _emit(args, result, lines)


def command_extremes(args):
    from . import extremes
    from .progress import Progress
    base = _scenario(args)
    names = [name.strip() for name in args.case.split(",") if name.strip()] if args.case else None
    known = [case.name for case in extremes.CASES]
    unknown = [name for name in names or () if name not in known]
    if unknown or names == []:
        raise UsageError(f"--case: unknown case {', '.join(unknown) or repr(args.case)}; known: {', '.join(known)}")
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = extremes.run_cases(base, fast=args.fast, names=names, progress=progress)
    finally:
        progress.close()
    _emit(args, result, extremes.report_lines(result))
    if not result["passed"]:
        raise extremes.UnexpectedOutcome(f"{sum(not row['passed'] for row in result['rows'])} case(s) did not "
                                         "end as expected (see the table)")


def _cell_list(text: str) -> tuple[str, ...]:
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    if not names:
        raise UsageError("--cells needs at least one cell type, e.g. --cells RBC,melanoma")
    return names


def _mix(text: str) -> tuple[tuple[str, float], ...]:
    """TYPE:WEIGHT pairs; every weight finite and >= 0, their sum positive."""
    pairs = []
    for part in text.split(","):
        name, _, weight = part.partition(":")
        try:
            pairs.append((name.strip(), units.parse_quantity(weight, "dimensionless", field="--mix")))
        except units.QuantityError:
            raise UsageError(f"--mix: wants TYPE:WEIGHT pairs with finite weights, such as RBC:0.9,melanoma:0.1 "
                             f"(got {text!r})") from None
    if any(weight < 0 for _, weight in pairs) or not sum(weight for _, weight in pairs) > 0:
        raise UsageError(f"--mix: weights must be >= 0 with a positive sum (got {text!r})")
    return tuple(pairs)


def _detection_window(text: str, scenario) -> tuple[float, float]:
    """The detection window (x0, x1) in m from "30,60" (um) or "30um,60um"; inside the channel, x0 < x1."""
    values = units.parse_list(text, "length", "um", field="--detection-window")
    if len(values) != 2 or not 0 <= values[0] < values[1]:
        raise UsageError(f"--detection-window: wants two lengths X0,X1 with 0 <= X0 < X1, e.g. 30,60 (um) "
                         f"(got {text!r})")
    if values[1] > scenario.channel.length:
        raise UsageError(f"--detection-window: {text} lies outside the channel "
                         f"(0, {scenario.channel.length * 1e6:g}) um")
    return values[0], values[1]


def _check_cells_fit(scenario, names) -> None:
    """Every cell type of the stream is known and fits through the injection inlet."""
    inlet = scenario.channel.inlet(scenario.channel.injection_inlet)
    width = inlet.span[1] - inlet.span[0]
    for name in sorted(set(names)):
        cell = scenario.cell_type(name)
        if cell.diameter >= width:
            raise ScenarioError("cell_types", f"a {name} {cell.diameter * 1e6:.4g} um across does not fit through "
                                              f"the injection inlet {inlet.name!r} ({width * 1e6:.4g} um wide)")


def stream_settings(args, scenario):
    """The ``StreamSettings`` of the stream options in ``args`` (vcyto stream, and each point of vcyto sweep);
    the quantities in ``args`` are SI (the option types convert them)."""
    from sim.arrivals import Arrivals

    from . import stream
    try:
        if args.count is not None:
            limits.check_cells(args.count)
        cells = args.cells if args.cells is not None else ("" if args.count else "RBC,melanoma")
        arrivals = Arrivals(cells=_cell_list(cells) if cells else (), count=args.count or 0,
                            mix=_mix(args.mix) if args.mix else (), rate=args.rate, process=args.arrivals,
                            min_spacing=args.min_spacing)
        _check_cells_fit(scenario, set(arrivals.cells) | {name for name, _ in arrivals.mix})
        detector = _detector_settings(args, scenario)
        controller = _controller_settings(args)
        window = getattr(args, "window_h", None)
        if window is not None:
            if args.model != "auto":
                raise UsageError(f"--window-h sets the feib windows of --model auto (the model is {args.model}): "
                                 "drop it or add --model auto")
            limits.check_mesh(scenario.channel.length, scenario.channel.height, window, "--window-h")
            try:
                scenario.with_numerics(mesh_h=window)           # resolves every inlet and outlet
            except ScenarioError as error:
                raise UsageError(f"--window-h: {str(error).split(': ', 1)[1]}") from None
        if args.model == "feib":
            _check_run_time(args, scenario, _device_time(arrivals, args.max_time), "--dt/--count/--rate")
        return stream.StreamSettings(arrivals, detector, controller, args.model, args.seed,
                                     max_time=args.max_time, window_mesh_h=window)
    except ValueError as error:
        if isinstance(error, (UsageError, ScenarioError, units.QuantityError)):
            raise
        raise UsageError(str(error)) from None



def _detector_settings(args, scenario):
    from controller.detector import DetectorSettings
    try:
        return DetectorSettings(window=_detection_window(args.detection_window, scenario), gate=args.gate,
                                noise_cv=args.noise)
    except ValueError as error:
        raise UsageError(f"--detection-window/--gate/--noise: {error}") from None


def _device_time(arrivals, cap) -> float:
    """The device time a stream will simulate, roughly: its arrivals plus 5 ms for the last cell to leave."""
    cells = len(arrivals.cells) or arrivals.count
    span = (cells - 1) / arrivals.rate + 5e-3
    return min(span, cap) if cap is not None else span


def _check_run_time(args, scenario, simulated: float, field: str):
    limits.check_run_time(simulated, scenario.numerics.dt, limits.mesh_dofs(
        scenario.channel.length, scenario.channel.height, scenario.numerics.mesh_h), field,
        allowed=getattr(args, "allow_long", False))


def _controller_settings(args):
    """The controller file (or the shipped defaults), then the controller options given on the command line."""
    from dataclasses import replace

    from controller.sorter import ControllerSettings
    base = ControllerSettings()
    if getattr(args, "controller", None):
        from .controllerfile import load_controller
        base = load_controller(args.controller)
    changes = {name: getattr(args, name) for name in ("delay", "lead", "pulse", "timing_error")
               if getattr(args, name, None) is not None}          # SI: the option types convert them
    if getattr(args, "mode", None):
        changes["mode"] = args.mode
    if getattr(args, "envelope", None):
        values = units.parse_list(args.envelope, "time", "ms", field="--envelope")
        if len(values) != 2 or values[0] > values[1]:
            raise UsageError(f"--envelope wants two offsets LO,HI with LO <= HI, such as -0.236,0.27 (ms) "
                             f"(got {args.envelope!r})")
        changes["envelope"] = tuple(values)
    if args.no_controller:
        changes["enabled"] = False
    return replace(base, **changes)


def stream_run_options() -> argparse.ArgumentParser:
    """A parser of the scenario and stream options alone: their names, types and defaults are vcyto sweep's."""
    parser = argparse.ArgumentParser(prog="vcyto stream", add_help=False)
    _scenario_options(parser)
    _stream_options(parser)
    return parser


def stream_run(args):
    """The scenario and the ``StreamSettings`` that the scenario and stream options in ``args`` describe."""
    scenario = _scenario(args)
    return scenario, stream_settings(args, scenario)


def command_stream(args):
    from . import runfiles
    scenario = _scenario(args)
    settings = stream_settings(args, scenario)
    output = _output_directory(args.output)
    if args.name is not None:
        if output is None:
            raise UsageError("--name: names the run's files in --output, which is '' (nothing is written)")
        try:
            outputs.check_name(args.name)
        except ValueError as error:
            raise UsageError(str(error)) from None
    _signals_seen.clear()
    view = runfiles.choose_view(args, output is not None, spawn_by_default=True, error=UsageError)
    files = None
    if output is not None:
        try:
            files = runfiles.StreamFiles(output, args.name, record=not args.no_record,
                                         rrd=view.kind == "save" and view.path is None)
        except outputs.NameTaken as error:
            raise UsageError(str(error)) from None
    result, stopped = _run_with_sinks(args, scenario, settings, view, files)
    _report_stream(args, result, stopped, view, files, settings, scenario)
    return _partial_status(args, result)


def _run_with_sinks(args, scenario, settings, view, files):
    """Run the loop with the MCAP and Rerun sinks; (summary, StreamStopped or None). The sinks are closed
    whatever happens; a run stopped by Ctrl-C, SIGTERM or a numerical failure returns its partial summary."""
    from . import runfiles, stream
    from .progress import Progress
    from .sinks import BackgroundSinks
    sinks = []
    if files is not None and files.path("mcap") is not None:
        from .recording import McapRecorder
        sinks.append(McapRecorder(files.path("mcap"), _run_metadata(scenario, settings),
                                  flush_every=args.flush_every, field_every=args.field_every))
    if view.kind is not None and (view.kind == "connect" or view.path or files is not None):
        sinks += _rerun_sink(args, scenario, settings, view, files)
    progress = Progress(quiet=args.quiet or args.json)
    background = BackgroundSinks(sinks) if sinks else None      # their work overlaps the plant's solve
    stopped = None
    try:
        with runfiles.signals_as_interrupt(_signals_seen):
            try:
                result = stream.run_stream(scenario, settings, progress, sinks=[background] if background else [])
            except stream.StreamStopped as error:
                stopped, result = error, error.result
            except KeyboardInterrupt:                      # before the loop began (setting up the plant)
                stopped = stream.StreamStopped("interrupted", "interrupted while setting up, before the first step",
                                               runfiles.stopped_summary(settings, "interrupted while setting up"))
                result = stopped.result
        progress.close()
        view.notes += runfiles.close_quietly(background, files and files.path("mcap"))   # a full disk surfaces here too
    except BaseException:
        progress.close()
        try:
            runfiles.close_quietly(background)
        finally:
            if files is not None:
                files.discard_unwritten()
        raise
    return result, stopped


def _rerun_sink(args, scenario, settings, view, files) -> list:
    """The Rerun sink of ``view``; if Rerun refuses it (a viewer gone between the check and the connection, a
    file it cannot create), one line says so and the view goes to a new .rrd, else there is none."""
    from . import runfiles
    from .rerunlog import RerunSink
    try:
        return [RerunSink(scenario, settings.detector.window, view.target(files and files.path("rrd")),
                          field_every=args.field_every)]
    except (RuntimeError, OSError) as problem:
        reason = " ".join(str(problem).split())[:160]
        if view.kind == "connect" and files is not None:
            view.kind, view.path = "save", outputs.unique_path(files.directory / f"{files.run_id}.rrd")
            runfiles.say(f"the Rerun viewer refused the connection ({reason}); saving the view to {view.path}")
            return _rerun_sink(args, scenario, settings, view, files)
        runfiles.say(f"cannot write the Rerun view ({reason}); the run goes on without it")
        view.kind = None
        return []


def _report_stream(args, result, stopped, view, files, settings, scenario):
    """Write the FCS events and the summary (partial ones marked), print the report and the paths; a stopped
    run then ends with its exit status (130 SIGINT, 143 SIGTERM, 1 numerical failure)."""
    from . import runfiles, stream
    if stopped is not None and stopped.status == "interrupted":
        result["reason"] = f"interrupted by {_signals_seen.get('last', 'SIGINT')}"
    lines = stream.report_lines(result) if result.get("cells") else []
    result["files"] = {}
    if files is not None and files.path("mcap") is not None:
        mcap = files.path("mcap")
        result["files"]["mcap"] = str(mcap)
        lines.append(f"recording: {mcap} (MCAP; replay with: vcyto replay {mcap})")
    if view.kind is not None and (view.kind == "connect" or view.path or files is not None):
        rrd = files.path("rrd") if files is not None else None
        result["files"]["rerun"] = view.url if view.kind == "connect" else str(view.path or rrd)
        lines.append(f"Rerun: {view.describe(rrd)}")
    if files is not None:
        result["run_id"] = files.run_id
        result["files"].update({"fcs": str(files.path("fcs")), "gatingml": str(files.path("gating.xml")),
                                "summary": str(files.path("json"))})
        files.finish(result, settings, scenario)
        lines.append(f"detector events: {files.path('fcs')} (FCS 3.1; classification gate: "
                     f"{files.path('gating.xml')}, Gating-ML 2.0); summary: {files.path('json')}")
    for note in view.notes:
        runfiles.say(note)
    _emit(args, result, lines)
    if stopped is None:
        return
    written = ", ".join(result["files"].get(key) for key in ("mcap", "summary", "fcs") if key in result["files"])
    kept = f"; what ran is in {written}" if written else ""
    if stopped.status == "failed":
        runfiles.say(f"error: the run failed at t = {result.get('simulated_time_ms', 0):.3f} ms: "
                     f"{' '.join(stopped.reason.split())}{kept}")
        raise RunStopped(EXIT_NUMERICAL)
    signal_name = _signals_seen.get("last", "SIGINT")
    runfiles.say(f"interrupted by {signal_name} at t = {result.get('simulated_time_ms', 0):.3f} ms{kept} "
                 "(the summary's status is \"interrupted\")")
    raise RunStopped(EXIT_SIGTERM if signal_name == "SIGTERM" else EXIT_SIGINT)


def _partial_status(args, result) -> int:
    """Exit status of a finished run: 0, or 1 for a run cut short that the user did not cap (README "Exit status")."""
    if result.get("status", "complete") == "complete":
        return 0
    asked = getattr(args, "allow_partial", False)
    print(f"vcyto: {'note' if asked else 'error'}: the run is partial ({result['status']}): {result['reason']}"
          + ("" if asked else "; its statistics are not those of the whole sample (--allow-partial to accept it)"),
          file=sys.stderr)
    return 0 if asked else EXIT_NUMERICAL


def command_calibrate(args):
    from . import calibrate
    from .controllerfile import controller_toml
    scenario = _scenario(args)
    output = _output_directory(args.output)
    base = _controller_settings(args)
    grid = _calibration_grid(args)
    pulse = None
    if args.pulse is not None or args.lead is not None:
        if args.pulse is None or args.lead is None:
            raise UsageError("--pulse and --lead go together: give both to measure the envelope of that pulse, "
                             "or neither to search for the shortest reliable pulse")
        pulse = (base.pulse, base.lead)
    detector = _detector_settings(args, scenario)
    from .progress import Progress
    progress = Progress(quiet=args.quiet or args.json)
    started = time.perf_counter()
    try:
        plant = calibrate.make_calibration_plant(scenario, args.model)
        result = calibrate.calibrate(plant, scenario, detector, grid, pulse, base, progress)
    except calibrate.CalibrationError as error:
        raise UsageError(str(error)) from None
    finally:
        progress.close()
    record = dict(result.as_dict(), model=args.model, saw_model=scenario.saw.model,
                  wall_time_s=time.perf_counter() - started, files={})
    if output is not None:
        run_id = outputs.reserve_run(output, ("toml", "json", "png"), None,
                                     prefix=f"calibration-{args.model}")
        stem = output / run_id
        provenance = {"command": " ".join(sys.argv), "model": args.model, "saw_model": scenario.saw.model,
                      "mesh_h_um": scenario.numerics.mesh_h * 1e6, "dt_us": scenario.numerics.dt * 1e6,
                      "date": time.strftime("%Y-%m-%d %H:%M:%S")}
        paths = {"controller": stem.with_suffix(".toml"), "summary": stem.with_suffix(".json"),
                 "figure": stem.with_suffix(".png")}
        outputs.write_into(paths["controller"], controller_toml(result.settings, provenance))
        calibrate.save_figure(result, paths["figure"])
        record["files"] = {kind: str(path) for kind, path in paths.items()}
        outputs.write_into(paths["summary"], strict_json(record) + "\n")
    _emit(args, record, calibrate.report_lines(record))


def _calibration_grid(args):
    from .calibrate import Grid
    values = units.parse_list(args.pulse_range, "time", "ms", field="--pulse-range")
    if len(values) != 2 or not 0 < values[0] <= values[1] <= 10e-3:
        raise UsageError(f"--pulse-range: wants LO,HI with 0 < LO <= HI <= 10 ms, e.g. 0.02,2 "
                         f"(got {args.pulse_range!r})")
    count = (values[1] - values[0]) / args.pulse_step + 1
    if count > 2000:
        raise UsageError(f"--pulse-step: {count:.3g} pulse lengths to try (at most 2,000); use a coarser step or a "
                         "narrower --pulse-range")
    leads = (values[1] + 0.4e-3) / args.lead_step
    offsets = 2 * args.offset_range / args.offset_step
    for option, runs in (("--lead-step", leads), ("--offset-step", offsets)):
        if runs > 5000:
            raise UsageError(f"{option}: {runs:.3g} calibration cells per scan (at most 5,000); use a coarser step "
                             "(the envelope's edges are bisected to --resolution anyway)")
    pulses = tuple(float(v) for v in np.round(np.arange(values[0], values[1] + 1e-12, args.pulse_step), 9))
    return Grid(pulses=pulses, lead_step=args.lead_step, offset_step=args.offset_step,
                offset_range=args.offset_range, resolution=args.resolution)


def _viewer_options(parser: argparse.ArgumentParser, live: bool = True):
    group = parser.add_argument_group("Rerun viewer (default: " + ("start the viewer installed with rerun-sdk if "
                                      "there is a display, else " if live else "") + "save an .rrd)")
    group.add_argument("--spawn", action="store_true",
                       help="start the Rerun viewer installed with rerun-sdk and stream to it (if it cannot start: "
                            "an .rrd instead)")
    group.add_argument("--connect", nargs="?", const="", metavar="URL",
                       help="stream to a running viewer (default rerun+http://127.0.0.1:9876/proxy; unreachable: "
                            "an .rrd instead)")
    group.add_argument("--viewer-bind", metavar="ADDRESS", default="127.0.0.1",
                       help="address a viewer started by vcyto listens on (default 127.0.0.1: this machine only; "
                            "0.0.0.0 opens port 9876 to the network)")
    group.add_argument("--save", metavar="FILE.rrd", help="write the Rerun view to this new file")
    group.add_argument("--no-viewer", action="store_true", help="no Rerun output")


def command_replay(args):
    from . import runfiles
    from .replay import ReplayError, replay
    path = Path(args.file)
    if not path.is_file():
        raise UsageError(f"recording {args.file} does not exist or is not a file")
    view = runfiles.choose_view(args, True, spawn_by_default=False, error=UsageError)
    if view.kind == "save" and view.path is None:
        view.path = outputs.unique_path(path.with_suffix(".replay.rrd"))
    try:
        result = replay(path, view.target())
    except (ReplayError, KeyError, TypeError, ValueError, IndexError, AttributeError) as error:
        if view.kind == "save" and view.path.exists():
            view.path.unlink(missing_ok=True)          # ours: created for this replay
        if isinstance(error, (ReplayError, ScenarioError)):
            raise UsageError(str(error)) from None
        raise UsageError(f"{path}: a message of the recording is malformed ({type(error).__name__}: "
                         f"{' '.join(str(error).split())[:120]}); it was not written by this vcyto") from None
    lines = [f"replayed {result['steps']} steps ({result['messages']} messages, "
             f"up to t = {result['last_time_ms']:.3f} ms) from {path}"]
    if result["damaged"]:
        lines.append(f"  the file is damaged or truncated ({result['problem']}): everything before the damage "
                     "was replayed, the rest is lost")
    lines.append(f"  Rerun: {view.describe()}")
    result["target"] = view.url if view.kind == "connect" else str(view.path)
    for note in view.notes:
        runfiles.say(note)
    _emit(args, result, lines)


def _run_metadata(scenario, settings) -> dict:
    import numpy
    import scipy
    import skfem

    from . import __version__
    from .config import scenario_to_toml
    return {"scenario_toml": scenario_to_toml(scenario), "seed": settings.seed, "model": settings.model,
            "arrivals": settings.arrivals, "detector": settings.detector, "controller": settings.controller,
            "command_line": " ".join(sys.argv), "vcyto": __version__, "numpy": numpy.__version__,
            "scipy": scipy.__version__, "scikit-fem": skfem.__version__, "python": sys.version.split()[0]}


def _output_directory(path: str | None) -> Path | None:
    """Create (if needed) and check the output directory before any work."""
    if path is None or path == "":
        return None
    directory = Path(path)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"cannot create output directory {path}: {error.strerror}") from None
    if not os.access(directory, os.W_OK):
        raise UsageError(f"output directory {path} is not writable")
    free = shutil.disk_usage(directory).free
    if free < MIN_FREE_BYTES:
        raise UsageError(f"only {free / 1e6:.0f} MB free in {path}: recordings need at least "
                         f"{MIN_FREE_BYTES / 1e6:.0f} MB; free some space or choose another --output")
    return directory


def command_sweep(args):
    from . import runfiles, sweep
    from .progress import Progress
    try:
        if args.scheduler is not None:
            sweep.check_scheduler(args.scheduler)
        spec = sweep.load_sweep(args.spec)
    except sweep.SweepError as error:
        raise UsageError(str(error)) from None
    output = _output_directory(args.output or str(Path("recordings") / "sweeps" / Path(args.spec).stem))
    workers = args.workers or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
    progress = Progress(quiet=args.quiet or args.json)
    try:
        with runfiles.signals_as_interrupt(_signals_seen), \
                sweep.executor(args.scheduler, workers) as (pool, slots, where):
            progress.note(f"{len(spec.points)} points on {where}; results in {output / sweep.RESULTS}")
            result = sweep.run_sweep(spec, output, pool, slots, progress, retry_failed=args.retry_failed,
                                     chunk=args.chunk, keep_old_rows=args.keep_old_rows)
    except sweep.SweepError as error:
        raise UsageError(str(error)) from None
    except KeyboardInterrupt:
        progress.close()
        print(f"vcyto: interrupted; finished points are in {output / sweep.RESULTS}; the same command completes "
              "the sweep", file=sys.stderr)
        raise
    finally:
        progress.close()
    result["executor"] = where
    if result["ok"]:
        sweep.save_plot(output / sweep.FIGURE, spec, result["rows"])
        result["files"]["figure"] = str(output / sweep.FIGURE)
    result["files"]["summary"] = str(output / sweep.SUMMARY)
    outputs.write_into(output / sweep.SUMMARY, strict_json(result) + "\n")
    _emit(args, result, sweep.report_lines(result))


def command_scenario(args):
    from .config import scenario_to_toml
    print(scenario_to_toml(_scenario(args)), end="")


def command_cache(args):
    """`vcyto cache [clear]`: where the set-up cache is and what it holds; `clear` empties it."""
    from .cache import clear, usage
    removed = clear() if args.action == "clear" else None
    result = usage()
    if removed is not None:
        result["removed"] = removed
    lines = [f"set-up cache: {result['directory']} ({'on' if result['enabled'] else 'off: VCYTO_CACHE=off'}), "
             f"{result['entries']} entries, {result['bytes'] / 1e6:.1f} MB"]
    if removed is not None:
        lines.append(f"removed {removed} files")
    _emit(args, result, lines)


def _cache_command(commands):
    cache = commands.add_parser("cache", help="the disk cache of set-up results (steady flows, solver couplings): "
                                "where it is, its size; 'clear' empties it")
    cache.add_argument("action", nargs="?", choices=("info", "clear"), default="info",
                       help="info (default): directory and size; clear: delete every entry")
    cache.add_argument("--json", action="store_true", help="print the result as JSON")
    cache.set_defaults(handler=command_cache)


def _stream_options(parser: argparse.ArgumentParser):
    """The options of one closed-loop run: arrivals, detector, controller, plant model, seed, duration.
    Quantities take a unit (``--lead 500us``); a bare number is in the unit the help names."""
    arrivals = parser.add_argument_group("cell arrivals (through the injection inlet)")
    arrivals.add_argument("--cells", help="explicit ordered list, e.g. RBC,melanoma,RBC (default RBC,melanoma "
                                          "unless --count is given)")
    arrivals.add_argument("--count", type=Integer(low=1), help="number of cells drawn from --mix (at least 1)")
    arrivals.add_argument("--mix", help="type mix for --count, e.g. RBC:0.9,melanoma:0.1")
    arrivals.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="500",
                          metavar="RATE", help="arrival rate, cells/s (default 500; e.g. 1kHz)")
    arrivals.add_argument("--arrivals", choices=("regular", "poisson"), default="regular",
                          help="arrival process (default regular)")
    arrivals.add_argument("--min-spacing", type=Quantity("time", "ms", low=0), default="0.5", metavar="TIME",
                          help="minimum time between arrivals (ms; default 0.5)")
    optics = parser.add_argument_group("detector and controller")
    optics.add_argument("--detection-window", default="30,60", metavar="X0,X1",
                        help="detection window along the channel (um; default 30,60; e.g. 30um,60um)")
    optics.add_argument("--gate", type=Number(low=0), default="0.5", help="fluorescence gate for type II (default 0.5)")
    optics.add_argument("--noise", type=Number(low=0, high=10), default="0.2",
                        help="fluorescence noise CV, 0-10 (default 0.2)")
    optics.add_argument("--controller", metavar="FILE",
                        help="controller settings file written by vcyto calibrate (default: the shipped calibration, "
                             "README 'Sorting like a sorter'); the options below override it")
    optics.add_argument("--delay", type=Quantity("time", "ms", low=0, low_open=True, high=10.0), metavar="TIME",
                        help="sort delay: detection to the SAW window at the reference velocity (ms; default 0.548)")
    optics.add_argument("--lead", type=Quantity("time", "ms", low=0, high=10.0), metavar="TIME",
                        help="IDT on this long before the predicted arrival (ms; default 0.3)")
    optics.add_argument("--pulse", type=Quantity("time", "ms", low=0, low_open=True, high=10.0), metavar="TIME",
                        help="IDT pulse length (ms; default 0.4)")
    optics.add_argument("--mode", choices=MODES,
                        help="sort mode: purity (abort when a type-I cell is predicted in the widened envelope; "
                             "the default), enrichment (abort only inside the envelope itself), yield (never abort), "
                             "single (purity, and abort two type-II cells in each other's envelope)")
    optics.add_argument("--envelope", metavar="LO,HI",
                        help="offsets from a sorted cell's arrival at which another cell is deflected too (ms; default "
                             "-0.236,0.27: vcyto calibrate on rom and feib, README 'Sorting like a sorter')")
    optics.add_argument("--timing-error", type=Quantity("time", "ms", low=0, high=10.0), metavar="TIME",
                        help="uncertainty of one predicted arrival; the purity window is the envelope widened by twice "
                             "this (ms; default 0.027)")
    optics.add_argument("--no-controller", action="store_true", help="never switch the IDT on")
    parser.add_argument("--model", choices=plants.MODELS, default="feib",
                        help="plant: full FE-IB (default); auto (rom, switching to feib while a melanoma "
                             "shares the channel or cells are close together); oneway (membranes deforming in "
                             "the blended steady flows, no feedback); "
                             "rom (cells as finite-size bodies in the blended steady flows, >10x faster than real "
                             "time without recording); or the streamline stand-in")
    parser.add_argument("--window-h", type=Quantity("length", "", low=0, low_open=True), metavar="LENGTH",
                        help="--model auto: mesh size of its feib windows (default 6.67um, or --mesh-h if coarser: "
                             "the coarsest mesh within tolerance on the tradeoff scenes; --window-h equal to "
                             "--mesh-h runs the windows at full resolution)")
    parser.add_argument("--seed", type=Integer(low=0, high=2**63 - 1), default="0",
                        help="random seed, >= 0 (default 0)")
    parser.add_argument("--max-time", type=Quantity("time", "ms", low=0, low_open=True, high=3.6e6), metavar="TIME",
                        help="cap the run at this simulated time (ms); by default it runs until every cell has left "
                             "(a capped run says so, its statistics are marked partial and cells never injected are "
                             "counted as such); exit status 1 unless --allow-partial")
    parser.add_argument("--allow-partial", action="store_true",
                        help="a run cut short by --max-time (or by cells stuck in the channel) exits 0")
    parser.add_argument("--allow-long", action="store_true",
                        help="run an FE-IB stream estimated to take more than 24 h (refused otherwise)")


def _calibration_options(parser: argparse.ArgumentParser):
    parser.add_argument("--model", choices=plants.CALIBRATION_MODELS, default="rom",
                        help="plant the calibration cells go through (default rom: about 1 s; feib: minutes to hours, "
                             "coarsen --pulse-step/--lead-step/--offset-step or give --pulse and --lead)")
    parser.add_argument("--detection-window", default="30,60", metavar="X0,X1", help="as for vcyto stream (um)")
    parser.add_argument("--gate", type=Number(low=0), default="0.5", help="fluorescence gate for type II (default 0.5)")
    parser.add_argument("--noise", type=Number(low=0, high=10), default="0.2",
                        help="fluorescence noise CV (default 0.2)")
    parser.add_argument("--controller", metavar="FILE", help="start from this controller file (mode and fields not "
                                                             "measured are kept)")
    parser.add_argument("--mode", choices=MODES, help="sort mode written to the controller file (default purity)")
    for name in ("delay", "envelope", "timing_error"):
        parser.set_defaults(**{name: None})
    parser.set_defaults(no_controller=False)
    time = Quantity("time", "ms", low=0, low_open=True, high=10.0)
    parser.add_argument("--pulse", type=time, metavar="TIME", help="with --lead: skip the pulse search and measure "
                                                                    "the envelope of this pulse (ms)")
    parser.add_argument("--lead", type=Quantity("time", "ms", low=0, high=10.0), metavar="TIME",
                        help="with --pulse: its lead (ms)")
    parser.add_argument("--pulse-range", default="0.02,2", metavar="LO,HI", help="pulse lengths searched (ms; "
                                                                                  "default 0.02,2)")
    parser.add_argument("--pulse-step", type=time, default="0.02", metavar="TIME",
                        help="pulse search step (ms; default 0.02)")
    parser.add_argument("--lead-step", type=time, default="0.01", metavar="TIME", help="lead search step (ms; "
                                                                                         "default 0.01)")
    parser.add_argument("--offset-step", type=time, default="0.02", metavar="TIME",
                        help="envelope scan step (ms; default 0.02); its edges are bisected to --resolution")
    parser.add_argument("--offset-range", type=time, default="1.5", metavar="TIME",
                        help="envelope scan from -this to +this (ms; default 1.5)")
    parser.add_argument("--resolution", type=time, default="0.0025", metavar="TIME",
                        help="envelope edge resolution (ms; default 0.0025)")
    parser.add_argument("--output", default="recordings", metavar="DIR",
                        help="where the controller file (.toml), the record (.json) and the plot (.png) go "
                             "(default recordings/; '' writes nothing)")
    _output_options(parser)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="vcyto", description="A virtual cytometer: a simulated SAW cell sorter. Quantities take a "
                                               "unit (25us, 0.5ms, 1kHz, 30um); a bare number is in the unit each "
                                               "option names. Exit status: 0 done, 1 numerical failure or a "
                                               "file that cannot be written, 2 bad input, 130/143 interrupted "
                                               "(SIGINT/SIGTERM).")
    from . import __version__
    parser.add_argument("--version", action="version", version=f"vcyto {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    flow = commands.add_parser("flow",
                               help="steady flow with the IDT off and on; where the injection streamline leaves")
    _scenario_options(flow)
    flow.add_argument("--png", metavar="FILE", help="save the speed field with the streamlines as a PNG")
    flow.add_argument("--calibrate-streaming", action="store_true",
                      help="find the streaming force that deflects the streamline as far as the paper's jet")
    _output_options(flow)
    flow.set_defaults(handler=command_flow)

    paper = commands.add_parser("paper", help="run the paper's scenario 1 (RBC, IDT off) or 2 (melanoma, IDT on)")
    paper.add_argument("number", type=int, choices=(1, 2),
                       help="1: RBC, IDT off, dt 2.5 us; 2: melanoma, IDT on, dt 25 us")
    _scenario_options(paper)
    _tolerance_options(paper)
    paper.add_argument("--png", metavar="FILE",
                       help="where to save the path over the flow (default recordings/paperN.png)")
    paper.add_argument("--no-png", action="store_true", help="do not save a PNG")
    paper.add_argument("--allow-long", action="store_true", help="run even if estimated to take more than 24 h")
    paper.add_argument("--max-time", type=Quantity("time", "ms", low=0, low_open=True, high=3600.0), default="20",
                       metavar="TIME", help="give up (outlet 'lost') after this much simulated time (ms; default 20)")
    _output_options(paper)
    paper.set_defaults(handler=command_paper)

    stream = commands.add_parser("stream",
                                 help="run cells through the closed sorting loop (detector, controller, plant)")
    _scenario_options(stream)
    _tolerance_options(stream)
    _stream_options(stream)
    stream.add_argument("--output", default="recordings", metavar="DIR",
                        help="where the run's files go: the MCAP recording, FCS 3.1 detector events, the gate "
                             "(Gating-ML 2.0) and a JSON summary (default recordings/; --output '' writes nothing)")
    stream.add_argument("--name", metavar="NAME",
                        help="name the run's files NAME.mcap, NAME.json, NAME.fcs, NAME.gating.xml, NAME.rrd (default "
                             "stream-DATE-TIME-MILLISECONDS-PID); a name whose files exist is refused")
    stream.add_argument("--no-record", action="store_true", help="no MCAP recording")
    stream.add_argument("--flush-every", type=Integer(low=1), default="50", metavar="N",
                        help="flush the recording every N control periods: a crash loses at most N (default 50)")
    stream.add_argument("--field-every", type=Integer(low=0), default="200", metavar="N",
                        help="record the velocity field every N control periods, 0 = never (default 200)")
    _viewer_options(stream)
    _output_options(stream)
    stream.set_defaults(handler=command_stream)

    calibration = commands.add_parser("calibrate", help="measure the sort envelope (sort delay, shortest reliable "
                                                        "pulse, deflection envelope) and write a controller file")
    _scenario_options(calibration)
    _calibration_options(calibration)
    calibration.set_defaults(handler=command_calibrate)

    replay_parser = commands.add_parser("replay", help="re-log an MCAP recording to Rerun")
    replay_parser.add_argument("file", metavar="FILE.mcap", help="a recording written by vcyto stream")
    replay_parser.add_argument("--spawn", action="store_true", help="start a Rerun viewer (needs a display)")
    replay_parser.add_argument("--connect", nargs="?", const="", metavar="URL", help="stream to a running viewer")
    replay_parser.add_argument("--save", metavar="FILE.rrd", help="write an .rrd file (default: next to the recording)")
    _output_options(replay_parser)
    replay_parser.set_defaults(handler=command_replay)

    stability = commands.add_parser("stability", help="measure the largest stable dt per cell type and mesh size")
    _scenario_options(stability)
    stability.add_argument("--cells", default="RBC,melanoma", help="cell types (default RBC,melanoma)")
    stability.add_argument("--mesh-sizes", default="6.667um,3.333um,1.667um",
                           help="comma-separated mesh sizes (default 6.667um,3.333um,1.667um)")
    _output_options(stability)
    stability.set_defaults(handler=command_stability)

    extremes = commands.add_parser("extremes", help="the FE-IB plant at extreme settings: each case runs correctly "
                                                    "or stops with a specific diagnosis")
    _scenario_options(extremes)
    extremes.add_argument("--fast", action="store_true", help="the test suite's variants: coarse meshes, short runs")
    extremes.add_argument("--case", metavar="NAMES", help="only these cases, e.g. a1,c2 (default: all)")
    _output_options(extremes)
    extremes.set_defaults(handler=command_extremes)

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
    _output_options(sweep)
    sweep.set_defaults(handler=command_sweep)

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
    _scenario_options(tradeoff_parser)
    _output_options(tradeoff_parser)
    tradeoff_parser.set_defaults(handler=command_tradeoff)
    scenario = commands.add_parser("scenario",
                                   help="print the effective scenario (defaults + file + overrides) as TOML")
    _scenario_options(scenario)
    scenario.set_defaults(handler=command_scenario)

    _cache_command(commands)
    bench = commands.add_parser("bench", help="benchmarks")
    targets = bench.add_subparsers(dest="target", required=True, metavar="TARGET")
    _tolerance_bench_command(targets)
    fluid = targets.add_parser("fluid", help="set-up and per-step cost of the fluid solver, per convection treatment")
    _scenario_options(fluid)
    fluid.add_argument("--repeats", type=Integer(low=2, high=100_000), default="40",
                       help="timed repetitions per median, >= 2 (default 40)")
    _output_options(fluid)
    fluid.set_defaults(handler=command_bench)
    treatments = targets.add_parser("treatments", help="how far imex, oseen and stokes steps differ from implicit ones")
    _scenario_options(treatments)
    treatments.add_argument("--steps", type=Integer(low=1, high=1_000_000), default="20",
                            help="steps after switching the IDT on (default 20)")
    _output_options(treatments)
    treatments.set_defaults(handler=command_bench)
    paper_bench = targets.add_parser("paper", help="a paper scenario with imex and with implicit convection: "
                                                   "outlet, exit time and path differences")
    paper_bench.add_argument("number", type=int, choices=(1, 2))
    _scenario_options(paper_bench)
    _output_options(paper_bench)
    paper_bench.set_defaults(handler=command_bench)
    auto_bench = targets.add_parser("auto",
                                    help="a mixed stream with --model auto and with feib: outcomes and wall time")
    auto_bench.add_argument("--count", type=Integer(low=1), default="100", help="cells (default 100)")
    auto_bench.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="500",
                            help="Poisson arrival rate, cells/s (default 500)")
    auto_bench.add_argument("--mix", default="RBC:0.8,melanoma:0.2", help="type mix (default RBC:0.8,melanoma:0.2)")
    auto_bench.add_argument("--seed", type=Integer(low=0, high=2**63 - 1), default="0", help="random seed (default 0)")
    _scenario_options(auto_bench)
    _output_options(auto_bench)
    auto_bench.set_defaults(handler=command_bench)
    membrane_bench = targets.add_parser("membrane", help="the paper's literal membrane method against the conserving "
                                                         "one: area kept, point spacing, outlets, cost per step")
    membrane_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="2",
                                help="interleaved runs per scenario (default 2)")
    _scenario_options(membrane_bench)
    _output_options(membrane_bench)
    membrane_bench.set_defaults(handler=command_bench)
    recording_bench = targets.add_parser("recording",
                                         help="wall-time overhead of recording (MCAP + Rerun) an FE-IB stream")
    recording_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="3",
                                 help="interleaved pairs without/with (default 3)")
    _scenario_options(recording_bench)
    _output_options(recording_bench)
    recording_bench.set_defaults(handler=command_bench)
    sweep_bench = targets.add_parser("sweep", help="one sweep on 1 and on 2 local workers: the speed-up")
    sweep_bench.add_argument("spec", nargs="?", metavar="SPEC",
                             help="sweep spec (default examples/sweeps/bench-rom.toml: 8 rom plants, 200 cells each)")
    sweep_bench.add_argument("--workers", default="1,2", metavar="N,M", help="pool sizes to compare (default 1,2)")
    sweep_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="1",
                             help="runs per pool size; medians (default 1)")
    _output_options(sweep_bench)
    sweep_bench.set_defaults(handler=command_bench)
    sort_bench = targets.add_parser("sort", help="long rom sorting runs with recording: loop cost per event, "
                                                 "linearity in run length, peak memory, file sizes")
    _scenario_options(sort_bench)
    sort_bench.add_argument("--counts", default="1000,10000", help="cells offered per run (default 1000,10000)")
    sort_bench.add_argument("--rate", type=float, default=2000.0,
                            help="offered rate, cells/s (default 2000: about 1000 events/s after the dead time)")
    sort_bench.add_argument("--seed", type=int, default=3, help="random seed (default 3)")
    sort_bench.add_argument("--no-record", action="store_true", help="no MCAP and no Rerun")
    sort_bench.add_argument("--no-rerun", action="store_true", help="MCAP only")
    _output_options(sort_bench)
    sort_bench.set_defaults(handler=command_bench)

    realtime_bench = targets.add_parser("realtime", help="real-time factor of the closed loop with the rom plant: "
                                                         "a Poisson stream, detector and controller, no recording")
    _scenario_options(realtime_bench)
    realtime_bench.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="1000",
                                help="arrival rate in cells/s (default 1000; e.g. 1kHz)")
    realtime_bench.add_argument("--duration", type=Quantity("time", "s", low=0, low_open=True), default="1s",
                                metavar="TIME",
                                help="device time of arrivals (s); count = rate x duration (default 1s)")
    realtime_bench.add_argument("--mix", default="RBC:0.9,melanoma:0.1", help="type mix (default RBC:0.9,melanoma:0.1)")
    realtime_bench.add_argument("--repeats", type=Integer(low=1, high=1000), default="3",
                                help="runs of the same stream (default 3)")
    realtime_bench.add_argument("--control-period", type=Quantity("time", "s", low=0, low_open=True, high=1.0),
                                metavar="TIME", help="control period (s; default: the plant's, 20us)")
    realtime_bench.add_argument("--seed", type=Integer(low=0, high=2**63 - 1), default="0",
                                help="random seed (default 0)")
    _output_options(realtime_bench)
    realtime_bench.set_defaults(handler=command_bench)
    controller_bench = targets.add_parser("controller", help="decision latency of the sorting controller")
    controller_bench.add_argument("--events", type=Integer(low=1, high=10_000_000), default="20000",
                                  help="synthetic events (default 20000)")
    _output_options(controller_bench)
    controller_bench.set_defaults(handler=command_bench)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        install_cache()
        status = args.handler(args)
    except (ScenarioError, UsageError, units.QuantityError) as error:
        return _fail(error, EXIT_INPUT)
    except (NumericalBlowUp, SolverError) as error:
        return _fail(error, EXIT_NUMERICAL)
    except RunStopped as stopped:
        return stopped.status
    except StreamStopped as stopped:            # a loop run by another command than stream (bench, tradeoff)
        if stopped.status != "interrupted":
            return _fail(stopped, EXIT_NUMERICAL)
        print("vcyto: interrupted", file=sys.stderr)
        return EXIT_SIGTERM if _signals_seen.get("last") == "SIGTERM" else EXIT_SIGINT
    except KeyboardInterrupt:
        print("vcyto: interrupted", file=sys.stderr)
        return EXIT_SIGTERM if _signals_seen.get("last") == "SIGTERM" else EXIT_SIGINT
    except MemoryError:
        return _fail(MemoryError("out of memory: the run needs more memory than this machine has; use a coarser "
                                 "mesh, fewer cells or fewer sweep points"), EXIT_NUMERICAL)
    except OSError as error:          # a disk that fills up, a file that vanished: the environment, not a bug
        where = f" {error.filename}" if getattr(error, "filename", None) else ""
        return _fail(OSError(f"cannot write or read{where}: {error.strerror or error}"), EXIT_NUMERICAL)
    except Exception as error:  # a bug, not bad input: say so in one line, keep the traceback on request
        if os.environ.get("VCYTO_DEBUG"):
            raise
        print(f"vcyto: internal error: {type(error).__name__}: {' '.join(str(error).split())} (set VCYTO_DEBUG=1 for "
              "the traceback; please report it)", file=sys.stderr)
        return EXIT_INTERNAL
    return status or 0


def _fail(error: Exception, status: int) -> int:
    if os.environ.get("VCYTO_DEBUG"):
        raise error
    print(f"vcyto: error: {' '.join(str(error).split())}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
