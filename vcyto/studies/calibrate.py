"""`vcyto calibrate`: the sort envelope of a device, measured as a sorter's calibration measures it.

Calibration cells go through the plant one at a time, open loop, seen by the same detector stub the
controller uses (``controller.detector``). Three measurements:

1. **Sort delay** (per detected class): the time from a cell's detection (leaving the detection window) to its
   centroid's arrival at the centre of the SAW window, as a distance D_c = (arrival - detection) * velocity so
   that the controller predicts arrival = detection + D_c / measured velocity. Each type is measured with the
   IDT off and with the IDT on during its detection (another cell's pulse changes the upstream flow a little);
   the largest prediction error over the types of a class is that class's ``timing_error``.
2. **Shortest reliable pulse**: for pulse lengths on a grid, the leads (pulse start before the predicted
   arrival) that send every target type to the sorted outlet, alone and when another target's pulse started
   ``Grid.preceding_gaps`` before its own (pulse trains: the flow a pulse leaves behind changes the next
   cell's measured velocity and deflection); the shortest pulse whose band of good leads is at least
   2 * (timing_error + control period) + the grid step wide, with the lead in the band's middle.
3. **Deflection envelope**: with that pulse, a cell of each type arriving at offset delta from the target's
   arrival (delta > 0: after it) and seen alone under the pulse; the offsets at which it does not leave by the
   default outlet (it is deflected upwards or into the divider). The class-I envelope is the union over the
   non-target types; the controller aborts (purity mode) when a class-I cell's predicted offset lies in it,
   widened by the timing errors of both cells.

The plant is reset for every calibration cell; on the ``rom`` plant (no interactions between cells) a cell
alone under a pulse is exactly a cell beside the target it was fired for. Pure computation: the CLI writes
the files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from controller.detector import Detector, DetectorSettings
from controller.events import TYPE_I, TYPE_II, Sighting
from controller.sorter import ControllerSettings
from sim.method.fluid import NumericalBlowUp
from sim.model.scenario import Scenario

SORTED, DEFAULT = "upper", "lower"


@dataclass(frozen=True)
class Passage:
    """One calibration cell's way through the device."""

    fate: str
    exit_y: float
    detected: float           # when it left the detection window (s), nan if never
    velocity: float           # as the detector measured it (m/s)
    arrival: float            # when its centroid crossed the SAW window's centre (s), nan if never


def passage(plant, type_name: str, pulse=None, detector: DetectorSettings = DetectorSettings(),
            limit: float = 20e-3, start: float = 0.0, schedule=None) -> Passage:
    """Run one ``type_name`` cell injected at ``start`` through ``plant`` with the IDT on during ``pulse`` (on, off)
    and during the window ``schedule(detection time, measured velocity)`` returns once the cell is detected
    (its own pulse, timed as the controller times it)."""
    window_centre = 0.5 * sum(plant.scenario.channel.saw_window.span)
    eye = Detector(detector, np.random.default_rng(0))
    observation = plant.reset([(start, type_name)])
    detected = velocity = arrival = math.nan
    previous = own = None
    while not plant.done and observation.time < start + limit:
        now = observation.time
        drive = 1.0 if any(window is not None and window[0] <= now + 1e-12 < window[1]
                           for window in (pulse, own)) else 0.0
        try:
            observation = plant.step(drive)
        except NumericalBlowUp as error:       # e.g. a membrane folded against the divider: not the default outlet
            return Passage(f"failed: {error}", math.nan, detected, velocity, arrival)
        for event in eye.observe(observation.time, [Sighting(c.key, c.x, c.y, c.area, c.brightness)
                                                     for c in observation.cells]):
            detected, velocity = event.time, event.velocity
            if schedule is not None:
                own = schedule(detected, velocity)
        if observation.cells:
            x = observation.cells[0].x
            if previous is not None and previous[1] < window_centre <= x and math.isnan(arrival):
                fraction = (window_centre - previous[1]) / (x - previous[1])
                arrival = previous[0] + fraction * (observation.time - previous[0])
            previous = (observation.time, x)
    cell = plant.truth().cells[0]
    fate = cell.fate if cell.fate != "in_channel" else "lost"
    return Passage(fate, cell.exit_y, detected, velocity, arrival)


