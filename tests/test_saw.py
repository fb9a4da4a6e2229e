"""The three SAW models: the jet (paper, envelope) independent of the carrier's phase; the lagged streaming force."""

import math
from dataclasses import replace

import numpy as np
import pytest

from sim.method.fluid import NavierStokes
from sim.model.boundary import cutoff, saw_jet_factor
from sim.model.scenario import Saw, Scenario

# steps that are not multiples of the 10 ns carrier period: the paper's formula, sampled at them, gave
# cos = +1, -1 alternating at 3.125 us and other values at every other one
ODD_STEPS = (3.125e-6, 7e-6, 3.3337e-6, 12.5013e-6, 0.8e-6 + 2.5e-9)


@pytest.mark.parametrize("model", ["paper", "envelope"])
def test_the_jet_is_the_same_wherever_a_step_lands_in_the_carriers_period(coarse_scenario, model):
    solver = NavierStokes(coarse_scenario.with_saw(model=model))
    for dt in ODD_STEPS + (2.5e-6, 25e-6):
        weights = {solver.jet_weight(m * dt + offset, 1.0) for m in range(1, 60) for offset in (0.0, 2.5e-9, 5e-9)}
        assert weights == {1.0}, (dt, weights)
    assert solver.jet_weight(3.125e-6, 0.0) == 0.0          # the drive switches it off
    assert solver.jet_weight(3.125e-6, 0.5) == 0.5          # and scales it


@pytest.mark.parametrize("dt", ODD_STEPS[:2])
def test_a_flow_step_does_not_depend_on_the_carriers_phase(coarse_scenario, dt):
    """The same step, started a quarter and a half carrier period apart, gives the same flow: only the elapsed
    time and the drive matter."""
    solver = NavierStokes(coarse_scenario.with_numerics(dt=dt))
    start = solver.steady(0.0)
    results = []
    for offset in (0.0, 2.5e-9, 5e-9):
        state = replace(start, time=start.time + offset)
        for _ in range(3):
            state = solver.step(state, actuation=1.0)
        results.append(state.velocity)
    on = solver.steady(1.0).velocity
    assert np.abs(results[0] - start.velocity).max() > 0.05 * np.abs(on - start.velocity).max()   # the jet acted
    for other in results[1:]:
        assert np.array_equal(other, results[0])


def test_envelope_is_the_paper_jet_and_streaming_has_none():
    assert saw_jet_factor(Saw(model="envelope")) == saw_jet_factor(Saw(model="paper")) == 1.0
    assert saw_jet_factor(Saw(model="streaming")) == 0.0
    assert Saw().jet_speed == pytest.approx(2 * math.pi * 1e-9 * 100e6)


def test_cutoff_is_one_inside_zero_outside_and_smooth():
    s = np.linspace(0, 30, 3001)
    m = cutoff(s, 0.0, 30.0, 3.0)
    assert m[0] == 0 and m[-1] == 0
    assert np.all(m[(s >= 3) & (s <= 27)] == 1.0)
    assert np.all(np.diff(m[s <= 15]) >= 0)
    assert np.abs(np.diff(m, 2)).max() < 1e-3            # no kinks at this sampling


def test_streaming_level_follows_the_idt_with_a_first_order_lag(coarse_scenario):
    solver = NavierStokes(coarse_scenario.with_saw(model="streaming", spin_up_time=1e-4))
    level, time, dt = 0.0, 0.0, 1e-6
    while time < 1e-4 - 1e-12:
        level = solver.streaming_level(level, 1.0, dt)
        time += dt
    assert level == pytest.approx(1 - math.exp(-1), rel=1e-9)
    assert solver.streaming_level(0.3, 0.0, 0.0) == pytest.approx(0.3)


@pytest.mark.slow
def test_scenario_two_leaves_by_the_upper_outlet_at_any_step():
    """Scenario II (the paper's method) at the paper's step, at steps that are not multiples of the carrier's
    period (3.125 us sampled cos = -1 every other step and sent the melanoma lower) and at coarser ones: the
    upper outlet every time, the exit ordinates within 1 um of each other."""
    from vcyto.studies.paper import run_paper
    base = Scenario().with_numerics(area_constraint="none", redistribute=False)
    exits = []
    for dt in (2.5e-6, 3.125e-6, 7e-6, 12.5e-6, 25e-6):
        cell = run_paper(2, base.with_numerics(dt=dt), max_time=5e-3)["cells"][0]
        assert cell["outlet"] == "upper", (dt, cell)
        exits.append(cell["exit_y_um"])
    assert max(exits) - min(exits) <= 1.0, exits
