"""The plant contract of the closed loop: what every plant offers, the data it exchanges, and its check.

A plant is reset with a schedule of arrivals (time in s, cell type name), then stepped one control period at
a time with the IDT drive in [0, 1]. A plant is deterministic: the same arrivals and the same drive give the
same observations and truth, so ``reset`` takes no seed. What is random in a run (the arrival times, the
detector's noise) is drawn outside the plant from the run's seed (``sim.model.arrivals``, ``controller.detector``);
a plant that one day draws numbers of its own takes its generator or seed in its constructor, so that
``check_plant``'s two fresh instances can be built alike. Each step returns an ``Observation``: what an instrument can
see (each cell in the channel as a ``CellView``: where it is, its size and label brightness). ``truth()``
gives the ground truth (``CellTruth``: types, fates, exit times) for logging and statistics only; it is
never shown to the controller. ``Plant`` names the required part; ``StepsUntil``, ``ReportsTruthUpdates``,
``HasFields``, ``HasDiagnostics`` and the two ``Adopts...`` protocols name the optional capabilities a loop
may use when a plant has them. ``check_plant`` tests a plant factory against the contract.

This module needs numpy and the standard library only: the controller imports it (``CellView`` is the
controller's ``Sighting``), and importing it loads neither scikit-fem nor numba.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class CellView:
    """What the optics see of one object in the channel at one instant: an opaque key, where it is (m),
    how big it is (area, m^2) and how brightly its label fluoresces (arbitrary units)."""

    key: int
    x: float
    y: float
    area: float
    brightness: float


@dataclass(frozen=True)
class Observation:
    """The cells in the channel as the optics see them at ``time`` (s)."""

    time: float
    cells: tuple[CellView, ...]


@dataclass(frozen=True)
class CellTruth:
    """The ground truth of one injected cell."""

    key: int
    type: str
    born: float
    fate: str                 # "in_channel", an outlet name, "wall" or "lost"
    exit_time: float
    exit_y: float
    x: float
    y: float
    area_ratio: float                     # FE-IB: measured while the whole membrane is in the channel
    membrane: np.ndarray | None = None    # (R, 2) material points, for logging
    measures: dict | None = None          # shape figures and their extremes (sim.method.feib.Measures), FE-IB only


@dataclass(frozen=True)
class Truth:
    """The ground truth of the injected cells at ``time`` (s), and how many scheduled cells still wait."""

    time: float
    cells: tuple[CellTruth, ...]
    waiting: int              # scheduled cells not yet injected


class Schedule:
    """Arrivals (time in s, cell type name) not yet injected, in time order."""

    def __init__(self, arrivals):
        self.items = sorted(arrivals)
        self.position = 0

    def due(self, time: float, tolerance: float):
        """Yield (index, arrival) for each arrival due by ``time`` (within ``tolerance``), consuming it."""
        while self.position < len(self.items) and self.items[self.position][0] <= time + tolerance:
            yield self.position, self.items[self.position]
            self.position += 1

    @property
    def waiting(self) -> int:
        return len(self.items) - self.position


@runtime_checkable
class Plant(Protocol):
    """What every plant offers the closed loop."""

    control_period: float     # s; ``step`` advances time by exactly this much

    def reset(self, arrivals) -> Observation: ...

    def step(self, actuation: float) -> Observation: ...

    def observe(self) -> Observation: ...

    def truth(self) -> Truth: ...

    @property
    def done(self) -> bool: ...


@runtime_checkable
class StepsUntil(Protocol):
    """Advances many control periods in one call (the rom plant): returns (periods, partial observations of
    the cells that crossed a stop or a record line), stopping after a forward crossing of a stop line.

    A plant with ``one_step_per_call = True`` (the FE-IB plant with a tolerance) takes one step of its own a call,
    across control period ends, returning (1, ...); it offers ``clock``, its last control period end, where the
    loop reads the controller's drive, and the loop shows every call to its sinks."""

    def step_until(self, actuation: float, until: float, stop_lines=(), record_lines=(),
                   max_periods: int = 10**7) -> tuple[int, list[Observation]]: ...


