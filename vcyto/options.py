"""The options of a closed-loop run as plain data -> the ``Scenario`` and the ``StreamSettings`` they describe.

The scenario options (``--scenario``, ``--set``, ``--mesh-h``, ...), the time-step tolerance and the stream
options (arrivals, detector, controller, plant model, seed, duration) are defined here once, with their types
and defaults (``vcyto.arguments``: quantities are read with their units and converted to SI), and converted
here: ``vcyto stream`` and its siblings read them from the command line, ``vcyto sweep`` from a spec's
``[base]`` and ``[parameters]`` tables. Bad values raise ``UsageError`` (or ``ScenarioError`` for a scenario
field), one line naming the option.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from controller.sorter import MODES, ControllerSettings
from sim.model.scenario import (
    CONVECTIONS,
    COUPLINGS,
    LINEAR_SOLVERS,
    MEMBRANE_METHODS,
    SAW_MODELS,
    TIME_SCHEMES,
    ScenarioError,
)
from sim.plants import registry as plants

from . import arguments as limits
from . import units
from .arguments import Integer, Number, Quantity
from .config import load_scenario
from .recording.runfiles import say

SHIPPED = ControllerSettings()      # the shipped calibration: the defaults --help names
MAX_TOLERANCE = 50e-6               # a path error per transit of --tolerance (the paper's outlets are 80 um wide)


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.4g}"


class UsageError(ValueError):
    """Bad command-line input that is not a scenario field."""


def scenario_options(parser: argparse.ArgumentParser):
    group = parser.add_argument_group("scenario (SI units; values may carry units such as 3.33um or 25us)")
    group.add_argument("--scenario", metavar="FILE", help="TOML scenario file (default: the paper's device)")
    group.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                       help="override one field, e.g. --set fluid.viscosity=1e-3 (repeatable)")
    group.add_argument("--mesh-h", metavar="LENGTH",
                       help="mesh size: the largest grid spacing, at most 0.2 %% above this; grid lines run through "
                            "the inlets' and outlets' ends, so the paper's device has uniform meshes for 10um / k "
                            "(10, 5, 3.33, 2.5, 2, 1.67um ...) and graded ones otherwise; a run states the mesh it "
                            "built and its DOFs (default 3.33um: 90 x 66 squares, the paper's 54,243 DOFs)")
    group.add_argument("--dt", metavar="TIME",
                       help="time step (default 2.5us; vcyto paper: the paper's step for the scenario)")
    group.add_argument("--convection", choices=CONVECTIONS, help="convection treatment (default imex)")
    group.add_argument("--time-scheme", choices=TIME_SCHEMES,
                       help="FE-IB time discretisation: euler (the paper's first-order step), bdf2 (second order; "
                            "docs/numerics.md) or auto (the default: bdf2 with --tolerance, euler otherwise)")
    group.add_argument("--membrane-coupling", choices=COUPLINGS,
                       help="membrane coupling: explicit (the force of the old positions; the default) or implicit "
                            "(the force of the new positions: stable at far larger steps, about 2x the cost a step; "
                            "docs/numerics.md \"The membrane coupling\")")
    group.add_argument("--saw-model", choices=SAW_MODELS, help="SAW model (default paper)")
    group.add_argument("--solver", choices=LINEAR_SOLVERS, help="linear solver (default auto)")
    group.add_argument("--membrane", choices=tuple(MEMBRANE_METHODS),
                       help="membrane method: conserving (area constraint + point redistribution; the default), "
                            "multiplier (conserving, with each cell's interior pressure solved in the step so that "
                            "the step itself keeps the area: one more back-solve a cell; docs/numerics.md) or "
                            "paper (the paper's literal method, which leaks area; the default of vcyto paper)")


def scenario_from(args, membrane: str | None = None):
    """The scenario of the options; ``membrane`` is the command's default membrane method (--membrane wins,
    and --set of single fields refines either)."""
    method = getattr(args, "membrane", None) or membrane
    overrides = [f"numerics.{field}={str(value).lower()}" for field, value in MEMBRANE_METHODS[method].items()] \
        if method else []
    overrides += list(args.overrides) + tolerance_override(args)
    if getattr(args, "time_scheme", None) not in (None, "auto") and getattr(args, "model", None) not in \
            (None, "feib", "auto"):
        raise UsageError(f"--time-scheme: sets the time scheme of the feib step only; drop it or use --model feib "
                         f"or auto (got --model {args.model})")
    for option, field in (("mesh_h", "numerics.mesh_h"), ("dt", "numerics.dt"), ("convection", "numerics.convection"),
                          ("time_scheme", "numerics.time_scheme"),
                          ("membrane_coupling", "numerics.membrane_coupling"), ("saw_model", "saw.model"),
                          ("solver", "numerics.linear_solver")):
        value = getattr(args, option, None)
        if value is not None:
            overrides.append(f"{field}={value}")
    scenario = load_scenario(args.scenario, overrides, field="--scenario")
    limits.check_mesh(scenario.channel.length, scenario.channel.height, scenario.numerics.mesh_h)
    scenario, note = as_built(scenario)
    if note and not getattr(args, "quiet", False):
        say(note)
    return scenario


def as_built(scenario):
    """``scenario`` with ``numerics.mesh_h`` the largest spacing of the mesh it builds (``sim.model.mesh.MeshSize``)
    and the note saying so, or None when the mesh is uniform with the size asked."""
    from sim.model.mesh import MeshSize
    size = MeshSize.of(scenario.channel, scenario.numerics.mesh_h)
    return (scenario.with_numerics(mesh_h=size.largest) if size.snapped else scenario), size.note()


def tolerance_options(parser: argparse.ArgumentParser):
    group = parser.add_argument_group("time steps chosen by a tolerance (docs/numerics.md)")
    group.add_argument("--tolerance", metavar="LENGTH",
                       help="pick each FE-IB step from dt, 2dt, 4dt, 8dt (dt = --dt, default 2.5us) by an error "
                            "estimate on the membranes, for at most this centroid path error per transit against "
                            "fixed steps of dt in the same time scheme (bdf2 unless --time-scheme says otherwise), "
                            "e.g. 1um (a bare number is in m; at most 50um); never above the cells' stability limit "
                            "(default: fixed dt)")


def length_value(text: str, field: str = "value") -> float:
    """A finite length (a bare number in m, or with a unit such as um); ``units.QuantityError`` otherwise."""
    return units.parse_quantity(text, "length", field=field)


def tolerance_override(args) -> list[str]:
    """``--tolerance LENGTH`` as the override numerics.tolerance=VALUE (a length: m, mm, um or nm)."""
    text = getattr(args, "tolerance", None)
    if text is None:
        return []
    value = length_value(text, "--tolerance")        # a wrong unit, NaN or infinity: QuantityError naming it
    if not value > 0:
        raise UsageError(f"--tolerance: must be a positive length such as 1um or 0.5um (got {text!r})")
    if value > MAX_TOLERANCE:         # a bare number is in m: `--tolerance 1` would be a metre
        raise UsageError(f"--tolerance: {text!r} is {value / 1e-6:g} um, more than the {MAX_TOLERANCE / 1e-6:g} um a "
                         "path error per transit can sensibly be; give a unit, such as 1um")
    if getattr(args, "model", None) not in (None, "feib"):
        raise UsageError(f"--tolerance: picks the steps of the feib model only; drop it or use --model feib "
                         f"(got --model {args.model})")
    return [f"numerics.tolerance={value!r}"]


def cell_list(text: str) -> tuple[str, ...]:
    names = tuple(name.strip() for name in text.split(","))
    if not any(names):
        raise UsageError("--cells: needs at least one cell type, e.g. --cells RBC,melanoma")
    if not all(names):
        raise UsageError(f"--cells: an empty entry (two commas, or one at an end) in {text[:80]!r}; list one cell "
                         "type between each pair of commas, e.g. RBC,melanoma")
    return names


def parse_mix(text: str) -> tuple[tuple[str, float], ...]:
    """TYPE:SHARE pairs: every share finite and >= 0, summing to 1 (to 1e-6). A mix that does not add up is refused
    rather than normalised: ``--mix melanoma:0.1`` meant a tenth of melanoma cells, and normalised it drew nothing
    but melanoma cells."""
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
    names = [name for name, _ in pairs]
    if repeated := sorted({name for name in names if names.count(name) > 1}):
        raise UsageError(f"--mix: {', '.join(repeated)} given more than once; give each type once, its weight the "
                         f"share of the sample (got {text!r})")
    total = sum(weight for _, weight in pairs)
    if abs(total - 1.0) > 1e-6:
        raise UsageError(f"--mix: the shares sum to {total:g}, not 1; give every type its share of the sample, "
                         f"e.g. RBC:0.9,melanoma:0.1 (got {text!r})")
    return tuple(pairs)


def detection_window(text: str, scenario) -> tuple[float, float]:
    """The detection window (x0, x1) in m from "30,60" (um) or "30um,60um"; inside the channel, x0 < x1."""
    values = units.parse_list(text, "length", "um", field="--detection-window")
    if len(values) != 2 or not 0 <= values[0] < values[1]:
        raise UsageError(f"--detection-window: wants two lengths X0,X1 with 0 <= X0 < X1, e.g. 30,60 (um) "
                         f"(got {text!r})")
    if values[1] > scenario.channel.length:
        raise UsageError(f"--detection-window: {text} lies outside the channel "
                         f"(0, {scenario.channel.length * 1e6:g}) um")
    return values[0], values[1]


def check_cells_fit(scenario, names) -> None:
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
    from . import stream
    try:
        if args.count is not None:
            limits.check_cells(args.count)
        arrivals = arrivals_settings(args)
        check_cells_fit(scenario, set(arrivals.cells) | {name for name, _ in arrivals.mix})
        detector = detector_settings(args, scenario)
        controller = controller_settings(args)
        window = getattr(args, "window_h", None)
        if window is not None:
            if args.model != "auto":
                raise UsageError(f"--window-h: sets the feib windows of --model auto (the model is {args.model}): "
                                 "drop it or add --model auto")
            limits.check_mesh(scenario.channel.length, scenario.channel.height, window, "--window-h")
            try:
                scenario.with_numerics(mesh_h=window)           # resolves every inlet and outlet
            except ScenarioError as error:
                raise UsageError(f"--window-h: {str(error).split(': ', 1)[1]}") from None
        plant_from, controller_from = plugin_spec(args, "plant_from"), plugin_spec(args, "controller_from")
        if plant_from is not None and args.model != "feib":
            raise UsageError(f"--plant-from: runs your plant instead of --model {args.model}: give one of them")
        if controller_from is not None and args.no_controller:
            raise UsageError("--controller-from: --no-controller turns the controller off: give one of them")
        check_device_time(arrivals, args.max_time)
        if args.model == "feib" and plant_from is None:
            check_run_time(args, scenario, _device_time(arrivals, args.max_time), "--dt/--count/--rate")
        return stream.StreamSettings(arrivals, detector, controller, args.model, args.seed,
                                     max_time=args.max_time, window_mesh_h=window, controller_from=controller_from,
                                     plant_from=plant_from, controller_wire=getattr(args, "controller_wire", None))
    except ValueError as error:
        if isinstance(error, (UsageError, ScenarioError, units.QuantityError)):
            raise
        raise UsageError(str(error)) from None


def wire_options(parser: argparse.ArgumentParser, what: str = "the run's") -> None:
    """``--controller-connect``, ``--controller-exec``, ``--controller-timeout``: a controller in another process
    (``vcyto.wire``) for ``what``."""
    wire = parser.add_argument_group(f"{what} controller in another process (docs/wire-protocol.md)")
    wire.add_argument("--controller-connect", metavar="ADDRESS",
                      help="the controller listening at ADDRESS: tcp:HOST:PORT (e.g. tcp:127.0.0.1:7070) or "
                           "unix:PATH, spoken to over the wire protocol")
    wire.add_argument("--controller-exec", metavar="CMD",
                      help="start the controller CMD (split as a shell would; {address} in it, and the environment "
                           "variable VCYTO_CONTROLLER_ADDRESS, say where to listen), connect, stop it at the end")
    wire.add_argument("--controller-timeout", type=Quantity("time", "s", low=0, low_open=True, high=3600),
                      metavar="TIME",
                      help="how long to wait for the connection, the handshake and each lock-step answer "
                           "(default 10 s); a controller that takes longer stops the run with an error")


def wire_controller(args):
    """The ``vcyto.wire.WireController`` that ``wire_options`` name, or None (``UsageError``: one line)."""
    from .wire import DEFAULT_TIMEOUT, WireController
    given = [(how, target) for how, target in (("connect", args.controller_connect), ("exec", args.controller_exec))
             if target is not None]
    if len(given) > 1:
        raise UsageError("--controller-connect: --controller-exec names the controller too: give one of them")
    if not given:
        if args.controller_timeout is not None:
            raise UsageError("--controller-timeout: applies to a controller in another process: add "
                             "--controller-connect ADDRESS or --controller-exec CMD, or drop it")
        return None
    how, target = given[0]
    timeout = DEFAULT_TIMEOUT if args.controller_timeout is None else args.controller_timeout
    try:
        return WireController(how, target, timeout)
    except ValueError as error:
        raise UsageError(f"--controller-{how}: {error}") from None


def plugin_spec(args, name: str) -> str | None:
    """``--controller-from`` / ``--plant-from``: its FILE.py:NAME, a file's path made absolute, checked by loading
    it (a usage error says what is wrong)."""
    spec = getattr(args, name, None)
    if spec is None:
        return None
    from . import plugins
    option = "--" + name.replace("_", "-")
    try:
        where, attribute = plugins.split(spec)
        if where.endswith(".py") or "/" in where:
            spec = f"{Path(where).expanduser().resolve()}:{attribute}"
        plugins.load(spec)
    except plugins.PluginError as error:
        raise UsageError(f"{option}: {error}") from None
    return spec


def arrivals_settings(args):
    """The ``Arrivals`` of the arrival options in ``args``; an error names the options it concerns."""
    from sim.model.arrivals import Arrivals
    if args.cells is not None and (args.count or args.mix):
        raise UsageError("--cells: lists the cells one by one, so it goes without --count and --mix; give either "
                         "--cells RBC,melanoma or --count N --mix RBC:0.9,melanoma:0.1")
    cells = cell_list(args.cells) if args.cells is not None else (() if args.count else ("RBC", "melanoma"))
    if args.count and not cells and not args.mix:
        raise UsageError("--count: needs --mix, the types to draw the cells from, e.g. --count 100 "
                         "--mix RBC:0.9,melanoma:0.1")
    mix = parse_mix(args.mix) if args.mix else ()
    try:
        return Arrivals(cells=cells, count=args.count or 0, mix=mix, rate=args.rate, process=args.arrivals,
                        min_spacing=args.min_spacing)
    except ValueError as error:
        raise UsageError(f"--cells/--count/--mix/--rate/--min-spacing: {error}") from None


def detector_settings(args, scenario):
    from controller.detector import DetectorSettings
    try:
        return DetectorSettings(window=detection_window(args.detection_window, scenario), gate=args.gate,
                                noise_cv=args.noise)
    except (UsageError, units.QuantityError):          # they name their option already
        raise
    except ValueError as error:
        raise UsageError(f"--detection-window/--gate/--noise: {error}") from None


def _device_time(arrivals, cap) -> float:
    """The device time a stream will simulate, roughly: its arrivals plus 5 ms for the last cell to leave."""
    cells = len(arrivals.cells) or arrivals.count
    span = (cells - 1) / arrivals.rate + 5e-3
    return min(span, cap) if cap is not None else span


MAX_DEVICE_TIME = 86400.0         # s of device time a stream may take without --max-time (--max-time's own limit):
                                  # a day of sorting (a rare-cell sort of 10^7 events at 1,000/s takes 2.8 h)


def check_device_time(arrivals, cap) -> None:
    """Refuse, unless capped by --max-time, a stream whose arrivals alone span more than ``MAX_DEVICE_TIME``
    (``--rate 1e-6`` with two cells: eleven days of device time)."""
    span = _device_time(arrivals, None)
    if cap is None and span > MAX_DEVICE_TIME:
        cells = len(arrivals.cells) or arrivals.count
        raise UsageError(f"--rate: {cells:,} cells at {arrivals.rate:g} cells/s take {span:,.4g} s of device time "
                         f"(more than {MAX_DEVICE_TIME:g} s); give a higher rate, fewer cells, or cap the run "
                         "with --max-time")


def check_run_time(args, scenario, simulated: float, field: str):
    limits.check_run_time(simulated, scenario.numerics.dt, limits.mesh_dofs(
        scenario.channel.length, scenario.channel.height, scenario.numerics.mesh_h), field,
        allowed=getattr(args, "allow_long", False))


def controller_settings(args):
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
            raise UsageError(f"--envelope: wants two offsets LO,HI with LO <= HI, such as -0.21,0.2 (ms) "
                             f"(got {args.envelope!r})")
        changes["envelope"] = tuple(values)
    if args.no_controller:
        changes["enabled"] = False
    return replace(base, **changes)


def late_pulse_note(settings) -> str | None:
    """A note when the lead is not shorter than the sort delay: no pulse can start before its cell is detected,
    so each starts late, at the decision (``controller.sorter``), or is aborted when it would already be over.
    Such leads are accepted (a sweep over the lead shows where sorting fails), but never silently."""
    if settings.lead < settings.delay:
        return None
    return (f"the lead {settings.lead * 1e3:g} ms is not shorter than the sort delay {settings.delay * 1e3:g} ms: a "
            "pulse cannot start before its cell is detected, so each starts late, at the decision, and a sort "
            "whose pulse would already be over is aborted ('too late'); use a lead below the delay to sort on time")


def short_pulse_note(settings, scenario) -> str | None:
    """A note when the pulse is shorter than a tenth of the SAW drive's spin-up time: the drive barely rises
    before it is switched off again, so the pulse deflects (almost) nothing. Accepted, never silently."""
    if not settings.enabled or settings.pulse >= scenario.saw.spin_up_time / 10:
        return None
    return (f"the pulse {settings.pulse * 1e3:g} ms is less than a tenth of the SAW drive's spin-up time "
            f"{scenario.saw.spin_up_time * 1e3:g} ms (saw.spin_up_time): the drive barely rises, so a sorted cell is "
            "most likely not deflected; use a pulse of the order of the spin-up time or longer")


def stream_run_options() -> argparse.ArgumentParser:
    """A parser of the scenario and stream options alone: their names, types and defaults are vcyto sweep's."""
    parser = argparse.ArgumentParser(prog="vcyto stream", add_help=False)
    scenario_options(parser)
    stream_options(parser)
    return parser


