"""The `vcyto` command line. Bad input ends with one line on stderr and exit status 2; a numerical
failure with one line and status 1; never a traceback (set VCYTO_DEBUG=1 to see one)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

from sim.fluid import NumericalBlowUp
from sim.linalg import SolverError
from sim.scenario import CONVECTIONS, MEMBRANE_METHODS, SAW_MODELS, ScenarioError

from .cache import install_default as install_cache
from .config import load_scenario

EXIT_INPUT = 2
EXIT_NUMERICAL = 1
EXIT_INTERNAL = 3
MIN_FREE_BYTES = 100e6


class UsageError(ValueError):
    """Bad command-line input that is not a scenario field."""


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
    group.add_argument("--dt", metavar="TIME", help="time step (default 2.5us; vcyto paper: the paper's step for the scenario)")
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
    return load_scenario(args.scenario, overrides)


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


def _output_path(path: str | None) -> Path | None:
    """Check before any work that an output file can be written."""
    if path is None:
        return None
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise UsageError(f"cannot write {path}: directory {directory} does not exist")
    if not os.access(directory, os.W_OK):
        raise UsageError(f"cannot write {path}: directory {directory} is not writable")
    return target


def _plain(value):
    """JSON fallback for numpy scalars and arrays."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def _emit(args, result: dict, lines: list[str]):
    if args.json:
        print(json.dumps(result, indent=2, default=_plain))
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
        if args.events < 1:
            raise UsageError(f"--events must be at least 1 (got {args.events})")
        result = bench.bench_controller(args.events)
        _emit(args, result, bench.controller_lines(result))
        return
    if args.target == "sweep":
        _bench_sweep(args, bench)
        return
    scenario = _scenario(args)
    if args.target == "realtime":
        _bench_realtime(args, bench, scenario, progress)
        return
    if args.target == "recording":
        from .progress import Progress
        if args.repeats < 1:
            raise UsageError(f"--repeats must be at least 1 (got {args.repeats})")
        result = bench.bench_recording(scenario, repeats=args.repeats, progress=Progress(quiet=args.quiet or args.json))
        _emit(args, result, bench.recording_lines(result))
        return
    if args.target == "auto":
        from .progress import Progress
        if args.count < 1:
            raise UsageError(f"--count must be at least 1 (got {args.count})")
        result = bench.bench_auto(scenario, args.count, args.rate, _mix(args.mix), args.seed,
                                  progress=Progress(quiet=args.quiet or args.json))
        _emit(args, result, bench.auto_lines(result))
        return
    if args.target == "membrane":
        from .progress import Progress
        if args.repeats < 1:
            raise UsageError(f"--repeats must be at least 1 (got {args.repeats})")
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
        if args.steps < 1:
            raise UsageError(f"--steps must be at least 1 (got {args.steps})")
        result = bench.bench_treatments(scenario, args.steps, progress)
        _emit(args, result, bench.treatment_lines(result))
        return
    if args.repeats < 2:
        raise UsageError(f"--repeats must be at least 2 (got {args.repeats})")
    result = bench.bench_fluid(scenario, args.repeats, progress)
    _emit(args, result, bench.report_lines(result))


def _bench_realtime(args, bench, scenario, progress):
    from .config import parse_quantity
    if args.repeats < 1 or args.rate <= 0:
        raise UsageError("--repeats must be at least 1 and --rate positive")
    try:
        duration = parse_quantity(args.duration)
        period = parse_quantity(args.control_period) if args.control_period else None
    except ValueError as error:
        raise UsageError(f"--duration/--control-period: {error}") from None
    if not duration > 0 or (period is not None and not period > 0):
        raise UsageError("--duration and --control-period must be positive times such as 1s or 10us")
    mix = _mix(args.mix)
    for name, _ in mix:
        scenario.cell_type(name)
    if any(weight < 0 for _, weight in mix) or sum(weight for _, weight in mix) <= 0:
        raise UsageError(f"--mix weights must be >= 0 with a positive sum (got {args.mix!r})")
    result = bench.bench_realtime(scenario, args.rate, duration, mix, args.repeats, period, args.seed, progress)
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
    png = _output_path(args.png if args.png else f"recordings/paper{args.number}.png") if not args.no_png else None
    if args.max_time <= 0:
        raise UsageError(f"--max-time must be positive (got {args.max_time} ms)")
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = paper.run_paper(args.number, scenario, args.max_time * 1e-3, progress)
    finally:
        progress.close()
    lines = paper.report_lines(result)
    if png:
        paper.save_png(str(png), result, scenario)
        result["png"] = str(png)
        lines.append(f"  saved {png}")
    _emit(args, paper.public(result), lines)


