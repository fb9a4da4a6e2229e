"""The reduced plant ``rom``: cells as finite-size passive bodies carried by two precomputed steady flows.

Physics kept:
- the flow is linear in the drive: v = v_off + sum_k q_k Phi_k, with v_off the steady Navier-Stokes flow of
  the scenario with the IDT off (the FE-IB plant's initial flow, from ``NavierStokes.steady``) and Phi_k the
  modes of the FE flow's measured response to the IDT (``sim.plants.rom_transient``: a jump, a fast and a slow
  viscous mode, summing to v_on - v_off), each mode's level q_k following the actuation through a
  first-order lag of its own time constant. With ``response_time`` given (or the ``streaming`` SAW model,
  or flows sampled without the transient) there is one mode, v_on - v_off, lagged by ``response_time``;
- a cell is an ellipse of its type's semi-axes whose centroid moves with the flow averaged over its area.
  For a cell whose interior is fluid that is exact (d/dt of the area centroid = area mean of v, by Reynolds'
  transport theorem and div v = 0), and it is what the FE-IB plant's centroid does in the undisturbed flow;
- walls: the ellipse may touch a wall but not cross it (its centroid is held its semi-axis off the wall, or
  its own extent off the end of a wall segment beside an inlet or outlet), so a cell pushed against a wall
  slides along it. A cell held against a wall that moves less than ``stall_speed`` for ``stall_time`` is
  stuck: its fate is ``wall``. A centroid crossing x = length leaves by the outlet at that ordinate. A cell
  pressed on a divider's face (the wall between two outlets) with its centroid in the divider's span
  settles there, fate ``wall`` (``catch_on_divider``): that is where the FE-IB plant's centroid leaves
  through the divider (``wall``), or its membrane folds against the face; it does not slide off the face
  into an outlet as a rigid ellipse would (docs/physics.md, "rom").
Physics ignored: deformation, the cells' effect on the fluid and on each other (cells may overlap), rotation,
inertia of the cell.

The fields are sampled once on a uniform grid (``RomFlows``, 1 um by default) from the exact P2 solution and
interpolated bilinearly; the area means are precomputed per cell type on the same grid, so moving a cell costs
two bilinear look-ups per substep. ``RomPlant.step_until`` advances many control periods in one numba call and
returns when the caller must look (a cell crosses a watched line, a time is reached, every cell has settled):
the closed loop then calls the detector and controller only when something can happen, with the same result
as calling them every period.
"""

from __future__ import annotations

import math
import time as clock
from dataclasses import dataclass, replace

import numpy as np

from ..fast import rom_kernels as kernels
from ..method.fluid import NavierStokes
from ..method.transfer import PointLocator
from ..model.arrivals import Cells, Drawn
from ..model.drive import lag_decay
from ..model.geometry import clip_to_channel, injection_point
from ..model.scenario import Channel, Scenario
from .feib import CellTruth, CellView, Observation, Truth
from .rom_transient import RESPONSE_POINT, TRANSIENT_LAGS, measure_response_time, sampled_modes  # noqa: F401

# Mean delay  int (1 - s(t)) dt  of the FE flow at (150, 115) um, where cells are deflected, after the IDT
# switches (``measure_response_time``; the same within 1 us at dt = 2.5 and 10 us): the Dirichlet jet of the
# ``paper``/``envelope`` models moves 76 % of the way in the first step and the rest with a viscous tail.
JET_RESPONSE_TIME = 41e-6
# The same for the ``streaming`` body force, on top of its own lag (spin_up_time): 282 us in all at 0.2 ms.
STREAMING_VISCOUS_DELAY = 82e-6
# The default control period: sorting outcomes of 5 x 1,000-cell streams differ from those at 2.5 us in
# 9 cells at 10 us, 8 at 20 us, 25 at 50 us and 40 at 100 us; each period is one midpoint substep.
CONTROL_PERIOD = 20e-6
_NO_LINES = np.zeros(0)
TRACE_ROWS = 4096              # rows of the trace buffer to start with (it grows when a traced period needs more)
LOG_ROWS = 4096                # rows of the crossing log to start with (likewise)
WINDOW_CELLS = 1 << 15         # cells whose state the plant holds at once (a longer sample slides through them)
_KIND = np.int8                # a cell's type index, as the arrivals are kept (the kernel's window: int64)
FATES = {kernels.WALL: "wall", kernels.LOST: "lost", kernels.IN_CHANNEL: "in_channel"}
_new = object.__new__