@dataclass(frozen=True)
class Delay:
    """Per class: the distance D (m) from the detector to the SAW window in velocity-time, and the largest
    prediction error (s) of arrival = detection + D / velocity over the types of the class and drive states."""

    distance: dict              # class -> D (m)
    timing_error: dict          # class -> s
    passages: dict              # (type, "off"|"on") -> Passage


def measure_delay(plant, scenario: Scenario, detector: DetectorSettings) -> Delay:
    passages = {}
    for cell_type in scenario.cell_types:
        passages[cell_type.name, "off"] = passage(plant, cell_type.name, None, detector)
        unpulsed = passages[cell_type.name, "off"]
        if math.isnan(unpulsed.detected) or math.isnan(unpulsed.arrival):
            raise CalibrationError(f"a lone {cell_type.name} never reached the SAW window (fate {unpulsed.fate}): "
                                   "check the detection window and the device")
        # the IDT on while the cell is detected, off before it reaches the window: another cell's pulse
        passages[cell_type.name, "on"] = passage(plant, cell_type.name, (0.0, unpulsed.detected), detector)
    distance, error = {}, {}
    for label in (TYPE_I, TYPE_II):
        members = [c.name for c in scenario.cell_types if _class_of(c) == label]
        if not members:
            continue
        samples = [(p.arrival - p.detected) * p.velocity for name in members for key, p in passages.items()
                   if key[0] == name and math.isfinite(p.arrival) and math.isfinite(p.detected)]
        distance[label] = float(np.median(samples))
        error[label] = max(abs(p.detected + distance[label] / p.velocity - p.arrival)
                           for (name, _), p in passages.items() if name in members and math.isfinite(p.arrival))
    return Delay(distance, error, passages)


@dataclass(frozen=True)
class PulseBand:
    """For one pulse length: the widest band (low, high) of leads (s) that sort every target type (None: none)."""

    pulse: float
    band: tuple[float, float] | None

    @property
    def width(self) -> float:
        return self.band[1] - self.band[0] if self.band else -math.inf


@dataclass(frozen=True)
class Grid:
    """The calibration's resolution: pulse lengths tried (s), lead and offset steps (s), offsets scanned (s)."""

    pulses: tuple[float, ...] = tuple(np.round(np.arange(0.02e-3, 2.0001e-3, 0.02e-3), 9))
    lead_step: float = 10e-6
    offset_step: float = 20e-6
    offset_range: float = 1.5e-3
    resolution: float = 2.5e-6          # the envelope's edges are bisected to this
    # a target must also be sorted when another target's pulse started this long before its own (s): pulse
    # trains, which cells one at a time never show (from the inlet's 0.5 ms dead time to where the effect fades)
    preceding_gaps: tuple[float, ...] = (0.6e-3, 0.8e-3, 1.0e-3, 1.2e-3, 1.4e-3, 1.6e-3, 1.8e-3, 2.0e-3)


def shortest_pulse(plant, scenario, detector, delay: Delay, grid: Grid, required: float, progress=None,
                   tried: list | None = None):
    """The shortest pulse of ``grid.pulses`` whose band of good leads is at least ``required`` wide, and the
    bands of every pulse tried (ascending; also appended to ``tried`` as they finish); CalibrationError if none
    is."""
    targets = [c.name for c in scenario.cell_types if c.target]
    if not targets:
        raise CalibrationError("the scenario has no target cell type: mark one with target = true in [[cell_types]]")
    tried = [] if tried is None else tried
    for pulse_length in grid.pulses:
        leads = np.arange(-0.2e-3, pulse_length + 0.2e-3 + 1e-12, grid.lead_step)
        good = [lead for lead in leads if all(_sorted(plant, name, delay, pulse_length, lead, detector,
                                                      grid.preceding_gaps) for name in targets)]
        tried.append(PulseBand(float(pulse_length), _widest_run(good, grid.lead_step)))
        if progress:
            progress.update(f"pulse {pulse_length * 1e3:.3f} ms: good leads {_band_text(tried[-1].band)}")
        if tried[-1].width >= required:
            return tried[-1], tried
    raise CalibrationError(f"no pulse up to {grid.pulses[-1] * 1e3:g} ms sends {', '.join(targets)} to the sorted "
                           f"outlet over {required * 1e3:.3f} ms of leads: check the SAW model and amplitude")