def stream_run(args):
    """The scenario and the ``StreamSettings`` that the scenario and stream options in ``args`` describe."""
    scenario = scenario_from(args)
    return scenario, stream_settings(args, scenario)


def stream_options(parser: argparse.ArgumentParser):
    """The options of one closed-loop run: arrivals, detector, controller, plant model, seed, duration.
    Quantities take a unit (``--lead 500us``); a bare number is in the unit the help names."""
    _arrival_options(parser)
    _sorting_options(parser)
    _plant_options(parser)


def _arrival_options(parser: argparse.ArgumentParser):
    arrivals = parser.add_argument_group("cell arrivals (through the injection inlet)")
    arrivals.add_argument("--cells", help="explicit ordered list, e.g. RBC,melanoma,RBC (default RBC,melanoma "
                                          "unless --count is given)")
    arrivals.add_argument("--count", type=Integer(low=1), help="number of cells drawn from --mix (at least 1)")
    arrivals.add_argument("--mix", help="type mix for --count: each type's share of the sample, summing to 1, e.g. "
                          "RBC:0.9,melanoma:0.1")
    arrivals.add_argument("--rate", type=Quantity("frequency", "Hz", low=0, low_open=True), default="500",
                          metavar="RATE", help="arrival rate, cells/s (default 500; e.g. 1kHz)")
    arrivals.add_argument("--arrivals", choices=("regular", "poisson"), default="regular",
                          help="arrival process (default regular)")
    arrivals.add_argument("--min-spacing", type=Quantity("time", "ms", low=0), default="0.5", metavar="TIME",
                          help="minimum time between arrivals (ms; default 0.5)")