def _lengths(text: str) -> list[float]:
    from .config import parse_quantity
    try:
        values = [parse_quantity(part) for part in text.split(",") if part.strip()]
    except ValueError as error:
        raise UsageError(f"--mesh-sizes: {error}") from None
    if not values or any(v <= 0 for v in values):
        raise UsageError(f"--mesh-sizes needs positive lengths such as 6.67um,3.33um (got {text!r})")
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
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = stabilitymap.stability_map(scenario, cells, sizes, progress)
    finally:
        progress.close()
    _emit(args, result, stabilitymap.report_lines(result))


def _positive_list(text: str, option: str, example: str, parse) -> list[float]:
    return _number_list(text, option, example, parse, lambda v: v > 0, "positive")


def _non_negative_list(text: str, option: str, example: str) -> list[float]:
    return _number_list(text, option, example, float, lambda v: v >= 0, "non-negative")


def _number_list(text: str, option: str, example: str, parse, valid, kind: str) -> list[float]:
    try:
        values = [parse(part) for part in text.split(",") if part.strip()]
    except ValueError:
        values = []
    if not values or not all(math.isfinite(v) and valid(v) for v in values):
        raise UsageError(f"{option} needs {kind} numbers separated by commas, such as {example} (got {text!r})")
    return values


def _times_before_pulse_end(text: str, option: str, example: str, what: str) -> list[float]:
    """Times in ms (returned in s) for the extra tradeoff scenes: positive and below 2 ms."""
    times = _positive_list(text, option, example, lambda part: float(part) * 1e-3)
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
        values = _positive_list(args.coupling, "--coupling", "2,2.5,3", float)
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
    pairs = []
    for part in text.split(","):
        name, _, weight = part.partition(":")
        try:
            pairs.append((name.strip(), float(weight)))
        except ValueError:
            raise UsageError(f"--mix wants TYPE:WEIGHT pairs such as RBC:0.9,melanoma:0.1 (got {text!r})") from None
    return tuple(pairs)


