"""`vcyto paper 1|2`: the paper's two scenarios (section 4) from entry to exit, with the paper's method.

Scenario I: an RBC enters through inlet 2, IDT off, dt = 2.5 us. Scenario II: a melanoma cell, IDT on with
the `paper` SAW model, dt = 25 us. Both on the paper's mesh (54,243 DOFs) from the steady flow of their
actuation state, the `imex` convection treatment unless the scenario says otherwise.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from sim.method.adaptive import AdaptiveSteps
from sim.method.feib import ImmersedBoundary
from sim.method.openloop import stepping, with_cells
from sim.model.scenario import UM, Scenario

from .. import STARTED
from ..restored import Restored
from . import figures
from .painter import Painter


@dataclass(frozen=True)
class PaperScenario:
    number: int
    cell: str
    dt: float
    actuation: float
    paper_outlet: str
    paper_wall_time: str


PAPER = {
    1: PaperScenario(1, "RBC", 2.5e-6, 0.0, "lower", "3 h 51 min"),
    2: PaperScenario(2, "melanoma", 25e-6, 1.0, "upper", "12 min"),
}


class Interrupted(KeyboardInterrupt):
    """A paper run stopped by Ctrl-C (or SIGTERM) after ``step`` steps, at ``time`` (s)."""

    def __init__(self, step: int, time: float):
        super().__init__(step, time)
        self.step, self.time = step, time


def paper_scenario(number: int, base: Scenario, dt_given: bool) -> Scenario:
    """The base scenario with the paper's time step for scenario ``number`` (unless the user set one)."""
    return base if dt_given else base.with_numerics(dt=PAPER[number].dt)


def run_paper(number: int, scenario: Scenario, max_time: float = 20e-3, progress=None, snapshots: int = 6) -> dict:
    """Run scenario ``number`` until the cell's centroid leaves (or ``max_time``); a JSON-ready summary."""
    spec = PAPER[number]
    note = progress.note if progress else (lambda message: None)
    update = progress.update if progress else (lambda message: None)
    started = time.perf_counter()
    note(f"assembling and factoring ({scenario.numerics.mesh_h / UM:.3g} um mesh)")
    plant = ImmersedBoundary(scenario)
    adaptive = AdaptiveSteps(plant) if scenario.numerics.tolerance > 0 else None     # dt picked per step
    setup = time.perf_counter() - started
    note("steady start flow " + ("(IDT on)" if spec.actuation else "(IDT off)"))
    state = with_cells(plant, plant.start(spec.actuation).flow, [(scenario.cell_type(spec.cell), None)])
    cell = state.cells[0]
    steady = time.perf_counter() - started - setup
    path, outlines, times = [cell.membrane.centroid()], [(0.0, cell.membrane.points)], [state.time]
    stepping_started = time.perf_counter()
    try:
        for state in stepping(adaptive.step if adaptive else plant.step, state, spec.actuation, until=max_time):
            membrane = state.cells[0].membrane
            path.append(membrane.centroid())
            times.append(state.time)
            update(f"step {state.step}, t = {state.time * 1e3:.3f} ms, centroid x = {path[-1][0] / UM:.1f} um")
    except KeyboardInterrupt:
        raise Interrupted(state.step, state.time) from None
    step_wall = time.perf_counter() - stepping_started
    final = state.cells[0]
    timings = plant.timings
    fluid = plant.fluid.timings
    return {
        "scenario": number,
        "method": method_description(scenario),
        "membrane_method": scenario.membrane_method(),
        "cells": [_cell_summary(spec.cell, final)],
        "paper_outlet": spec.paper_outlet,
        "paper_wall_time": spec.paper_wall_time,
        "dt_us": scenario.numerics.dt * 1e6,
        "mesh_h_um": scenario.numerics.mesh_h / UM,
        "dofs": plant.fluid.space.dofs,
        "convection": scenario.numerics.convection,
        "time_scheme": scenario.numerics.scheme,
        "membrane_coupling": scenario.numerics.membrane_coupling,
        "saw_model": scenario.saw.model,
        "steps": state.step,
        "wall_time_s": {
            "process": time.perf_counter() - STARTED,
            "setup": setup,
            "steady_start": steady,
            "stepping": step_wall,
            "per_step_ms": 1e3 * step_wall / max(state.step, 1),
            "fluid_load": fluid.load,
            "fluid_solve": fluid.solve,
            "membrane": timings.membrane,
            "health_checks": timings.health,
        },
        "time_steps": adaptive.summary(state.time) if adaptive else None,
        "area_restored": _restored(spec.cell, final),
        "_path": np.array(path),
        "_times": np.array(times),
        "_outlines": _pick(outlines + [(state.time, final.membrane.points)], snapshots),
        "_flow": state.flow,
        "_plant": plant,
        "_final": final,
    }


def _cell_summary(type_name: str, final) -> dict:
    """The cell's outlet (``lost`` if still in the channel), exit, area kept and membrane points at the end."""
    measures = final.measures
    return {"type": type_name, "outlet": final.fate if not final.in_channel else "lost",
            "exit_time_ms": final.exit_time * 1e3, "exit_y_um": final.exit_y / UM,
            "area_ratio_final": measures.area_ratio, "area_ratio_min": measures.area_ratio_min,
            "area_ratio_max": measures.area_ratio_max, "area_restored": measures.area_corrected,
            "area_resampled": measures.area_resampled,
            "spacing_over_h": [measures.spacing_lowest, measures.spacing_highest],
            "membrane_points": final.membrane.count, "redistributions": final.membrane.redistributions}


