"""The reduced plant ``oneway``: membranes that deform in the precomputed flow but do not push back on it.

Each membrane point moves (forward Euler, as in the FE-IB plant's (27)) with

    V_r = v(X_r) + sum_s G_eps(X_r - X_s) f_s,

- v = (1 - s) v_off + s v_on, the steady IDT-off and IDT-on flows of the ``rom`` plant (``sim.plants.rom.RomFlows``,
  sampled on a grid from the exact P2 solutions) blended by the lagged drive level s;
- f = -dE/dX the membrane forces of the paper's energy (with the interior pressure of the area constraint,
  as the scenario's ``numerics.area_constraint`` asks), and G_eps the regularised Stokeslet of free space
  in 2D (Cortez 2001, blob 3 eps^3 / (2 pi (r^2 + eps^2)^(5/2)), eps = mesh_h): the membrane's own
  forces move it through the fluid as they would in an unbounded fluid, so a cell relaxes, and resists
  being deformed, on about the right time scale. A membrane's forces sum to zero, so the logarithm's
  arbitrary length scale (Stokes' paradox) drops out.
Ignored: the cells' effect on the flow and on each other, the walls' effect on the membrane's own
motion (no image system), the flow's transient shape (one lag). Kept from the FE-IB plant: the spline
membranes and their energy, the area constraint's projection and point redistribution, fates, the
health checks. No linear solve per step: the cost is O(R^2) per cell.
"""

from __future__ import annotations

import math

import numpy as np

from ..method.feib import Cell, membrane_forces, new_cell, settle
from ..method.health import HealthLimits, check_cells
from ..model.drive import lagged
from ..model.geometry import clip_to_channel
from ..model.scenario import Scenario
from .contract import Observation, Schedule, Truth
from .feib import membrane_truths, membrane_views
from .rom import RomFlows, default_response_time


def stokeslet_velocities(points: np.ndarray, forces: np.ndarray, viscosity: float, epsilon: float) -> np.ndarray:
    """Velocities (R, 2) at ``points`` induced by point forces (N/m) at the same points: regularised Stokeslets."""
    offset = points[:, None, :] - points[None, :, :]
    r2 = np.sum(offset**2, axis=-1)
    big_r = np.sqrt(r2 + epsilon**2)
    a = -np.log(big_r + epsilon) + epsilon * (big_r + 2 * epsilon) / ((big_r + epsilon) * big_r)
    b = (big_r + 2 * epsilon) / ((big_r + epsilon) ** 2 * big_r)
    projected = np.einsum("rsk,sk->rs", offset, forces)
    return (a @ forces + np.einsum("rs,rsk->rk", b * projected, offset)) / (4 * math.pi * viscosity)


class OneWayPlant:
    """Deforming membranes in the blended steady flows (module docstring), behind the plant contract."""

    model = "oneway"      # its name in the registry (sim.plants.registry): what a summary says ran

    def __init__(self, scenario: Scenario, control_period: float | None = None, flows: RomFlows | None = None,
                 response_time: float | None = None, epsilon: float | None = None):
        self.scenario = scenario
        dt = scenario.numerics.dt
        self.control_period = control_period or dt
        self.substeps = max(1, round(self.control_period / dt))
        self.flows = flows or RomFlows.of(scenario)
        self.response_time = default_response_time(scenario) if response_time is None else response_time
        self.epsilon = scenario.numerics.mesh_h if epsilon is None else epsilon
        self.limits = HealthLimits.of(scenario)
        self.reset([])

    # ------------------------------------------------------------------ the contract
    def reset(self, arrivals) -> Observation:
        self.schedule = Schedule(arrivals)
        self.time, self.level, self.steps = 0.0, 0.0, 0
        self.cells: list[Cell] = []
        self._inject()
        return self.observe()

    def _inject(self):
        for key, (_, name) in self.schedule.due(self.time, 0.5 * self.scenario.numerics.dt):
            self.cells.append(new_cell(self.scenario, self.scenario.cell_type(name), key, self.time, warn=False))

    def step(self, actuation: float) -> Observation:
        for _ in range(self.substeps):
            self._step(actuation)
            self._inject()
        return self.observe()

    def _step(self, actuation: float):
        numerics, channel = self.scenario.numerics, self.scenario.channel
        dt = numerics.dt
        self.level = lagged(self.level, actuation, dt, self.response_time)
        self.time += dt
        self.steps += 1
        moved = []
        for index, cell in enumerate(self.cells):
            if not cell.in_channel:
                continue
            points = cell.membrane.points
            inside = points[:, 0] < channel.length
            forces = membrane_forces(cell.membrane, numerics) * inside[:, None]
            velocity = self.flows.velocity(clip_to_channel(points, channel), self.level)
            velocity += stokeslet_velocities(points, forces, self.scenario.fluid.viscosity, self.epsilon)
            self.cells[index] = settle(cell, points + dt * velocity, self.time, self.scenario)
            moved.append(self.cells[index])
        check_cells(moved, self.limits, self.steps, self.time)

    @property
    def done(self) -> bool:
        return self.schedule.waiting == 0 and not any(cell.in_channel for cell in self.cells)

    def observe(self) -> Observation:
        return Observation(self.time, membrane_views(self.cells))

    def truth(self) -> Truth:
        return Truth(self.time, membrane_truths(self.cells), self.schedule.waiting)

    def diagnostics(self) -> dict:
        return {"dt": self.scenario.numerics.dt, "physics_steps": self.steps, "level": self.level, "health": "ok"}