def _sorted(plant, name, delay, pulse_length, lead, detector, gaps=()) -> bool:
    """Whether a lone ``name`` cell is sorted by the pulse of ``pulse_length`` at ``lead``, and also (for each of
    ``gaps``) when another target's pulse started that long before its own: the flow that pulse leaves behind
    changes the cell's measured velocity and its deflection, which a cell alone never shows."""
    unpulsed = delay.passages[name, "off"]
    distance = delay.distance[TYPE_II]
    on = unpulsed.detected + distance / unpulsed.velocity - lead
    if passage(plant, name, (on, on + pulse_length), detector).fate != SORTED:
        return False

    def own(detected, velocity):               # timed from this run's detection, as the controller does
        start = detected + distance / velocity - lead
        return start, start + pulse_length
    shift = max(gaps, default=0.0)             # the cell injected late enough for the earlier pulse to fit
    return all(passage(plant, name, (on + shift - gap, on + shift - gap + pulse_length), detector, start=shift,
                       schedule=own).fate == SORTED for gap in gaps)


def _widest_run(values, step):
    """The widest run (low, high) of consecutive grid values (None if there are none)."""
    best, start, previous = None, None, None
    for value in values:
        if previous is None or value - previous > 1.5 * step:
            start = value
        previous = value
        if best is None or previous - start > best[1] - best[0]:
            best = (float(start), float(previous))
    return best


def _band_text(band) -> str:
    return "none" if band is None else f"{band[0] * 1e3:.3f}-{band[1] * 1e3:.3f} ms"


def deflected(plant, name: str, delay: Delay, offset: float, pulse_length: float, lead: float, detector) -> str:
    """The fate of a lone ``name`` cell arriving ``offset`` (s) after a target whose pulse is (lead, pulse)."""
    unpulsed = delay.passages[name, "off"]
    on = unpulsed.arrival - offset - lead
    return passage(plant, name, (on, on + pulse_length), detector).fate


def envelope_of(plant, name: str, delay: Delay, pulse_length: float, lead: float, detector, grid: Grid):
    """The offsets at which a lone ``name`` cell does not leave by the default outlet under a target's pulse:
    a scan at ``grid.offset_step``, its outermost deflected offsets bisected to ``grid.resolution``.
    Returns ((low, high) or None, [(offset, fate), ...] of every run)."""
    runs = []

    def fate(offset):
        result = deflected(plant, name, delay, offset, pulse_length, lead, detector)
        runs.append((float(offset), result))
        return result != DEFAULT

    offsets = np.arange(-grid.offset_range, grid.offset_range + 1e-12, grid.offset_step)
    hits = [offset for offset in offsets if fate(offset)]
    if not hits:
        return None, sorted(runs)
    low = _bisect(fate, hits[0] - grid.offset_step, hits[0], grid.resolution, inside_high=True)
    high = _bisect(fate, hits[-1], hits[-1] + grid.offset_step, grid.resolution, inside_high=False)
    return (low, high), sorted(runs)


def _bisect(inside, a: float, b: float, resolution: float, inside_high: bool) -> float:
    """The edge of the deflected set between ``a`` and ``b`` (one in it, one not), to ``resolution``; the
    value returned is in the set."""
    while b - a > resolution:
        middle = 0.5 * (a + b)
        if inside(middle) == inside_high:
            b = middle
        else:
            a = middle
    return b if inside_high else a


