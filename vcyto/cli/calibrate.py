"""`vcyto calibrate`: measure the sort envelope (sort delay, shortest reliable pulse, deflection envelope) and
write a controller file."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from controller.protocol import ControllerError
from controller.sorter import MODES
from sim.plants import registry as plants

from .. import outputs, units
from ..arguments import Number, Quantity
from ..options import (
    controller_settings,
    detector_settings,
    plugin_spec,
    scenario_from,
    scenario_options,
    wire_controller,
    wire_options,
)
from ..outputs import strict_json
from ..recording import runfiles
from .common import (
    EXIT_NUMERICAL,
    SMALL_FILES_BYTES,
    RunStopped,
    UsageError,
    emit,
    output_directory,
    output_options,
    signals_seen,
)


def add_command(commands):
    calibration = commands.add_parser("calibrate", help="measure the sort envelope (sort delay, shortest reliable "
                                                        "pulse, deflection envelope) and write a controller file")
    scenario_options(calibration)
    _calibration_options(calibration)
    calibration.set_defaults(handler=command_calibrate)


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
    parser.add_argument("--plant-from", metavar="FILE.py:NAME",
                        help="calibrate your plant instead of --model: NAME (in FILE.py, or MODULE:NAME) is called "
                             "with the scenario and returns a plant (docs/controllers.md)")
    parser.add_argument("--controller-from", metavar="FILE.py:NAME",
                        help="then check your controller: NAME, called with the new calibration, sorts "
                             + ",".join(CHECK_CELLS) + " on the calibrated plant; the report says where each cell went")
    wire_options(parser, "the check's")
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
    output_options(parser)


CHECK_CELLS = ("RBC", "melanoma", "RBC", "melanoma")


def command_calibrate(args):
    from ..controllerfile import controller_toml
    from ..studies import calibrate
    scenario = scenario_from(args)
    output = output_directory(args.output, min_free=SMALL_FILES_BYTES)
    base = controller_settings(args)
    grid = _calibration_grid(args)
    pulse = None
    if args.pulse is not None or args.lead is not None:
        if args.pulse is None or args.lead is None:
            raise UsageError("--pulse/--lead: they go together: give both to measure the envelope of that pulse, "
                             "or neither to search for the shortest reliable pulse")
        pulse = (base.pulse, base.lead)
    detector = detector_settings(args, scenario)
    plant_from, controller_from = plugin_spec(args, "plant_from"), plugin_spec(args, "controller_from")
    reached = wire_controller(args)
    if reached is not None and controller_from is not None:
        raise UsageError(f"{reached.option}: --controller-from names the controller too: give one of them")
    checked = (controller_from, reached) if controller_from is not None or reached is not None else None
    if plant_from is not None and args.model != "rom":
        raise UsageError(f"--plant-from: calibrates your plant instead of --model {args.model}: give one of them")
    from ..progress import Progress
    progress = Progress(quiet=args.quiet or args.json)
    started = time.perf_counter()
    try:
        plant = _plant(scenario, args.model, plant_from)
        result = calibrate.calibrate(plant, scenario, detector, grid, pulse, base, progress)
        check = _check(scenario, plant, detector, result.settings, *checked) if checked else None
    except calibrate.CalibrationError as error:
        raise UsageError(str(error)) from None
    except calibrate.CalibrationInterrupted as interrupted:
        progress.close()
        emit(args, {"interrupted": True, "measured": interrupted.lines}, interrupted.lines)
        raise KeyboardInterrupt from None        # nothing is saved; the exit is an interrupt's (130)
    finally:
        progress.close()
    record = dict(result.as_dict(), model=_model_name(plant), saw_model=scenario.saw.model,
                  wall_time_s=time.perf_counter() - started, files={})
    if check is not None:
        record["check"] = check
    interrupted = False
    if output is not None:
        # Ctrl-C or SIGTERM while the files are written waits for them: the calibration is finished, and a
        # controller file without its record (or a record still saying "running") would mislead
        with runfiles.interrupts_deferred(signals_seen) as saving:
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
        interrupted = saving.pending
    emit(args, record, calibrate.report_lines(record) + ([_check_line(check)] if check else []))
    if interrupted:
        raise KeyboardInterrupt         # the files are whole and listed; the exit is an interrupt's (130)


def _plant(scenario, model: str, plant_from: str | None):
    """The plant the calibration cells go through: ``--model``'s, or the user's (a broken one: a usage error)."""
    from .. import plugins
    from ..studies import calibrate
    if plant_from is None:
        return calibrate.make_calibration_plant(scenario, model)
    try:
        return plugins.plant(plant_from, scenario)
    except plugins.PluginError as error:
        raise UsageError(f"--plant-from: {error}") from None


def _model_name(plant) -> str:
    from ..stream import model_name
    return model_name(plant)


def _check(scenario, plant, detector, settings, controller_from: str | None, reached=None) -> dict:
    """The user's controller (``controller_from``'s, built from the new calibration, or one in another process,
    ``reached``: it gets the new calibration's device facts) on ``CHECK_CELLS``: where each cell went."""
    from sim.model.arrivals import Arrivals

    from .. import plugins
    from ..stream import StreamSettings, run_stream
    stream_settings = StreamSettings(Arrivals(cells=CHECK_CELLS), detector, settings, model="rom",
                                     controller_from=controller_from, controller_wire=reached)
    try:
        result = run_stream(scenario, stream_settings, plant=plant)
    except plugins.PluginError as error:
        raise UsageError(f"--controller-from: {error}") from None
    except (ControllerError, ConnectionError) as error:
        print(f"vcyto: error: {reached.option}: {' '.join(str(error).split())}", file=sys.stderr)
        raise RunStopped(EXIT_NUMERICAL) from None
    cells = [{"type": c["type"], "true_class": c["true_class"], "decision": c["decision"], "outlet": c["outlet"]}
             for c in result["cells"]]
    right = sum(c["outlet"] == ("upper" if c["true_class"] == "II" else "lower") for c in cells)
    return {"controller": result["controller_name"], "cells": cells, "sorted_right": right, "status": result["status"]}


def _check_line(check: dict) -> str:
    went = ", ".join(f"{c['type']} -> {c['outlet']}" for c in check["cells"])
    return (f"check: controller {check['controller']} with this calibration: {went} "
            f"({check['sorted_right']} of {len(check['cells'])} by the right outlet)")


def _calibration_grid(args):
    from ..studies.calibrate import Grid
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