def _sorting_options(parser: argparse.ArgumentParser):
    optics = parser.add_argument_group("detector and controller")
    optics.add_argument("--detection-window", default="30,60", metavar="X0,X1",
                        help="detection window along the channel (um; default 30,60; e.g. 30um,60um)")
    optics.add_argument("--gate", type=Number(low=0), default="0.5", help="fluorescence gate for type II (default 0.5)")
    optics.add_argument("--noise", type=Number(low=0, high=10), default="0.2",
                        help="fluorescence noise CV, 0-10 (default 0.2)")
    optics.add_argument("--controller", metavar="FILE",
                        help="controller settings file written by vcyto calibrate (default: the shipped calibration, "
                             "docs/usage.md 'Sorting like a sorter'); the options below override it")
    optics.add_argument("--delay", type=Quantity("time", "ms", low=0, low_open=True, high=10.0), metavar="TIME",
                        help="sort delay: detection to the SAW window at the reference velocity (ms; default "
                             f"{_ms(SHIPPED.delay)})")
    optics.add_argument("--lead", type=Quantity("time", "ms", low=0, high=10.0), metavar="TIME",
                        help=f"IDT on this long before the predicted arrival (ms; default {_ms(SHIPPED.lead)})")
    optics.add_argument("--pulse", type=Quantity("time", "ms", low=0, low_open=True, high=10.0), metavar="TIME",
                        help=f"IDT pulse length (ms; default {_ms(SHIPPED.pulse)})")
    optics.add_argument("--mode", choices=MODES,
                        help="sort mode: purity (abort when a type-I cell is predicted in the widened envelope; "
                             "the default), enrichment (abort only inside the envelope itself), yield (never abort), "
                             "single (purity, and abort two type-II cells in each other's envelope)")
    optics.add_argument("--envelope", metavar="LO,HI",
                        help="offsets from a sorted cell's arrival at which another cell is deflected too (ms; default "
                             f"{_ms(SHIPPED.envelope[0])},{_ms(SHIPPED.envelope[1])}: vcyto calibrate on rom and feib, "
                             "docs/usage.md 'Sorting like a sorter')")
    optics.add_argument("--timing-error", type=Quantity("time", "ms", low=0, high=10.0), metavar="TIME",
                        help="uncertainty of one predicted arrival; the purity window is the envelope widened by twice "
                             f"this (ms; default {_ms(SHIPPED.timing_error)})")
    optics.add_argument("--no-controller", action="store_true", help="never switch the IDT on")
    optics.add_argument("--controller-from", metavar="FILE.py:NAME",
                        help="your controller: NAME (a class or factory in FILE.py, or MODULE:NAME) is called with "
                             "the controller settings (the calibration and the options above) and returns an object "
                             "with on_event(event, clock) (docs/controllers.md)")


def _plant_options(parser: argparse.ArgumentParser):
    parser.add_argument("--plant-from", metavar="FILE.py:NAME",
                        help="your plant instead of --model: NAME (a class or factory in FILE.py, or MODULE:NAME) is "
                             "called with the scenario and returns a plant (sim.plants.contract.Plant; "
                             "docs/controllers.md)")
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
    parser.add_argument("--max-time", type=Quantity("time", "ms", low=0, low_open=True, high=MAX_DEVICE_TIME * 1e3),
                        metavar="TIME",
                        help="cap the run at this simulated time (ms); by default it runs until every cell has left "
                             "(a capped run says so, its statistics are marked partial and cells never injected are "
                             "counted as such); exit status 1 unless --allow-partial")
    parser.add_argument("--allow-partial", action="store_true",
                        help="a run cut short by --max-time (or by cells stuck in the channel) exits 0")
    parser.add_argument("--allow-long", action="store_true",
                        help="run an FE-IB stream estimated to take more than 24 h (refused otherwise)")

