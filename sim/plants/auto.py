"""The plant ``auto``: the cheapest model whose error stays within tolerance, chosen per time window.

The ladder measured by ``vcyto tradeoff`` (docs/results.md, "Speed against accuracy") says where the reduced model
``rom`` is good enough: an isolated RBC with the IDT off and an isolated melanoma with the IDT on leave by
the FE-IB outlet with a mean centroid path error of 0.3-4 um; two cells close together are not (their
hydrodynamic interaction, absent from ``rom``, moves them by 10-50 um). A large stiff cell (a melanoma)
interacts further than that: ``rom`` carries an isolated melanoma 6 % faster than ``feib`` through
x = 20-100 um (2D confinement of a 16 um rigid body, absent from the undisturbed flow ``rom`` averages), so in
a stream its detection and its pulse come tens of us early and the cells behind it drift; on the 100-cell
streams that flips RBCs trailing a sorted melanoma (docs/results.md). The rule, evaluated every control period on the
cells in the channel:

- ``feib`` while a stiff cell shares the channel with any other cell (stiff: capillary number
  Ca = eta U_saw / kappa_e < ``stiff_capillary``, default 100; U_saw = the largest change of the steady flow
  the IDT makes, 0.66 m/s: Ca = 14 for a melanoma, 658 for an RBC);
- ``feib`` while two cells are closer than ``coupling`` x (r_i + r_j) (r = a cell type's largest semi-axis;
  default coupling 3: 35 um for a melanoma and an RBC; chosen with ``vcyto tradeoff --coupling``, docs/results.md);
- back to ``rom`` once neither has held, with every pair further apart than ``release`` x that distance
  (hysteresis, default 1.25), for ``dwell`` (default 50 us);
- ``rom`` otherwise: a cell alone, and soft cells further apart. ``stiff_capillary`` = 0 turns the stiff-cell
  rule off (the rule of the earlier tables in docs/results.md).

Known gap (docs/results.md): a soft cell (an RBC) reaching the SAW window alone as a pulse ends is carried poorly by
``rom`` (up to 18 um), and no rule here catches it; where such a cell exits within a micrometre of an outlet's
edge (the 0.565 ms pair scene) ``auto`` and the window model itself can disagree with the reference's outlet.

The window model is ``feib`` on a mesh of size ``window_mesh_h`` (default ``WINDOW_MESH_H`` = 6.67 um, twice the
paper's h, or the scenario's own h if coarser): the cheapest FE-IB level the tradeoff table puts within
tolerance on every scene (close pair: 0.95 um mean path error against the paper's mesh, at a quarter of the
cost per step). A pair's interaction is a flow on the scale of the cells (16 um for a melanoma), which that
mesh resolves; an RBC (7.5 um) is thinner than two of its cells, so inside a window it moves like a finite
tracer and its shape is not resolved (deformation is not carried out of a window anyway). The ``rom`` flows
come from the scenario's own mesh. ``window_mesh_h`` = the scenario's h gives windows at full resolution.

Hand-overs: rom -> feib builds the FE state from the rom state: the flow is the blend (1 - s) v_off + s v_on of
the steady flows at the drive level s (Navier-Stokes at Re ~ 1-3 is nearly linear in the boundary data), and
each cell gets its undeformed membrane at its centroid; feib -> rom hands the centroids and the drive level
back. Deformation is not carried from one feib window to the next. Every switch is logged (time, model,
reason) in ``switches`` and the current model and reason are in ``diagnostics()`` (so in recordings).
"""

from __future__ import annotations

import math

import numpy as np

from ..method.feib import ImmersedBoundary, State
from ..method.fluid import Flow, NavierStokes
from ..model.drive import lagged
from ..model.scenario import Scenario
from .feib import FeibPlant, Observation, Truth
from .rom import RomFlows, RomPlant

