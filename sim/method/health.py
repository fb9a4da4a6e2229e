"""Health checks of the FE-IB state, run every step: a blow-up is stopped and explained, never recorded.

Checks per cell in the channel: finite positions; the membrane not torn apart (its length at most
``numerics.max_stretch`` times its resting length: the paper's Remark 2.4, an inflow too fast for the
membrane); no self-intersection of the membrane polygon; enclosed area within ``numerics.max_area_change``
of the initial area (the paper's method leaks area, see docs/numerics.md; the default 75 % lets the paper's
scenarios run and stops a collapse or an explosion); membrane points inside the channel (or past
x = length through an outlet). A cell that left the channel in this step is checked for finite positions
and tearing too, so a membrane that explodes through the outlet is not counted as an outcome.

Which hint a failure carries depends on the membrane's explicit time step ``membrane_time_step``, about
eta dq / kappa_e (tension) or eta dq^3 / kappa_b (bending), dq the reference spacing of its points (docs/results.md,
"Stability"): a step beyond a quarter of it may be the cause, and the hint is a smaller dt; a step far
below it is not, and the hint names what is (the flow folding or tearing the membrane). The smaller dt it
suggests is the cell's limit by the stability law fitted to measured limits (``sim.method.steplimit``), or a quarter of
dt if dt is already below that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fast import kernels
from ..model.scenario import UM, CellType, Scenario
from .fluid import NumericalBlowUp
from .membrane import Membrane
from .steplimit import limit_of


def paper_bound(cell_type: CellType, scenario: Scenario) -> float:
    """The right-hand side of the paper's (33) times h, with C_cell = 1, on the initial shape
    (``sim.method.stability``): it shows the paper's scaling (like h), not a limit (``sim.method.steplimit`` has the
    measured one)."""
    spacing = scenario.numerics.membrane_spacing * scenario.numerics.mesh_h
    membrane = Membrane.of(cell_type, (0.0, 0.0), spacing)
    first = np.linalg.norm(membrane.evaluate(4, derivative=1), axis=1).max()
    third = np.linalg.norm(membrane.evaluate(4, derivative=3), axis=1).max()
    stiffness = cell_type.kappa_e * first + cell_type.kappa_b * third
    return scenario.fluid.viscosity * scenario.numerics.mesh_h / (8 * stiffness)


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
    max_stretch: float = 20.0
    viscosity: float = 6.0e-3
    scenario: Scenario | None = None

    @classmethod
    def of(cls, scenario: Scenario) -> "HealthLimits":
        channel = scenario.channel
        return cls(channel.length, channel.height, tuple(o.span for o in channel.outlets),
                   scenario.numerics.max_area_change, scenario.numerics.dt, 1e-3 * scenario.numerics.mesh_h,
                   scenario.numerics.max_stretch, scenario.fluid.viscosity, scenario)

    def stable_dt(self, cell_type: CellType | None) -> float | None:
        """The cell's largest stable dt by the stability law (``sim.method.steplimit``) in this scenario (None without a
        cell type or scenario)."""
        if cell_type is None or self.scenario is None:
            return None
        return limit_of(cell_type, self.scenario)

    def suggested_dt(self, cell_type: CellType | None = None) -> float:
        """A smaller dt to try: the cell's stable dt (``stable_dt``) when dt is above it, else dt / 4."""
        stable = self.stable_dt(cell_type)
        return stable if stable is not None and self.dt > stable * (1 + 1e-9) else self.dt / 4

    def dt_hint(self, cell_type: CellType | None = None) -> str:
        suggested = self.suggested_dt(cell_type)
        advice = f"try dt = {_duration(suggested)}"
        if cell_type is not None and suggested == self.stable_dt(cell_type):
            advice += f" (the limit of a {cell_type.name} on this mesh by the stability law fitted to measured " \
                      "limits; `vcyto stability` measures it)"
        return (f"the time step dt = {_duration(self.dt)} is probably beyond this cell's stability limit: {advice}")

    def dt_is_suspect(self, membrane) -> bool:
        """Whether dt is close to or beyond the membrane's explicit limit (within a factor 4 of it)."""
        return self.dt > membrane_time_step(membrane, self.viscosity) / 4

    def fold_hint(self, membrane) -> str:
        """The hint for a fold when dt is not the suspect: the flow folded the membrane."""
        if self.dt_is_suspect(membrane):
            return self.dt_hint(membrane.cell_type) + ", or use more membrane points (numerics.membrane_spacing)"
        return (f"dt = {self.dt * 1e6:.4g} us is far below this membrane's explicit limit (about "
                f"{membrane_time_step(membrane, self.viscosity) * 1e6:.3g} us), so it is not a time-step instability: "
                "the flow folded the membrane (a filament thinner than the mesh, or a cell pressed against a wall or "
                "held at a corner); use a finer mesh (numerics.mesh_h) or slower inflow")


