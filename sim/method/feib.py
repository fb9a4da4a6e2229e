"""The semi-implicit FE-IB step (paper section 3.1): membrane forces (25) -> fluid (26) -> membranes (27).

One step from (v^m, X^m):
  1. f_r = -dE_h/dX_r at X^m for every cell (``Membrane.forces``) and spread: <F_h, w> = sum_r f_r . w(X_r);
  2. backward-Euler Navier-Stokes for v^{m+1} with that load (``NavierStokes.step``);
  3. X_r^{m+1} = X_r^m + dt v^{m+1}(X_r^m), the velocity interpolated at the points located in step 1.
With an area constraint (``numerics.area_constraint``, docs/numerics.md "Cells that keep their size") step 1 adds
the interior pressure that balances the force's area-changing part (``pressure``) and step 3 moves the
membrane along its normal to restore the cell's area (``projection``); with ``numerics.redistribute`` the
points are re-spaced along the spline whenever a spacing leaves ``numerics.spacing_band``.
Then each cell's fate is settled (the outlet its centroid crosses x = length through), its shape figures
are updated (``Measures``) and the health checks run (``sim.method.health``). Membrane points that have passed
x = length through an outlet are outside the mesh: they move with the outlet's velocity at x = length (the
outflow continued straight) and exert no force on the fluid.
"""

from __future__ import annotations

import logging
import time as clock
from dataclasses import dataclass, replace

import numpy as np

from ..model.geometry import MESH_INSET, clip_to_channel, injection_point
from ..model.scenario import CellType, Scenario
from .fluid import Flow, NavierStokes
from .health import HealthLimits, check_cells, under_resolved
from .membrane import Membrane
from .multiplier import Update, area_pressures
from .streamline import outlet_at
from .transfer import PointLocator

IN_CHANNEL = "in_channel"
LOG = logging.getLogger(__name__)
LOG.addHandler(logging.NullHandler())       # sim prints nothing: warnings reach only handlers the application adds


@dataclass(frozen=True)
class Measures:
    """A cell's shape figures now and their extremes since birth: area / initial area, point spacing / h.

    Updated while the whole membrane is inside the channel (points past the outlet move by a made-up rule);
    ``area_corrected`` sums the area the projection restored (|dA| / A0 per step): what leaked before it;
    ``area_resampled`` sums the area the point redistributions' resampling changed (|dA| / A0 each; with an area
    constraint the redistribution puts it back itself, so this is not part of the leak).
    """

    area_ratio: float = 1.0
    perimeter: float = float("nan")
    spacing_min: float = float("nan")
    spacing_max: float = float("nan")
    area_ratio_min: float = 1.0
    area_ratio_max: float = 1.0
    spacing_lowest: float = float("inf")
    spacing_highest: float = 0.0
    area_corrected: float = 0.0
    area_resampled: float = 0.0

    @classmethod
    def of(cls, membrane: Membrane, mesh_h: float, before: "Measures | None" = None, corrected: float = 0.0,
           resampled: float = 0.0):
        ratio = membrane.area() / membrane.initial_area
        lengths = membrane.spacing()
        low, high = float(lengths.min()) / mesh_h, float(lengths.max()) / mesh_h
        before = before or cls()
        return cls(ratio, float(lengths.sum()), low, high, min(before.area_ratio_min, ratio),
                   max(before.area_ratio_max, ratio), min(before.spacing_lowest, low),
                   max(before.spacing_highest, high), before.area_corrected + corrected,
                   before.area_resampled + resampled)

    def as_dict(self) -> dict:
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


@dataclass(frozen=True)
class Cell:
    """A cell in the device: its membrane and, once settled, its fate ('lower'/'upper'/... , 'wall', 'lost')."""

    id: int
    membrane: Membrane
    fate: str = IN_CHANNEL
    exit_time: float = float("nan")
    exit_y: float = float("nan")
    born: float = 0.0
    measures: Measures = Measures()
    history: tuple = ()     # bdf2: the points at the flow's history times (the latest first; fewer if born since)

    @property
    def in_channel(self) -> bool:
        return self.fate == IN_CHANNEL


