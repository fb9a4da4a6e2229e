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
from typing import Any

import numpy as np

from controller.detector import Detector, DetectorSettings
from controller.events import Sighting
from controller.protocol import ControllerError, DeviceFacts
from controller.sorter import ControllerSettings, SortController
from sim.fast.linalg import SolverError
from sim.method.fluid import NumericalBlowUp
from sim.model.arrivals import Arrivals, offer
from sim.model.scenario import Scenario
from sim.plants import contract
from sim.plants import registry as plants

from . import sortreport
from .control import Control, InProcess, Timing, describe
from .sortreport import report_lines, statistics_of, true_class  # noqa: F401  (the loop's public names)
from .steps import Moment, ProgressSink, StepRecord, is_paced, needs_state
from .trace import TRACE_BATCH, Tracer

MODELS = plants.MODELS
STATUSES = ("complete", "truncated", "interrupted", "failed")


class StreamStopped(Exception):
    """A run that did not finish: ``status`` is "interrupted" (KeyboardInterrupt, which SIGTERM is turned into
    by the CLI) or "failed" (a numerical failure: ``sim.method.fluid.NumericalBlowUp`` or
    ``sim.fast.linalg.SolverError``; or a controller that broke the protocol: ``controller.protocol.ControllerError``,
    or lost its connection). ``result`` is the summary of what ran up to then (its "status" and "reason" say why it is
    partial); ``__cause__`` is the original exception."""

    def __init__(self, status: str, reason: str, result: dict):
        super().__init__(reason)
        self.status, self.reason, self.result = status, reason, result

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
    window_mesh_h: float | None = None        # auto: mesh of its feib windows (None: sim.plants.auto's default)
    drain_time: float = DRAIN_TIME
    record_interval: float = RECORD_INTERVAL
    controller_from: str | None = None        # FILE.py:NAME or MODULE:NAME of a controller (vcyto.plugins)
    plant_from: str | None = None             # FILE.py:NAME or MODULE:NAME of a plant; replaces ``model``
    controller_wire: Any = None               # a controller in another process (``vcyto.wire.WireController``)

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)} (got {self.model!r})")
        if self.max_time is not None and not (math.isfinite(self.max_time) and self.max_time > 0):
            raise ValueError(f"max_time must be a finite positive time (got {self.max_time!r})")
        for name in ("drain_time", "record_interval"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a finite positive time (got {getattr(self, name)!r})")
        if self.controller_wire is not None and self.controller_from is not None:
            raise ValueError(f"{self.controller_wire.option} and --controller-from both name the controller: give "
                             "one of them")
        if self.window_mesh_h is not None and not (math.isfinite(self.window_mesh_h) and self.window_mesh_h > 0):
            raise ValueError("the auto model's window mesh size must be a positive length "
                             f"(got {self.window_mesh_h!r})")


def make_plant(scenario: Scenario, settings: StreamSettings):
    """A fresh plant of ``settings.model`` (the registry ``sim.plants.registry``). Set-up results (steady flows,
    matrices, factorisations) come from the disk cache, as on the command line (``vcyto.cache``;
    ``VCYTO_CACHE=off``)."""
    if settings.plant_from is not None:
        from . import plugins
        return plugins.plant(settings.plant_from, scenario)
    from .cache import ensure_default
    ensure_default()
    options = {"window_mesh_h": settings.window_mesh_h} if settings.model == "auto" else {}
    return plants.build(settings.model, scenario, control_period=settings.control_period, **options)


def settings_controller(settings: StreamSettings):
    """The controller ``settings`` name: ``controller_from``'s (``vcyto.plugins``), else the built-in one
    (``controller.sorter``), each built from ``settings.controller``."""
    if settings.controller_from is not None:
        from . import plugins
        return plugins.controller(settings.controller_from, settings.controller)
    return SortController(settings.controller)


def run_stream(scenario: Scenario, settings: StreamSettings, progress=None, plant=None, sinks=(), controller=None,
               timing: Timing = Timing(), table=None, checkpoint=None, ready=None) -> dict:
    """Run the loop until every admitted cell has left (or a cap); a JSON-ready summary (``sortreport``).

    ``controller``: any object implementing ``controller.protocol.Controller`` (default: ``settings``'s,
    ``settings_controller``: the built-in ``SortController`` unless ``controller_from`` names one), a class of
    one (built from ``settings.controller``), or a port
    to one in another process (``vcyto.wire``); the loop reaches it only through the protocol. ``plant``: a
    plant of one's own (``sim.plants.contract.Plant``; default: a fresh one of ``settings.model``). ``timing``:
    lock-step (default) or paced real time (``vcyto.control``). The summary names the controller and the plant
    that ran.

    ``sinks`` (e.g. an MCAP recorder) get each step through ``on_step``; the caller closes them. The ``truth``
    they get holds the cells in the channel and those that left since the previous step. A plant that can group
    periods (``step_until``, the rom plant) is stepped up to the next moment the loop must look: a cell crossing
    the end of the detection window, the next pulse edge, an unanswered event's deadline (real time), the cap,
    and with recording sinks every ``record_interval`` unless the plant traces its cells at that cadence itself
    (``sim.plants.contract.Traces``: the recorded steps reach the sinks as columns, ``vcyto.trace``, the plant runs on
    between the loop's own stops); the detector is fed the cells that crossed an edge of its window,
    one period before and at the crossing. It reacts to nothing else and the controller to nothing but its
    events, so the outcome is the same as stepping period by period (tested), at a fraction of the cost.

    The sort report is built as cells leave (``sortreport.SortLedger``, memory bounded by the cells in the
    channel); ``table``: the path of the per-cell table it writes (Parquet, ``vcyto.celltable``), or None;
    ``checkpoint``: a ``vcyto.recording.checkpoint.Checkpoint`` that writes the summary and events as the run goes,
    or None. ``ready``: called once the loop is set up (the plant built and reset to the sample), before its first
    step (the executable settles its garbage collector there: ``vcyto.cli.common.settle_collector``), or None.
    """
    port = None
    if controller is None and settings.controller_wire is not None:     # opened here, closed when the run ends
        controller = port = settings.controller_wire.open(timing)
    try:
        loop = Loop(scenario, settings, progress, plant, sinks, controller, timing, table, checkpoint)
        if ready is not None:
            ready()
        return _run(loop)
    finally:
        if port is not None:
            port.close()


def _run(loop: Loop) -> dict:
    status, reason, failure = "complete", "", None
    try:
        while loop.proceed:
            loop.step()
        loop.control.finish()
    except KeyboardInterrupt:
        status, reason = "interrupted", "interrupted by the user (SIGINT or SIGTERM)"
    except (NumericalBlowUp, SolverError, OSError) as error:      # OSError: a sink could not write (a full disk)
        status, reason, failure = "failed", str(error), error
    except (ControllerError, ConnectionError) as error:
        status, reason, failure = "failed", f"controller: {error}", error
    except OSError as error:                 # a file of the run could not be written (a full disk)
        status, reason, failure = "failed", f"{error.filename or 'a file of the run'}: {error.strerror}", error
    loop.finish()
    result = loop.summary(status, reason)
    if status == "interrupted":
        raise StreamStopped(status, reason, result)
    if status == "failed":
        raise StreamStopped(status, reason, result) from failure
    return result


def model_name(plant) -> str:
    """What a summary says ran: a registered model's name (``sim.plants.registry``), else the plant's own name."""
    model = getattr(type(plant), "model", None)
    if isinstance(model, str) and model in MODELS and type(plant).__module__.startswith("sim."):
        return model
    return describe(plant)


def _port(controller):
    """A port to ``controller``: itself if it is one (``vcyto.wire``), else an in-process port to the object."""
    if callable(getattr(controller, "post", None)) and callable(getattr(controller, "replies", None)):
        return controller
    return InProcess(controller)


def announce_end(sinks, result):
    """Tell the sinks how the run ended (a partial run's recording must say it is partial)."""
    stats = result["statistics"]
    ending = {"status": result["status"], "reason": result["reason"], "simulated_time_ms": result["simulated_time_ms"],
              **{key: stats.get(key) for key in ("offered", "events", "sorted", "aborts", "purity", "yield",
                                                 "not_injected", "not_yet_due", "missed_decisions")},
              **({"control": result["control"]} if "control" in result else {})}
    for sink in sinks:
        if hasattr(sink, "on_end"):
            sink.on_end(ending)


def _truncation(plant, settings, cap, drain_cap) -> str:
    truth = plant.truth()
    waiting = truth.waiting
    inside = sum(cell.fate == "in_channel" for cell in truth.cells)
    if settings.max_time is not None and cap < drain_cap:
        return (f"stopped at --max-time {settings.max_time * 1e3:g} ms as asked: {inside} cells still in the "
                f"channel; {waiting} admitted cells were not yet due (not counted)")
    return (f"{inside} cells still in the channel {settings.drain_time * 1e3:g} ms after the last arrival "
            "(stuck or too slow): their outcomes are unknown")


class Loop:
    """One closed-loop run, built once (the sample, the plant reset to it, the detector, the controller's port)
    and stepped by its driver, ``run_stream`` or another (``vcyto.rl``): ``while loop.proceed: loop.step()``,
    then ``finish()`` and ``summary(status, reason)``.

    A step is ``advance()`` (the plant up to the next moment the loop must look; the events the detector
    completed then), the controller told of each event (``control.deliver``; lock-step: each answer is taken
    before device time goes on), and ``conclude(events)`` (answers settled, the drive for the next stretch, the
    sinks shown the step when due). A driver may deliver the events one at a time between the two.
    """

    def __init__(self, scenario: Scenario, settings: StreamSettings, progress=None, plant=None, sinks=(),
                 controller=None, timing: Timing = Timing(), table=None, checkpoint=None):
        started = self.started = time.perf_counter()
        self.scenario, self.settings, self.sinks_given = scenario, settings, tuple(sinks)
        rng = np.random.default_rng(settings.seed)
        arrivals_rng, detector_rng = rng.spawn(2)
        sample = self.sample = offer(settings.arrivals, arrivals_rng)
        if plant is None and progress is not None:
            progress.note(f"setting up the {settings.model} plant (kept in the set-up cache after the first run)")
        plant = self.plant = plant or make_plant(scenario, settings)
        if controller is None:
            controller = settings_controller(settings)
        elif isinstance(controller, type):      # a class: built from the controller settings, as --controller-from
            controller = controller(settings.controller)
        self.port = _port(controller)
        facts = DeviceFacts.from_settings(settings.controller, plant.control_period, settings.detector.window)
        self.detector, self.control = Detector(settings.detector, detector_rng), Control(self.port, facts, timing)
        # the sort report, built as cells leave (not paced: it sees the steps the loop shows anyway)
        self.report = sortreport.SortLedger(sample, scenario, settings, self.control.ledger.predicted_arrival,
                                            table=table, checkpoint=checkpoint)
        observers = list(sinks) + [self.report] + ([ProgressSink(progress, len(sample.admitted))]
                                                   if progress is not None else [])
        self.sinks = tuple(observers)
        self.paced = any(is_paced(sink) for sink in self.sinks)      # recordings: the state every record_interval
        self.detected, self.settled = 0, set()
        self.actuation = self.idt_time = 0.0
        self.steps = 0
        self.fields = _field_payload(plant) if self.paced and isinstance(plant, contract.HasFields) else None
        self.grouped = isinstance(plant, contract.StepsUntil)
        # one step a call (the FE-IB plant with a tolerance): every call is shown, none stopped for the records
        self.single = self.grouped and getattr(plant, "one_step_per_call", False)
        self.truth_updates = plant.truth_update if isinstance(plant, contract.ReportsTruthUpdates) else None
        # the plant's observation and diagnostics only where a sink reads them (the sort report does not)
        self.state_wanted = any(needs_state(sink) for sink in self.sinks)
        self.diagnostics = plant.diagnostics if isinstance(plant, contract.HasDiagnostics) and self.state_wanted \
            else None
        self.pending, self.shown = [], 0.0          # events not yet shown to the sinks; when they last saw a step
        self._looked = None                         # the plant as looked at for the sinks, not yet shown
        self.observation = plant.reset(sample.admitted)
        # an event-driven plant that traces its cells: recorded steps without stopping the plant (vcyto.trace)
        self.tracer = (Tracer(plant, settings.record_interval) if self.paced and self.grouped and not self.single
                       and isinstance(plant, contract.Traces) else None)
        self.decided = []                           # decisions not yet shown (tracing: gathered every step)
        self.setup = time.perf_counter() - started
        self.rss_setup = _peak_rss_mb()
        last_arrival = sample.admitted[-1][0] if sample.admitted else 0.0
        self.drain_cap = last_arrival + settings.drain_time
        self.cap = min(self.drain_cap, settings.max_time) if settings.max_time is not None else self.drain_cap
        self.rss_loop = None

    @property
    def proceed(self) -> bool:
        """Whether the run goes on: cells are still to leave and the cap is not reached."""
        return not self.plant.done and self.now < self.cap

    @property
    def now(self) -> float:
        return self.plant.time if self.grouped else self.observation.time

    @property
    def clock(self) -> float:
        """The controller's time: the plant's last control period end when it steps across them (the drive
        changes only at their ends, as when the loop steps period by period), else the plant's time."""
        return self.plant.clock if self.single else self.now

    def step(self):
        events = self.advance()
        self.control.post(events)
        # what the sinks are shown of the plant does not depend on the answers: looked at while the controller
        # thinks (over the wire, in another process), then the answers are collected (lock-step)
        look = self._looked = self._look() if self._show_due(events) else None
        self.control.collect()
        self.conclude(events, look)

    def advance(self) -> list:
        """The plant up to the next moment the loop must look; the detector events completed by then."""
        plant, control, cap = self.plant, self.control, self.cap
        if self.grouped:
            # what the detector reacts to: the cells crossing its lines, one period before and at the crossing
            started = self.now
            until = min(control.next_change(self.clock), cap)
            if self.paced and not self.single:
                until = min(until, self.shown + self.settings.record_interval * (TRACE_BATCH if self.tracer else 1))
            window_start, window_end = self.settings.detector.window
            periods, seen = plant.step_until(self.actuation, until, stop_lines=(window_end,),
                                             record_lines=(window_start,))
            now = self.now
            self.idt_time += self.actuation * (now - started)
            if self.tracer is not None:
                self.tracer.take(self.steps + periods, self.actuation)
        else:
            self.observation, periods = plant.step(self.actuation), 1
            seen = [self.observation]
            self.idt_time += self.actuation * plant.control_period
            now = self.now
        self.steps += periods
        control.pace(now)
        new_events = [event for view in seen for event in self.detector.observe(view.time, _sightings(view))]
        self.detected += len(new_events)
        return new_events

    def conclude(self, new_events, look=None):
        """After the controller was told of ``new_events``: late answers settled, the drive set, the sinks shown
        (``look``: the plant as ``_look`` saw it at this stop, if already taken)."""
        control, now = self.control, self.now
        control.settle(now)
        self.actuation = control.actuation(self.plant.clock if self.single else now)
        self.pending.extend(new_events)
        if self.tracer is not None:
            # a tracing plant is shown when a recorded step has passed, and with every event and decision (so that
            # each recorded step sees the classes it would have seen had the loop stopped there)
            self.decided += self.control.ledger.take_changes()
            if self.sinks and (look is not None or self.tracer.due or self.pending or self.decided or self.plant.done):
                self._show(look, final=self.plant.done)
        elif look is not None or self._show_due():
            self._show(look)

    def _show_due(self, events=()) -> bool:
        """Whether the sinks see this stop (``events``: those just posted, not yet in ``pending``): every step, or
        an event-driven plant's state every record_interval (events and decisions wait for it), and its last; a
        tracing plant's when a recorded step has passed or with an event (or a decision: known only later)."""
        if not self.sinks:
            return False
        if self.tracer is not None:
            return bool(self.tracer.due or self.pending or events or self.plant.done)
        return (not self.grouped or self.single or self.plant.done
                or self.now >= self.shown + self.settings.record_interval - 1e-12)

    def _look(self) -> tuple:
        """The plant at this stop as the sinks see it: its observation, the cells' truth, its diagnostics."""
        if self.grouped:
            self.observation = self.plant.observe() if self.state_wanted else Moment(self.plant.time)
        return (self.observation, self.truth_update(), self.diagnostics() if self.diagnostics is not None else None)

    def _show(self, look=None, final: bool = False):
        look, self._looked = look or self._looked, None       # a look taken before an answer failed is not lost
        observation, truth, diagnostics = look if look is not None else self._look()
        trace = None
        if self.tracer is not None:
            trace = self.tracer.batch(self.actuation, (self.steps, observation) if final else None)
        decisions, self.decided = tuple(self.decided + self.control.ledger.take_changes()), []
        self.detector.forget([cell.key for cell in truth.cells if cell.fate != "in_channel"])    # bounded memory
        record = StepRecord(self.steps, observation, truth, self.actuation, tuple(self.pending), decisions,
                            self.fields, diagnostics, trace)
        for sink in self.sinks:
            sink.on_step(record)
        self.pending, self.shown = [], self.now

    def truth_update(self):
        """The cells in the channel and those that left since the last call (each settled cell once)."""
        if self.truth_updates is not None:
            return self.truth_updates()
        truth = self.plant.truth()
        cells = tuple(cell for cell in truth.cells if cell.fate == "in_channel" or cell.key not in self.settled)
        self.settled.update(cell.key for cell in cells if cell.fate != "in_channel")
        return type(truth)(truth.time, cells, truth.waiting)

    def finish(self):
        """Show the sinks what they have not seen yet (the last step, events and cells that left since)."""
        if self.sinks and (self.grouped or self._looked) and (self.pending or self.decided or self._looked
                                                              or self.now > self.shown):
            self._show(final=True)
        self.rss_loop = _peak_rss_mb()

    def summary(self, status: str = "complete", reason: str = "") -> dict:
        """The run's JSON-ready summary (``sortreport``); ``status`` and ``reason`` say how it ended (a run that
        ended ``complete`` with cells left in the channel is ``truncated``). The sinks are told how it ended."""
        plant, settings, sinks = self.plant, self.settings, self.sinks_given
        if status == "complete" and not plant.done:
            status, reason = "truncated", _truncation(plant, settings, self.cap, self.drain_cap)
        result = self.report.summary(self.now, self.control.ledger.latencies, partial=status != "complete")
        result.update(status=status, reason=reason, wall_time_s=time.perf_counter() - self.started,
                      setup_time_s=self.setup, idt_on_time_ms=self.idt_time * 1e3, steps=self.steps,
                      # peak resident memory after the set-up, at the loop's end (its state), and with the report
                      memory_mb={"after_setup": self.rss_setup, "after_loop": self.rss_loop, "peak": _peak_rss_mb()})
        result["control"] = self.control.report()
        result["controller_name"] = self.port.name
        result["model"] = model_name(plant)
        if isinstance(plant, contract.ReportsTimeSteps):     # feib: the dt used over time (--tolerance)
            result["time_steps"] = plant.time_steps()
        announce_end(sinks, result)
        if isinstance(plant, contract.SwitchesModels):       # the auto plant: what it picked, when and why
            result["auto"] = {"switches": [{"time_ms": t * 1e3, "model": model, "reason": why}
                                           for t, model, why in plant.switches],
                              "feib_fraction": plant.diagnostics()["feib_fraction"]}
        return result


def _peak_rss_mb() -> float | None:
    """The process's peak resident memory so far (MB; None where the platform does not say)."""
    try:
        import resource
    except ImportError:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 1024 if sys.platform != "darwin" else peak / 2**20


def _sightings(observation):
    """What the detector sees of an observation's cells: its own sequence when they are all the plant contract's views
    (frozen), else each as one."""
    cells = observation.cells
    for c in cells:
        if type(c) is not Sighting:
            return [c if type(c) is Sighting else Sighting(c.key, c.x, c.y, c.area, c.brightness) for c in cells]
    return cells


def _field_payload(plant):
    from .recording.mcap import velocity_field

    def payload():
        vertices, velocity, pressure, grid_x, grid_y = plant.fields()
        return velocity_field(vertices, velocity, pressure, grid_x, grid_y, plant.truth().time)
    return payload
