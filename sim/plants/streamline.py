"""The plant ``streamline``: a cheap stand-in for the closed loop.

The steady flows with the IDT off and on, blended by a first-order lag of the drive, carry each cell's centroid
(no deformation, no feedback on the fluid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..method.fluid import NavierStokes
from ..method.streamline import outlet_at
from ..method.transfer import PointLocator
from ..model.drive import lagged
from ..model.geometry import MESH_INSET, clip_to_channel, injection_point
from ..model.scenario import Scenario
from .contract import CellTruth, CellView, Observation, Schedule, Truth


@dataclass
class _Point:
    key: int
    type: str
    born: float
    position: np.ndarray
    fate: str = "in_channel"
    exit_time: float = float("nan")
    exit_y: float = float("nan")


class StreamlinePlant:
    """Cells as points carried by the blend (1 - s) v_off + s v_on of two steady flows, s lagging the drive.

    ``response_time`` is the lag of the flow behind the IDT (first order). Cheap: one interpolation per
    cell per control period. It ignores cell size and deformation and the cells' effect on the fluid.
    """

    model = "streamline"      # its name in the registry (sim.plants.registry): what a summary says ran

    def __init__(self, scenario: Scenario, control_period: float = 10e-6, response_time: float = 0.1e-3,
                 fluid: NavierStokes | None = None):
        self.scenario = scenario
        self.control_period = control_period
        self.response_time = response_time
        fluid = fluid or NavierStokes(scenario.with_numerics(convection="stokes"))
        self.flows = np.stack([fluid.steady(0.0).velocity, fluid.steady(1.0).velocity])   # (2, 2, N)
        self.locator = PointLocator(fluid.space.cmesh, fluid.space.velocity_basis.element_dofs)
        self._values = self.flows.reshape(4, -1)

    def reset(self, arrivals) -> Observation:
        self.schedule = Schedule(arrivals)
        self.time = 0.0
        self.level = 0.0
        self.points: list[_Point] = []
        self._inject()
        return self.observe()

    def _inject(self):
        for key, (_, name) in self.schedule.due(self.time, 0.5 * self.control_period):
            start = np.array(injection_point(self.scenario, self.scenario.cell_type(name)))
            self.points.append(_Point(key, name, self.time, start))

    def _velocity(self, positions, level):
        values = self.locator.interpolate(self._values, positions)            # (n, 4)
        return (1 - level) * values[:, 0:2] + level * values[:, 2:4]

    def step(self, actuation: float) -> Observation:
        dt = self.control_period
        previous = self.level
        self.level = lagged(self.level, actuation, dt, self.response_time)
        active = [p for p in self.points if p.fate == "in_channel"]
        if active:
            positions = np.array([p.position for p in active])
            half = positions + 0.5 * dt * self._velocity(positions, previous)
            inside = clip_to_channel(half, self.scenario.channel, inset=MESH_INSET, walls=False)
            moved = positions + dt * self._velocity(inside, 0.5 * (previous + self.level))
            for point, old, new in zip(active, positions, moved):
                self._settle(point, old, new)
        self.time += dt
        self._inject()
        return self.observe()

    def _settle(self, point, old, new):
        channel = self.scenario.channel
        if not np.all(np.isfinite(new)):
            point.fate = "lost"
            return
        point.position = new
        if new[0] >= channel.length:
            weight = (channel.length - old[0]) / (new[0] - old[0])
            point.exit_y = float(old[1] + weight * (new[1] - old[1]))
            point.exit_time = self.time + weight * self.control_period
            point.fate = outlet_at(channel, point.exit_y)
        elif not (0 <= new[1] <= channel.height):
            point.fate = "wall"

    def observe(self) -> Observation:
        views = tuple(CellView(p.key, float(p.position[0]), float(p.position[1]),
                               self.scenario.cell_type(p.type).area, self.scenario.cell_type(p.type).fluorescence)
                      for p in self.points if p.fate == "in_channel")
        return Observation(self.time, views)

    def truth(self) -> Truth:
        cells = tuple(CellTruth(p.key, p.type, p.born, p.fate, p.exit_time, p.exit_y, float(p.position[0]),
                                float(p.position[1]), 1.0) for p in self.points)
        return Truth(self.time, cells, self.schedule.waiting)

    @property
    def done(self) -> bool:
        return self.schedule.waiting == 0 and all(p.fate != "in_channel" for p in self.points)