@dataclass(frozen=True)
class State:
    """The plant's state: the flow and every cell (in the channel or settled)."""

    flow: Flow
    cells: tuple[Cell, ...] = ()
    step: int = 0

    @property
    def time(self) -> float:
        return self.flow.time


@dataclass
class Timings:
    """Wall time per part of the FE-IB steps (seconds)."""

    membrane: float = 0.0
    fluid: float = 0.0
    health: float = 0.0
    steps: int = 0


class ImmersedBoundary:
    """The coupled FE-IB plant of a scenario: ``start``, ``add_cell`` and ``step``."""

    def __init__(self, scenario: Scenario, fluid: NavierStokes | None = None):
        self.scenario = scenario
        self.fluid = fluid or NavierStokes(scenario)
        space = self.fluid.space
        self.locator = PointLocator(space.cmesh, space.velocity_basis.element_dofs)
        self.limits = HealthLimits.of(scenario)
        self.timings = Timings()
        self.coupling = None
        if scenario.numerics.membrane_coupling == "implicit":      # the force at the new positions
            from .coupling import ImplicitCoupling
            self.coupling = ImplicitCoupling(self)

    # ------------------------------------------------------------------ cells
    def new_cell(self, cell_type: CellType, cell_id: int, time: float, centre=None, warn: bool = True) -> Cell:
        return new_cell(self.scenario, cell_type, cell_id, time, centre, warn)

    def start(self, actuation: float = 0.0, cells=()) -> State:
        """The initial flow of the scenario (steady at ``actuation`` by default) with ``cells``."""
        return State(self.fluid.initial_flow(actuation), tuple(cells))

    # ------------------------------------------------------------------ the step
    def step(self, state: State, actuation: float = 0.0, dt: float | None = None, fluid: NavierStokes | None = None,
             ahead: "bool | NavierStokes" = True) -> State:
        """One step of size ``dt`` (default ``numerics.dt``) with ``fluid``, a solver factored for that dt (default:
        this plant's, for ``numerics.dt``), in the fluid's time scheme. With ``numerics.tolerance`` the steps' dt is
        chosen from outside (``sim.method.adaptive.AdaptiveSteps`` wraps this step and passes dt and its solver).

        euler (the paper's): the force at X^m, X^{m+1} = X^m + dt v^{m+1}(X^m). bdf2: the force at
        X* = 2 X^m - X^{m-1}, X^{m+1} = (4 X^m - X^{m-1}) / 3 + 2 dt / 3 v^{m+1}(X*), X^{m-1} the points at
        t - dt from the cell's history (``sim.method.timeschemes.value_back``; a redistribution carries the history to
        the new points' spline parameters); a new cell takes X* = X^m and the Euler update. With
        ``numerics.membrane_coupling`` implicit the force is that of the new points (``sim.method.coupling``: X^{m+1}
        from a small system per cell, the flow corrected by one more back-solve). ``ahead``: the fluid starts the
        next step's momentum integrals (``NavierStokes.prefetch``) while the membranes move."""
        if dt is None:
            if self.scenario.numerics.tolerance > 0:
                raise ValueError("numerics.tolerance picks each step's dt: step through "
                                 "sim.method.adaptive.AdaptiveSteps")
            dt = self.scenario.numerics.dt
        fluid = fluid or self.fluid
        if fluid.scenario.numerics.dt != dt:
            raise ValueError(f"a step of {dt} s needs a fluid solver factored for it (this one: "
                             f"{fluid.scenario.numerics.dt} s)")
        scheme = fluid.scheme
        started = clock.perf_counter()
        active = [cell for cell in state.cells if cell.in_channel]
        before = [self._before(scheme, cell, state.flow, dt) for cell in active]
        at = [scheme.extrapolated(cell.membrane.points, old) for cell, old in zip(active, before)]
        load, located = self.membrane_load(active, at)
        fluid_started = clock.perf_counter()
        implicit = self.coupling is not None and bool(active)
        kept = self._kept_areas(active, before, at, located, dt)
        flow = fluid.step(state.flow, actuation, load if active else None,
                          ahead=False if implicit or kept else ahead)
        if kept:            # the area constraint's multiplier: each cell's interior pressure in the same step
            flow, _ = area_pressures(fluid, self.locator, flow, kept, self._force_weights)
            if ahead and not implicit:
                (fluid if ahead is True else ahead).prefetch(flow)
        membrane_started = clock.perf_counter()
        news = []
        for cell, old, (elements, reference) in zip(active, before, located):
            velocity = self.locator.interpolate_located(flow.velocity, elements, reference)
            points = cell.membrane.points
            news.append(scheme.advanced(points, old, dt, velocity))
        solved = fluid.timings.solve
        if implicit:        # the force at the new points: each cell's small system and one more back-solve
            news, flow = self.coupling.correct(fluid, flow, [cell.membrane for cell in active], at, news, located,
                                               [p[:, 0] < self.scenario.channel.length for p in at],
                                               [dt if old is None else 2 * dt / 3 for old in before])
            if ahead is True:
                fluid.prefetch(flow)
            elif ahead:
                ahead.prefetch(flow)
        moved = {}
        for cell, new in zip(active, news):
            moved[cell.id] = settle(cell, new, flow.time, self.scenario, dt,
                                    scheme.carried(cell.membrane.points, cell.history))
        cells = tuple(moved.get(cell.id, cell) for cell in state.cells)
        health_started = clock.perf_counter()
        check_cells([moved[cell.id] for cell in active], self.limits, state.step + 1, flow.time)
        finished = clock.perf_counter()
        solved = fluid.timings.solve - solved          # the implicit coupling's back-solve: the fluid's
        self.timings.membrane += (fluid_started - started) + (health_started - membrane_started) - solved
        self.timings.fluid += membrane_started - fluid_started + solved
        self.timings.health += finished - health_started
        self.timings.steps += 1
        return State(flow, cells, state.step + 1)

    def _kept_areas(self, active, before, at, located, dt) -> list[Update]:
        """The cells wholly in the channel whose area the multiplier keeps (``sim.method.multiplier``), as
        ``Update``s."""
        if "multiplier" not in self.scenario.numerics.area_constraint:
            return []
        length = self.scenario.channel.length
        return [Update(cell.membrane, cell.membrane.points if old is None else (4 * cell.membrane.points - old) / 3,
                       dt if old is None else 2 * dt / 3, where, points)
                for cell, old, points, where in zip(active, before, at, located)
                if (cell.membrane.points[:, 0] < length).all() and (points[:, 0] < length).all()]

    def _force_weights(self, points: np.ndarray) -> np.ndarray:
        """1 for points in the channel, 0 for those through an outlet (they exert no force)."""
        return (points[:, 0] < self.scenario.channel.length).astype(float)

    @staticmethod
    def _before(scheme, cell: Cell, flow: Flow, dt: float) -> np.ndarray | None:
        """The cell's points at t - dt the scheme uses (None: a one-step scheme, or no history)."""
        history = cell.history[:len(flow.history)]
        return scheme.back(flow.time, cell.membrane.points, [t for t, _ in flow.history[:len(history)]], history, dt)

    def membrane_load(self, cells, at=None):
        """The P2 load (2, N) of the membrane forces of ``cells`` and where each cell's points lie in the mesh
        (element, reference coordinates; points through an outlet located just inside it, with no force);
        ``at``: a list of points per cell to evaluate the forces and locations at (default: the membranes')."""
        load = np.zeros((2, self.fluid.space.N))
        located = []
        for index, cell in enumerate(cells):
            points = cell.membrane.points if at is None else at[index]
            membrane = cell.membrane if at is None else cell.membrane.with_points(points)
            elements, reference = self.locator.locate(self._inside(points))
            inside = points[:, 0] < self.scenario.channel.length
            forces = membrane_forces(membrane, self.scenario.numerics) * inside[:, None]
            self.locator.spread_located(forces, elements, reference, load)
            located.append((elements, reference))
        return load, located

    def _inside(self, points):
        """Points past x = length (through an outlet) are evaluated at x = length, just inside the mesh."""
        return clip_to_channel(points, self.scenario.channel, inset=MESH_INSET, walls=False)

    def _settle(self, cell: Cell, points: np.ndarray, time: float) -> Cell:
        return settle(cell, points, time, self.scenario)


