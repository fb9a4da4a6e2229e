"""Why rom's deflection envelope was narrower than feib's: the measurements behind docs/physics.md, "rom".

    python examples/envelope_study.py decay      # the FE flow's blend level after the IDT switches off
    python examples/envelope_study.py paths      # a rigid RBC in the exact FE flow vs in blends of the steady flows
    python examples/envelope_study.py membrane   # feib's RBC membrane near the divider (slow: ~1 min)

All on the paper's device (``paper`` SAW model) at mesh h = 6.67 um, dt 10 us, under the shipped pulse
(0.40 ms, lead 0.30 ms) at offsets from the target's arrival. Prints; writes nothing.
"""

from __future__ import annotations

import math
import sys

import numpy as np

from controller.sorter import ControllerSettings
from sim.fast import rom_kernels as kernels
from sim.method.fluid import NavierStokes
from sim.method.transfer import PointLocator
from sim.model.scenario import Scenario
from sim.plants.rom import area_mean_rule, default_response_time, wall_segments
from sim.plants.rom_transient import TRANSIENT_LAGS, fit_modes, step_response

SCENARIO = Scenario().with_numerics(mesh_h=20e-6 / 3, dt=10e-6)
SHIPPED = ControllerSettings()
OFFSETS = (-0.28e-3, -0.24e-3, -0.2e-3, 0.0, 0.08e-3, 0.12e-3, 0.16e-3, 0.2e-3, 0.24e-3, 0.28e-3)


def decay():
    """The least-squares blend level of the FE flow where the jet acts, during and after a 0.4 ms pulse."""
    fluid = NavierStokes(SCENARIO)
    off, on = fluid.steady(0.0).velocity, fluid.steady(1.0).velocity
    change = (on - off).ravel()
    acting = np.repeat(np.abs(on - off).max(axis=0) > 0.1 * np.abs(on - off).max(), 2)
    state, lag = fluid.steady(0.0), default_response_time(SCENARIO)
    for n in range(100):
        state = fluid.step(state, 1.0 if n < 40 else 0.0)
        d, c = (state.velocity - off).ravel()[acting], change[acting]
        level = d @ c / (c @ c)
        rom = 1 - math.exp(-state.time / lag) if n < 40 else (1 - math.exp(-0.4e-3 / lag)) * math.exp(
            -(state.time - 0.4e-3) / lag)
        if n % 5 == 0 or n in (40, 41):
            print(f"t {state.time * 1e3:.2f} ms  FE level {level:.3f}  shape residual "
                  f"{np.linalg.norm(d - level * c) / np.linalg.norm(c):.3f}  rom's 41 us lag {rom:.3f}")
    times, responses, change = step_response(fluid, 1.2e-3)
    print("fit residual of the step response (max, rms): three modes",
          *(f"{v:.3f}" for v in _stats(fit_modes(times, responses, change, TRANSIENT_LAGS)[1])),
          " one 41 us lag", *(f"{v:.3f}" for v in _stats(
              np.linalg.norm(np.outer(1 - np.exp(-times / lag), change) - responses, axis=1)
              / np.linalg.norm(change))))


def _stats(residual):
    return residual.max(), float(np.sqrt(np.mean(residual**2)))


def paths():
    """A rigid RBC (rom's body: area mean, wall hold-off) in the exact FE flow (``fe``), and in the steady
    flows blended at rom's former 41 us lag (``lag``) or at the FE flow's own level history (``level``: the
    FE's timing with the steady jet's shape)."""
    fluid = NavierStokes(SCENARIO)
    locator = PointLocator(fluid.space.cmesh, fluid.space.velocity_basis.element_dofs)
    cell = SCENARIO.cell_type("RBC")
    offsets, weights = area_mean_rule(cell.semi_axes)
    off, on = fluid.steady(0.0), fluid.steady(1.0)
    times, responses, change = step_response(fluid, 1.5e-3)
    step = (np.concatenate([[0.0], times]), np.concatenate([[0.0], responses @ change / (change @ change)]))
    for mode in ("lag", "level", "fe"):
        flows = (off, on, step)
        arrival = _carry(fluid, locator, cell, offsets, weights, flows, None, mode)[1]
        for offset in OFFSETS:
            pulse = (arrival - offset - SHIPPED.lead, arrival - offset - SHIPPED.lead + SHIPPED.pulse)
            fate, _, path = _carry(fluid, locator, cell, offsets, weights, flows, pulse, mode)
            ys = [np.interp(x, path[:, 0], path[:, 1]) * 1e6 for x in (120e-6, 150e-6, 200e-6, 250e-6, 290e-6)]
            print(f"{mode:3s} offset {offset * 1e3:+.2f} ms: {fate}; y at x = 120/150/200/250/290 um: "
                  + " ".join(f"{y:.1f}" for y in ys))