# The plant's views and truths, built many times a stop: their instances' ``__dict__`` filled field by field in the
# order of their fields, which makes the same objects as the frozen dataclasses' own ``__init__`` (equal, same repr,
# pickled alike: ``tests/test_rom.py``) at a third to a half of its cost (one ``object.__setattr__`` call a field).
def _view(key, x, y, area, brightness) -> CellView:
    view = _new(CellView)
    fields = view.__dict__
    fields["key"] = key
    fields["x"] = x
    fields["y"] = y
    fields["area"] = area
    fields["brightness"] = brightness
    return view


def _truth(key, name, born, fate, exit_time, exit_y, x, y) -> CellTruth:
    """A cell's truth as ``CellTruth(key, name, born, fate, exit_time, exit_y, x, y, 1.0)`` (no membrane, no
    measures)."""
    cell = _new(CellTruth)
    fields = cell.__dict__
    fields["key"] = key
    fields["type"] = name
    fields["born"] = born
    fields["fate"] = fate
    fields["exit_time"] = exit_time
    fields["exit_y"] = exit_y
    fields["x"] = x
    fields["y"] = y
    fields["area_ratio"] = 1.0
    fields["membrane"] = None
    fields["measures"] = None
    return cell


def _observation(time, cells) -> Observation:
    observation = _new(Observation)
    fields = observation.__dict__
    fields["time"] = time
    fields["cells"] = cells
    return observation


def default_response_time(scenario: Scenario) -> float:
    """The lag of the flow behind the drive: measured mean delays of the FE flow (see the constants)."""
    if scenario.saw.model == "streaming":
        return scenario.saw.spin_up_time + STREAMING_VISCOUS_DELAY
    return JET_RESPONSE_TIME


def area_mean_rule(semi_axes, rings: int = 3, spokes: int = 8):
    """Offsets (m, 2) and weights (m,) of the mean over an ellipse: Gauss-Legendre in r^2, equal angles.

    Exact for polynomials up to degree 2 rings - 1 in r^2 and spokes - 1 in angle (tested against a finer rule).
    """
    nodes, weights = np.polynomial.legendre.leggauss(rings)
    radii = np.sqrt(0.5 * (nodes + 1))                  # r^2 uniform in (0, 1): equal area
    angles = 2 * np.pi * (np.arange(spokes) + 0.5) / spokes
    r, theta = np.meshgrid(radii, angles, indexing="ij")
    offsets = np.column_stack([(semi_axes[0] * r * np.cos(theta)).ravel(), (semi_axes[1] * r * np.sin(theta)).ravel()])
    return offsets, np.repeat(0.5 * weights / spokes, spokes)


