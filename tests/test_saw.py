"""The three SAW models: the paper's aliasing, the envelope, and the lagged streaming force."""

import math

import numpy as np
import pytest

from sim.boundary import cutoff, saw_jet_factor
from sim.fluid import NavierStokes
from sim.scenario import Saw


def test_paper_jet_is_aliased_to_its_peak_at_the_papers_step_times():
    saw = Saw(model="paper")
    for dt in (2.5e-6, 25e-6):
        factors = [saw_jet_factor(saw, m * dt) for m in range(1, 200)]
        assert np.allclose(factors, 1.0, atol=1e-6)       # f dt is an integer: every step samples cos = 1
    assert saw_jet_factor(saw, 2.5e-9) == pytest.approx(0.0, abs=1e-9)   # a quarter period is 0


def test_envelope_is_the_jet_without_the_carrier():
    assert saw_jet_factor(Saw(model="envelope"), 1.234e-9) == 1.0
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