def stream_settings(args, scenario):
    """The ``StreamSettings`` of the stream options in ``args`` (vcyto stream, and each point of vcyto sweep)."""
    from controller.detector import DetectorSettings
    from controller.sorter import ControllerSettings
    from sim.arrivals import Arrivals
    from . import stream
    try:
        cells = args.cells if args.cells is not None else ("" if args.count else "RBC,melanoma")
        arrivals = Arrivals(cells=_cell_list(cells) if cells else (), count=args.count or 0,
                            mix=_mix(args.mix) if args.mix else (), rate=args.rate, process=args.arrivals,
                            min_spacing=args.min_spacing * 1e-3)
        for name in set(arrivals.cells) | {name for name, _ in arrivals.mix}:
            scenario.cell_type(name)
        low, high = (float(v) * 1e-6 for v in args.detection_window.split(","))
        if high > scenario.channel.length:
            raise UsageError(f"--detection-window {args.detection_window} um lies outside the channel "
                             f"(0, {scenario.channel.length * 1e6:g}) um")
        detector = DetectorSettings(window=(low, high), gate=args.gate, noise_cv=args.noise)
        controller = ControllerSettings(delay=args.delay * 1e-3, lead=args.lead * 1e-3, pulse=args.pulse * 1e-3,
                                        mode=args.mode, coincidence_window=args.coincidence * 1e-3,
                                        enabled=not args.no_controller)
        window = getattr(args, "window_h", None)
        if window is not None:
            from .config import parse_quantity
            if args.model != "auto":
                raise UsageError(f"--window-h sets the feib windows of --model auto (the model is {args.model}): "
                                 "drop it or add --model auto")
            text, window = window, parse_quantity(window)
            if not window > 0:
                raise UsageError(f"--window-h must be a positive length such as 6.67um (got {text!r})")
        return stream.StreamSettings(arrivals, detector, controller, args.model, args.seed,
                                     max_time=args.max_time * 1e-3, window_mesh_h=window)
    except ValueError as error:
        if isinstance(error, (UsageError, ScenarioError)):
            raise
        raise UsageError(str(error)) from None



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
    from . import stream
    from .progress import Progress
    scenario = _scenario(args)
    settings = stream_settings(args, scenario)
    output = _output_directory(args.output)
    run_id = time.strftime("stream-%Y%m%d-%H%M%S")
    sinks = []
    if output is not None and not args.no_record:
        from .recording import McapRecorder
        sinks.append(McapRecorder(output / f"{run_id}.mcap", _run_metadata(scenario, settings),
                                  flush_every=args.flush_every, field_every=args.field_every))
    target = _viewer_target(args, output / f"{run_id}.rrd" if output is not None else None, spawn_by_default=True)
    if target is not None:
        from .viewer import RerunSink
        sinks.append(RerunSink(scenario, settings.detector.window, target, field_every=args.field_every))
    progress = Progress(quiet=args.quiet or args.json)
    from .sinks import BackgroundSinks
    background = BackgroundSinks(sinks) if sinks else None      # their work overlaps the plant's solve
    try:
        with _sigterm_as_interrupt():
            result = stream.run_stream(scenario, settings, progress, sinks=[background] if background else [])
    except KeyboardInterrupt:
        progress.close()
        if background:
            background.close()
        for sink in sinks:
            if hasattr(sink, "path"):
                print(f"vcyto: interrupted; the recording up to now is in {sink.path}", file=sys.stderr)
        raise
    finally:
        progress.close()
        if background:
            background.close()
    lines = stream.report_lines(result)
    result["files"] = {}
    for sink in sinks:
        if hasattr(sink, "path"):
            result["files"]["mcap"] = str(sink.path)
            lines.append(f"recording: {sink.path} (MCAP; replay with: vcyto replay {sink.path})")
    if target is not None:
        result["files"]["rerun"] = target[0] if target[0] != "save" else str(target[1])
        lines.append(f"Rerun: {'saved to ' + str(target[1]) if target[0] == 'save' else target[0]}")
    if output is not None:
        from . import fcs
        fcs_path = fcs.write_fcs(output / f"{run_id}.fcs", result, {"VCYTO_COMMAND": " ".join(sys.argv)})
        summary_path = output / f"{run_id}.json"
        summary_path.write_text(json.dumps(result, indent=2, default=_plain))
        result.setdefault("files", {}).update({"fcs": str(fcs_path), "summary": str(summary_path)})
        lines.append(f"detector events: {fcs_path} (FCS 3.1); summary: {summary_path}")
    _emit(args, result, lines)


def _viewer_target(args, default_save: Path | None, spawn_by_default: bool):
    """Where a Rerun view goes: --save, --connect, --spawn, else a viewer (if ``spawn_by_default`` and there is a
    display) or ``default_save``. Spawning without a display would block, so it falls back to the file."""
    from .viewer import has_display
    if getattr(args, "no_viewer", False):
        return None
    if args.save:
        return ("save", _output_path(args.save))
    if args.connect is not None:
        return ("connect", args.connect)
    if (args.spawn or spawn_by_default) and has_display():
        return ("spawn",)
    if args.spawn:
        print("vcyto: no display for --spawn; saving the Rerun view to a file instead", file=sys.stderr)
    return ("save", default_save) if default_save is not None else None


