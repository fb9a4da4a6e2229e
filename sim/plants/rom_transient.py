"""The shape of the flow's transient for the ``rom`` plant: modes of the FE flow's response to the IDT.

When the IDT switches, the FE flow does not move from the IDT-off to the IDT-on steady flow along the
straight line between them: in the first step (10 us) the pressure carries ~3/4 of the change at once over a
wider region than the steady jet (the fluid the window pushes must go somewhere at once: the instantaneous
response reaches further upstream), and the rest follows by viscous diffusion, more slowly the wider the
scale. Navier-Stokes at Re ~ 1-3 is nearly linear in the boundary data (switch-on and switch-off responses
sum to the steady change within 1.6 %), so the response to any drive is the superposition of step
responses, and the step response is well described by a sum of exponentials with fixed time constants
tau_k and spatial modes Phi_k:

    v(t) - v_off = sum_k (1 - exp(-t / tau_k)) Phi_k,    sum_k Phi_k = v_on - v_off,

(tau_0 = 0: the jump). ``measure_modes`` steps the FE flow from the IDT-off steady flow with the IDT on,
and fits the modes by linear least squares at the fixed time constants ``TRANSIENT_LAGS`` (the sum
constraint eliminates the last mode). The rom plant then carries one level per mode, each a first-order lag
of the drive. The measurement runs on a mesh no finer than ``TRANSIENT_MESH_H`` (the modes are smooth; the
fast modes are taken from it and the slowest mode is the steady change of the scenario's own mesh minus
them), at ``TRANSIENT_DT``; its results go through ``sim.fast.store`` (cached by the application).
"""

from __future__ import annotations

import math
import sys
import time as clock

import numpy as np

from ..fast.linalg import mkl_version
from ..fast.store import module_digest, reuse
from ..method.fluid import NavierStokes, solver_code_digest
from ..method.transfer import PointLocator
from ..model.scenario import Scenario, ScenarioError

TRANSIENT_LAGS = (0.0, 30e-6, 150e-6)     # s: the jump, a fast and a slow viscous mode
TRANSIENT_DT = 10e-6                       # s: the FE step of the measurement
TRANSIENT_DURATION = 1.2e-3                # s: 8 x the slowest lag
TRANSIENT_MESH_H = 20e-6 / 3               # m: the coarsest mesh the measurement uses
RESPONSE_POINT = (150e-6, 115e-6)          # m: where cells are deflected (``measure_response_time``)


def step_response(fluid: NavierStokes, duration: float):
    """The FE flow after the IDT switches on in the steady IDT-off flow: times (n,), v(t_n) - v_off (n, 2N) and
    the steady change v_on - v_off (2N,)."""
    off, on = fluid.steady(0.0), fluid.steady(1.0)
    state, times, responses = off, [], []
    for _ in range(round(duration / fluid.scenario.numerics.dt)):
        state = fluid.step(state, 1.0)
        times.append(state.time)
        responses.append((state.velocity - off.velocity).ravel())
    return np.array(times), np.array(responses), (on.velocity - off.velocity).ravel()


def fit_modes(times, responses, change, lags=TRANSIENT_LAGS):
    """Modes (K, D) with sum ``change`` minimising sum_n |sum_k (1 - exp(-t_n / tau_k)) Phi_k - R_n|^2, and the
    residual of each snapshot relative to |change| (n,)."""
    times, responses, change = np.asarray(times, float), np.asarray(responses, float), np.asarray(change, float)
    design = np.array([[1.0 if tau == 0 else -math.expm1(-t / tau) for tau in lags] for t in times])
    free = design[:, :-1] - design[:, -1:]                 # Phi_last = change - sum of the others
    target = responses - design[:, -1:] * change[None]
    solution = np.linalg.lstsq(free, target, rcond=None)[0] if len(lags) > 1 else np.zeros((0, change.size))
    modes = np.vstack([solution, change - solution.sum(axis=0)])
    residual = np.linalg.norm(design @ modes - responses, axis=1) / np.linalg.norm(change)
    return modes, residual