@dataclass(frozen=True)
class Calibration:
    """What ``calibrate`` measured, and the controller settings it implies."""

    settings: ControllerSettings
    delay: Delay
    pulse_bands: list
    envelopes: dict              # type name -> (low, high) or None
    scans: dict                  # type name -> [(offset, fate), ...]
    grid: Grid
    control_period: float
    runs: int

    def as_dict(self) -> dict:
        """A JSON-ready record (times in ms, distances in um)."""
        ms = 1e3
        settings = self.settings
        return {
            "controller": {"delay_ms": settings.delay * ms, "reference_velocity_m_s": settings.reference_velocity,
                           "lead_ms": settings.lead * ms, "pulse_ms": settings.pulse * ms,
                           "envelope_ms": [v * ms for v in settings.envelope],
                           "timing_error_ms": settings.timing_error * ms},
            "delay": {"distance_um": {k: v * 1e6 for k, v in self.delay.distance.items()},
                      "prediction_error_ms": {k: v * ms for k, v in self.delay.timing_error.items()},
                      "passages": [{"type": name, "idt_during_detection": state, "fate": p.fate,
                                    "detected_ms": _finite(p.detected * ms), "velocity_m_s": _finite(p.velocity),
                                    "arrival_ms": _finite(p.arrival * ms)}
                                   for (name, state), p in self.delay.passages.items()]},
            "pulses": [{"pulse_ms": band.pulse * ms,
                        "good_leads_ms": [v * ms for v in band.band] if band.band else None}
                       for band in self.pulse_bands],
            "envelopes_ms": {name: [v * ms for v in env] if env else None for name, env in self.envelopes.items()},
            "scans": {name: [[offset * ms, fate] for offset, fate in runs] for name, runs in self.scans.items()},
            "resolution_ms": {"lead": self.grid.lead_step * ms, "offset_scan": self.grid.offset_step * ms,
                              "envelope_edge": self.grid.resolution * ms},
            "control_period_ms": self.control_period * ms, "runs": self.runs,
            "look_ahead": look_ahead(settings),
        }


def look_ahead(settings: ControllerSettings) -> dict:
    """The controller's look-ahead, delay - lead: a type-I cell predicted later than that after a target is
    detected only once the target's pulse has started, too late to abort it. Purity mode needs it to cover the
    widened envelope's trailing edge (ms, and whether it does)."""
    reach = settings.delay - settings.lead
    edge = settings.window()[1]
    return {"look_ahead_ms": reach * 1e3, "widened_trailing_edge_ms": edge * 1e3, "covers_envelope": reach >= edge}


def _finite(value: float):
    return value if math.isfinite(value) else None


def calibrate(plant, scenario: Scenario, detector: DetectorSettings = DetectorSettings(), grid: Grid = Grid(),
              pulse: tuple[float, float] | None = None, base: ControllerSettings = ControllerSettings(),
              progress=None) -> Calibration:
    """Measure the sort delay, the shortest reliable pulse (unless ``pulse`` = (length, lead) is given) and the
    deflection envelope of every type on ``plant``; the controller settings (mode etc. from ``base``) they imply.
    An interrupt raises ``CalibrationInterrupted`` with what was measured before it."""
    plant = _Counted(plant)
    finished, bands = [], []
    try:
        return _calibrate(plant, scenario, detector, grid, pulse, base, progress, finished, bands)
    except KeyboardInterrupt:
        lines = finished[:1] + [f"pulse {band.pulse * 1e3:.3f} ms: good leads {_band_text(band.band)}"
                                for band in bands] + finished[1:]
        raise CalibrationInterrupted(lines + [
            f"PARTIAL: interrupted after {plant.resets} calibration cells; nothing saved (a controller file needs "
            "every measurement)"]) from None


class CalibrationInterrupted(KeyboardInterrupt):
    """A calibration stopped by Ctrl-C or SIGTERM; ``lines``: what it had measured (a partial report)."""

    def __init__(self, lines: list[str]):
        super().__init__()
        self.lines = lines


