"""`vcyto tradeoff`: the speed-accuracy trade of the plant models, measured on fixed scenes.

Each scene (a few cells and a fixed IDT schedule) runs on every level of the ladder (model + resolution);
every level is compared with the reference (the first level: the finest FE-IB) cell by cell: outlet, exit
time, centroid path (distance at the level's own times to the reference path interpolated there), area
kept; and timed (set-up apart from the run). Results: a Markdown table, a CSV file and a Pareto plot of
run wall time against path error.
"""

from __future__ import annotations

import csv
import math
import time
from collections import defaultdict
from dataclasses import dataclass, replace

import numpy as np

from sim.method.health import HealthError
from sim.method.openloop import stepping
from sim.model.mesh import MeshSize
from sim.model.scenario import UM, Scenario, ScenarioError


@dataclass(frozen=True)
class Scene:
    """Cells injected at given times and an IDT drive that is on within any of ``pulses`` (s)."""

    name: str
    arrivals: tuple
    pulses: tuple = ()
    max_time: float = 8e-3

    def actuation(self, time_s: float) -> float:
        return 1.0 if any(on <= time_s < off for on, off in self.pulses) else 0.0


SCENES = (
    Scene("isolated RBC, IDT off", ((0.0, "RBC"),)),
    Scene("isolated melanoma, IDT on", ((0.0, "melanoma"),), ((0.0, math.inf),)),
    # the melanoma's pulse (from its detection to after its passage) catches the RBC 0.25 ms behind it
    Scene("melanoma and RBC 0.25 ms apart, pulse 0.9-2.1 ms", ((0.0, "melanoma"), (0.25e-3, "RBC")), ((0.9e-3, 2.1e-3),
                                                                                                      )),
)


def lone_rbc_scene(start: float) -> Scene:
    """An RBC alone, injected at ``start`` (s), under the close-pair scene's pulse (``vcyto tradeoff --lone-rbc``):
    the pair's RBC without the melanoma."""
    return Scene(f"RBC alone from {start * 1e3:g} ms, pulse 0.9-2.1 ms", ((start, "RBC"),), ((0.9e-3, 2.1e-3),))


def pair_scene(gap: float) -> Scene:
    """The close-pair scene with the RBC ``gap`` (s) behind the melanoma (``vcyto tradeoff --pair-gap``)."""
    return Scene(f"melanoma and RBC {gap * 1e3:g} ms apart, pulse 0.9-2.1 ms", ((0.0, "melanoma"), (gap, "RBC")),
                 ((0.9e-3, 2.1e-3),))


@dataclass(frozen=True)
class Level:
    """A plant model at a resolution: mesh h, time step (feib, oneway) or control period (rom), flow grid,
    and (auto) the mesh of its feib windows (None: ``sim.plants.auto``'s default)."""

    model: str
    mesh_h: float
    dt: float
    grid: float = 1e-6
    window: float | None = None
    coupling: float | None = None      # auto: its coupling factor (None: sim.plants.auto's default)
    stiff: float | None = None         # auto: its stiff-cell capillary number (None: sim.plants.auto's default; 0: off)
    tolerance: float | None = None     # feib: dt picked per step from dt..8 dt for this path error (adaptive)
    scheme: str = "auto"               # feib: numerics.time_scheme (auto: bdf2 with a tolerance, euler otherwise)
    membrane_coupling: str = "auto"    # feib: numerics.membrane_coupling (auto: the scenario's; sim.method.coupling)

    @property
    def window_mesh_h(self) -> float:
        from sim.plants.auto import WINDOW_MESH_H
        return self.window or max(self.mesh_h, WINDOW_MESH_H)

    @property
    def label(self) -> str:
        step = "dt" if self.model != "rom" else "period"
        text = f"{self.model} h={self.mesh_h / UM:.3g}um {step}={self.dt * 1e6:g}us"
        text += f" grid={self.grid / UM:g}um" if self.model in ("rom", "oneway", "auto") else ""
        if self.model == "auto":
            text += f" window h={self.window_mesh_h / UM:.3g}um"
        text += f" coupling={self.coupling:g}" if self.coupling is not None else ""
        text += f" tolerance={self.tolerance / UM:g}um" if self.tolerance is not None else ""
        if self.model == "feib" and (self.scheme == "bdf2" or (self.scheme == "auto" and self.tolerance is not None)):
            text += " bdf2"             # auto: bdf2 with a tolerance (and convection imex, the ladder's default)
        text += " implicit coupling" if self.model == "feib" and self.membrane_coupling == "implicit" else ""
        return text + (f" stiff Ca<{self.stiff:g}" if self.stiff is not None else "")