WINDOW_MESH_H = 20e-6 / 3       # m: the coarsest FE-IB mesh within tolerance on the tradeoff scenes
STIFF_CAPILLARY = 100.0         # cells with eta U_saw / kappa_e below this interact with every other cell


class AutoPlant:
    model = "auto"      # its name in the registry (sim.plants.registry): what a summary says ran

    def __init__(self, scenario: Scenario, control_period: float | None = None, coupling: float = 3.0,
                 release: float = 1.25, dwell: float = 50e-6, grid_spacing: float = 1e-6,
                 window_mesh_h: float | None = None, stiff_capillary: float = STIFF_CAPILLARY):
        self.scenario = scenario
        self.control_period = scenario.numerics.dt
        if control_period is not None and abs(control_period - self.control_period) > 1e-12:
            raise ValueError(f"the auto plant's control period is the time step dt = {self.control_period * 1e6:g} us")
        self.coupling, self.release, self.dwell = coupling, release, dwell
        own_h = scenario.numerics.mesh_h
        self.window_mesh_h = max(own_h, WINDOW_MESH_H) if window_mesh_h is None else window_mesh_h
        if not (math.isfinite(self.window_mesh_h) and self.window_mesh_h > 0):
            raise ValueError(f"window_mesh_h must be a positive length in m (got {window_mesh_h!r})")
        fine = NavierStokes(scenario)
        same = math.isclose(self.window_mesh_h, own_h, rel_tol=1e-9)
        window = scenario if same else scenario.with_numerics(mesh_h=self.window_mesh_h)
        self.feib = FeibPlant(window, plant=ImmersedBoundary(window, fine if same else None))
        self.feib.warn_under_resolved = False     # windows: validated as tracers (docstring), not a user's mesh
        fluid = self.feib.ib.fluid
        self._steady = (fluid.steady(0.0), fluid.steady(1.0))
        rom_steady = self._steady if same else (fine.steady(0.0), fine.steady(1.0))
        off, on = (flow.velocity for flow in rom_steady)
        flows = RomFlows.sample(scenario, fine, np.concatenate([off, on - off]), grid_spacing, {})
        flows = flows.measured_transient(scenario)          # rom's measured transient modes, as rom's own
        self.rom = RomPlant(scenario, control_period=self.control_period, flows=flows, window=None)
        self._radius = {c.name: max(c.semi_axes) for c in scenario.cell_types}
        if not (stiff_capillary >= 0):
            raise ValueError(f"stiff_capillary must be >= 0 (got {stiff_capillary!r})")
        self.stiff_capillary = stiff_capillary
        saw_speed = float(np.max(np.hypot(*(on - off))))
        self.capillary = {c.name: scenario.fluid.viscosity * saw_speed / c.kappa_e for c in scenario.cell_types}
        self.reset([])

    # ------------------------------------------------------------------ the contract
    def reset(self, arrivals) -> Observation:
        self.arrivals = sorted(arrivals)
        self._types = [name for _, name in self.arrivals]
        self.rom.reset(self.arrivals)
        self.feib.reset(self.arrivals)
        self.model, self.reason, self.level, self._apart_since = "rom", "start: no cells close together", 0.0, None
        self.switches = [(0.0, "rom", self.reason)]
        self.settled = {}
        self.feib_steps = self.steps = 0
        self._observation = self.rom.observe()
        return self._observation

    def step(self, actuation: float) -> Observation:
        dt = self.control_period
        self.level = lagged(self.level, actuation, dt, self.rom.response_time)
        active = self.rom if self.model == "rom" else self.feib
        self._observation = active.step(actuation)
        self.steps += 1
        self.feib_steps += self.model == "feib"
        self._choose()
        return self._observation

    def _closest_pair(self, observation):
        worst, pair = math.inf, None
        cells = observation.cells
        for i in range(len(cells)):
            for j in range(i + 1, len(cells)):
                a, b = cells[i], cells[j]
                reach = self._radius[self._types[a.key]] + self._radius[self._types[b.key]]
                ratio = math.hypot(a.x - b.x, a.y - b.y) / reach
                if ratio < worst:
                    worst, pair = ratio, (a.key, b.key)
        return worst, pair

    def _stiff_company(self, observation):
        """A stiff cell and another cell in the channel with it (keys), or None."""
        cells = observation.cells
        if len(cells) > 1:
            for cell in cells:
                if self.capillary[self._types[cell.key]] < self.stiff_capillary:
                    return cell.key, next(other.key for other in cells if other.key != cell.key)
        return None

    def _choose(self):
        ratio, pair = self._closest_pair(self._observation)
        stiff = self._stiff_company(self._observation)
        now = self._observation.time
        if self.model == "rom" and (stiff or ratio < self.coupling):
            if stiff:
                name = self._types[stiff[0]]
                reason = (f"cell {stiff[0]} ({name}, Ca = {self.capillary[name]:.3g} < {self.stiff_capillary:g}) "
                          f"shares the channel with cell {stiff[1]}")
            else:
                reason = f"cells {pair[0]} and {pair[1]} within {ratio:.2f} x (r1 + r2) < {self.coupling:g}"
            self._to_feib(reason)
        elif self.model == "feib":
            if stiff or ratio < self.coupling * self.release:
                self._apart_since = None
            elif self._apart_since is None:
                self._apart_since = now
            elif now - self._apart_since >= self.dwell - 1e-12:
                self._to_rom(f"no stiff cell with company, no two cells within {self.coupling * self.release:g} "
                             f"x (r1 + r2), for {self.dwell * 1e6:g} us")

    def _keep_settled(self, truth: Truth):
        for cell in truth.cells:
            if cell.fate != "in_channel" and cell.key not in self.settled:
                self.settled[cell.key] = cell

    def _to_feib(self, reason: str):
        truth = self.rom.truth()
        self._keep_settled(truth)
        off, on = self._steady
        s = self.level
        flow = Flow(truth.time, (1 - s) * off.velocity + s * on.velocity, (1 - s) * off.pressure + s * on.pressure,
                    streaming_level=s)
        ib = self.feib.ib
        cells = tuple(ib.new_cell(self.scenario.cell_type(c.type), c.key, c.born, centre=(c.x, c.y), warn=False)
                      for c in truth.cells if c.fate == "in_channel")
        self.feib.adopt(State(flow, cells, round(truth.time / self.control_period)), injected=len(truth.cells))
        self._switch("feib", reason, truth.time)

    def _to_rom(self, reason: str):
        truth = self.feib.truth()
        self._keep_settled(truth)
        inside = {c.key: (c.x, c.y, c.born) for c in truth.cells if c.fate == "in_channel"}
        self.rom.adopt(truth.time, self.level, inside, injected=len(self.arrivals) - truth.waiting)
        self._switch("rom", reason, truth.time)

    def _switch(self, model: str, reason: str, time_s: float):
        self.model, self.reason, self._apart_since = model, reason, None
        self.switches.append((time_s, model, reason))

    @property
    def done(self) -> bool:
        return (self.rom if self.model == "rom" else self.feib).done

    def observe(self) -> Observation:
        return self._observation

    def truth(self) -> Truth:
        active = (self.rom if self.model == "rom" else self.feib).truth()
        self._keep_settled(active)
        current = {c.key: c for c in active.cells if c.fate == "in_channel"}
        cells = tuple(self.settled.get(key) or current[key] for key in sorted(set(self.settled) | set(current)))
        return Truth(active.time, cells, active.waiting)

    def diagnostics(self) -> dict:
        return {"dt": self.control_period, "model": self.model, "reason": self.reason,
                "window_mesh_h": self.window_mesh_h, "stiff_capillary": self.stiff_capillary,
                "feib_fraction": self.feib_steps / max(self.steps, 1), "switches": len(self.switches) - 1,
                "health": "ok"}
