"""The `oneway` plant: membranes deforming in the precomputed flows without pushing back."""

import math
from dataclasses import replace

import numpy as np
import pytest

from sim.model.scenario import UM, CellType, Scenario
from sim.plants.feib import check_plant
from sim.plants.oneway import OneWayPlant, stokeslet_velocities
from sim.plants.rom import RomFlows

ETA = 6e-3


def singular_stokeslet(x, force):
    r = np.linalg.norm(x)
    return (-math.log(r) * force + (force @ x) * x / r**2) / (4 * math.pi * ETA)


def test_regularised_stokeslet_far_field_is_the_stokeslet():
    points = np.array([[0.0, 0.0], [1 * UM, 0.5 * UM], [200 * UM, 50 * UM]])
    forces = np.array([[1e-6, 2e-6], [-1e-6, -2e-6], [0.0, 0.0]])          # a force pair: no net force
    velocity = stokeslet_velocities(points, forces, ETA, epsilon=0.1 * UM)[2]
    expected = singular_stokeslet(points[2] - points[0], forces[0]) + singular_stokeslet(points[2] - points[1],
                                                                                         forces[1])
    assert velocity == pytest.approx(expected, rel=1e-3)


def test_a_pushed_pair_moves_apart_symmetrically():
    points = np.array([[0.0, 0.0], [2 * UM, 0.0]])
    forces = np.array([[-1e-6, 0.0], [1e-6, 0.0]])
    velocity = stokeslet_velocities(points, forces, ETA, epsilon=1 * UM)
    assert velocity[0, 0] < 0 < velocity[1, 0]
    assert velocity[0] == pytest.approx(-velocity[1], abs=1e-18)


@pytest.fixture(scope="module")
def coarse():
    scenario = Scenario().with_numerics(mesh_h=5 * UM, dt=5e-6)
    return scenario, RomFlows.of(scenario, spacing=2 * UM)


def test_oneway_plant_follows_the_contract(coarse):
    scenario, flows = coarse
    problems = check_plant(lambda: OneWayPlant(scenario, flows=flows), [(0.0, "RBC"), (30e-6, "melanoma")], steps=15)
    assert problems == []


def test_an_ellipse_at_rest_relaxes_to_the_circle_of_its_area(coarse):
    kind = CellType("ellipse", 2.8e-4, 1.2e-16, (10 * UM, 6 * UM))
    scenario = replace(coarse[0], cell_types=(kind,)).with_numerics(dt=2e-6)
    plant = OneWayPlant(scenario, flows=RomFlows.uniform(scenario, (0.0, 0.0), (0.0, 0.0)))
    plant.reset([(0.0, "ellipse")])
    start = plant.cells[0].membrane
    for _ in range(500):                              # 1 ms
        plant.step(0.0)
    end = plant.cells[0].membrane
    centred = end.points - end.centroid()
    small, large = np.linalg.eigvalsh(centred.T @ centred)
    assert math.sqrt(large / small) < 1.05
    assert end.area() == pytest.approx(start.initial_area, rel=1e-6)
    assert np.hypot(*centred.T).mean() == pytest.approx(math.sqrt(start.initial_area / math.pi), rel=0.01)


@pytest.mark.parametrize("cell, actuation, outlet", [("RBC", 0.0, "lower"), ("melanoma", 1.0, "upper")])
def test_isolated_cells_leave_by_the_feib_outlets(coarse, cell, actuation, outlet):
    scenario, flows = coarse
    plant = OneWayPlant(scenario, flows=flows)
    plant.reset([(0.0, cell)])
    plant.level = actuation
    while not plant.done and plant.time < 8e-3:
        plant.step(actuation)
    truth = plant.truth().cells[0]
    assert truth.fate == outlet
    assert abs(truth.measures["area_ratio_min"] - 1) < 1e-6