@dataclass(frozen=True)
class RomFlows:
    """The IDT-off flow and the modes of the response to the IDT on a uniform grid: point values and
    per-cell-type area means.

    Arrays are (nx, ny, C) (``point``) and (types, nx, ny, C) (``cells``) with channels
    [u_off, v_off, u_on - u_off, v_on - v_off, du_1, dv_1, ..., du_M, dv_M] at the nodes (i dx, j dy): mode k
    has time constant ``lags[k]``; the modes sum to v_on - v_off. ``lags`` None: C = 4, one mode, v_on - v_off,
    lagged by the plant's ``response_time``.
    ``cell_types`` names the types.
    """

    spacing: tuple[float, float]
    size: tuple[float, float]
    point: np.ndarray
    cells: np.ndarray
    cell_types: tuple[str, ...]
    timings: dict
    lags: tuple[float, ...] | None = None
    fit_residual: float | None = None      # the transient fit's largest residual, relative to |v_on - v_off|
    grid: float | None = None              # the spacing asked of ``sample`` (the grid's nodes follow from it)

    @classmethod
    def of(cls, scenario: Scenario, spacing: float = 1e-6, fluid: NavierStokes | None = None,
           transient: bool = True) -> "RomFlows":
        """Solve the two steady flows (``fluid``, default: the scenario's own) and sample them every ``spacing``;
        with ``transient`` (and a Dirichlet SAW model) also the modes of the FE flow's response to the IDT."""
        started = clock.perf_counter()
        fluid = fluid or NavierStokes(scenario)
        off, on = fluid.steady(0.0).velocity, fluid.steady(1.0).velocity
        solved = clock.perf_counter()
        values = np.concatenate([off, on - off])                       # (4, N)
        flows = cls.sample(scenario, fluid, values, spacing, {"steady_flows_s": solved - started})
        return flows.measured_transient(scenario) if transient else flows

    def measured_transient(self, scenario: Scenario) -> "RomFlows":
        """These flows with the modes of the FE flow's measured response to the IDT (``sim.plants.rom_transient``;
        cached through ``sim.fast.store``); unchanged for the ``streaming`` SAW model (its own spin-up lag)."""
        if scenario.saw.model == "streaming" or self.lags is not None or self.grid is None:
            return self
        return self.with_transient(sampled_modes(scenario, self.grid, RomFlows.sample), TRANSIENT_LAGS)

    def with_transient(self, modes: dict, lags) -> "RomFlows":
        """These flows with the single change split into the modes of ``sim.plants.rom_transient.sampled_modes``
        (all but the last; the last is the steady change minus them)."""
        def split(fields, fast):
            if fast.shape[:-1] != fields.shape[:-1]:
                raise ValueError("the transient modes were sampled on another grid than these flows")
            rest = fields[..., 2:4] - fast.reshape(*fast.shape[:-1], -1, 2).sum(axis=-2)
            return np.concatenate([fields[..., :4], fast, rest], axis=-1)
        timings = dict(self.timings, transient_s=float(modes["seconds"]))
        return replace(self, point=split(self.point, modes["point"]), cells=split(self.cells, modes["cells"]),
                       lags=tuple(float(tau) for tau in lags), timings=timings,
                       fit_residual=float(np.max(modes["residual"])))

    def single_lag(self) -> "RomFlows":
        """These flows with their modes summed into one (the blended steady flows)."""
        if self.lags is None:
            return self
        return replace(self, point=self.point[..., :4].copy(), cells=self.cells[..., :4].copy(), lags=None,
                       fit_residual=None)

    @classmethod
    def sample(cls, scenario, fluid, values, spacing, timings) -> "RomFlows":
        started = clock.perf_counter()
        channel = scenario.channel
        x = np.linspace(0.0, channel.length, math.ceil(channel.length / spacing - 1e-9) + 1)
        y = np.linspace(0.0, channel.height, math.ceil(channel.height / spacing - 1e-9) + 1)
        nodes = np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1).reshape(-1, 2)
        locator = PointLocator(fluid.space.cmesh, fluid.space.velocity_basis.element_dofs)

        def at(points):
            return locator.interpolate(values, clip_to_channel(points, channel))

        point = at(nodes).reshape(len(x), len(y), 4)
        cells = np.zeros((len(scenario.cell_types), len(x), len(y), 4))
        for k, cell_type in enumerate(scenario.cell_types):
            for offset, weight in zip(*area_mean_rule(cell_type.semi_axes)):
                cells[k] += weight * at(nodes + offset).reshape(len(x), len(y), 4)
        timings = dict(timings, sampling_s=clock.perf_counter() - started)
        return cls((x[1] - x[0], y[1] - y[0]), (channel.length, channel.height), point, cells,
                   tuple(c.name for c in scenario.cell_types), timings, grid=float(spacing))

    @classmethod
    def uniform(cls, scenario: Scenario, off, on, spacing: float = 2e-6) -> "RomFlows":
        """Constant flows ``off`` and ``on`` (u, v) everywhere: synthetic fields for tests."""
        channel = scenario.channel
        nx, ny = math.ceil(channel.length / spacing) + 1, math.ceil(channel.height / spacing) + 1
        channels = np.array([off[0], off[1], on[0] - off[0], on[1] - off[1]], dtype=float)
        point = np.broadcast_to(channels, (nx, ny, 4)).copy()
        cells = np.broadcast_to(channels, (len(scenario.cell_types), nx, ny, 4)).copy()
        return cls((channel.length / (nx - 1), channel.height / (ny - 1)), (channel.length, channel.height), point,
                   cells, tuple(c.name for c in scenario.cell_types), {})

    def velocity(self, points, level=0.0, cell_type: str | None = None) -> np.ndarray:
        """The gridded flow (n, 2) at ``points`` (n, 2): point values, or a cell type's area means; ``level`` is
        every mode's level (a number: the steady blend at that level) or one per mode."""
        fields = self.point[None] if cell_type is None else self.cells[self.cell_types.index(cell_type)][None]
        params = np.zeros(8)
        params[[kernels.LENGTH, kernels.HEIGHT, kernels.SPACING_X, kernels.SPACING_Y]] = [*self.size, *self.spacing]
        levels = np.broadcast_to(np.asarray(level, dtype=float), (len(self.lags or (0,)),)).copy()
        return np.array([kernels.bilinear(fields, 0, x, y, levels, params) for x, y in np.asarray(points, float)])