PAPER_H = 10 * UM / 3
LADDER = (
    Level("feib", PAPER_H, 2.5e-6),                   # the reference: the paper's resolution and step
    Level("feib", PAPER_H, 10e-6),
    Level("feib", PAPER_H, 2.5e-6, scheme="bdf2"),    # the second-order step at the reference's dt
    Level("feib", PAPER_H, 10e-6, scheme="bdf2"),
    Level("feib", PAPER_H, 2.5e-6, tolerance=1e-6),   # dt from 2.5-40 us by the error estimate (bdf2)
    Level("feib", PAPER_H, 2.5e-6, tolerance=3e-6),
    Level("feib", 2 * PAPER_H, 10e-6),
    Level("feib", PAPER_H, 50e-6, membrane_coupling="implicit"),     # near and above the melanoma's explicit limit
    Level("feib", PAPER_H, 100e-6, membrane_coupling="implicit"),
    Level("oneway", PAPER_H, 2.5e-6),
    Level("oneway", PAPER_H, 10e-6),
    Level("rom", PAPER_H, 20e-6),
    Level("rom", PAPER_H, 50e-6, grid=2e-6),
    Level("auto", PAPER_H, 2.5e-6, window=PAPER_H),    # feib windows at the reference's own mesh
    Level("auto", PAPER_H, 2.5e-6),                    # the default: windows on the coarsest mesh within tolerance
)
FAST_LADDER = (
    Level("feib", 2 * PAPER_H, 10e-6),                # the reference of the reduced set (CI)
    Level("feib", 2 * PAPER_H, 25e-6),
    Level("feib", 2 * PAPER_H, 10e-6, tolerance=3e-6),
    Level("oneway", 2 * PAPER_H, 10e-6, grid=2e-6),
    Level("rom", 2 * PAPER_H, 20e-6, grid=2e-6),
    Level("auto", 2 * PAPER_H, 10e-6, grid=2e-6),
)
TOLERANCE_UM = 5.0          # auto's target: outlets as the reference's, mean centroid path distance below this


class _Flows:
    """The steady flows of the reduced models, solved and sampled once per (mesh h, grid)."""

    def __init__(self, scenario: Scenario):
        self.scenario, self.cache = scenario, {}

    def get(self, level: Level):
        from sim.plants.rom import RomFlows
        key = (level.mesh_h, level.grid)
        if key not in self.cache:
            self.cache[key] = RomFlows.of(self.scenario.with_numerics(mesh_h=level.mesh_h), level.grid)
        return self.cache[key]


def make_plant(scenario: Scenario, level: Level, flows: _Flows):
    """A fresh plant of ``level`` (the registry ``sim.plants.registry``) on the level's mesh and time step."""
    from sim.plants import registry as plants
    numerics = {"mesh_h": level.mesh_h} if level.model == "rom" else {"mesh_h": level.mesh_h, "dt": level.dt}
    scenario = scenario.with_numerics(**numerics)
    if level.model == "feib":
        coupling = scenario.numerics.membrane_coupling if level.membrane_coupling == "auto" else level.membrane_coupling
        return plants.build("feib", scenario.with_numerics(tolerance=level.tolerance or 0.0, time_scheme=level.scheme,
                                                           membrane_coupling=coupling))
    if level.model == "auto":
        rule = {name: value for name, value in (("coupling", level.coupling), ("stiff_capillary", level.stiff))
                if value is not None}
        return plants.build("auto", scenario, grid_spacing=level.grid, window_mesh_h=level.window_mesh_h, **rule)
    period = level.dt if level.model == "rom" else None
    return plants.build(level.model, scenario, control_period=period, flows=flows.get(level))


