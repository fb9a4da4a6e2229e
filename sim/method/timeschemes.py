"""The FE-IB step's time schemes, registered by name (``numerics.time_scheme``), and their step history.

Each scheme knows its coefficients and what history it keeps; the fluid step (``sim.method.fluid``) and the
membrane update (``sim.method.feib``) ask it instead of testing its name:

- ``euler`` (the paper's, first order): rho (v^{m+1} - v^m) / dt; the force at X^m; X^{m+1} = X^m + dt v^{m+1}(X^m).
- ``bdf2`` (second order): rho (3 v^{m+1} - 4 v^m + v^{m-1}) / (2 dt); the force at X* = 2 X^m - X^{m-1};
  X^{m+1} = (4 X^m - X^{m-1}) / 3 + 2 dt / 3 v^{m+1}(X*). v^{m-1} and X^{m-1} are the values at t - dt, also after a
  change of step size (``sim.method.adaptive``): an earlier value where its time is t - dt, else the parabola
  through the last three (``value_back``). Without history (a start, a new cell) a step is Euler's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimeScheme:
    """A one-step scheme (backward Euler in the fluid, the paper's explicit membrane update): ``derivative`` the
    coefficients of (v^{m+1}, v^m, v^{m-1}, ...) in dt dv/dt (their sum is zero), ``order`` its order of accuracy,
    ``kept`` how many earlier values a step carries on (0: none)."""

    name: str
    order: int
    derivative: tuple
    kept: int = 0

    @property
    def mass(self) -> float:
        """The coefficient of v^{m+1} in dt dv/dt: the step's matrix holds rho mass / dt M."""
        return self.derivative[0]

    def carried(self, latest, history: tuple) -> tuple:
        """The history a step passes on: ``latest`` (the value it started from) and the earlier ones it keeps."""
        return ((latest,) + history[:self.kept - 1]) if self.kept else ()

    def back(self, time: float, value: np.ndarray, times, values, dt: float) -> np.ndarray | None:
        """The value at ``time - dt`` the step uses (``value_back``), or None (a one-step scheme, or no history)."""
        return value_back(time, value, times, values, time - dt) if self.kept else None

    def extrapolated(self, points: np.ndarray, before: np.ndarray | None) -> np.ndarray:
        """Where the membrane forces of a step are evaluated (``before``: the points at t - dt, or None)."""
        return points

    def advanced(self, points: np.ndarray, before: np.ndarray | None, dt: float, velocity: np.ndarray) -> np.ndarray:
        """The membrane points after a step with ``velocity`` (v^{m+1} at the extrapolated points)."""
        return points + dt * velocity


@dataclass(frozen=True)
class BackwardDifference2(TimeScheme):
    """BDF2: the force at X* = 2 X^m - X^{m-1}, X^{m+1} = (4 X^m - X^{m-1}) / 3 + 2 dt / 3 v^{m+1}(X*); Euler's
    step where there is no X^{m-1}."""

    def extrapolated(self, points, before):
        return points if before is None else 2 * points - before

    def advanced(self, points, before, dt, velocity):
        if before is None:
            return super().advanced(points, before, dt, velocity)
        return (4 * points - before) / 3 + (2 * dt / 3) * velocity


SCHEMES: dict[str, TimeScheme] = {}


def add_scheme(scheme: TimeScheme) -> TimeScheme:
    """Register ``scheme`` under its name (``numerics.time_scheme`` names it)."""
    SCHEMES[scheme.name] = scheme
    return scheme


EULER = add_scheme(TimeScheme("euler", order=1, derivative=(1.0, -1.0)))
BDF2 = add_scheme(BackwardDifference2("bdf2", order=2, derivative=(1.5, -2.0, 0.5), kept=2))


def scheme_named(name: str) -> TimeScheme:
    """The registered scheme ``name`` (a scenario's resolved ``numerics.scheme``)."""
    return SCHEMES[name]


def value_back(time: float, value: np.ndarray, times, values, target: float) -> np.ndarray | None:
    """bdf2's history: the value at ``target`` (one step back) from the value at ``time`` and the earlier
    ``values`` at ``times`` (the latest first): an earlier value where its time is the target (equal steps, or
    one level up after two equal steps), else the parabola through the three (the line through two) there;
    None without history."""
    if not len(values):
        return None
    index = earlier_at(time, times, target)
    if index is not None:
        return values[index]
    return lagrange([time, *times], [value, *values], target)


def earlier_at(time: float, times, target: float) -> int | None:
    """The index in ``times`` (earlier than ``time``, the latest first) of the one that is ``target``, else None."""
    for index, known in enumerate(times):
        if abs(known - target) <= 1e-9 * abs(time - target):
            return index
    return None


def lagrange_weights(nodes, target: float) -> list[float]:
    """The weights of the values at ``nodes`` in the polynomial through them, evaluated at ``target``."""
    weights = []
    for i, node in enumerate(nodes):
        weight = 1.0
        for j, other in enumerate(nodes):
            if j != i:
                weight *= (target - other) / (node - other)
        weights.append(weight)
    return weights


def lagrange(nodes, values, target: float):
    """The polynomial through ``values`` at ``nodes`` (numbers or arrays), evaluated at ``target``."""
    result = 0.0
    for weight, point in zip(lagrange_weights(nodes, target), values):
        result = result + weight * point
    return result
