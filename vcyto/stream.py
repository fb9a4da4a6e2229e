"""`vcyto stream`: the closed sorting loop. The one function that owns the loop is ``run_stream``.

plant.step(actuation) -> observation -> detector -> controller -> actuation for the next control period;
outcomes come from the plant's ground truth, which the controller never sees.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass, field

import numpy as np

from controller.detector import Detector, DetectorSettings
from controller.events import TYPE_I, TYPE_II, Sighting
from controller.sorter import ControllerSettings, SortController
from sim.arrivals import Arrivals, schedule
from sim.fluid import NumericalBlowUp
from sim.linalg import SolverError
from sim.plant import FeibPlant, StreamlinePlant
from sim.scenario import UM, Scenario

MODELS = ("feib", "streamline", "rom", "oneway", "auto")
STATUSES = ("complete", "truncated", "interrupted", "failed")


class StreamStopped(Exception):
    """A run that did not finish: ``status`` is "interrupted" (KeyboardInterrupt, which SIGTERM is turned into
    by the CLI) or "failed" (a numerical failure: ``sim.fluid.NumericalBlowUp`` or ``sim.linalg.SolverError``).
    ``result`` is the summary of what ran up to then (its "status" and "reason" say why it is partial);
    ``__cause__`` is the original exception."""

    def __init__(self, status: str, reason: str, result: dict):
        super().__init__(reason)
        self.status, self.reason, self.result = status, reason, result
SORTED_OUTLET = "upper"
TYPE_II_CELLS = ("melanoma",)


@dataclass(frozen=True)
class StreamSettings:
    arrivals: Arrivals
    detector: DetectorSettings = field(default_factory=DetectorSettings)
    controller: ControllerSettings = field(default_factory=ControllerSettings)
    model: str = "feib"
    seed: int = 0
    control_period: float | None = None       # default: the plant's natural period (dt for feib)
    max_time: float = 50e-3
    window_mesh_h: float | None = None        # auto: mesh of its feib windows (None: sim.auto's default)

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)} (got {self.model!r})")
        if self.max_time <= 0:
            raise ValueError("max_time must be positive")
        if self.window_mesh_h is not None and not (math.isfinite(self.window_mesh_h) and self.window_mesh_h > 0):
            raise ValueError(f"the auto model's window mesh size must be a positive length (got {self.window_mesh_h!r})")


def make_plant(scenario: Scenario, settings: StreamSettings):
    if settings.model == "streamline":
        return StreamlinePlant(scenario, control_period=settings.control_period or 10e-6)
    if settings.model == "rom":
        from sim.rom import RomPlant
        return RomPlant(scenario, control_period=settings.control_period)
    if settings.model == "auto":
        from sim.auto import AutoPlant
        return AutoPlant(scenario, control_period=settings.control_period, window_mesh_h=settings.window_mesh_h)
    if settings.model == "oneway":
        from sim.oneway import OneWayPlant
        return OneWayPlant(scenario, control_period=settings.control_period)
    return FeibPlant(scenario, control_period=settings.control_period)


def run_stream(scenario: Scenario, settings: StreamSettings, progress=None, plant=None, sinks=()) -> dict:
    """Run the loop until every scheduled cell has left (or ``max_time``); a JSON-ready summary.

    ``sinks`` (e.g. an MCAP recorder) get every control period through ``on_step``; the caller closes them.
    Without sinks, a plant that can group periods (``step_until``, the rom plant) is stepped up to the next
    moment the loop must look: a cell crossing the end of the detection window, the controller's next pulse
    edge, ``max_time``; the detector is fed the cells that crossed an edge of its window, one period before
    and at the crossing. It reacts to nothing else and the controller to nothing but its events, so the
    outcome is the same as stepping period by period (tested), at a fraction of the cost.
    """
    started = time.perf_counter()
    rng = np.random.default_rng(settings.seed)
    arrivals_rng, detector_rng = rng.spawn(2)
    planned = schedule(settings.arrivals, arrivals_rng)
    plant = plant or make_plant(scenario, settings)
    detector = Detector(settings.detector, detector_rng)
    controller = SortController(settings.controller)
    observation = plant.reset(planned, seed=settings.seed)
    setup = time.perf_counter() - started
    events, reported, actuation, idt_time, step = {}, set(), 0.0, 0.0, 0
    fields = _field_payload(plant) if hasattr(plant, "fields") else None
    grouped = not sinks and hasattr(plant, "step_until")
    window_start, window_end = settings.detector.window     # the detector reacts to crossings of these
    keys = {cell.key for cell in observation.cells}
    now = observation.time
    status, reason = "complete", ""
    try:
        while not plant.done and now < settings.max_time:
            if grouped:
                # what the detector reacts to: the cells crossing its lines, one period before and at the crossing
                until = min(controller.next_change(now), settings.max_time)
                periods, seen = plant.step_until(actuation, until, stop_lines=(window_end,), record_lines=(window_start,))
                now = plant.time
            else:
                observation, periods = plant.step(actuation), 1
                seen, now = [observation], observation.time
            step += periods
            idt_time += actuation * plant.control_period * periods
            new_events = [event for view in seen for event in detector.observe(view.time, _sightings(view))]
            for event in new_events:
                controller.on_event(event)
                events[event.key] = event
                if progress:
                    decision = controller.decision_for(event.event_id)
                    progress.note(f"t = {event.time * 1e3:7.3f} ms  cell {event.key}: detected type {event.classification}"
                                  f" (fluorescence {event.fluorescence:.2f}), decision {decision.action}")
            actuation = controller.actuation(now)
            if sinks:
                truth = plant.truth()
                decisions = controller.take_changes()
                diagnostics = plant.diagnostics() if hasattr(plant, "diagnostics") else None
                for sink in sinks:
                    sink.on_step(step, observation, truth, actuation, new_events, decisions, fields, diagnostics)
            if progress:
                observation = plant.observe() if grouped else observation
                previous, keys = keys, {cell.key for cell in observation.cells}
                if not previous <= keys:          # a cell has left the channel: report how
                    _report_exits(plant.truth(), reported, progress)
                progress.update(f"t = {observation.time * 1e3:.3f} ms, {len(observation.cells)} cells in the channel, "
                                f"IDT {'on' if actuation else 'off'}")
    except KeyboardInterrupt:
        status, reason = "interrupted", "interrupted by the user (SIGINT or SIGTERM)"
    except (NumericalBlowUp, SolverError) as error:
        status, reason, failure = "failed", str(error), error
    if progress:
        _report_exits(plant.truth(), reported, progress)
    result = summarise(planned, plant.truth(), events, controller, time.perf_counter() - started, setup, idt_time,
                       settings, scenario)
    if status == "complete" and not plant.done:
        status, reason = "truncated", f"stopped at max_time = {settings.max_time * 1e3:g} ms before every cell had left"
    result["status"], result["reason"] = status, reason
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


def _sightings(observation) -> list[Sighting]:
    return [Sighting(c.key, c.x, c.y, c.area, c.brightness) for c in observation.cells]


def _field_payload(plant):
    from .recording import velocity_field

    def payload():
        vertices, velocity, pressure, grid_x, grid_y = plant.fields()
        return velocity_field(vertices, velocity, pressure, grid_x, grid_y, plant.truth().time)
    return payload


def _report_exits(truth, reported, progress):
    for cell in truth.cells:
        if cell.fate != "in_channel" and cell.key not in reported:
            reported.add(cell.key)
            progress.note(f"t = {cell.exit_time * 1e3:7.3f} ms  cell {cell.key} ({cell.type}) left by: {cell.fate}")


def true_class(type_name: str) -> str:
    return TYPE_II if type_name in TYPE_II_CELLS else TYPE_I


def summarise(planned, truth, events, controller, wall, setup, idt_time, settings, scenario) -> dict:
    by_key = {cell.key: cell for cell in truth.cells}
    cells = []
    for key, (arrival, type_name) in enumerate(planned):
        cell = by_key.get(key)
        event = events.get(key)
        decision = controller.decision_for(event.event_id) if event else None
        cells.append({
            "key": key, "type": type_name, "true_class": true_class(type_name), "arrival_ms": arrival * 1e3,
            "detected_class": event.classification if event else None,
            "detection_time_ms": event.time * 1e3 if event else None,
            "fluorescence": event.fluorescence if event else None,
            "scatter": event.scatter if event else None,
            "velocity_mm_s": event.velocity * 1e3 if event else None,
            "decision": decision.action if decision else None,
            "outlet": (cell.fate if cell.fate != "in_channel" else "lost") if cell else "lost",
            "exit_time_ms": cell.exit_time * 1e3 if cell else None,
            "exit_y_um": cell.exit_y * 1e6 if cell and math.isfinite(cell.exit_y) else None,
            "area_ratio": cell.area_ratio if cell else None,
            **_shape_summary(cell.measures if cell else None),
        })
    return {"cells": cells, "statistics": statistics_of(cells, truth.time),
            "wall_time_s": wall, "setup_time_s": setup, "simulated_time_ms": truth.time * 1e3,
            "idt_on_time_ms": idt_time * 1e3, "model": settings.model, "seed": settings.seed,
            "controller_mode": settings.controller.mode,
            "controller_latency_us": _latency(controller.latencies)}


def _shape_summary(measures: dict | None) -> dict:
    """Area kept over the transit and the band of point spacings (FE-IB cells; None for point-like models)."""
    if not measures:
        return {"area_ratio_range": None, "spacing_over_h": None, "area_corrected": None}
    return {"area_ratio_range": [measures["area_ratio_min"], measures["area_ratio_max"]],
            "spacing_over_h": [measures["spacing_lowest"], measures["spacing_highest"]],
            "area_corrected": measures["area_corrected"]}


def _latency(samples):
    if not samples:
        return {}
    micro = np.array(samples) * 1e6
    return {"median": float(np.median(micro)), "p99": float(np.percentile(micro, 99)), "max": float(micro.max())}


def statistics_of(cells, simulated_time) -> dict:
    """Purity, yield, abort rate, throughput and misclassifications from per-cell outcomes."""
    sorted_cells = [c for c in cells if c["outlet"] == SORTED_OUTLET]
    wanted = [c for c in cells if c["true_class"] == TYPE_II]
    detected_ii = [c for c in cells if c["detected_class"] == TYPE_II]
    aborts = [c for c in cells if c["decision"] == "abort"]
    exits = [c["exit_time_ms"] for c in cells if c["exit_time_ms"] is not None and c["outlet"] != "lost"]
    return {
        "cells": len(cells),
        "purity": (sum(c["true_class"] == TYPE_II for c in sorted_cells) / len(sorted_cells)) if sorted_cells else None,
        "yield": (sum(c["outlet"] == SORTED_OUTLET for c in wanted) / len(wanted)) if wanted else None,
        "abort_rate": (len(aborts) / len(detected_ii)) if detected_ii else None,
        "aborts": len(aborts),
        "misclassified": sum(c["detected_class"] is not None and c["detected_class"] != c["true_class"] for c in cells),
        "undetected": sum(c["detected_class"] is None for c in cells),
        "throughput_cells_per_s": (len(cells) / (max(exits) * 1e-3)) if exits else None,
        "outlets": {outlet: sum(c["outlet"] == outlet for c in cells)
                    for outlet in sorted({c["outlet"] for c in cells})},
    }


def report_lines(result: dict) -> list[str]:
    lines = [f"{'cell':>4}  {'type':<9} {'detected':>8}  {'decision':<8} {'outlet':<7} {'exit (ms)':>9}  "
             f"{'area kept (min-max)':<20} spacing / h"]
    for cell in result["cells"]:
        exit_ms = f"{cell['exit_time_ms']:9.3f}" if cell["exit_time_ms"] is not None else "        -"
        low_high = cell.get("area_ratio_range")
        area = f"{100 * low_high[0]:6.2f}-{100 * low_high[1]:6.2f} %" if low_high else "-"
        spacing = cell.get("spacing_over_h")
        band = f"{spacing[0]:.2f}-{spacing[1]:.2f}" if spacing else "-"
        lines.append(f"{cell['key']:>4}  {cell['type']:<9} {cell['detected_class'] or '-':>8}  "
                     f"{cell['decision'] or '-':<8} {cell['outlet']:<7} {exit_ms}  {area:<20} {band}")
    stats = result["statistics"]

    def percent(value):
        return "n/a" if value is None else f"{100 * value:.1f} %"

    throughput = stats["throughput_cells_per_s"]
    lines += [
        f"purity {percent(stats['purity'])}, yield {percent(stats['yield'])}, abort rate {percent(stats['abort_rate'])}"
        f" ({stats['aborts']} aborts), misclassified {stats['misclassified']}, undetected {stats['undetected']}",
        f"throughput {throughput:.0f} cells/s of simulated time" if throughput else "throughput n/a",
        f"simulated {result['simulated_time_ms']:.3f} ms (IDT on {result['idt_on_time_ms']:.3f} ms) in "
        f"{result['wall_time_s']:.1f} s wall ({result['model']} model, set-up {result['setup_time_s']:.1f} s); "
        f"controller latency p99 {result['controller_latency_us'].get('p99', float('nan')):.1f} us",
    ]
    if (result.get("time_steps") or {}).get("levels_us"):
        from .paper import time_step_line
        lines += [line.strip() for line in time_step_line(result["time_steps"])]
    if "auto" in result:
        auto = result["auto"]
        lines.append(f"auto: feib for {100 * auto['feib_fraction']:.1f} % of the periods, "
                     f"{len(auto['switches']) - 1} switches" + "".join(
                         f"\n  t = {s['time_ms']:7.3f} ms -> {s['model']}: {s['reason']}" for s in auto["switches"][1:9])
                     + ("\n  ..." if len(auto["switches"]) > 9 else ""))
    return lines