@runtime_checkable
class Traces(Protocol):
    """A plant that steps many periods a call (``StepsUntil``) and records its cells for recordings itself:
    ``trace(interval)`` asks for the cells in the channel at every period index that is a multiple of the
    cadence it returns (``interval`` rounded up to whole periods); ``take_trace()`` hands over the rows since its
    last call as arrays (period index, key, (x, y)), in time order."""

    def trace(self, interval: float) -> int: ...

    def take_trace(self) -> tuple: ...


@runtime_checkable
class ReportsTruthUpdates(Protocol):
    """Reports the truth of the cells in the channel and of those settled since the last call, each once."""

    def truth_update(self) -> Truth: ...


@runtime_checkable
class HasFields(Protocol):
    """Exposes its flow for recordings: (vertices, velocity, pressure, grid x, grid y)."""

    def fields(self): ...


@runtime_checkable
class HasDiagnostics(Protocol):
    """Reports solver figures for logging (a dict of plain numbers and strings)."""

    def diagnostics(self) -> dict: ...


@runtime_checkable
class ReportsTimeSteps(Protocol):
    """Reports the time steps it took over the run (an adaptive step: ``sim.method.adaptive``), as a plain dict."""

    def time_steps(self) -> dict: ...


@runtime_checkable
class SwitchesModels(Protocol):
    """Switches between models during a run (the auto plant): ``switches`` lists (time s, model, reason)."""

    switches: list


@runtime_checkable
class AdoptsMembranes(Protocol):
    """Continues from a membrane state (``sim.method.feib.State``) with the first ``injected`` arrivals injected."""

    def adopt(self, state, injected: int): ...


@runtime_checkable
class AdoptsCentroids(Protocol):
    """Continues at ``time_s`` and drive ``level`` from cell centroids {key: (x, y, born)}."""

    def adopt(self, time_s: float, level: float, cells: dict, injected: int): ...


def _run(plant, arrivals, steps: int):
    observations = [plant.reset(arrivals)]
    for step in range(steps):
        observations.append(plant.step(1.0 if step % 7 < 3 else 0.0))
    outcomes = [tuple(None if value != value else value for value in (c.key, c.type, c.fate, c.exit_time, c.exit_y,
                                                                      c.x, c.y))   # NaN (not left) compares equal
                for c in plant.truth().cells]
    return observations, outcomes


def check_plant(make_plant: Callable[[], Plant], arrivals, steps: int = 20) -> list[str]:
    """Check a plant factory against the contract; returns a list of violations (empty when it conforms).

    ``make_plant()`` must build a fresh plant each call; two are built and run with the same arrivals and
    drive. Checked: they are distinct objects and give the same observations and outcomes; time advances
    by one control period per step; every scheduled cell is waiting, in the channel or settled, exactly once.
    """
    first_plant, second_plant = make_plant(), make_plant()
    if first_plant is second_plant:
        return ["make_plant returned the same plant twice: pass a factory of fresh plants"]
    problems = [f"does not offer {name}" for name in ("reset", "step", "observe", "truth", "done", "control_period")
                if name not in dir(first_plant)]
    if problems:
        return problems
    first, first_outcomes = _run(first_plant, arrivals, steps)
    second, second_outcomes = _run(second_plant, arrivals, steps)
    if first != second or first_outcomes != second_outcomes:
        problems.append("not deterministic: two fresh plants with the same arrivals and drive gave different results")
    times = np.array([o.time for o in first])
    if not np.allclose(np.diff(times), first_plant.control_period, rtol=1e-9, atol=1e-15):
        problems.append("time does not advance by one control period per step")
    truth = first_plant.truth()
    keys = [cell.key for cell in truth.cells]
    if len(set(keys)) != len(keys) or len(keys) + truth.waiting != len(arrivals):
        problems.append(f"cells not conserved: {len(keys)} known + {truth.waiting} waiting != "
                        f"{len(arrivals)} scheduled")
    return problems