def _viewer_options(parser: argparse.ArgumentParser):
    group = parser.add_argument_group("Rerun viewer (default: spawn one if there is a display, else save an .rrd)")
    group.add_argument("--spawn", action="store_true", help="start a Rerun viewer and stream to it")
    group.add_argument("--connect", nargs="?", const="", metavar="URL",
                       help="stream to a running viewer (default rerun+http://127.0.0.1:9876/proxy)")
    group.add_argument("--save", metavar="FILE.rrd", help="write the Rerun view to a file")
    group.add_argument("--no-viewer", action="store_true", help="no Rerun output")


def command_replay(args):
    from .replay import ReplayError, replay
    path = Path(args.file)
    if not path.is_file():
        raise UsageError(f"recording {args.file} does not exist")
    target = _viewer_target(args, path.with_suffix(".replay.rrd"), spawn_by_default=False)
    try:
        result = replay(path, target)
    except ReplayError as error:
        raise UsageError(str(error)) from None
    lines = [f"replayed {result['steps']} steps ({result['messages']} messages, up to t = {result['last_time_ms']:.3f} ms)"
             f" from {path}"]
    if result["damaged"]:
        lines.append(f"  the file is damaged or truncated ({result['problem']}): everything before the damage "
                     "was replayed, the rest is lost")
    lines.append(f"  Rerun: {'saved to ' + str(target[1]) if target[0] == 'save' else target[0]}")
    result["target"] = str(target[1]) if target[0] == "save" else target[0]
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