def _calibrate(plant, scenario, detector, grid, pulse, base, progress, finished: list, tried: list) -> Calibration:
    delay = measure_delay(plant, scenario, detector)
    finished.append("detector to SAW window: " + ", ".join(f"class {label} {distance * 1e6:.2f} um"
                                                          for label, distance in delay.distance.items())
                    + "; timing error " + ", ".join(f"class {label} {error * 1e6:.1f} us"
                                                    for label, error in delay.timing_error.items()))
    period = plant.control_period
    timing_error = max(delay.timing_error.values()) + period      # pulse edges fall on the control period's grid
    if pulse is None:
        chosen, bands = shortest_pulse(plant, scenario, detector, delay, grid,
                                       2 * timing_error + grid.lead_step, progress, tried)
        pulse_length, lead = chosen.pulse, 0.5 * (chosen.band[0] + chosen.band[1])
    else:
        (pulse_length, lead), bands = pulse, []
        failing = [c.name for c in scenario.cell_types
                   if c.target and not _sorted(plant, c.name, delay, pulse_length, lead, detector,
                                               grid.preceding_gaps)]
        if failing:
            raise CalibrationError(f"a {pulse_length * 1e3:g} ms pulse with lead {lead * 1e3:g} ms does not send "
                                   f"{', '.join(failing)} to the sorted outlet, alone or after another target's "
                                   "pulse 0.6-2 ms before: lengthen it or change the lead (or drop --pulse/--lead "
                                   "to search)")
    envelopes, scans = {}, {}
    for cell_type in scenario.cell_types:
        if progress:
            progress.update(f"envelope of {cell_type.name} under a {pulse_length * 1e3:.3f} ms pulse")
        envelopes[cell_type.name], scans[cell_type.name] = envelope_of(plant, cell_type.name, delay, pulse_length,
                                                                       lead, detector, grid)
        envelope = envelopes[cell_type.name]
        finished.append(f"envelope of {cell_type.name} under a {pulse_length * 1e3:.3f} ms pulse: " + (
            "never deflected" if envelope is None else f"{envelope[0] * 1e3:+.4f} to {envelope[1] * 1e3:+.4f} ms"))
    others = [envelopes[c.name] for c in scenario.cell_types if not c.target and envelopes[c.name]]
    envelope = (min(e[0] for e in others), max(e[1] for e in others)) if others else (0.0, 0.0)
    reference = delay.passages[next(c.name for c in scenario.cell_types if c.target), "off"].velocity
    settings = replace(base, delay=delay.distance[TYPE_II] / reference, reference_velocity=reference,
                       lead=lead, pulse=pulse_length, envelope=envelope, timing_error=timing_error)
    return Calibration(settings, delay, bands, envelopes, scans, grid, period, plant.resets)


class _Counted:
    """A plant that counts its resets (one per calibration cell)."""

    def __init__(self, plant):
        self._plant, self.resets = plant, 0

    def reset(self, *args, **kwargs):
        self.resets += 1
        return self._plant.reset(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._plant, name)


class CalibrationError(ValueError):
    """The device cannot be calibrated as asked (e.g. no pulse sends the target to the sorted outlet)."""


def _class_of(cell_type) -> str:
    return TYPE_II if cell_type.target else TYPE_I


def make_calibration_plant(scenario: Scenario, model: str, control_period: float | None = None):
    """A plant of ``model`` for calibration cells (``rom``, ``auto``, ``oneway`` or ``feib``)."""
    from sim.plants import registry as plants
    return plants.build(model, scenario, control_period=control_period)


