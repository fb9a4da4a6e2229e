"""Would a second-order membrane update let `--tolerance 1um` take larger steps? The measurement behind
docs/numerics.md, "Time steps chosen by a tolerance".

    python examples/membrane_update_study.py                   # Scenario II (melanoma, IDT on), h = 6.67 um
    python examples/membrane_update_study.py 6.67 RBC 0         # Scenario I (RBC, IDT off)

Arguments: mesh h (um), cell type, IDT drive, and the fixed time steps (us, comma-separated, finest first;
default 1.25,2.5,5,10,20). Each step runs with FE-IB's first-order update X' = X + dt v^{m+1}(X) (the
paper's) and with the trapezoidal one the tolerance's error estimate compares it with,
X' = X + dt/2 (v^m(X) + v^{m+1}(X + dt v^{m+1}(X))); every path is compared with the trapezoidal one at
the finest step (centroid distance at the run's own times, the reference interpolated there, as in
`vcyto tradeoff`). Prints; writes nothing. About 30 s at 6.67 um.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from sim.method.feib import ImmersedBoundary, State, settle
from sim.method.health import NumericalBlowUp, check_cells
from sim.method.openloop import stepping, with_cells
from sim.model.scenario import UM, Scenario


class TrapezoidalUpdate(ImmersedBoundary):
    """FE-IB with the membrane moved by the trapezoidal rule (the fluid step is unchanged)."""

    def step(self, state, actuation=0.0, dt=None, fluid=None, ahead=False):
        fluid = fluid or self.fluid
        dt = fluid.scenario.numerics.dt if dt is None else dt
        active = [cell for cell in state.cells if cell.in_channel]
        load, located = self.membrane_load(active)
        flow = fluid.step(state.flow, actuation, load if active else None)
        moved = {}
        for cell, (elements, reference) in zip(active, located):
            old = self.locator.interpolate_located(state.flow.velocity, elements, reference)
            new = self.locator.interpolate_located(flow.velocity, elements, reference)
            predicted = self.locator.locate(self._inside(cell.membrane.points + dt * new))
            there = self.locator.interpolate_located(flow.velocity, *predicted)
            moved[cell.id] = settle(cell, cell.membrane.points + 0.5 * dt * (old + there), flow.time,
                                    self.scenario, dt)
        check_cells([moved[cell.id] for cell in active], self.limits, state.step + 1, flow.time)
        return State(flow, tuple(moved.get(cell.id, cell) for cell in state.cells), state.step + 1)


def path(plant_class, scenario, cell_type, drive):
    plant = plant_class(scenario)
    state = with_cells(plant, plant.start(drive).flow, [(scenario.cell_type(cell_type), None)])
    times, centroids = [0.0], [state.cells[0].membrane.centroid()]
    for state in stepping(plant.step, state, drive, until=20e-3):
        times.append(state.time)
        centroids.append(state.cells[0].membrane.centroid())
    return np.array(times), np.array(centroids), state.cells[0].fate


def distance(run, reference):
    """Max and mean centroid distance (um) at the run's times up to the earlier end."""
    (times, centroids, _), (ref_times, ref_centroids, _) = run, reference
    keep = times <= min(times[-1], ref_times[-1])
    there = np.column_stack([np.interp(times[keep], ref_times, ref_centroids[:, k]) for k in range(2)])
    gaps = np.hypot(*(centroids[keep] - there).T) / UM
    return gaps.max(), gaps.mean()


def main(arguments):
    mesh_h = float(arguments[0]) * UM if arguments else 20 * UM / 3
    cell_type = arguments[1] if len(arguments) > 1 else "melanoma"
    drive = float(arguments[2]) if len(arguments) > 2 else 1.0
    steps = [float(dt) * 1e-6 for dt in (arguments[3] if len(arguments) > 3 else "1.25,2.5,5,10,20").split(",")]
    runs = {}
    for name, plant_class in (("first order", ImmersedBoundary), ("trapezoidal", TrapezoidalUpdate)):
        for dt in steps:
            started = time.perf_counter()
            try:
                runs[name, dt] = path(plant_class, Scenario().with_numerics(mesh_h=mesh_h, dt=dt), cell_type, drive)
                print(f"{name:12s} dt {dt * 1e6:5g} us: {runs[name, dt][2]} outlet "
                      f"({time.perf_counter() - started:.1f} s)", flush=True)
            except NumericalBlowUp as error:
                print(f"{name:12s} dt {dt * 1e6:5g} us: unstable: {str(error)[:110]}", flush=True)
    reference = runs["trapezoidal", steps[0]]
    print(f"\ncentroid path distance to the trapezoidal update at dt = {steps[0] * 1e6:g} us (max / mean, um):")
    for dt in steps:
        cells = [f"{'%.2f / %.2f' % distance(runs[name, dt], reference) if (name, dt) in runs else 'unstable':>13s}"
                 for name in ("first order", "trapezoidal")]
        print(f"  dt {dt * 1e6:5g} us   first order {cells[0]}   trapezoidal {cells[1]}")


if __name__ == "__main__":
    main(sys.argv[1:])