def new_cell(scenario: Scenario, cell_type: CellType, cell_id: int, time: float, centre=None,
             warn: bool = True) -> Cell:
    """A cell of ``cell_type`` at ``centre`` (default: the injection point) with the scenario's membrane
    resolution; ``warn``: log a warning when the mesh does not resolve it (``sim.method.health.under_resolved``)."""
    numerics = scenario.numerics
    centre = injection_point(scenario, cell_type) if centre is None else centre
    membrane = Membrane.of(cell_type, centre, numerics.membrane_spacing * numerics.mesh_h)
    if warn and (warning := under_resolved(cell_type, numerics.mesh_h)) is not None:
        LOG.warning("cell %d: %s", cell_id, warning)
    return Cell(cell_id, membrane, born=time, measures=Measures.of(membrane, numerics.mesh_h))


def reshape(membrane: Membrane, numerics, history: tuple = ()) -> tuple[Membrane, float, float, tuple]:
    """The redistribution of points and the area constraint's projection, as ``numerics`` asks; the
    relative area the projection restored, the relative area the redistribution's resampling changed (with an
    area constraint the redistribution puts it back itself: the resampled spline is moved along its normal to the
    area of the spline it came from), and ``history`` (earlier points, bdf2's) carried to the redistributed
    points' spline parameters."""
    resampled = 0.0
    if numerics.redistribute:
        spacing = membrane.spacing() / numerics.mesh_h
        low, high = numerics.spacing_band
        if spacing.min() < low or spacing.max() > high:
            area = membrane.area()
            membrane, history = membrane.resampled_carrying(numerics.membrane_spacing * numerics.mesh_h, history)
            resampled = abs(membrane.area() - area) / membrane.initial_area
            if numerics.area_constraint != "none":      # a re-parametrisation keeps the shape's area
                membrane = membrane.with_area(area)
    corrected = 0.0
    if "projection" in numerics.area_constraint:
        corrected = abs(membrane.area() / membrane.initial_area - 1)
        membrane = membrane.with_area(membrane.initial_area)
    return membrane, corrected, resampled, history