def save_figure(calibration: Calibration, path) -> None:
    """The envelope scans (fate against offset, one row per type) and the pulse bands, as a PNG."""
    from .figures import pyplot, save_figure
    plt = pyplot()
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 3.6), gridspec_kw={"width_ratios": [3, 2]})
    colours = {SORTED: "tab:red", DEFAULT: "tab:blue"}
    names = list(calibration.scans)
    for row, name in enumerate(names):
        runs = calibration.scans[name]
        left.scatter([offset * 1e3 for offset, _ in runs], [row] * len(runs), s=12,
                     c=[colours.get(fate, "tab:gray") for _, fate in runs])
        envelope = calibration.envelopes[name]
        if envelope:
            left.plot([v * 1e3 for v in envelope], [row + 0.25] * 2, "k-", lw=3)
    low, high = calibration.settings.window()
    left.axvspan(low * 1e3, high * 1e3, color="0.85", zorder=0, label="abort window (envelope + 2 x timing error)")
    left.set_yticks(range(len(names)), names)
    left.set_ylim(-0.6, len(names) - 0.2)
    left.set_xlabel("arrival offset from the sorted cell (ms)")
    left.set_title("deflection envelope: red upper, blue lower, grey divider/failed", fontsize=9)
    left.legend(loc="lower right", fontsize=7)
    for band in calibration.pulse_bands:
        if band.band:
            right.plot([v * 1e3 for v in band.band], [band.pulse * 1e3] * 2, "g-", lw=3)
        else:
            right.plot([0.0], [band.pulse * 1e3], "x", color="0.6")
    settings = calibration.settings
    right.plot([settings.lead * 1e3], [settings.pulse * 1e3], "k*", ms=10, label="chosen")
    right.set_xlabel("lead: pulse start before the predicted arrival (ms)")
    right.set_ylabel("pulse length (ms)")
    right.set_title("leads that sort every target type (x: none)", fontsize=9)
    right.legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)
    plt.close(figure)


def report_lines(result: dict) -> list[str]:
    """The calibration as text (``result``: ``Calibration.as_dict`` plus model and files)."""
    c = result["controller"]
    distances = ', '.join(f'class {k} {v:.2f} um' for k, v in result['delay']['distance_um'].items())
    lines = [f"sort delay {c['delay_ms']:.4f} ms at {c['reference_velocity_m_s'] * 1e3:.1f} mm/s "
             f"(detector to SAW window: {distances});"
             f" timing error {c['timing_error_ms'] * 1e3:.1f} us per predicted arrival",
             (f"shortest reliable pulse {c['pulse_ms']:.3f} ms, lead {c['lead_ms']:.3f} ms" if result["pulses"] else
              f"pulse {c['pulse_ms']:.3f} ms, lead {c['lead_ms']:.3f} ms (given; it sorts every target type)")]
    for name, envelope in result["envelopes_ms"].items():
        lines.append(f"  envelope of {name}: " + ("never deflected" if envelope is None else
                                                  f"{envelope[0]:+.4f} to {envelope[1]:+.4f} ms"))
    lines.append(f"controller envelope (type I) {c['envelope_ms'][0]:+.4f} to {c['envelope_ms'][1]:+.4f} ms, width "
                 f"{c['envelope_ms'][1] - c['envelope_ms'][0]:.4f} ms; resolution: edges "
                 f"{result['resolution_ms']['envelope_edge'] * 1e3:.1f} us, "
                 f"leads {result['resolution_ms']['lead'] * 1e3:.0f} us")
    ahead = result.get("look_ahead")
    if ahead:
        verdict = "covers" if ahead["covers_envelope"] else (
            "does NOT cover (purity mode cannot abort for a type-I cell detected after the pulse starts: "
            "shorten the pulse or move the detection window upstream)")
        lines.append(f"look-ahead (delay - lead) {ahead['look_ahead_ms']:.4f} ms {verdict} the widened trailing "
                     f"edge {ahead['widened_trailing_edge_ms']:+.4f} ms")
    lines.append(f"model {result['model']}, SAW model {result['saw_model']}, control period "
                 f"{result['control_period_ms'] * 1e3:.1f} us, {result['runs']} calibration cells in "
                 f"{result['wall_time_s']:.1f} s")
    lines += [f"{kind}: {path}" for kind, path in result.get("files", {}).items()]
    return lines