class _sigterm_as_interrupt:
    """Within the block, SIGTERM raises KeyboardInterrupt so files are finalised as on Ctrl-C."""

    def __enter__(self):
        import signal
        def interrupt(signum, frame):
            raise KeyboardInterrupt
        try:
            self._previous = signal.signal(signal.SIGTERM, interrupt)
        except ValueError:          # not the main thread
            self._previous = None
        return self

    def __exit__(self, *exc):
        import signal
        if self._previous is not None:
            signal.signal(signal.SIGTERM, self._previous)
        return False


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
    from . import sweep
    from .progress import Progress
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be at least 1 (got {args.workers})")
    if args.chunk < 1:
        raise UsageError(f"--chunk must be at least 1 (got {args.chunk})")
    try:
        spec = sweep.load_sweep(args.spec)
    except sweep.SweepError as error:
        raise UsageError(str(error)) from None
    output = _output_directory(args.output or str(Path("recordings") / "sweeps" / Path(args.spec).stem))
    workers = args.workers or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
    progress = Progress(quiet=args.quiet or args.json)
    try:
        with _sigterm_as_interrupt(), sweep.executor(args.scheduler, workers) as (pool, slots, where):
            progress.note(f"{len(spec.points)} points on {where}; results in {output / sweep.RESULTS}")
            result = sweep.run_sweep(spec, output, pool, slots, progress, retry_failed=args.retry_failed,
                                     chunk=args.chunk)
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
    (output / sweep.SUMMARY).write_text(json.dumps(result, indent=2, default=_plain))
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
    """The options of one closed-loop run: arrivals, detector, controller, plant model, seed, duration."""
    arrivals = parser.add_argument_group("cell arrivals (through the injection inlet)")
    arrivals.add_argument("--cells", help="explicit ordered list, e.g. RBC,melanoma,RBC (default RBC,melanoma "
                                          "unless --count is given)")
    arrivals.add_argument("--count", type=int, help="number of cells drawn from --mix")
    arrivals.add_argument("--mix", help="type mix for --count, e.g. RBC:0.9,melanoma:0.1")
    arrivals.add_argument("--rate", type=float, default=500.0, help="arrival rate in cells/s (default 500)")
    arrivals.add_argument("--arrivals", choices=("regular", "poisson"), default="regular",
                          help="arrival process (default regular)")
    arrivals.add_argument("--min-spacing", type=float, default=0.5, metavar="MS",
                          help="minimum time between arrivals in ms (default 0.5)")
    optics = parser.add_argument_group("detector and controller")
    optics.add_argument("--detection-window", default="30,60", metavar="X0,X1",
                        help="detection window along the channel in um (default 30,60)")
    optics.add_argument("--gate", type=float, default=0.5, help="fluorescence gate for type II (default 0.5)")
    optics.add_argument("--noise", type=float, default=0.2, help="fluorescence noise CV (default 0.2)")
    optics.add_argument("--delay", type=float, default=0.56, metavar="MS",
                        help="calibrated delay from the detector to the SAW window at 0.095 m/s (default 0.56)")
    optics.add_argument("--lead", type=float, default=0.5, metavar="MS",
                        help="IDT on this long before the predicted arrival (default 0.5)")
    optics.add_argument("--pulse", type=float, default=1.2, metavar="MS", help="IDT pulse length (default 1.2)")
    optics.add_argument("--mode", choices=("purity", "yield"), default="purity", help="sort mode (default purity)")
    optics.add_argument("--coincidence", type=float, default=1.2, metavar="MS",
                        help="purity mode aborts a sort with a type-I cell predicted within half this (default 1.2)")
    optics.add_argument("--no-controller", action="store_true", help="never switch the IDT on")
    parser.add_argument("--model", choices=("feib", "auto", "oneway", "rom", "streamline"), default="feib",
                        help="plant: full FE-IB (default); auto (rom, switching to feib while a melanoma "
                             "shares the channel or cells are close together); oneway (membranes deforming in "
                             "the blended steady flows, no feedback); "
                             "rom (cells as finite-size bodies in the blended steady flows, >10x faster than real "
                             "time without recording); or the streamline stand-in")
    parser.add_argument("--window-h", metavar="LENGTH",
                        help="--model auto: mesh size of its feib windows (default 6.67um, or --mesh-h if coarser: "
                             "the coarsest mesh within tolerance on the tradeoff scenes; --window-h equal to "
                             "--mesh-h runs the windows at full resolution)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--max-time", type=float, default=50.0, metavar="MS", help="stop after this simulated time")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vcyto", description="A virtual cytometer: a simulated SAW cell sorter.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    flow = commands.add_parser("flow", help="steady flow with the IDT off and on; where the injection streamline leaves")
    _scenario_options(flow)
    flow.add_argument("--png", metavar="FILE", help="save the speed field with the streamlines as a PNG")
    flow.add_argument("--calibrate-streaming", action="store_true",
                      help="find the streaming force that deflects the streamline as far as the paper's jet")
    _output_options(flow)
    flow.set_defaults(handler=command_flow)

    paper = commands.add_parser("paper", help="run the paper's scenario 1 (RBC, IDT off) or 2 (melanoma, IDT on)")
    paper.add_argument("number", type=int, choices=(1, 2), help="1: RBC, IDT off, dt 2.5 us; 2: melanoma, IDT on, dt 25 us")
    _scenario_options(paper)
    _tolerance_options(paper)
    paper.add_argument("--png", metavar="FILE", help="where to save the path over the flow (default recordings/paperN.png)")
    paper.add_argument("--no-png", action="store_true", help="do not save a PNG")
    paper.add_argument("--max-time", type=float, default=20.0, metavar="MS",
                       help="give up (outlet 'lost') after this much simulated time in ms (default 20)")
    _output_options(paper)
    paper.set_defaults(handler=command_paper)

    stream = commands.add_parser("stream", help="run cells through the closed sorting loop (detector, controller, plant)")
    _scenario_options(stream)
    _tolerance_options(stream)
    _stream_options(stream)
    stream.add_argument("--output", default="recordings", metavar="DIR",
                        help="where the run's files go: the MCAP recording, FCS 3.1 detector events and a JSON "
                             "summary (default recordings/; --output '' writes nothing)")
    stream.add_argument("--no-record", action="store_true", help="no MCAP recording")
    stream.add_argument("--flush-every", type=int, default=50, metavar="N",
                        help="flush the recording every N control periods: a crash loses at most N (default 50)")
    stream.add_argument("--field-every", type=int, default=200, metavar="N",
                        help="record the velocity field every N control periods, 0 = never (default 200)")
    _viewer_options(stream)
    _output_options(stream)
    stream.set_defaults(handler=command_stream)

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
    sweep.add_argument("--output", metavar="DIR", help="where results.csv, summary.png and sweep.json go; a re-run "
                                                       "skips the points already there (default recordings/sweeps/SPEC)")
    sweep.add_argument("--workers", type=int, metavar="N", help="worker processes (default: the CPU count)")
    sweep.add_argument("--scheduler", metavar="ADDRESS", help="run on the Dask scheduler at ADDRESS (e.g. "
                                                              "tcp://host:8786), or 'local' to start a LocalCluster")
    sweep.add_argument("--retry-failed", action="store_true", help="run the points recorded as failed again")
    sweep.add_argument("--chunk", type=int, default=8, metavar="N",
                       help="points sharing a plant go to one worker N at a time (default 8)")
    _output_options(sweep)
    sweep.set_defaults(handler=command_sweep)

    tradeoff_parser = commands.add_parser("tradeoff", help="speed against accuracy of the plant models on fixed scenes "
                                                           "(table, CSV, Pareto plot)")
    tradeoff_parser.add_argument("--fast", action="store_true",
                                 help="the reduced set (coarse mesh, reference FE-IB at h = 6.67 um; a few minutes)")
    tradeoff_parser.add_argument("--output", default="recordings/tradeoff", metavar="DIR",
                                 help="where tradeoff.md, tradeoff.csv and tradeoff.png go (default recordings/tradeoff)")
    tradeoff_parser.add_argument("--coupling", metavar="LIST",
                                 help="add an auto level for each coupling factor, e.g. 2,2.5 (the default auto level has coupling 3)")
    tradeoff_parser.add_argument("--stiff-capillary", metavar="LIST",
                                 help="add an auto level for each stiff-cell capillary number, e.g. 0,100 (0 turns the "
                                      "stiff-cell rule off; the default auto level has 100)")
    tradeoff_parser.add_argument("--pair-gap", metavar="MS",
                                 help="add a close-pair scene for each gap (ms, below 2) between the melanoma and the "
                                      "RBC, e.g. 0.5,1.0 (the fixed scene's gap is 0.25)")
    tradeoff_parser.add_argument("--lone-rbc", metavar="MS",
                                 help="add a scene for each time (ms, below 2) with an RBC alone injected then under "
                                      "the pair scenes' 0.9-2.1 ms pulse, e.g. 0.565 (the pair's RBC without the melanoma)")
    _scenario_options(tradeoff_parser)
    _output_options(tradeoff_parser)
    tradeoff_parser.set_defaults(handler=command_tradeoff)
    scenario = commands.add_parser("scenario", help="print the effective scenario (defaults + file + overrides) as TOML")
    _scenario_options(scenario)
    scenario.set_defaults(handler=command_scenario)

    _cache_command(commands)
    bench = commands.add_parser("bench", help="benchmarks")
    targets = bench.add_subparsers(dest="target", required=True, metavar="TARGET")
    _tolerance_bench_command(targets)
    fluid = targets.add_parser("fluid", help="set-up and per-step cost of the fluid solver, per convection treatment")
    _scenario_options(fluid)
    fluid.add_argument("--repeats", type=int, default=40, help="timed repetitions per median (default 40)")
    _output_options(fluid)
    fluid.set_defaults(handler=command_bench)
    treatments = targets.add_parser("treatments", help="how far imex, oseen and stokes steps differ from implicit ones")
    _scenario_options(treatments)
    treatments.add_argument("--steps", type=int, default=20, help="steps after switching the IDT on (default 20)")
    _output_options(treatments)
    treatments.set_defaults(handler=command_bench)
    paper_bench = targets.add_parser("paper", help="a paper scenario with imex and with implicit convection: "
                                                   "outlet, exit time and path differences")
    paper_bench.add_argument("number", type=int, choices=(1, 2))
    _scenario_options(paper_bench)
    _output_options(paper_bench)
    paper_bench.set_defaults(handler=command_bench)
    auto_bench = targets.add_parser("auto", help="a mixed stream with --model auto and with feib: outcomes and wall time")
    auto_bench.add_argument("--count", type=int, default=100, help="cells (default 100)")
    auto_bench.add_argument("--rate", type=float, default=500.0, help="Poisson arrival rate, cells/s (default 500)")
    auto_bench.add_argument("--mix", default="RBC:0.8,melanoma:0.2", help="type mix (default RBC:0.8,melanoma:0.2)")
    auto_bench.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    _scenario_options(auto_bench)
    _output_options(auto_bench)
    auto_bench.set_defaults(handler=command_bench)
    membrane_bench = targets.add_parser("membrane", help="the paper's literal membrane method against the conserving "
                                                         "one: area kept, point spacing, outlets, cost per step")
    membrane_bench.add_argument("--repeats", type=int, default=2, help="interleaved runs per scenario (default 2)")
    _scenario_options(membrane_bench)
    _output_options(membrane_bench)
    membrane_bench.set_defaults(handler=command_bench)
    recording_bench = targets.add_parser("recording", help="wall-time overhead of recording (MCAP + Rerun) an FE-IB stream")
    recording_bench.add_argument("--repeats", type=int, default=3, help="interleaved pairs without/with (default 3)")
    _scenario_options(recording_bench)
    _output_options(recording_bench)
    recording_bench.set_defaults(handler=command_bench)
    sweep_bench = targets.add_parser("sweep", help="one sweep on 1 and on 2 local workers: the speed-up")
    sweep_bench.add_argument("spec", nargs="?", metavar="SPEC",
                             help="sweep spec (default examples/sweeps/bench-rom.toml: 8 rom plants, 200 cells each)")
    sweep_bench.add_argument("--workers", default="1,2", metavar="N,M", help="pool sizes to compare (default 1,2)")
    sweep_bench.add_argument("--repeats", type=int, default=1, help="runs per pool size; medians (default 1)")
    _output_options(sweep_bench)
    sweep_bench.set_defaults(handler=command_bench)
    realtime_bench = targets.add_parser("realtime", help="real-time factor of the closed loop with the rom plant: "
                                                         "a Poisson stream, detector and controller, no recording")
    _scenario_options(realtime_bench)
    realtime_bench.add_argument("--rate", type=float, default=1000.0, help="arrival rate in cells/s (default 1000)")
    realtime_bench.add_argument("--duration", default="1s", metavar="TIME",
                                help="device time of arrivals; count = rate x duration (default 1s)")
    realtime_bench.add_argument("--mix", default="RBC:0.9,melanoma:0.1", help="type mix (default RBC:0.9,melanoma:0.1)")
    realtime_bench.add_argument("--repeats", type=int, default=3, help="runs of the same stream (default 3)")
    realtime_bench.add_argument("--control-period", metavar="TIME", help="control period (default: the plant's, 10us)")
    realtime_bench.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    _output_options(realtime_bench)
    realtime_bench.set_defaults(handler=command_bench)
    controller_bench = targets.add_parser("controller", help="decision latency of the sorting controller")
    controller_bench.add_argument("--events", type=int, default=20_000, help="synthetic events (default 20000)")
    _output_options(controller_bench)
    controller_bench.set_defaults(handler=command_bench)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        install_cache()
        args.handler(args)
    except (ScenarioError, UsageError) as error:
        return _fail(error, EXIT_INPUT)
    except (NumericalBlowUp, SolverError) as error:
        return _fail(error, EXIT_NUMERICAL)
    except KeyboardInterrupt:
        print("vcyto: interrupted", file=sys.stderr)
        return 130
    except Exception as error:  # a bug, not bad input: say so in one line, keep the traceback on request
        if os.environ.get("VCYTO_DEBUG"):
            raise
        print(f"vcyto: internal error: {type(error).__name__}: {error} (set VCYTO_DEBUG=1 for the traceback; "
              "please report it)", file=sys.stderr)
        return EXIT_INTERNAL
    return 0


def _fail(error: Exception, status: int) -> int:
    if os.environ.get("VCYTO_DEBUG"):
        raise error
    print(f"vcyto: error: {error}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