def _restored(type_name: str, final) -> dict | None:
    """The projection's restoration figures (``vcyto.restored``) of the run's one cell."""
    restored = Restored()
    restored.add(type_name, final.measures.area_corrected)
    return restored.summary()


def method_description(scenario: Scenario) -> str:
    numerics = scenario.numerics
    method = scenario.membrane_method()
    if method == "paper":
        return "paper (the paper's literal FE-IB method: no area constraint, no redistribution; it leaks area)"
    detail = (f"area constraint {numerics.area_constraint}, "
              + ("points redistributed outside " + "-".join(f"{v:g}" for v in numerics.spacing_band) + " h"
                 if numerics.redistribute else "no redistribution"))
    return f"{method} ({detail})"


def _pick(items, count):
    if len(items) <= count:
        return items
    indices = np.linspace(0, len(items) - 1, count).round().astype(int)
    return [items[i] for i in indices]


def time_step_line(summary: dict | None) -> list[str]:
    """One line on the dt used, when a tolerance picked it (``sim.method.adaptive``'s summary)."""
    if not summary:
        return []
    parts = ", ".join(f"{dt:g} us: {steps} steps, {ms:.3f} ms" for dt, steps, ms
                      in zip(summary["levels_us"], summary["steps"], summary["time_ms"]) if steps)
    scheme = f" ({summary['scheme']})" if summary.get("scheme") else ""
    retaken = summary.get("retaken", 0)
    redone = f"; {retaken} retaken at {summary['levels_us'][0]:g} us (a redistribution inside)" if retaken else ""
    return [f"  time steps for a {summary['tolerance_um']:g} um tolerance{scheme}: {parts}; "
            f"{len(summary['changes'])} changes{redone}"]


def report_lines(result: dict) -> list[str]:
    cell = result["cells"][0]
    wall = result["wall_time_s"]
    return [
        f"paper scenario {result['scenario']}: {cell['type']}, {result['method']}",
        f"  mesh h = {result['mesh_h_um']:.3g} um ({result['dofs']:,} DOFs), dt = {result['dt_us']:g} us "
        f"({result['time_scheme']}, {result.get('membrane_coupling', 'explicit')} coupling), convection "
        f"{result['convection']}, SAW model {result['saw_model']}",
        f"  outlet: {cell['outlet']} (paper: {result['paper_outlet']}), exit at t = {cell['exit_time_ms']:.3f} ms, "
        f"y = {cell['exit_y_um']:.1f} um, after {result['steps']} steps",
        f"  enclosed area at exit: {100 * cell['area_ratio_final']:.2f} % of the initial area "
        f"(range {100 * cell['area_ratio_min']:.2f}-{100 * cell['area_ratio_max']:.2f} %); point spacing "
        f"{cell['spacing_over_h'][0]:.2f}-{cell['spacing_over_h'][1]:.2f} h, {cell['membrane_points']} points at exit, "
        f"{cell['redistributions']} redistributions",
        f"  area restored by the projection over the transit: {100 * cell['area_restored']:.3f} % of the initial "
        f"area (the redistributions changed {100 * cell['area_resampled']:.3f} %)",
        f"  wall time {wall['process']:.1f} s for the whole process (paper: {result['paper_wall_time']}): "
        f"set-up {wall['setup']:.2f} s, steady start {wall['steady_start']:.2f} s, {result['steps']} steps "
        f"{wall['stepping']:.2f} s ({wall['per_step_ms']:.2f} ms/step)",
        f"  per part: fluid load {wall['fluid_load']:.2f} s, fluid solve {wall['fluid_solve']:.2f} s, "
        f"membrane {wall['membrane']:.2f} s, health checks {wall['health_checks']:.2f} s",
    ] + time_step_line(result.get("time_steps"))


def png_spec(result: dict, scenario: Scenario) -> dict:
    """The data of the PNG (``vcyto.studies.painter.paper_figure``): the final speed field with the centroid path and
    membrane outlines along it, the device and a title."""
    speed, extent = figures.speed_image(result["_plant"].locator, result["_flow"].velocity, scenario)
    centroids = result["_path"]
    lines = [(centroids[:, 0] / UM, centroids[:, 1] / UM, "w", 1.2)]
    for _, points in result["_outlines"]:
        closed = np.vstack([points, points[:1]])
        lines.append((closed[:, 0] / UM, closed[:, 1] / UM, "tab:red", 1.0))
    cell = result["cells"][0]
    title = (f"paper scenario {result['scenario']}: {cell['type']} leaves by the {cell['outlet']} outlet "
             f"at t = {cell['exit_time_ms']:.2f} ms")
    return {"speed": speed, "extent": extent, "lines": lines + figures.device_lines(scenario), "title": title}


def save_png(path: str, result: dict, scenario: Scenario, painter: Painter | None = None) -> str:
    """The final speed field with the centroid path and membrane outlines along it, drawn by ``painter``'s
    helper process when there is one (``vcyto.studies.painter``); returns where it was drawn ("helper" or "here")."""
    return (painter or Painter(start=False)).paint("paper", path, png_spec(result, scenario))


def public(result: dict) -> dict:
    """The summary without the in-memory objects (for JSON)."""
    return {key: value for key, value in result.items() if not key.startswith("_")}
