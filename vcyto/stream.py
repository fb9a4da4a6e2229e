"""`vcyto stream`: the closed sorting loop. The one function that owns the loop is ``run_stream``.

plant.step(actuation) -> observation -> detector -> controller -> actuation for the next control period;
outcomes come from the plant's ground truth, which the controller never sees. A run ends when every cell of
the sample has left the device; ``max_time`` is an explicit cap, and a run that reaches it (or whose cells
are still in the channel ``drain_time`` after the last arrival) is reported as truncated, never as complete.
The loop's work per period depends on the cells in the channel, not on how many have passed: plants that
can report only what changed (``truth_update``) are asked for that, and the summary is built once at the end.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from controller.detector import Detector, DetectorSettings
from controller.events import Sighting
from controller.sorter import ControllerSettings, SortController
from sim import plants
from sim.arrivals import Arrivals, offer
from sim.fluid import NumericalBlowUp
from sim.linalg import SolverError
from sim.scenario import Scenario

from . import sortreport
from .sortreport import report_lines, statistics_of, true_class  # noqa: F401  (the loop's public names)

MODELS = plants.MODELS
STATUSES = ("complete", "truncated", "interrupted", "failed")


class StreamStopped(Exception):
    """A run that did not finish: ``status`` is "interrupted" (KeyboardInterrupt, which SIGTERM is turned into
    by the CLI) or "failed" (a numerical failure: ``sim.fluid.NumericalBlowUp`` or ``sim.linalg.SolverError``).
    ``result`` is the summary of what ran up to then (its "status" and "reason" say why it is partial);
    ``__cause__`` is the original exception."""

    def __init__(self, status: str, reason: str, result: dict):
        super().__init__(reason)
        self.status, self.reason, self.result = status, reason, result

NOTE_LIMIT = 200               # per-cell lines on screen for samples up to this size; beyond, counts only
DRAIN_TIME = 20e-3             # s after the last arrival by which every cell must have left (else: truncated)
RECORD_INTERVAL = 0.25e-3      # s: an event-driven plant shows its state to the sinks this often (paths ~25 um)


@dataclass(frozen=True)
class StreamSettings:
    arrivals: Arrivals
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    controller: ControllerSettings = field(default_factory=ControllerSettings)
    model: str = "feib"
    seed: int = 0
    control_period: float | None = None       # default: the plant's natural period (dt for feib)
    max_time: float | None = None             # an explicit cap on simulated time (None: until the sample ends)
    window_mesh_h: float | None = None        # auto: mesh of its feib windows (None: sim.auto's default)
    drain_time: float = DRAIN_TIME
    record_interval: float = RECORD_INTERVAL

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)} (got {self.model!r})")
        if self.max_time is not None and not (math.isfinite(self.max_time) and self.max_time > 0):
            raise ValueError(f"max_time must be a finite positive time (got {self.max_time!r})")
        for name in ("drain_time", "record_interval"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a finite positive time (got {getattr(self, name)!r})")
        if self.window_mesh_h is not None and not (math.isfinite(self.window_mesh_h) and self.window_mesh_h > 0):
            raise ValueError(f"the auto model's window mesh size must be a positive length (got {self.window_mesh_h!r})")


def make_plant(scenario: Scenario, settings: StreamSettings):
    """A fresh plant of ``settings.model`` (the registry ``sim.plants``)."""
    options = {"window_mesh_h": settings.window_mesh_h} if settings.model == "auto" else {}
    return plants.build(settings.model, scenario, control_period=settings.control_period, **options)


def run_stream(scenario: Scenario, settings: StreamSettings, progress=None, plant=None, sinks=()) -> dict:
    """Run the loop until every admitted cell has left (or a cap); a JSON-ready summary (``sortreport``).

    ``sinks`` (e.g. an MCAP recorder) get each step through ``on_step``; the caller closes them. The ``truth``
    they get holds the cells in the channel and those that left since the previous step. A plant that can group
    periods (``step_until``, the rom plant) is stepped up to the next moment the loop must look: a cell crossing
    the end of the detection window, the controller's next pulse edge, the cap, and with sinks every
    ``record_interval``; the detector is fed the cells that crossed an edge of its window, one period before and
    at the crossing. It reacts to nothing else and the controller to nothing but its events, so the outcome is
    the same as stepping period by period (tested), at a fraction of the cost.
    """
    started = time.perf_counter()
    rng = np.random.default_rng(settings.seed)
    arrivals_rng, detector_rng = rng.spawn(2)
    sample = offer(settings.arrivals, arrivals_rng)
    plant = plant or make_plant(scenario, settings)
    run = _Run(plant, settings, Detector(settings.detector, detector_rng), SortController(settings.controller),
               sinks, progress, len(sample.admitted))
    run.observation = plant.reset(sample.admitted)
    setup = time.perf_counter() - started
    rss_setup = _peak_rss_mb()
    last_arrival = sample.admitted[-1][0] if sample.admitted else 0.0
    drain_cap = last_arrival + settings.drain_time
    cap = min(drain_cap, settings.max_time) if settings.max_time is not None else drain_cap
    status, reason, failure = "complete", "", None
    try:
        while not plant.done and run.now < cap:
            run.step(cap)
    except KeyboardInterrupt:
        status, reason = "interrupted", "interrupted by the user (SIGINT or SIGTERM)"
    except (NumericalBlowUp, SolverError) as error:
        status, reason, failure = "failed", str(error), error
    run.finish()
    if status == "complete" and not plant.done:
        status, reason = "truncated", _truncation(plant, settings, cap, drain_cap)
    result = sortreport.summarise(sample, plant.truth(), run.events, run.controller, scenario, settings)
    result.update(status=status, reason=reason, wall_time_s=time.perf_counter() - started, setup_time_s=setup,
                  idt_on_time_ms=run.idt_time * 1e3, steps=run.steps, memory_mb={"after_setup": rss_setup,
                                                                                  "peak": _peak_rss_mb()})
    if hasattr(plant, "time_steps"):           # feib: the dt used over time (sim.adaptive with --tolerance)
        result["time_steps"] = plant.time_steps()
    _announce_end(sinks, result)
    if hasattr(plant, "switches"):             # the auto plant: what it picked, when and why
        result["auto"] = {"switches": [{"time_ms": t * 1e3, "model": model, "reason": why}
                                       for t, model, why in plant.switches],
                          "feib_fraction": plant.diagnostics()["feib_fraction"]}
    if hasattr(plant, "time_steps"):           # feib: the dt used over time (sim.adaptive with --tolerance)
        result["time_steps"] = plant.time_steps()
    if status == "interrupted":
        raise StreamStopped(status, reason, result)
    if status == "failed":
        raise StreamStopped(status, reason, result) from failure
    return result


def _announce_end(sinks, result):
    """Tell the sinks how the run ended (a partial run's recording must say it is partial)."""
    stats = result["statistics"]
    ending = {"status": result["status"], "reason": result["reason"], "simulated_time_ms": result["simulated_time_ms"],
              **{key: stats.get(key) for key in ("offered", "events", "sorted", "aborts", "purity", "yield",
                                                 "not_injected")}}
    for sink in sinks:
        if hasattr(sink, "on_end"):
            sink.on_end(ending)


def _truncation(plant, settings, cap, drain_cap) -> str:
    truth = plant.truth()
    waiting = truth.waiting
    inside = sum(cell.fate == "in_channel" for cell in truth.cells)
    if settings.max_time is not None and cap < drain_cap:
        return (f"stopped at --max-time {settings.max_time * 1e3:g} ms as asked: {waiting} cells never injected, "
                f"{inside} still in the channel")
    return (f"{inside} cells still in the channel {settings.drain_time * 1e3:g} ms after the last arrival "
            "(stuck or too slow): their outcomes are unknown")


class _Run:
    """The state of one closed-loop run between its steps (``run_stream`` owns the loop)."""

    def __init__(self, plant, settings, detector, controller, sinks, progress, count):
        self.plant, self.settings, self.detector, self.controller = plant, settings, detector, controller
        self.sinks, self.progress = sinks, progress
        self.notes = progress is not None and count <= NOTE_LIMIT
        self.events, self.settled, self.left = {}, set(), 0
        self.actuation = self.idt_time = 0.0
        self.steps = 0
        self.fields = _field_payload(plant) if sinks and hasattr(plant, "fields") else None
        self.grouped = hasattr(plant, "step_until")
        self.observation = None
        self.truth_update = getattr(plant, "truth_update", None)
        self.pending, self.shown = [], 0.0          # events not yet shown to the sinks; when they last saw a step

    @property
    def now(self) -> float:
        return self.plant.time if self.grouped else self.observation.time

    def step(self, cap: float):
        plant, controller = self.plant, self.controller
        if self.grouped:
            # what the detector reacts to: the cells crossing its lines, one period before and at the crossing
            until = min(controller.next_change(self.now), cap)
            if self.sinks:
                until = min(until, self.shown + self.settings.record_interval)
            window_start, window_end = self.settings.detector.window
            periods, seen = plant.step_until(self.actuation, until, stop_lines=(window_end,),
                                             record_lines=(window_start,))
        else:
            self.observation, periods = plant.step(self.actuation), 1
            seen = [self.observation]
        self.steps += periods
        self.idt_time += self.actuation * plant.control_period * periods
        new_events = [event for view in seen for event in self.detector.observe(view.time, _sightings(view))]
        for event in new_events:
            controller.on_event(event)
            self.events[event.key] = event
            if self.notes:
                decision = controller.decision_for(event.event_id)
                self.progress.note(f"t = {event.time * 1e3:7.3f} ms  cell {event.key}: detected type "
                                   f"{event.classification} (fluorescence {event.fluorescence:.2f}), "
                                   f"decision {decision.action}")
        self.actuation = controller.actuation(self.now)
        self.pending.extend(new_events)
        # an event-driven plant shows its state every record_interval (events and decisions wait for it)
        due = not self.grouped or self.now >= self.shown + self.settings.record_interval - 1e-12 or plant.done
        if due and (self.sinks or self.progress):
            if self.grouped:
                self.observation = plant.observe()
            self._show(self.pending)
            self.pending, self.shown = [], self.now

    def _show(self, new_events):
        truth = self._truth()
        if self.sinks:
            decisions = self.controller.take_changes()
            diagnostics = self.plant.diagnostics() if hasattr(self.plant, "diagnostics") else None
            for sink in self.sinks:
                sink.on_step(self.steps, self.observation, truth, self.actuation, new_events, decisions, self.fields,
                             diagnostics)
        if self.progress:
            self._report(truth)
            self.progress.update(f"t = {self.now * 1e3:.3f} ms, {len(self.observation.cells)} cells in the channel, "
                                 f"{self.left} left, {len(self.events)} detected, IDT {'on' if self.actuation else 'off'}")

    def _truth(self):
        """The cells in the channel and those that left since the last call (each settled cell once)."""
        if self.truth_update is not None:
            return self.truth_update()
        truth = self.plant.truth()
        cells = tuple(cell for cell in truth.cells if cell.fate == "in_channel" or cell.key not in self.settled)
        self.settled.update(cell.key for cell in cells if cell.fate != "in_channel")
        return type(truth)(truth.time, cells, truth.waiting)

    def _report(self, truth):
        for cell in truth.cells:
            if cell.fate != "in_channel":
                self.left += 1
                if self.notes:
                    self.progress.note(f"t = {cell.exit_time * 1e3:7.3f} ms  cell {cell.key} ({cell.type}) left by: "
                                       f"{cell.fate}")

    def finish(self):
        if self.sinks and self.grouped and (self.pending or self.now > self.shown):
            self.observation = self.plant.observe()
            self._show(self.pending)
        elif self.progress:
            self._report(self._truth())


def _peak_rss_mb() -> float | None:
    """The process's peak resident memory so far (MB; None where the platform does not say)."""
    try:
        import resource
    except ImportError:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024 if sys.platform != "darwin" else peak / 2**20


def _sightings(observation) -> list[Sighting]:
    return [Sighting(c.key, c.x, c.y, c.area, c.brightness) for c in observation.cells]


def _field_payload(plant):
    from .recording import velocity_field

    def payload():
        vertices, velocity, pressure, grid_x, grid_y = plant.fields()
        return velocity_field(vertices, velocity, pressure, grid_x, grid_y, plant.truth().time)
    return payload