def transient_scenario(scenario: Scenario) -> Scenario:
    """The scenario the transient is measured on: its mesh coarsened to ``TRANSIENT_MESH_H`` (if that resolves
    its cells and window), the step ``TRANSIENT_DT``, starting from the steady flow."""
    numerics = {"dt": TRANSIENT_DT, "initial_flow": "steady", "tolerance": 0.0}
    try:
        return scenario.with_numerics(mesh_h=max(scenario.numerics.mesh_h, TRANSIENT_MESH_H), **numerics)
    except ScenarioError:
        return scenario.with_numerics(**numerics)


def measure_modes(scenario: Scenario, lags=TRANSIENT_LAGS, duration: float = TRANSIENT_DURATION):
    """The FE fluid of ``transient_scenario``, the fitted modes (K, 2, N) on it and the fit's residuals (n,)."""
    fluid = NavierStokes(transient_scenario(scenario))
    times, responses, change = step_response(fluid, duration)
    modes, residual = fit_modes(times, responses, change, lags)
    return fluid, modes.reshape(len(lags), 2, -1), residual


def sampled_modes(scenario: Scenario, spacing: float, sample, lags=TRANSIENT_LAGS,
                  duration: float = TRANSIENT_DURATION):
    """All modes but the last, sampled on the rom grid by ``sample`` (``sim.plants.rom.RomFlows.sample``, passed in so
    that this module does not import the rom plant, which imports it): a dict of ``point`` (nx, ny, 2K - 2),
    ``cells`` (types, nx, ny, 2K - 2), ``residual`` (n,), ``seconds``."""

    def build():
        started = clock.perf_counter()
        fluid, modes, residual = measure_modes(scenario, lags, duration)
        values = modes[:-1].reshape(-1, modes.shape[-1])           # (2K - 2, N)
        sampled = sample(scenario, fluid, values, spacing, {})
        return {"point": sampled.point, "cells": sampled.cells, "residual": residual,
                "seconds": np.array(clock.perf_counter() - started)}

    numerics = transient_scenario(scenario).numerics
    key = {"channel": repr(scenario.channel), "fluid": repr(scenario.fluid), "saw": repr(scenario.saw),
           "cell_types": repr([(c.name, c.semi_axes) for c in scenario.cell_types]), "spacing": float(spacing),
           "mesh_h": float(numerics.mesh_h), "dt": float(numerics.dt), "numerics": repr(numerics),
           "lags": [float(tau) for tau in lags], "duration": float(duration), "mkl": mkl_version(),
           "code": solver_code_digest() + module_digest(sys.modules[__name__])}
    return reuse("rom-transient", key, build)


def measure_response_time(fluid: NavierStokes, point=RESPONSE_POINT, duration: float = 1.2e-3) -> float:
    """Mean delay of the FE flow at ``point`` after the IDT switches on in the steady IDT-off flow.

    s(t) = (v(t) - v_off) . (v_on - v_off) / |v_on - v_off|^2 at the point (s = 1: the IDT-on flow); the
    delay is the integral of 1 - s over ``duration``, which is the time constant of the first-order lag with
    the same integral (the same mean lag of a cell's displacement).
    """
    space = fluid.space
    locator = PointLocator(space.cmesh, space.velocity_basis.element_dofs)
    off, on = fluid.steady(0.0), fluid.steady(1.0)
    where = np.array([point], dtype=float)
    v_off, v_on = locator.interpolate(off.velocity, where)[0], locator.interpolate(on.velocity, where)[0]
    change = v_on - v_off
    state, delay = off, 0.0
    for _ in range(round(duration / fluid.scenario.numerics.dt)):
        state = fluid.step(state, 1.0)
        level = (locator.interpolate(state.velocity, where)[0] - v_off) @ change / (change @ change)
        delay += (1.0 - level) * fluid.scenario.numerics.dt
    return float(delay)
