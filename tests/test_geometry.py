"""The shared helpers of the plants: the drive's first-order lag, the injection point, clipping to the channel."""

import math

import numpy as np
import pytest

from sim.method.feib import new_cell
from sim.model.drive import lag_decay, lagged
from sim.model.geometry import MESH_INSET, clip_to_channel, injection_point, injection_y
from sim.model.scenario import UM, Scenario


def test_the_lag_is_the_exact_solution_of_its_equation():
    tau, dt = 41e-6, 20e-6
    assert lagged(0.0, 1.0, dt, tau) == pytest.approx(1 - math.exp(-dt / tau), rel=1e-15)
    halves = lagged(lagged(0.3, 1.0, dt / 2, tau), 1.0, dt / 2, tau)         # the semigroup property
    assert halves == pytest.approx(lagged(0.3, 1.0, dt, tau), rel=1e-14)
    assert lagged(1.0, 0.0, 10 * tau, tau) == pytest.approx(math.exp(-10), rel=1e-14)


def test_no_lag_follows_the_drive_at_once():
    assert lag_decay(1e-6, 0.0) == 0.0
    assert lagged(0.25, 1.0, 1e-6, 0.0) == 1.0 and lagged(0.75, 0.0, 1e-6, 0.0) == 0.0


def test_a_cell_starts_just_inside_the_channel_on_the_injection_inlets_centre():
    scenario = Scenario()
    melanoma = scenario.cell_type("melanoma")
    x, y = injection_point(scenario, melanoma)
    assert x == pytest.approx(8 * UM + 1 * UM) and y == pytest.approx(115 * UM) == injection_y(scenario.channel)
    cell = new_cell(scenario.with_numerics(mesh_h=10 * UM), melanoma, 0, 0.0, warn=False)
    assert np.allclose(cell.membrane.points.mean(axis=0), (x, y), atol=0.05 * UM)


def test_clipping_keeps_points_inside_and_moves_only_those_outside():
    channel = Scenario().channel
    length, height = channel.length, channel.height
    points = np.array([[100 * UM, 50 * UM], [length + 5 * UM, 60 * UM], [-1 * UM, height + 2 * UM]])
    walls = clip_to_channel(points, channel)
    assert np.array_equal(walls[0], points[0])
    assert walls[1].tolist() == [length, 60 * UM] and walls[2].tolist() == [0.0, height]
    outlet_only = clip_to_channel(points, channel, inset=MESH_INSET, walls=False)
    assert outlet_only[1, 0] < length and outlet_only[1, 0] == pytest.approx(length, rel=1e-11)
    assert np.array_equal(outlet_only[2], points[2])                 # outside the walls: the health checks' business
