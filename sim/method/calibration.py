"""Calibration of the ``streaming`` SAW model against the paper's jet (docs/physics.md, "SAW models").

The streaming force amplitude is chosen so that the steady centre streamline of the injection inlet
leaves at the ordinate the paper's Dirichlet jet gives (about 141 um on the paper's device): the
same deflection, produced by a mass-conserving body force instead of net mass injection.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..model.geometry import injection_y
from ..model.scenario import Scenario
from .fluid import NavierStokes
from .streamline import Streamline, trace
from .transfer import PointLocator


@dataclass(frozen=True)
class FlowPaths:
    """The injection inlet's centre streamline with the IDT off and on."""

    off: Streamline
    on: Streamline
    wall_time: float


def injection_streamline(scenario: Scenario, actuation: float, solver: NavierStokes | None = None):
    """The steady flow at ``actuation`` and its streamline from the injection inlet's centre."""
    solver = solver or NavierStokes(scenario)
    flow = solver.steady(actuation)
    locator = PointLocator(solver.space.cmesh, solver.space.velocity_basis.element_dofs)
    start = (0.0, injection_y(scenario.channel))
    return flow, trace(locator, flow.velocity, scenario.channel, start, solver.space.cmesh.h)


def calibrate_streaming_force(scenario: Scenario, target_y: float | None = None, tolerance: float = 0.5e-6,
                              bounds=(1e6, 1e9), max_iterations: int = 30):
    """The streaming force (N/m^3) whose steady streamline exits at ``target_y``.

    Without ``target_y`` the target is the exit ordinate of the ``envelope`` jet on the same scenario.
    Bisection on log(force); returns (force, exit_y, iterations).
    """
    if target_y is None:
        _, reference = injection_streamline(replace(scenario, saw=replace(scenario.saw, model="envelope")), 1.0)
        target_y = reference.exit_y
    low, high = (math.log(b) for b in bounds)
    exit_y = float("nan")
    for iteration in range(1, max_iterations + 1):
        middle = 0.5 * (low + high)
        trial = replace(scenario, saw=replace(scenario.saw, model="streaming", streaming_force=math.exp(middle)))
        _, path = injection_streamline(trial, 1.0)
        exit_y = path.exit_y if path.outlet != "lost" else float("inf")
        if abs(exit_y - target_y) <= tolerance:
            break
        if exit_y < target_y:
            low = middle
        else:
            high = middle
    return math.exp(middle), exit_y, iteration