def run_scene(plant, scene: Scene) -> dict:
    """Step ``plant`` through ``scene``; per cell: fate, exit time and ordinate, area kept, centroid path."""
    observation = plant.reset(list(scene.arrivals))
    paths = defaultdict(list)
    started = time.perf_counter()
    failure = None
    try:
        for observation in _steps(plant, scene, observation):
            for view in observation.cells:
                paths[view.key].append((observation.time, view.x, view.y))
    except HealthError as error:
        failure = str(error)
    wall = time.perf_counter() - started
    cells = {}
    for cell in plant.truth().cells:
        measures = cell.measures or {}
        cells[cell.key] = {"type": cell.type, "fate": cell.fate if cell.fate != "in_channel" else "lost",
                           "exit_time": cell.exit_time, "exit_y": cell.exit_y,
                           "area_ratio_min": measures.get("area_ratio_min"), "path": np.array(paths[cell.key])}
    return {"wall_s": wall, "cells": cells, "failure": failure}


def _steps(plant, scene: Scene, observation):
    """The observations after each step: period by period, or, for a plant that steps across control periods
    (``one_step_per_call``: feib with a tolerance), one step at a time up to the next pulse edge, the drive
    taken at the last period end, as the closed loop drives it (``vcyto.stream``)."""
    if not getattr(plant, "one_step_per_call", False):
        yield from stepping(lambda _, drive: plant.step(drive), observation, scene.actuation,
                            until=scene.max_time, running=lambda _: not plant.done)
        return
    while not plant.done and plant.time < scene.max_time:
        clock = plant.clock
        edges = [edge for pulse in scene.pulses for edge in pulse if clock < edge < math.inf]
        plant.step_until(scene.actuation(clock), min(edges + [scene.max_time]))
        yield plant.observe()


def compare(run: dict, reference: dict) -> dict:
    """Outlet agreement, path distance (max, mean), exit time error and area loss of a run against the reference."""
    agree, distances, exit_errors, losses = 0, [], [], []
    for key, cell in run["cells"].items():
        ref = reference["cells"].get(key)
        if ref is None:
            continue
        agree += cell["fate"] == ref["fate"]
        path, ref_path = cell["path"], ref["path"]
        if len(path) and len(ref_path) > 1:
            inside = (path[:, 0] >= ref_path[0, 0]) & (path[:, 0] <= ref_path[-1, 0])
            t = path[inside, 0]
            if len(t):
                gap = np.hypot(path[inside, 1] - np.interp(t, ref_path[:, 0], ref_path[:, 1]),
                               path[inside, 2] - np.interp(t, ref_path[:, 0], ref_path[:, 2]))
                distances.append(gap)
        if math.isfinite(cell["exit_time"]) and math.isfinite(ref["exit_time"]):
            exit_errors.append(abs(cell["exit_time"] - ref["exit_time"]))
        if cell["area_ratio_min"] is not None:
            losses.append(1 - cell["area_ratio_min"])
    gaps = np.concatenate(distances) if distances else np.array([np.nan])
    return {"outlets_agree": agree, "cells": len(reference["cells"]),
            "path_max_um": float(np.max(gaps)) / UM, "path_mean_um": float(np.mean(gaps)) / UM,
            "exit_error_us": (max(exit_errors) * 1e6) if exit_errors else None,
            "area_loss_percent": (100 * max(losses)) if losses else None}


def tradeoff(scenario: Scenario, ladder=LADDER, scenes=SCENES, progress=None) -> dict:
    """Every scene on every level; rows compared with the first level (the reference). An interrupt (Ctrl-C,
    SIGTERM) ends it with the rows finished so far, ``interrupted`` set. The feib levels' time schemes are
    resolved in ``scenario`` first (``resolved_ladder``)."""
    from ..progress import rows_until_interrupted
    ladder = resolved_ladder(scenario, ladder)
    rows, interrupted = rows_until_interrupted(lambda rows: _measure(scenario, ladder, scenes, progress, rows))
    return {"reference": ladder[0].label, "rows": rows, "interrupted": interrupted,
            "planned_rows": len(ladder) * len(scenes)}


def resolved_ladder(scenario: Scenario, ladder) -> tuple:
    """The ladder with each feib level's time scheme as ``scenario`` makes it (``auto`` takes ``--time-scheme``,
    then bdf2 with a tolerance and a constant matrix, euler otherwise), so its label says what runs; a level
    whose scheme cannot run with the scenario's convection (bdf2 with oseen or implicit) is left out, and a
    level that became another's duplicate too."""
    levels, labels = [], set()
    for level in ladder:
        if level.model == "feib":
            scheme = scenario.numerics.time_scheme if level.scheme == "auto" else level.scheme
            coupling = scenario.numerics.membrane_coupling if level.membrane_coupling == "auto" \
                else level.membrane_coupling
            try:
                numerics = scenario.with_numerics(tolerance=level.tolerance or 0.0, time_scheme=scheme,
                                                  membrane_coupling=coupling).numerics
            except ScenarioError:
                continue
            level = replace(level, scheme=numerics.scheme, membrane_coupling=numerics.membrane_coupling)
        if level.label not in labels:
            labels.add(level.label)
            levels.append(level)
    return tuple(levels)