def wall_segments(channel: Channel) -> np.ndarray:
    """The channel's walls as axis-aligned segments (x0, y0, x1, y1, inward normal x, y)."""
    length, height = channel.length, channel.height
    rows = [(0.0, 0.0, length, 0.0, 0.0, 1.0), (0.0, height, length, height, 0.0, -1.0)]
    for x, openings, normal in ((0.0, channel.inlets, 1.0), (length, channel.outlets, -1.0)):
        low = 0.0
        for span in sorted(opening.span for opening in openings):
            if span[0] > low:
                rows.append((x, low, x, span[0], normal, 0.0))
            low = span[1]
        if low < height:
            rows.append((x, low, x, height, normal, 0.0))
    return np.array(rows)


def divider_spans(channel: Channel) -> np.ndarray:
    """The dividers (m, 2): the spans (low, high) of wall on x = length between two outlets."""
    spans = sorted(outlet.span for outlet in channel.outlets)
    return np.array([(a[1], b[0]) for a, b in zip(spans, spans[1:]) if b[0] > a[1]], dtype=float).reshape(-1, 2)


class RomPlant:
    """Cells carried through the flow's modes (module docstring) behind the plant contract.

    ``control_period`` is the period of ``step``; each period is ``ceil(control_period / max_substep)``
    midpoint substeps. ``step_until`` groups periods (the closed loop's fast path). Set-up (the two steady
    solves and the sampling, a few seconds at the paper's mesh) happens once, in ``RomFlows.of``.
    """

    model = "rom"      # its name in the registry (sim.plants.registry): what a summary says ran

    def __init__(self, scenario: Scenario, control_period: float | None = None, response_time: float | None = None,
                 flows: RomFlows | None = None, grid_spacing: float = 1e-6, max_substep: float = 20e-6,
                 stall_speed: float = 1e-4, stall_time: float = 1e-3, catch_on_divider: bool = True,
                 window: int | None = WINDOW_CELLS):
        control_period = CONTROL_PERIOD if control_period is None else control_period
        if not control_period > 0 or not max_substep > 0:
            raise ValueError("control_period and max_substep must be positive")
        self.scenario = scenario
        self.control_period = control_period
        self.window = window
        self.response_time = default_response_time(scenario) if response_time is None else response_time
        if not self.response_time >= 0:
            raise ValueError(f"response_time must be >= 0 s (got {self.response_time!r})")
        flows = flows or RomFlows.of(scenario, grid_spacing)
        self.flows = flows.single_lag() if response_time is not None else flows     # a given lag: one mode
        if self.flows.cell_types != tuple(c.name for c in scenario.cell_types):
            raise ValueError("the flows were sampled for other cell types than the scenario's")
        self.lags = self.flows.lags or (self.response_time,)
        self.substeps = max(1, math.ceil(control_period / max_substep - 1e-9))
        step = control_period / self.substeps
        self._lags = np.array([[lag_decay(fraction * step, tau) for fraction in (1.0, 0.5)]
                               + [0.0, 0.0] for tau in self.lags])        # columns 2-3: the kernel's scratch
        channel = scenario.channel
        self._params = np.array([control_period, self.substeps, channel.length, channel.height,
                                 *self.flows.spacing, stall_speed, stall_time])
        self._segments = wall_segments(channel)
        self._dividers = divider_spans(channel) if catch_on_divider else np.zeros((0, 2))
        self._outlets = np.array([outlet.span for outlet in channel.outlets])
        self._outlet_names = {kernels.OUTLET + k: outlet.name for k, outlet in enumerate(channel.outlets)}
        self._fate_names = {**FATES, **self._outlet_names}      # a fate code's name
        types = scenario.cell_types
        self._semi_axes = np.array([c.semi_axes for c in types])
        self._start = np.array([injection_point(scenario, c) for c in types])
        self._area = [c.area for c in types]
        self._brightness = [c.fluorescence for c in types]
        self._names = [c.name for c in types]
        self._lines = (((), ()), _NO_LINES, _NO_LINES)
        started = clock.perf_counter()
        self.reset([])
        self.step(0.0)                      # compiles (or loads) the kernels now: part of the set-up
        self.timings = dict(self.flows.timings, kernels_s=clock.perf_counter() - started)

    # ------------------------------------------------------------------ the contract
    def reset(self, arrivals) -> Observation:
        self._sample, self._types = self._schedule(arrivals)
        n = self._count = len(self._sample)
        self._base = 0                      # the key of the window's first cell (``_slide``)
        self._cell_state(n if self.window is None else min(n, self.window))
        self._log_step = np.zeros(LOG_ROWS, dtype=np.int64)
        self._log_key = np.zeros(LOG_ROWS, dtype=np.int64)
        self._log_positions = np.zeros((LOG_ROWS, 4))
        self._counters = np.zeros(9, dtype=np.int64)
        self._trace_step = np.zeros(TRACE_ROWS, dtype=np.int64)
        self._trace_key = np.zeros(TRACE_ROWS, dtype=np.int64)
        self._trace_positions = np.zeros((TRACE_ROWS, 2))
        self._level = np.zeros(len(self.lags))
        self._unreported, self._reported = 0, set()        # truth_update's position: keys below are all reported
        self._view()
        kernels.inject(self._start, self._kind, self._arrival, self._born, self._position, self._fate,
                       self._counters, 0.0, 0.5 * self.control_period, self._before)
        return self.observe()

    # ------------------------------------------------------------------ the window of cells
    # A long sample slides through a window of ``window`` cells: the kernel sees the per-cell state of the window's
    # cells (local index = key - ``_base``) and the arrivals from its first cell on; cells that have settled and been
    # reported (``truth_update``) are dropped from its start when it is half full of them, so the plant's memory
    # depends on the window, not on the sample's length. The kernel is never run past the last arrival the window
    # holds (``_horizon``), so the cells it steps are those it would step with every cell's state at hand.
    # the per-cell state: (its shape after the cells, dtype, value of a cell not yet injected)
    _STATE = {"_born": ((), float, np.nan), "_position": ((2,), float, np.nan),
              "_fate": ((), np.int64, kernels.WAITING), "_exit_time": ((), float, np.nan),
              "_exit_y": ((), float, np.nan), "_stalled": ((), float, 0.0), "_before": ((2,), float, 0.0),
              "_touched": ((), np.bool_, False)}

    def _cell_state(self, size: int):
        for name, (shape, dtype, fill) in self._STATE.items():
            setattr(self, name, np.full((size, *shape), fill, dtype=dtype))

    def _view(self):
        """The kernel's arguments for the window at ``_base``."""
        end = self._base + len(self._born)
        times, kinds = self._sample.arrays(self._base, end + 1)       # and the first arrival beyond the window
        self._arrival = times[:end - self._base]
        self._kind = self._types[kinds[:end - self._base]].astype(np.int64)
        self._beyond = float(times[-1]) if end < self._count else math.inf
        self._arrays = (self.flows.cells, self._params, self._segments, self._dividers, self._outlets,
                        self._semi_axes, self._start, self._kind, self._arrival, self._born, self._position,
                        self._fate, self._exit_time, self._exit_y, self._stalled, self._counters, self._level,
                        self._lags, self._before, self._touched, self._log_step, self._log_key,
                        self._log_positions, self._trace_step, self._trace_key,
                        self._trace_positions)   # the kernel's arguments, in order

    def _horizon(self) -> float:
        """How far the kernel may run: two periods before the first arrival beyond the window (inf: none)."""
        return self._beyond - 2 * self.control_period

    def _make_room(self):
        """Slide the window when half of it is settled and reported, and whenever it holds too few arrivals for the
        next periods (growing it if no cell can be dropped): the kernel then runs at least two periods safely."""
        while self._horizon() != math.inf:
            counters, size = self._counters, len(self._born)
            drop = min(int(counters[kernels.FIRST]), self._unreported - self._base)
            cramped = self._horizon() <= self.time + 2 * self.control_period
            if drop >= size // 2 or (cramped and drop > 0):
                self._slide(drop)
            elif cramped:                   # every cell of the window still in the channel or unreported
                grown = {name: getattr(self, name) for name in self._STATE}
                self._cell_state(2 * size)
                for name, state in grown.items():
                    getattr(self, name)[:size] = state
                self._view()
            else:
                return

    def _slide(self, drop: int):
        """Drop the window's first ``drop`` cells (settled and reported)."""
        for name, (_, _, fill) in self._STATE.items():
            state = getattr(self, name)
            state[:-drop] = state[drop:].copy()
            state[-drop:] = fill
        counters = self._counters
        counters[kernels.NEXT] -= drop
        counters[kernels.FIRST] -= drop
        self._trace_key[:int(counters[kernels.TRACED])] -= drop      # rows not yet taken keep their keys
        self._base += drop
        self._view()

    def _schedule(self, arrivals):
        """The sample, read a stretch at a time (``arrays(start, stop)``: times and indices into its ``names``), and
        the plant's type index of each of its names. A sample drawn at the inlet (``sim.model.arrivals.Drawn``: in
        time order, drawn again as it is read) and one held as ``Cells`` in time order without ties are read as they
        are; (time, name) pairs are sorted into ``Cells`` first. Unknown names fail here, as in the other plants."""
        index = {name: k for k, name in enumerate(self._names)}
        if not (isinstance(arrivals, Drawn) or isinstance(arrivals, Cells) and np.all(np.diff(arrivals.times) > 0)):
            items = sorted(arrivals)
            arrivals = Cells([t for t, _ in items], [index.get(name, -1) for _, name in items], self._names)
            names = {name for _, name in items}
        else:
            names = arrivals.names
        for name in names:
            self.scenario.cell_type(name)
        return arrivals, np.array([index.get(name, -1) for name in arrivals.names], dtype=_KIND)

    def step(self, actuation: float) -> Observation:
        """One control period at the drive ``actuation``."""
        self._make_room()
        self._advance(actuation, math.inf, 1)
        return self.observe()

    def step_until(self, actuation: float, until: float, stop_lines=(), record_lines=(), max_periods: int = 10**7):
        """Whole control periods at ``actuation`` until time ``until``, every cell settled, or a stop line.

        Returns (periods, seen). It stops after the period in which a cell in the channel crosses a line
        x = w of ``stop_lines`` forwards. ``seen`` lists, in time order, partial observations of the cells
        that crossed a stop or a record line: for each period in which some did, those cells one period
        before and at its end. A detector that reacts only to cells crossing these lines, fed ``seen``, does
        what it would do if fed every period's observation (seeing a cell twice at one time changes nothing).
        """
        lines = (stop_lines, record_lines)
        if lines != self._lines[0]:
            self._lines = (lines, *(np.asarray(group, dtype=float).reshape(-1) for group in lines))
        periods, seen = 0, []
        while True:
            self._make_room()
            horizon = self._horizon()
            done, reason = self._advance(actuation, min(until, horizon), max_periods - periods, *self._lines[1:])
            if done == 0 and reason == kernels.LIMIT and max_periods > periods and not self.done:
                # the log or the trace has no room for one more period's rows (a crowd of cells; a trace not taken)
                self._grow()
                continue
            periods += done
            seen += self._crossings()
            # the window's horizon reached (or its cells all settled) before ``until``: slide it and go on
            if reason in (kernels.UNTIL, kernels.DONE) and horizon < until and not self.done and \
                    self.time < until and periods < max_periods:
                continue
            return periods, seen

    # ------------------------------------------------------------------ the trace (recordings)
    def trace(self, interval: float) -> int:
        """Trace the cells in the channel every ``interval`` of simulated time from now on (rounded up to whole
        control periods, at period indices that are multiples of it): ``take_trace`` hands the rows over. Returns
        the cadence in periods."""
        every = max(1, math.ceil(interval / self.control_period - 1e-9))
        self._counters[kernels.TRACE_EVERY] = every         # until the next reset
        return every

    def take_trace(self):
        """(period index, key, (x, y)) rows traced since the last call, as arrays (copies), in time order."""
        rows = self._counters.item(kernels.TRACED)
        self._counters[kernels.TRACED] = 0
        return (self._trace_step[:rows].copy(), self._trace_key[:rows] + self._base,
                self._trace_positions[:rows].copy())

    def _grow(self):
        """Twice the room in the crossing log and the trace (their rows are handed over after each call)."""
        log, trace = 2 * len(self._log_key), 2 * len(self._trace_key)
        self._log_step, self._log_key = np.zeros(log, dtype=np.int64), np.zeros(log, dtype=np.int64)
        self._log_positions = np.zeros((log, 4))
        traced = int(self._counters[kernels.TRACED])          # rows not yet taken are kept
        self._trace_step = np.concatenate([self._trace_step[:traced], np.zeros(trace - traced, dtype=np.int64)])
        self._trace_key = np.concatenate([self._trace_key[:traced], np.zeros(trace - traced, dtype=np.int64)])
        self._trace_positions = np.concatenate([self._trace_positions[:traced], np.zeros((trace - traced, 2))])
        self._arrays = (*self._arrays[:-6], self._log_step, self._log_key, self._log_positions, self._trace_step,
                        self._trace_key, self._trace_positions)

    def _crossings(self) -> list[Observation]:
        """The partial observations of the cells whose crossings the last ``step_until`` logged."""
        logged = self._counters.item(kernels.LOGGED)
        if not logged:
            return []
        seen = []                                   # (period, key, x, y): before and after each logged crossing
        for step, key, (x0, y0, x1, y1) in zip(self._log_step[:logged].tolist(), self._log_key[:logged].tolist(),
                                               self._log_positions[:logged].tolist()):
            if x0 > -math.inf:                      # not injected in that period
                seen.append((step - 1, key, x0, y0))
            seen.append((step, key, x1, y1))
        seen.sort()
        snapshots, views, area, brightness, kind, base = [], [], self._area, self._brightness, self._kind, self._base
        for n, (step, key, x, y) in enumerate(seen):
            if not views or views[-1].key != key + base:    # a cell logged twice in one period is seen once
                views.append(_view(key + base, x, y, area[kind[key]], brightness[kind[key]]))
            if n + 1 == len(seen) or seen[n + 1][0] != step:
                snapshots.append(_observation(step * self.control_period, tuple(views)))
                views = []
        return snapshots

    def _advance(self, actuation, until, max_periods, stop_lines=_NO_LINES, record_lines=_NO_LINES):
        return kernels.advance(*self._arrays, float(actuation), float(until), int(max_periods), stop_lines,
                               record_lines)

    @property
    def time(self) -> float:
        return self._counters.item(kernels.STEP) * self.control_period     # item: a Python int

    @property
    def done(self) -> bool:
        counters = self._counters
        return self._base + counters.item(kernels.NEXT) == self._count and counters.item(kernels.ACTIVE) == 0

    def observe(self) -> Observation:
        step, _, first, *_ = counters = self._counters.tolist()
        last = counters[kernels.NEXT]
        area, brightness, base = self._area, self._brightness, self._base
        views = tuple([_view(key + base, x, y, area[kind], brightness[kind])
                       for key, (x, y), fate, kind in zip(range(first, last), self._position[first:last].tolist(),
                                                          self._fate[first:last].tolist(),
                                                          self._kind[first:last].tolist())
                       if fate == kernels.IN_CHANNEL])
        return _observation(step * self.control_period, views)

    def truth(self) -> Truth:
        """Ground truth of every injected cell the window holds (all of them when the sample fits in it; its cost
        grows with the cells run: call it at the end)."""
        cells = tuple(self._record(self._base + i) for i in range(int(self._counters[kernels.NEXT])))
        return Truth(self.time, cells, self._count - self._base - int(self._counters[kernels.NEXT]))

    def truth_update(self) -> Truth:
        """Ground truth of the cells in the channel and of those that settled since the previous call (each
        settled cell once); its cost depends on the cells in the channel, not on how many have passed."""
        base = self._base
        start, upto = self._unreported, base + self._counters.item(kernels.NEXT)
        cells, reported, names, fates = [], self._reported, self._names, self._fate_names
        window = slice(start - base, upto - base)   # read in bulk: one conversion per array, not per value
        for i, code, kind, born, exit_time, exit_y, (x, y) in zip(
                range(start, upto), self._fate[window].tolist(), self._kind[window].tolist(),
                self._born[window].tolist(), self._exit_time[window].tolist(), self._exit_y[window].tolist(),
                self._position[window].tolist()):
            if i in reported:
                continue
            fate = fates[code]
            if fate != "in_channel":
                reported.add(i)
            cells.append(_truth(i, names[kind], born, fate, exit_time, exit_y, x, y))
        while self._unreported < upto and self._unreported in reported:
            reported.discard(self._unreported)
            self._unreported += 1
        return Truth(self.time, tuple(cells), self._count - upto)

    def _record(self, key: int) -> CellTruth:
        i = key - self._base
        code = int(self._fate[i])
        fate = self._outlet_names.get(code) or FATES[code]
        return CellTruth(key, self._names[self._kind[i]], float(self._born[i]), fate, float(self._exit_time[i]),
                         float(self._exit_y[i]), float(self._position[i, 0]), float(self._position[i, 1]), 1.0)

    def adopt(self, time_s: float, level: float, cells: dict, injected: int):
        """Continue from another plant's state (the ``auto`` plant's hand-over): at ``time_s`` (a whole number
        of control periods) and drive level ``level``, the first ``injected`` arrivals injected, ``cells``
        {key: (x, y, born)} in the channel; the other injected cells count as settled elsewhere (``lost``
        here: the caller keeps their records). The plant must hold every cell (``window`` None)."""
        if len(self._born) < self._count:
            raise ValueError("adopt needs a rom plant that holds every cell of its sample (window=None)")
        counters = self._counters
        counters[kernels.STEP] = round(time_s / self.control_period)
        counters[kernels.NEXT] = injected
        counters[kernels.ACTIVE] = len(cells)
        counters[kernels.FIRST] = min(cells, default=injected)
        self._fate[:injected] = kernels.LOST
        for key, (x, y, born) in cells.items():
            self._fate[key] = kernels.IN_CHANNEL
            self._position[key] = (x, y)
            self._before[key] = (x, y)
            self._born[key] = born
            self._stalled[key] = 0.0
        self._unreported, self._reported = 0, set()
        self._level[:] = level              # every mode at the hand-over's level (the blended steady flow)

    def diagnostics(self) -> dict:
        """Figures for logging: substep, physics steps so far, drive level, wall contacts (cell-substeps)."""
        levels = self._level.tolist()
        return {"dt": self.control_period / self.substeps, "physics_steps": int(self._counters[kernels.PHYSICS_STEPS]),
                "level": sum(levels) / len(levels), "levels": levels, "response_time": self.response_time,
                "wall_contacts": int(self._counters[kernels.CONTACTS]), "health": "ok"}