def _carry(fluid, locator, cell, offsets, weights, flows, pulse, mode):
    """(fate, arrival at the window's centre, path (n, 2)) of one rigid cell."""
    off, on, (step_times, step_levels) = flows
    channel, dt, lag = SCENARIO.channel, SCENARIO.numerics.dt, default_response_time(SCENARIO)
    segments, outlets = wall_segments(channel), np.array([o.span for o in channel.outlets])
    upper = np.array([channel.length, channel.height])
    a, b = cell.semi_axes
    x, y, t, level, state, arrival, path, touched = a + 1e-6, 0.5 * sum(channel.inlet(channel.injection_inlet).span), \
        0.0, 0.0, off, math.nan, [], False
    centre = 0.5 * sum(channel.saw_window.span)

    def mean(velocity, px, py):
        return weights @ locator.interpolate(velocity, np.clip(np.array([px, py]) + offsets, 0.0, upper))
    while t < 6e-3:
        drive = 1.0 if pulse and pulse[0] <= t + 1e-12 < pulse[1] else 0.0
        if mode == "fe":
            state = fluid.step(state, drive)
            velocity = state.velocity
        elif mode == "level":               # linear response: the step response from the pulse's start, less
            level = sum(sign * np.interp(t + dt - edge, step_times, step_levels)      # that from its end
                        for sign, edge in zip((1.0, -1.0), pulse or ()) if t + dt > edge)
            velocity = (1 - level) * off.velocity + level * on.velocity
        else:
            level = drive + (level - drive) * math.exp(-dt / lag)
            velocity = (1 - level) * off.velocity + level * on.velocity
        u1 = mean(velocity, x, y)
        u2 = mean(velocity, x + 0.5 * dt * u1[0], y + 0.5 * dt * u1[1])
        nx, ny, contact = kernels.hold_off(x + dt * u2[0], y + dt * u2[1], a, b, segments)
        touched = touched or (contact and nx > channel.length - 2 * a)
        if x < centre <= nx and math.isnan(arrival):
            arrival = t + dt * (centre - x) / (nx - x)
        if nx >= channel.length:
            exit_y = y + (channel.length - x) / (nx - x) * (ny - y)
            fate = {kernels.OUTLET + k: o.name for k, o in enumerate(channel.outlets)}.get(
                kernels.outlet_code(exit_y, outlets), "wall")
            return fate + (" (touched the divider)" if touched else ""), arrival, np.array(path)
        x, y, t = nx, ny, t + dt
        path.append((x, y))
    return "in channel", arrival, np.array(path)


def membrane():
    """feib's RBC under the pulse: its membrane's extent as it nears the divider, and its fate."""
    from sim.plants.feib import FeibPlant
    plant = FeibPlant(SCENARIO)
    plant.reset([(0.0, "RBC")])
    centre, arrival, previous = 0.5 * sum(SCENARIO.channel.saw_window.span), math.nan, None
    while not plant.done and math.isnan(arrival):
        observation = plant.step(0.0)
        if observation.cells and previous is not None and previous[1] < centre <= observation.cells[0].x:
            arrival = observation.time
        previous = (observation.time, observation.cells[0].x) if observation.cells else previous
    for offset in (0.16e-3, 0.24e-3, 0.28e-3):
        start = arrival - offset - SHIPPED.lead
        observation, shown = plant.reset([(0.0, "RBC")]), 240e-6
        try:
            while not plant.done and observation.time < 6e-3:
                observation = plant.step(1.0 if start <= observation.time + 1e-12 < start + SHIPPED.pulse else 0.0)
                cells = [c for c in plant.state.cells if c.in_channel]
                if cells and cells[0].membrane.points[:, 0].mean() > shown:
                    points = cells[0].membrane.points
                    shown += 15e-6
                    print(f"offset {offset * 1e3:+.2f} ms: centre x {points[:, 0].mean() * 1e6:.0f} um, semi-extents "
                          f"{np.ptp(points[:, 0]) * 5e5:.1f} x {np.ptp(points[:, 1]) * 5e5:.1f} um")
            print(f"offset {offset * 1e3:+.2f} ms: fate {plant.truth().cells[0].fate}")
        except Exception as error:          # a membrane that folds ends the run: no outcome
            print(f"offset {offset * 1e3:+.2f} ms: no outcome ({str(error)[:70]}...)")


if __name__ == "__main__":
    {"decay": decay, "paths": paths, "membrane": membrane}[sys.argv[1] if len(sys.argv) > 1 else "decay"]()
