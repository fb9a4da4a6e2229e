"""Health checks of the FE-IB state, run every step: a blow-up is stopped and explained, never recorded.

Checks per cell in the channel: finite positions; no self-intersection of the membrane polygon; enclosed
area within ``numerics.max_area_change`` of the initial area (the paper's method leaks area, see
README; the default 75 % lets the paper's scenarios run and stops a collapse or an explosion); membrane
points inside the channel (or past x = length through an outlet).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kernels
from .fluid import NumericalBlowUp
from .scenario import UM, Scenario


class HealthError(NumericalBlowUp):
    """A failed health check: which cell, which step, what went wrong, and a hint."""

    def __init__(self, cell_id: int, step: int, time: float, problem: str, hint: str):
        self.cell_id, self.step, self.time, self.problem, self.hint = cell_id, step, time, problem, hint
        super().__init__(f"cell {cell_id} at step {step} (t = {time * 1e3:.4f} ms): {problem}; {hint}")


@dataclass(frozen=True)
class HealthLimits:
    length: float
    height: float
    outlet_spans: tuple
    max_area_change: float
    dt: float
    tolerance: float

    @classmethod
    def of(cls, scenario: Scenario) -> "HealthLimits":
        channel = scenario.channel
        return cls(channel.length, channel.height, tuple(o.span for o in channel.outlets),
                   scenario.numerics.max_area_change, scenario.numerics.dt, 1e-3 * scenario.numerics.mesh_h)

    def dt_hint(self) -> str:
        return (f"the time step dt = {self.dt * 1e6:.4g} us is probably beyond this cell's stability limit: "
                f"try dt = {self.dt / 4 * 1e6:.4g} us")


def check_cells(cells, limits: HealthLimits, step: int, time: float):
    """Raise ``HealthError`` for the first cell in the channel that fails a check."""
    for cell in cells:
        if cell.in_channel:
            check_cell(cell, limits, step, time)


def check_cell(cell, limits: HealthLimits, step: int, time: float):
    points = cell.membrane.points
    if not np.all(np.isfinite(points)):
        raise HealthError(cell.id, step, time, "non-finite membrane positions", limits.dt_hint())
    i, j = kernels.first_self_intersection(np.ascontiguousarray(points))
    if i >= 0:
        raise HealthError(cell.id, step, time, f"the membrane intersects itself (edges {i} and {j})",
                          limits.dt_hint() + ", or use more membrane points (numerics.membrane_spacing)")
    ratio = cell.membrane.area() / cell.membrane.initial_area
    if abs(ratio - 1) > limits.max_area_change:
        raise HealthError(cell.id, step, time, f"enclosed area is {100 * ratio:.0f} % of the initial area",
                          limits.dt_hint() + " (or raise numerics.max_area_change if the loss is expected)")
    outside = _outside_channel(points, limits)
    if outside.any():
        worst = points[np.argmax(outside)]
        raise HealthError(cell.id, step, time,
                          f"membrane point at ({worst[0] / UM:.2f}, {worst[1] / UM:.2f}) um is outside the channel",
                          "the cell was pushed through a wall: " + limits.dt_hint())


def _outside_channel(points, limits: HealthLimits) -> np.ndarray:
    x, y = points[:, 0], points[:, 1]
    tol = limits.tolerance
    outside = (x < -tol) | (y < -tol) | (y > limits.height + tol)
    past_outlet = x > limits.length + tol
    if past_outlet.any():
        through_outlet = np.zeros_like(past_outlet)
        for low, high in limits.outlet_spans:
            through_outlet |= (y >= low) & (y <= high)
        outside |= past_outlet & ~through_outlet
    return outside