def settle(cell: Cell, points: np.ndarray, time: float, scenario: Scenario, dt: float | None = None,
           history: tuple = ()) -> Cell:
    """The cell with its new points (reshaped while wholly inside, with its measures) after a step of ``dt``
    (default ``numerics.dt``); its fate once its centroid crosses x = length (the outlet at the crossing ordinate).
    ``history``: earlier points, the latest first, kept as the cell's (bdf2; carried along a redistribution)."""
    dt = scenario.numerics.dt if dt is None else dt
    membrane = cell.membrane.with_points(points)
    measures = cell.measures
    length = scenario.channel.length
    if (points[:, 0] < length).all():
        membrane, corrected, resampled, history = reshape(membrane, scenario.numerics, history)
        measures = Measures.of(membrane, scenario.numerics.mesh_h, measures, corrected, resampled)
    before, after = cell.membrane.centroid(), membrane.centroid()
    if after[0] < length:
        return replace(cell, membrane=membrane, measures=measures, history=history)
    weight = (length - before[0]) / (after[0] - before[0])
    exit_y = before[1] + weight * (after[1] - before[1])
    exit_time = time - dt * (1 - weight)
    return replace(cell, membrane=membrane, fate=outlet_at(scenario.channel, exit_y),
                   exit_time=exit_time, exit_y=exit_y, measures=measures)


def membrane_forces(membrane: Membrane, numerics) -> np.ndarray:
    """f = -dE/dX, with the interior pressure of the area constraint when ``numerics`` asks for it."""
    forces = membrane.forces()
    if "pressure" in numerics.area_constraint:
        forces, _ = membrane.pressure_balanced(forces)
    return forces