def _measure(scenario, ladder, scenes, progress, rows):
    note = progress.note if progress else (lambda message: None)
    flows = _Flows(scenario)
    references = {}
    for level in ladder:
        started = time.perf_counter()
        note(f"{level.label}: set-up")
        plant = make_plant(scenario, level, flows)
        setup = time.perf_counter() - started
        for scene in scenes:
            note(f"{level.label}: {scene.name}")
            run = run_scene(plant, scene)
            references.setdefault(scene.name, run)
            outlets = ",".join(cell["fate"] for _, cell in sorted(run["cells"].items()))
            rows.append({"scene": scene.name, "level": level.label, "model": level.model,
                         "mesh_h_um": level.mesh_h / UM, "dofs": MeshSize.of(scenario.channel, level.mesh_h).dofs,
                         "dt_us": level.dt * 1e6, "setup_s": setup,
                         "run_s": run["wall_s"], "outlets": outlets, "failure": run["failure"],
                         **compare(run, references[scene.name])})


COLUMNS = ("scene", "level", "outlets", "outlets_agree", "path_max_um", "path_mean_um", "exit_error_us",
           "area_loss_percent", "setup_s", "run_s")


def _cell(value, digits=3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def table_lines(result: dict) -> list[str]:
    lines = [f"reference: {result['reference']}", "",
             "| scene | level | outlets | agree | path max (um) | path mean (um) | exit time error (us) | "
             "area loss (%) | set-up (s) | run (s) |", "|" + "---|" * len(COLUMNS)]
    for row in result["rows"]:
        agree = f"{row['outlets_agree']}/{row['cells']}"
        outlets = row["outlets"] + (f" (stopped: {row['failure']})" if row["failure"] else "")
        level = row["level"] + (f" ({row['dofs']:,} DOFs)" if row.get("dofs") else "")
        values = [row["scene"], level, outlets, agree] + [_cell(row[c]) for c in COLUMNS[4:]]
        lines.append("| " + " | ".join(values) + " |")
    if result.get("interrupted"):
        lines += ["", f"PARTIAL: interrupted after {len(result['rows'])} of {result['planned_rows']} rows; the rows "
                      "not listed did not run"]
    return lines


def save(result: dict, directory) -> dict:
    """tradeoff.md, tradeoff.csv and tradeoff.png (run wall time against mean path error, per level)."""
    from pathlib import Path

    from ..outputs import write_into, write_whole
    from .figures import pyplot, save_figure
    directory = Path(directory)

    def write_csv(temporary):
        with open(temporary, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(result["rows"][0]))
            writer.writeheader()
            writer.writerows(result["rows"])
    write_into(directory / "tradeoff.md", "\n".join(table_lines(result)) + "\n")
    write_whole(directory / "tradeoff.csv", write_csv)
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(10, 4.8), constrained_layout=True)
    by_level = defaultdict(list)
    for row in result["rows"]:
        by_level[row["level"]].append(row)
    for level, rows in by_level.items():
        wall = sum(r["run_s"] for r in rows)
        error = np.nanmean([r["path_mean_um"] for r in rows])
        mismatch = sum(r["cells"] - r["outlets_agree"] for r in rows)
        floor = max(error, 1e-3)
        axis.scatter(wall, floor, marker="o" if not mismatch else "x", s=50,
                     label=level + (f" ({mismatch} outlet(s) differ)" if mismatch else ""))
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlabel("run wall time, all scenes (s)")
    axis.set_ylabel("mean centroid path distance to the reference (um)\n(reference drawn at 1e-3)")
    axis.set_title("speed against accuracy (x: an outlet differs from the reference)")
    axis.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5), frameon=False)
    save_figure(figure, directory / "tradeoff.png")
    plt.close(figure)
    return {name: str(directory / name) for name in ("tradeoff.md", "tradeoff.csv", "tradeoff.png")}
