"""The largest stable time step of the semi-implicit FE-IB scheme, measured by bisection.

A trial runs one cell from the injection point through its paper scenario's flow (RBC: IDT off,
melanoma and others: IDT on) for ``trial_time`` (or until it leaves). It is stable when the
health checks pass throughout and the membrane's elastic energy stays within ``energy_growth`` times
that of a reference run at a small step at the same times: a cell that the flow stretches gains energy
physically (the RBC does, a lot), an unstable one gains it exponentially per step. Bisection in log(dt)
between a stable and an unstable step.

The paper's bound (33) reads dt / h <= eta / (8 C_cell (kappa_e Lambda_1 + kappa_b Lambda_2)); C_cell is
an unknown constant of the mesh and curve geometry, so ``paper_bound`` evaluates it with C_cell = 1 and
Lambda_1 = max |X_q|, Lambda_2 = max |X_qqq| of the initial shape: it shows the scaling, not a number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..model.scenario import CellType, Scenario
from .feib import ImmersedBoundary
from .fluid import Flow, NavierStokes
from .health import HealthError, paper_bound  # noqa: F401  (paper_bound: part of this module's API)
from .openloop import stepping, with_cells


@dataclass(frozen=True)
class StabilityResult:
    cell: str
    mesh_h: float
    stable_dt: float
    unstable_dt: float
    trials: int
    failure: str


def actuation_for(cell_type: CellType) -> float:
    return 0.0 if cell_type.name == "RBC" else 1.0


def _run(scenario, cell_type, dt, start, steps):
    """Yield (time, energy) of the cell each step until it leaves; HealthError propagates."""
    trial_scenario = scenario.with_numerics(dt=dt)
    plant = ImmersedBoundary(trial_scenario, NavierStokes(trial_scenario))
    actuation = actuation_for(cell_type)
    for state in stepping(plant.step, with_cells(plant, start, [(cell_type, None)]), actuation, max_steps=steps):
        cell = state.cells[0]
        if not cell.in_channel:
            return
        membrane = cell.membrane
        yield state.time - start.time, membrane.energy() + cell_type.kappa_e * membrane.reference_length / 2


def reference_energy(scenario, cell_type, start, trial_time, dt):
    """The energy history (times, energies) of a run at a small, stable ``dt``."""
    history = np.array(list(_run(scenario, cell_type, dt, start, math.ceil(trial_time / dt) + 1)))
    return history[:, 0], history[:, 1]


def trial(scenario: Scenario, cell_type: CellType, dt: float, start: Flow, trial_time: float, reference,
          energy_growth: float = 2.0):
    """Run one trial at ``dt`` over the reference run's time span; returns (stable, reason)."""
    times, energies = reference
    try:
        for time, energy in _run(scenario, cell_type, dt, start, math.floor(trial_time / dt + 1e-9)):
            expected = np.interp(time, times, energies)
            if energy > energy_growth * expected:
                return False, f"membrane energy {energy / expected:.0f}x that of the reference run"
    except HealthError as error:
        return False, error.problem
    return True, ""


def stable_dt(scenario: Scenario, cell_type: CellType, low: float = 2e-6, ratio: float = 1.25,
              trial_time: float = 2e-3, min_steps: int = 20, start: Flow | None = None):
    """Bisect dt in [low, trial_time / min_steps] until high / low <= ratio.

    ``low`` is the reference run's step; a trial needs at least ``min_steps`` steps to show an
    instability, so the largest step tried is trial_time / min_steps (100 us by default).
    """
    high = trial_time / min_steps
    start = start or NavierStokes(scenario).steady(actuation_for(cell_type))
    reference = reference_energy(scenario, cell_type, start, trial_time, low)
    trials = 0
    failure = ""
    stable, reason = trial(scenario, cell_type, high, start, trial_time, reference)
    trials += 1
    if stable:
        return StabilityResult(cell_type.name, scenario.numerics.mesh_h, high, float("inf"), trials, "")
    failure = reason
    while high / low > ratio:
        middle = math.sqrt(low * high)
        stable, reason = trial(scenario, cell_type, middle, start, trial_time, reference)
        trials += 1
        if stable:
            low = middle
        else:
            high, failure = middle, reason
    return StabilityResult(cell_type.name, scenario.numerics.mesh_h, low, high, trials, failure)