def _duration(seconds: float) -> str:
    return f"{seconds * 1e3:.4g} ms" if seconds >= 1e-3 else f"{seconds * 1e6:.4g} us"


def under_resolved(cell_type, mesh_h: float) -> str | None:
    """Why a cell of ``cell_type`` is under-resolved on a mesh of size ``mesh_h`` (diameter below two mesh
    cells), or None. Such a cell still runs: it moves like a tracer (its outlet agrees with a fine mesh's,
    docs/results.md, "Stability at the extremes"), but its deformation and area are not resolved."""
    if cell_type.diameter >= 2 * mesh_h * (1 - 1e-9):
        return None
    return (f"{cell_type.name} is resolved by fewer than two mesh cells (diameter {cell_type.diameter / UM:.3g} um, "
            f"h = {mesh_h / UM:.3g} um): it moves like a tracer and its shape is not resolved; for its shape use "
            f"numerics.mesh_h <= {cell_type.diameter / 2 / UM:.3g} um")


def membrane_time_step(membrane, viscosity: float) -> float:
    """The explicit membrane's time scale eta * min(dq / kappa_e, dq^3 / kappa_b) (docs/results.md, "Stability")."""
    kind, dq = membrane.cell_type, membrane.dq
    tension = viscosity * dq / kind.kappa_e
    return min(tension, viscosity * dq**3 / kind.kappa_b) if kind.kappa_b > 0 else tension


def stretch(membrane) -> float:
    """The membrane's length over its resting length L (the mean of |X_q|)."""
    return membrane.perimeter() / membrane.reference_length


def check_cells(cells, limits: HealthLimits, step: int, time: float):
    """Raise ``HealthError`` for the first cell in the channel that fails a check."""
    for cell in cells:
        if cell.in_channel:
            check_cell(cell, limits, step, time)
        else:
            check_leaving_cell(cell, limits, step, time)


def check_leaving_cell(cell, limits: HealthLimits, step: int, time: float):
    """A cell that left in this step: its exit counts only if the membrane is whole."""
    if not np.all(np.isfinite(cell.membrane.points)):
        raise HealthError(cell.id, step, time, "non-finite membrane positions", limits.dt_hint(cell.membrane.cell_type))
    _check_torn(cell, limits, step, time)


def _check_torn(cell, limits: HealthLimits, step: int, time: float):
    ratio = stretch(cell.membrane)
    if ratio > limits.max_stretch:
        cell_type = cell.membrane.cell_type
        hint = ("the flow is too fast for this membrane (the paper's Remark 2.4: an inflow violating its condition "
                "(16) tears membranes apart): lower the inlet speeds (channel.inlets.N.v_hat)")
        stable = limits.stable_dt(cell_type)
        if stable is not None and limits.dt > stable:       # far too large: the likelier cause first
            hint = limits.dt_hint(cell_type) + "; if it tears at that dt too, " + hint
        elif limits.dt_is_suspect(cell.membrane):
            hint += "; dt is also near this membrane's explicit limit: " + limits.dt_hint(cell_type)
        raise HealthError(cell.id, step, time,
                          f"the membrane is torn apart: stretched to {ratio:.1f} times its resting length "
                          f"(numerics.max_stretch = {limits.max_stretch:g})", hint)


def check_cell(cell, limits: HealthLimits, step: int, time: float):
    points = cell.membrane.points
    if not np.all(np.isfinite(points)):
        raise HealthError(cell.id, step, time, "non-finite membrane positions", limits.dt_hint(cell.membrane.cell_type))
    _check_torn(cell, limits, step, time)
    i, j = kernels.first_self_intersection(np.ascontiguousarray(points))
    if i >= 0:
        raise HealthError(cell.id, step, time, f"the membrane intersects itself (edges {i} and {j})",
                          limits.fold_hint(cell.membrane))
    ratio = cell.membrane.area() / cell.membrane.initial_area
    if abs(ratio - 1) > limits.max_area_change:
        raise HealthError(cell.id, step, time, f"enclosed area is {100 * ratio:.0f} % of the initial area",
                          limits.dt_hint(cell.membrane.cell_type)
                          + " (or raise numerics.max_area_change if the loss is expected)")
    outside = _outside_channel(points, limits)
    if outside.any():
        worst = points[np.argmax(outside)]
        raise HealthError(cell.id, step, time,
                          f"membrane point at ({worst[0] / UM:.2f}, {worst[1] / UM:.2f}) um is outside the channel",
                          "the cell was pushed through a wall: " + limits.dt_hint(cell.membrane.cell_type))


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
