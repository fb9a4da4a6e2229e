"""`vcyto extremes`: the FE-IB plant at the extremes of its settings (docs/results.md, "Stability at the extremes").

Each case runs one extreme setting and says beforehand what must happen: either the run is correct
(every cell leaves by an outlet, or, for a short run, is still whole at the end, plus the case's own
figure, e.g. the outlet a fine mesh gives) or the health checks stop it with a specific diagnosis (phrases
the one-line message must contain and phrases it must not). `fast` variants use coarse meshes and short
runs (the test suite runs them); the full variants run to the exit or on a finer mesh.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

from sim.method.feib import Cell, ImmersedBoundary
from sim.method.fluid import NumericalBlowUp
from sim.method.health import membrane_time_step
from sim.method.membrane import Membrane
from sim.method.openloop import stepping, with_cells
from sim.model.scenario import UM, CellType, Scenario

OUTLETS = ("lower", "upper")


class UnexpectedOutcome(NumericalBlowUp):
    """A case did not end as expected (the command's exit status 1)."""


# peak inflow speed x dt / h in the inflow cases: at 0.5 the imex flow itself blows up at x24 (docs/results.md)
CFL = 0.1


@dataclass
class Run:
    """What one case's simulation did: the cells at the end, or the diagnosis that stopped it."""

    cells: tuple[Cell, ...] = ()
    steps: int = 0
    time: float = 0.0
    diagnosis: str = ""
    wall_time: float = 0.0
    step_ms: float = float("nan")
    max_stretch: float = 1.0
    warnings: list = field(default_factory=list)

    @property
    def ran(self) -> bool:
        return not self.diagnosis


@dataclass(frozen=True)
class Setting:
    """One simulation: a scenario, the cells (type, centre or None for the injection point), the IDT, a duration."""

    scenario: Scenario
    cells: tuple[tuple[CellType, tuple[float, float] | None], ...]
    actuation: float = 0.0
    duration: float = 20e-3
    to_exit: bool = True            # False: a short run, correct if every cell is still whole at the end


@dataclass(frozen=True)
class Case:
    """An extreme setting and the outcome it must have.

    ``runs``: whether the run must complete; ``contains`` / ``excludes``: phrases the diagnosis must (not)
    have; ``check``: a further test of a completed run, returning what is wrong or "".
    """

    name: str
    title: str
    setting: str
    expected: str
    build: Callable[[Scenario, bool], Setting]
    runs: bool
    contains: tuple[str, ...] = ()
    excludes: tuple[str, ...] = ()
    check: Callable[[Run, Scenario, bool], str] | None = None
    fates: tuple[str, ...] = OUTLETS


# ---------------------------------------------------------------------------------------------- the runs
class _Collect(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def simulate(setting: Setting) -> Run:
    """Run the setting's cells until all have left (or the duration); a health-check stop is a diagnosis."""
    collect = _Collect()
    logger = logging.getLogger("sim.method.feib")
    logger.addHandler(collect)
    run = Run()
    started = time.perf_counter()
    try:
        plant = ImmersedBoundary(setting.scenario)
        state = with_cells(plant, plant.start(setting.actuation).flow, setting.cells)
        run.cells = state.cells
        stepping_started = time.perf_counter()
        for state in stepping(plant.step, state, setting.actuation, until=setting.duration - 1e-12):
            run.cells, run.steps, run.time = state.cells, state.step, state.time
            run.max_stretch = max([run.max_stretch] + [_stretch(cell) for cell in state.cells if cell.in_channel])
        run.step_ms = 1e3 * (time.perf_counter() - stepping_started) / max(run.steps, 1)
    except NumericalBlowUp as error:
        run.diagnosis = str(error)
    finally:
        logger.removeHandler(collect)
    run.warnings = collect.messages
    run.wall_time = time.perf_counter() - started
    return run


def _stretch(cell: Cell) -> float:
    perimeter = cell.measures.perimeter
    return perimeter / cell.membrane.reference_length if math.isfinite(perimeter) else 1.0


def judge(case: Case, setting: Setting, run: Run, fast: bool) -> list[str]:
    """What is wrong with the run against the case's expectation (empty: it passed)."""
    problems = []
    if case.runs:
        if not run.ran:
            return [f"expected to run, stopped: {run.diagnosis}"]
        fates = [cell.fate for cell in run.cells]
        if setting.to_exit and any(fate not in case.fates for fate in fates):
            problems.append(f"cells ended {', '.join(fates)}, expected {' or '.join(case.fates)}")
        if case.check:
            problems += [problem for problem in [case.check(run, setting.scenario, fast)] if problem]
        return problems
    if run.ran:
        return ["expected a diagnosis, the run completed"]
    problems += [f"diagnosis lacks {phrase!r}" for phrase in case.contains if phrase not in run.diagnosis]
    problems += [f"diagnosis has {phrase!r}" for phrase in case.excludes if phrase in run.diagnosis]
    return problems


# ---------------------------------------------------------------------------------------------- the cases
def _scaled(cell_type: CellType, kappa_e: float, name: str) -> CellType:
    return replace(cell_type, name=name, kappa_e=cell_type.kappa_e * kappa_e)


def _with_inflow(scenario: Scenario, factor: float) -> Scenario:
    channel = scenario.channel
    inlets = tuple(replace(inlet, v_hat=inlet.v_hat * factor) for inlet in channel.inlets)
    return replace(scenario, channel=replace(channel, inlets=inlets))


def _round_dt(dt: float) -> float:
    """dt rounded down to 10 ns (a step that reads as it is written)."""
    return max(1e-8, math.floor(dt / 1e-8 + 1e-9) * 1e-8)


PAPER_H = 10 * UM / 3
LIMIT_DT = 37.5e-6          # below the melanoma's measured limit at the paper's mesh (61.3 us, docs/results.md)


def _dt_at_limit(base, fast):
    return Setting(base.with_numerics(mesh_h=PAPER_H, dt=LIMIT_DT), ((base.cell_type("melanoma"), None),), 1.0)


def _dt_beyond_limit(base, fast):
    return Setting(base.with_numerics(mesh_h=PAPER_H, dt=4 * LIMIT_DT), ((base.cell_type("melanoma"), None),), 1.0)


def _stiff(base):
    return _scaled(base.cell_type("melanoma"), 100.0, "melanoma x100")


def _stiff_step(base) -> float:
    """The stiff membrane's explicit time step eta dq / kappa_e at h = 6.67 um (docs/results.md, "Stability")."""
    scenario = base.with_numerics(mesh_h=20 * UM / 3)
    numerics = scenario.numerics
    membrane = Membrane.of(_stiff(base), (0.0, 0.0), numerics.membrane_spacing * numerics.mesh_h)
    return _round_dt(membrane_time_step(membrane, scenario.fluid.viscosity))


def _stiff_too_large_dt(base, fast):
    return Setting(base.with_numerics(mesh_h=20 * UM / 3, dt=25e-6), ((_stiff(base), None),), 0.0)


def _stiff_estimated_dt(base, fast):
    return Setting(base.with_numerics(mesh_h=20 * UM / 3, dt=_stiff_step(base)), ((_stiff(base), None),), 0.0,
                   duration=0.2e-3 if fast else 20e-3, to_exit=not fast)


def _soft(base, method):
    scenario = base.with_numerics(mesh_h=20 * UM / 3, dt=10e-6).with_membrane(method)
    return Setting(scenario, ((_scaled(base.cell_type("RBC"), 0.01, "RBC /100"), None),), 0.0)


def _inflow(factor, mesh_h=10 * UM, max_stretch=None):
    """The inflow case at ``factor`` x the paper's inlet speeds; ``max_stretch`` overrides the rupture limit (the
    default 20 lets a membrane at x40 fold before it tears: both stop the run, only tearing names Remark 2.4)."""
    def build(base, fast):
        peak = factor * max(_peak_speed(base, inlet) for inlet in base.channel.inlets)
        scenario = _with_inflow(base, factor).with_numerics(mesh_h=mesh_h, dt=_round_dt(min(10e-6,
                                                                                            CFL * mesh_h / peak)))
        if max_stretch is not None:
            scenario = scenario.with_numerics(max_stretch=max_stretch)
        return Setting(scenario, ((base.cell_type("melanoma"), None),), 0.0)
    return build


def _peak_speed(scenario: Scenario, inlet) -> float:
    """The parabola's peak speed: v_hat (w/2)^2 with lengths in 10 um (``paper`` reading) or v_hat (``peak``)."""
    half_width = 0.5 * (inlet.span[1] - inlet.span[0])
    return inlet.v_hat * ((half_width / (10 * UM)) ** 2 if scenario.channel.profile_reading == "paper" else 1.0)


WALL_GAP = 0.5 * UM


def _touching_wall(base, fast):
    melanoma = base.cell_type("melanoma")
    centre = (100 * UM, melanoma.semi_axes[1] + WALL_GAP)
    return Setting(base.with_numerics(mesh_h=20 * UM / 3, dt=10e-6), ((melanoma, centre),), 0.0)


def _into_end_wall(base, fast):
    """A melanoma 0.5 um before the end wall between the outlets (x = 300 um, 100-120 um), centred on it."""
    melanoma = base.cell_type("melanoma")
    centre = (base.channel.length - melanoma.semi_axes[0] - WALL_GAP, 110 * UM)
    return Setting(base.with_numerics(mesh_h=20 * UM / 3, dt=10e-6), ((melanoma, centre),), 0.0)


def _on_the_wall(run, base, fast):
    cell = run.cells[0]
    spans = sorted(outlet.span for outlet in base.channel.outlets)
    between = any(low[1] < cell.exit_y < high[0] for low, high in zip(spans, spans[1:]))
    return "" if between else f"exit ordinate {cell.exit_y / UM:.1f} um is not on the wall between the outlets"


def _under_resolved(mesh_h):
    def build(base, fast):
        return Setting(base.with_numerics(mesh_h=mesh_h, dt=10e-6), ((base.cell_type("RBC"), None),), 0.0)
    return build


def _many(base, fast):
    """A block of cells across the inlet streams, alternating RBC and melanoma, none touching another or a wall."""
    columns, rows = (3, 4) if fast else (4, 5)
    ys = [60 * UM + j * (100 * UM / (rows - 1)) for j in range(rows)]
    xs = [25 * UM + i * 30 * UM for i in range(columns)]
    kinds = (base.cell_type("RBC"), base.cell_type("melanoma"))
    cells = tuple((kinds[(i + j) % 2], (x, y)) for i, x in enumerate(xs) for j, y in enumerate(ys))
    return Setting(base.with_numerics(mesh_h=20 * UM / 3, dt=10e-6), cells, 0.0)


def _upper(run, base, fast):
    return "" if run.cells[0].fate == "upper" else f"melanoma left by {run.cells[0].fate}, not upper"


def _kept_area(run, base, fast):
    measures = run.cells[0].measures
    return "" if abs(measures.area_ratio_min - 1) < 0.01 and abs(measures.area_ratio_max - 1) < 0.01 \
        else f"area ratio {measures.area_ratio_min:.3f}-{measures.area_ratio_max:.3f}"


def _in_band(run, base, fast):
    high = run.cells[0].measures.spacing_highest
    return "" if high <= 0.7 + 1e-9 else f"spacing rose to {high:.2f} h"


def _points_separate(run, base, fast):
    high = run.cells[0].measures.spacing_highest
    return "" if high > 1.0 else f"spacing stayed at {high:.2f} h"


def _below_tear(run, base, fast):
    return "" if run.max_stretch < 20 else f"stretched {run.max_stretch:.1f}x"


def _fine_mesh_outlet(run, base, fast):
    """The under-resolved RBC leaves where it does on the paper's mesh (within 2 um), and it was warned about."""
    if not any("fewer than two mesh cells" in message for message in run.warnings):
        return "no under-resolution warning"
    fine = simulate(_under_resolved(PAPER_H)(base, fast))
    coarse, reference = run.cells[0], fine.cells[0] if fine.ran else None
    if reference is None or coarse.fate != reference.fate or abs(coarse.exit_y - reference.exit_y) > 2 * UM:
        return f"outlet {coarse.fate} at y = {coarse.exit_y / UM:.1f} um; paper mesh: " + \
            (f"{reference.fate} at y = {reference.exit_y / UM:.1f} um" if reference else fine.diagnosis)
    run.warnings.append(f"paper mesh: {reference.fate} at y = {reference.exit_y / UM:.1f} um")
    return ""


CASES = (
    Case("a1", "dt at the limit", "melanoma, IDT on, h 3.33 um, dt 37.5 us (its limit: 61.3 us)", "runs: upper outlet",
         _dt_at_limit, True, check=_upper),
    Case("a2", "dt 4x the limit", "melanoma, IDT on, h 3.33 um, dt 150 us", "stops: smaller dt suggested",
         _dt_beyond_limit, False, contains=("stability limit", "try dt =", "stability law fitted to measured limits")),
    Case("b1", "very stiff, large dt", "melanoma kappa_e x100 (2.8e-2 N/m), h 6.67 um, dt 25 us",
         "stops: smaller dt suggested", _stiff_too_large_dt, False, contains=("try dt =",)),
    Case("b2", "very stiff, estimated dt", "melanoma kappa_e x100, h 6.67 um, dt = eta dq / kappa_e",
         "runs, area kept", _stiff_estimated_dt, True, check=_kept_area),
    Case("b3", "very soft, conserving", "RBC kappa_e /100 (6e-8 N/m), h 6.67 um, dt 10 us, conserving",
         "runs: spacing <= 0.7 h", lambda base, fast: _soft(base, "conserving"), True, check=_in_band),
    Case("b4", "very soft, paper's method", "RBC kappa_e /100, h 6.67 um, dt 10 us, paper's method",
         "runs: points separate (> 1 h)", lambda base, fast: _soft(base, "paper"), True, check=_points_separate),
    Case("c1", "inflow x8", "melanoma, all v_hat x8, IDT off, h 10 um, CFL 0.1", "runs: stretch < 10",
         _inflow(8.0), True, check=_below_tear),
    Case("c2", "inflow x40", "melanoma, all v_hat x40, IDT off, h 10 um, CFL 0.1, max_stretch 10",
         "stops: torn apart, inflow too fast",
         _inflow(40.0, max_stretch=10.0), False, contains=("torn apart", "too fast for this membrane", "Remark 2.4",
                                                           "v_hat"),
         excludes=("try dt",)),
    Case("d1", "touching a wall", "melanoma at x 100 um, 0.5 um above the lower wall, h 6.67 um, dt 10 us",
         "runs: slides along, lower outlet", _touching_wall, True, fates=("lower",)),
    Case("d2", "driven into a wall", "melanoma 0.5 um before the end wall between the outlets, h 6.67 um",
         "runs: fate 'wall', y between outlets", _into_end_wall, True, check=_on_the_wall, fates=("wall",)),
    Case("e", "under-resolved cell", "RBC (7.5 um) on h 10 um, dt 10 us", "runs with a warning; paper mesh's outlet",
         _under_resolved(10 * UM), True, check=_fine_mesh_outlet),
    Case("f", "many cells", "12 cells (RBC, melanoma) at once, h 6.67 um, dt 10 us; full: 20",
         "runs: every cell leaves by an outlet", _many, True),
)


def run_case(case: Case, base: Scenario | None = None, fast: bool = True) -> dict:
    """Run one case; a JSON-ready row with the outcome and whether it is the expected one."""
    base = base or Scenario()
    setting = case.build(base, fast)
    run = simulate(setting)
    problems = judge(case, setting, run, fast)
    return {
        "case": case.name, "title": case.title, "setting": case.setting, "expected": case.expected,
        "observed": observed(run, setting), "passed": not problems, "problems": problems,
        "ran": run.ran, "diagnosis": run.diagnosis, "warnings": run.warnings,
        "cells": [_cell_row(cell) for cell in run.cells], "steps": run.steps, "simulated_ms": run.time * 1e3,
        "dt_us": setting.scenario.numerics.dt * 1e6, "mesh_h_um": setting.scenario.numerics.mesh_h / UM,
        "max_stretch": run.max_stretch, "step_ms": run.step_ms, "wall_time_s": run.wall_time,
    }


def _cell_row(cell: Cell) -> dict:
    measures = cell.measures
    return {"id": cell.id, "type": cell.membrane.cell_type.name, "fate": cell.fate,
            "exit_y_um": cell.exit_y / UM, "area_ratio": [measures.area_ratio_min, measures.area_ratio_max],
            "spacing_over_h": [measures.spacing_lowest, measures.spacing_highest]}


def observed(run: Run, setting: Setting) -> str:
    """One line: the figures of a completed run, or the diagnosis that stopped it."""
    if not run.ran:
        return f"stopped: {run.diagnosis}"
    fates = [cell.fate for cell in run.cells]
    counts = ", ".join(f"{fate} x{fates.count(fate)}" if len(fates) > 1 else fate for fate in dict.fromkeys(fates))
    low = min(cell.measures.area_ratio_min for cell in run.cells)
    high = max(cell.measures.area_ratio_max for cell in run.cells)
    spacing = (min(cell.measures.spacing_lowest for cell in run.cells),
               max(cell.measures.spacing_highest for cell in run.cells))
    parts = [f"ran {run.steps} steps ({run.time * 1e3:.3g} ms): " + (counts if setting.to_exit else "cells whole"),
             f"area kept {100 * low:.1f}-{100 * high:.1f} %", f"spacing {spacing[0]:.2f}-{spacing[1]:.2f} h",
             f"max stretch {run.max_stretch:.1f}", f"{run.step_ms:.1f} ms/step"]
    return "; ".join(parts + _distinct_warnings(run.warnings))


def _distinct_warnings(messages) -> list[str]:
    """One line per distinct warning, the cell ids of the same warning gathered ("cells 0, 2: ...")."""
    gathered = {}
    for message in messages:
        head, _, text = message.partition(": ") if message.startswith("cell ") else ("", "", message)
        gathered.setdefault(text, []).append(head.removeprefix("cell "))
    return [(f"cell{'s' if len(ids) > 1 else ''} {', '.join(ids)}: " if ids[0] else "") + text
            for text, ids in gathered.items()]


def run_cases(base: Scenario | None = None, fast: bool = True, names=None, progress=None) -> dict:
    from ..progress import rows_until_interrupted
    note = progress.note if progress else (lambda message: None)

    def measure(rows):
        for case in CASES:
            if names and case.name not in names:
                continue
            note(f"case {case.name}: {case.title}")
            rows.append(run_case(case, base, fast))
    rows, interrupted = rows_until_interrupted(measure)
    return {"variant": "fast" if fast else "full", "rows": rows, "passed": all(row["passed"] for row in rows),
            "interrupted": interrupted}


def report_lines(result: dict) -> list[str]:
    lines = [f"stability at the extremes ({result['variant']} variants)",
             f"  {'case':<4} {'setting':<62} {'expected':<38} pass  observed"]
    for row in result["rows"]:
        lines.append(f"  {row['case']:<4} {row['setting']:<62} {row['expected']:<38} "
                     f"{'yes ' if row['passed'] else 'NO  '}  {row['observed']}")
        lines += [f"       problem: {problem}" for problem in row["problems"]]
    passed = sum(row["passed"] for row in result["rows"])
    lines.append(f"  {passed} of {len(result['rows'])} cases as expected"
                 + (" (PARTIAL: interrupted; the cases not listed did not run)" if result.get("interrupted") else ""))
    return lines
