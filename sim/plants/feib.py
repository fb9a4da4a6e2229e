"""The FE-IB plant of the closed loop, and the FE-IB helpers the membrane plants share.

The contract they implement (``Plant``, ``Observation``, ``Truth``, ``check_plant``, ...) is ``sim.plants.contract``;
its names stay importable from here.

``FeibPlant``: the full two-way coupled FE-IB model (``sim.method.feib``), several physics steps per control
period when the period is longer than dt (``AdaptiveFeibPlant``: with the steps a tolerance picks).
"""

from __future__ import annotations

import math

from ..method.adaptive import AdaptiveSteps
from ..method.feib import ImmersedBoundary, State
from ..model.scenario import Scenario
from .contract import CellTruth, CellView, Observation, Schedule, Truth, check_plant  # noqa: F401 (re-exported)

_Schedule = Schedule          # the name FeibPlant uses


def membrane_views(cells) -> tuple[CellView, ...]:
    """What the optics see of membrane cells (``sim.method.feib.Cell``) in the channel."""
    views = []
    for cell in cells:
        if cell.in_channel:
            x, y = cell.membrane.centroid()
            views.append(CellView(cell.id, float(x), float(y), cell.membrane.area(),
                                  cell.membrane.cell_type.fluorescence))
    return tuple(views)


def membrane_truths(cells) -> tuple[CellTruth, ...]:
    """The ground truth of membrane cells (``sim.method.feib.Cell``), with their points and shape measures."""
    truths = []
    for cell in cells:
        x, y = cell.membrane.centroid()
        truths.append(CellTruth(cell.id, cell.membrane.cell_type.name, cell.born, cell.fate, cell.exit_time,
                                cell.exit_y, float(x), float(y), cell.measures.area_ratio, cell.membrane.points,
                                cell.measures.as_dict()))
    return tuple(truths)


ADAPTIVE_PERIOD = 10e-6      # the longest control period of a FeibPlant whose steps a tolerance picks


class FeibPlant:
    """The FE-IB model behind the plant contract."""

    model = "feib"      # its name in the registry (sim.plants.registry): what a summary says ran

    def __init__(self, scenario: Scenario, control_period: float | None = None, plant: ImmersedBoundary | None = None):
        self.scenario = scenario
        self.ib = plant or ImmersedBoundary(scenario)
        # with a tolerance the steps' dt is chosen per step (sim.method.adaptive), wrapping the FE-IB step
        self.adaptive = AdaptiveSteps(self.ib) if scenario.numerics.tolerance > 0 else None
        dt = scenario.numerics.dt
        # with a tolerance the period holds one step of the coarsest level (sim.method.adaptive), at most 10 us (the
        # IDT drive changes only between periods: a longer one would delay pulses by more than the steps' error)
        natural = dt if self.adaptive is None else max(dt, min(self.adaptive.levels[-1], ADAPTIVE_PERIOD))
        self.control_period = control_period or natural
        self.substeps = max(1, round(self.control_period / dt))
        self._initial = None
        self.state = None
        self.warn_under_resolved = True       # log cells the mesh does not resolve (sim.method.health.under_resolved)

    def reset(self, arrivals) -> Observation:
        if self._initial is None:
            self._initial = self.ib.fluid.initial_flow(0.0)
        self.schedule = _Schedule(arrivals)
        self.state = State(self._initial, ())
        if self.adaptive is not None:
            self.adaptive.reset()
        self._inject()
        return self.observe()

    def _inject(self):
        dt = self.scenario.numerics.dt
        new = [self.ib.new_cell(self.scenario.cell_type(name), key, self.state.time, warn=self.warn_under_resolved)
               for key, (_, name) in self.schedule.due(self.state.time, 0.5 * dt)]
        if new:
            self.state = State(self.state.flow, self.state.cells + tuple(new), self.state.step)

    def step(self, actuation: float) -> Observation:
        if self.adaptive is not None:
            return self._adaptive_step(actuation)
        for _ in range(self.substeps):
            self.state = self.ib.step(self.state, actuation)
            self._inject()
        return self.observe()

    def _adaptive_step(self, actuation: float) -> Observation:
        """One control period in steps of the levels ``sim.method.adaptive`` picks, stopping where a cell is due (on
        the dt grid, as the fixed step injects it)."""
        dt = self.scenario.numerics.dt
        end = (round(self.state.time / self.control_period) + 1) * self.control_period
        while self.state.time < end - 0.5 * dt:
            self.state = self.adaptive.step(self.state, actuation, until=min(end, self._next_due()))
            self._inject()
        return self.observe()

    def _next_due(self) -> float:
        """When the next scheduled cell is injected (on the dt grid, as the fixed step injects it), if after now."""
        dt = self.scenario.numerics.dt
        if self.schedule.waiting:
            arrival = self.schedule.items[self.schedule.position][0]
            due = dt * math.ceil((arrival - 0.5 * dt) / dt - 1e-9)
            if due > self.state.time + 0.5 * dt:
                return due
        return math.inf

    @property
    def time(self) -> float:
        return self.state.time

    def time_steps(self) -> dict:
        """The dt used: fixed, or per level with the changes over time (``sim.method.adaptive``)."""
        if self.adaptive is None:
            return {"dt_us": self.scenario.numerics.dt * 1e6, "steps": self.ib.timings.steps,
                    "scheme": self.scenario.numerics.scheme}
        return self.adaptive.summary(self.state.time)

    def adopt(self, state: State, injected: int):
        """Continue from ``state`` (built from another plant's) with the first ``injected`` arrivals injected."""
        self.schedule.position = injected
        self.state = state

    def observe(self) -> Observation:
        return Observation(self.state.time, membrane_views(self.state.cells))

    def truth(self) -> Truth:
        return Truth(self.state.time, membrane_truths(self.state.cells), self.schedule.waiting)

    @property
    def done(self) -> bool:
        return self.schedule.waiting == 0 and not any(cell.in_channel for cell in self.state.cells)

    def fields(self):
        """The current velocity and pressure at the mesh vertices and the vertex grid (for recordings)."""
        cmesh = self.ib.fluid.space.cmesh
        return cmesh.mesh.p, self.state.flow.velocity, self.state.flow.pressure, cmesh.x, cmesh.y

    def diagnostics(self) -> dict:
        """Solver figures for logging: dt, steps so far, cumulative wall time per part (s)."""
        timings, fluid = self.ib.timings, self.ib.fluid.timings
        adaptive = self.adaptive
        dt = self.scenario.numerics.dt if adaptive is None or not adaptive.history else adaptive.history[-1][1]
        return {"dt": dt, "physics_steps": timings.steps, "fluid_solve_s": fluid.solve,
                "fluid_load_s": fluid.load, "membrane_s": timings.membrane, "health_checks_s": timings.health,
                "health": "ok"}


class AdaptiveFeibPlant(FeibPlant):
    """The FE-IB plant whose steps a tolerance picks (``sim.method.adaptive``), event-driven: ``step_until`` takes one
    step a call, across the controller's period ends while the drive holds.

    The IDT drive changes only at the controller's period ends; a step that ends there can be no longer than
    the time left in the period, so a period begun with a fine step ends with more fine steps. The closed
    loop (``vcyto.stream``) instead tells the plant when the drive may change next (``until``: a pulse edge,
    taken at the first period end at or after it, where the period-by-period loop switches) and the plant steps
    freely up to it, at the levels the estimate, the stability cap and the redistributions allow. The detector
    is fed the cells that crossed one of its lines in a step, at the step's start and end (it interpolates the
    crossing time between them). ``step`` (one control period) stays for the loops that step periods."""

    one_step_per_call = True       # the loop shows every call to its sinks and does not stop it at a record interval

    @property
    def clock(self) -> float:
        """The controller's time: the last control period end (the drive changes only there)."""
        return math.floor(self.state.time / self.control_period + 1e-9) * self.control_period

    def step_until(self, actuation: float, until: float, stop_lines=(), record_lines=(), max_periods: int = 10**7):
        """One step at ``actuation``, ending at or before the first control period end at or after ``until`` and
        where the next cell is due. Returns (1, seen): ``seen`` the partial observations, at the step's start and
        end, of the cells whose centroid crossed a line x = w of ``stop_lines`` or ``record_lines`` forwards."""
        period = self.control_period
        stop = self._next_due()
        if math.isfinite(until):
            end = math.ceil(until / period - 1e-9) * period
            if end <= self.state.time + 0.5 * self.scenario.numerics.dt:
                end = self.clock + period
            stop = min(stop, end)
        before = self.state
        self.state = self.adaptive.step(before, actuation, until=None if math.isinf(stop) else stop)
        self._inject()
        return 1, self._crossed(before, tuple(stop_lines) + tuple(record_lines))

    def _crossed(self, before: State, lines) -> list[Observation]:
        """The cells in the channel at the step's start whose centroid crossed one of ``lines`` forwards in it,
        as two partial observations (start, end); none when no cell crossed."""
        start = {view.key: view for view in membrane_views(before.cells)}
        end = {view.key: view for view in membrane_views(self.state.cells)}
        keys = [key for key, view in start.items() if key in end
                and any(view.x < line <= end[key].x for line in lines)]
        if not keys:
            return []
        return [Observation(before.time, tuple(start[key] for key in keys)),
                Observation(self.state.time, tuple(end[key] for key in keys))]
