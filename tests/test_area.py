"""Cells that keep their size (docs/numerics.md, "Cells that keep their size"): the area constraint and the
redistribution of membrane points, against the paper's literal method which leaks."""

import math

import numpy as np
import pytest
from test_feib import aspect_ratio, quiescent, relax, run_to_exit

from sim.method.feib import ImmersedBoundary, Measures, State
from sim.method.fluid import NavierStokes
from sim.method.membrane import Membrane
from sim.model.scenario import UM, CellType

ELLIPSE = CellType("ellipse", 2.8e-4, 1.2e-16, (10 * UM, 6 * UM))


@pytest.fixture
def stretched():
    """An ellipse whose points crowd at one end: uneven stretch along the membrane."""
    angles = np.linspace(0, 2 * np.pi, 40, endpoint=False) ** 1.3 / (2 * np.pi) ** 0.3
    points = np.column_stack([10 * UM * np.cos(angles), 6 * UM * np.sin(angles)])
    return Membrane(points, ELLIPSE, reference_length=40 * UM)


def test_area_gradient_is_the_derivative_of_the_area(stretched):
    direction = np.random.default_rng(1).standard_normal(stretched.points.shape)
    eps = 1e-3 * UM
    difference = (stretched.area(stretched.points + eps * direction)
                  - stretched.area(stretched.points - eps * direction))
    assert difference / (2 * eps) == pytest.approx(np.sum(stretched.area_gradient() * direction), rel=1e-7)


def test_projection_restores_the_area_exactly(stretched):
    shrunk = stretched.with_points(0.9 * stretched.points)
    assert shrunk.area() == pytest.approx(0.81 * stretched.area(), rel=1e-12)
    assert shrunk.with_area(stretched.area()).area() == pytest.approx(stretched.area(), rel=1e-12)


def test_pressure_balanced_forces_do_no_work_on_the_area_and_cancel_on_a_circle(stretched):
    balanced, pressure = stretched.pressure_balanced(stretched.forces())
    gradient = stretched.area_gradient()
    assert abs(np.sum(balanced * gradient)) < 1e-12 * np.linalg.norm(balanced) * np.linalg.norm(gradient)
    assert pressure > 0          # the membrane is in tension: the interior pushes outward
    circle = Membrane.of(CellType("c", 2.8e-4, 1.2e-16, (8 * UM, 8 * UM)), (0, 0), 1.6 * UM)
    forces, pressure = circle.pressure_balanced(circle.forces())
    assert np.abs(forces).max() < 1e-9 * np.abs(circle.forces()).max()
    assert pressure == pytest.approx(2.8e-4 / (8 * UM), rel=0.02)      # Laplace: tension / radius


def test_redistribution_spaces_points_evenly_keeps_the_shape_and_releases_stretch(stretched):
    spacing = stretched.spacing()
    assert spacing.max() > 2 * spacing.min()
    resampled = stretched.resampled(1.0 * UM)
    assert resampled.count == math.ceil(stretched.perimeter() / UM)
    assert resampled.spacing().max() < 1.02 * resampled.spacing().min()
    assert resampled.area() == pytest.approx(stretched.area(), rel=1e-5)
    assert resampled.perimeter() == pytest.approx(stretched.perimeter(), rel=1e-5)
    # every new point lies on the old curve: distance to a dense sampling of the old spline
    dense = stretched.evaluate(1024)
    distances = np.min(np.hypot(*(resampled.points[:, None, :] - dense[None]).transpose(2, 0, 1)), axis=1)
    assert distances.max() < 2e-3 * UM         # the samples of the old spline are 2 nm apart

    def stretching(m):                                                   # kappa_e/2 int |X_q|^2
        return 0.5 * m.cell_type.kappa_e * np.sum(m.spacing() ** 2) / m.dq

    assert stretching(resampled) < stretching(stretched)
    assert resampled.reference_length == stretched.reference_length and resampled.redistributions == 1
    assert resampled.initial_area == stretched.initial_area


@pytest.fixture(scope="module")
def box_at_rest():
    """The paper's mesh with every inlet shut, dt 25 us: one fluid solver for both methods."""
    return NavierStokes(quiescent(10 * UM / 3, 25e-6))


def melanoma_at_rest(fluid, membrane, duration=5e-3):
    scenario = quiescent(10 * UM / 3, 25e-6, membrane=membrane)
    plant = ImmersedBoundary(scenario, fluid)
    cell = plant.new_cell(scenario.cell_type("melanoma"), 0, 0.0, centre=(150 * UM, 110 * UM))
    state = State(fluid.rest(), (cell,))
    while state.time < duration - 1e-9:
        state = plant.step(state)
    return state


def test_melanoma_at_rest_keeps_its_area_with_the_conserving_method_and_leaks_with_the_papers(box_at_rest):
    conserving = melanoma_at_rest(box_at_rest, "conserving")
    literal = melanoma_at_rest(box_at_rest, "paper")
    kept = conserving.cells[0].measures
    assert kept.area_ratio_min > 0.99 and kept.area_ratio_max < 1.01
    assert kept.area_corrected < 1e-6          # the interior pressure balances the tension: nothing to restore
    assert np.abs(conserving.flow.velocity).max() < 1e-9      # and the fluid stays at rest
    assert literal.cells[0].measures.area_ratio < 0.7          # measured: 46.5 % of the area left after 5 ms


def test_relaxing_ellipse_keeps_its_area_and_becomes_the_circle_of_that_area():
    history = relax(5 * UM, steps=400, membrane="conserving")
    start, end = history[0], history[-1]
    assert abs(end.area() / start.area() - 1) < 0.01
    assert aspect_ratio(start.points) > 1.4 and aspect_ratio(end.points) < 1.05
    radius = np.hypot(*(end.points - end.centroid()).T)
    assert radius.mean() == pytest.approx(math.sqrt(start.area() / math.pi), rel=0.01)


def test_scenario_2_conserving_keeps_the_melanomas_area_and_still_sorts_it_upper(paper_scenario):
    cell = run_to_exit(ImmersedBoundary(paper_scenario.with_numerics(dt=25e-6)), "melanoma", 1.0)
    assert cell.fate == "upper"
    assert cell.measures.area_ratio_min > 0.99 and cell.measures.area_ratio_max < 1.01
    assert 0.3 <= cell.measures.spacing_lowest and cell.measures.spacing_highest <= 0.7


def test_scenario_1_conserving_keeps_the_rbcs_points_in_the_band_and_still_leaves_lower(paper_solver, paper_scenario):
    cell = run_to_exit(ImmersedBoundary(paper_scenario, paper_solver), "RBC", 0.0)
    assert cell.fate == "lower"
    low, high = paper_scenario.numerics.spacing_band
    assert low <= cell.measures.spacing_lowest and cell.measures.spacing_highest <= high
    assert cell.membrane.redistributions > 0            # the RBC stretches: its points had to be redistributed
    assert abs(cell.measures.area_ratio_min - 1) < 0.01


def test_measures_follow_the_extremes():
    membrane = Membrane.of(ELLIPSE, (0, 0), 1 * UM)
    first = Measures.of(membrane, 2 * UM)
    second = Measures.of(membrane.with_points(1.1 * membrane.points), 2 * UM, first)
    assert second.area_ratio == pytest.approx(1.21) and second.area_ratio_min == pytest.approx(1.0)
    assert second.spacing_highest == pytest.approx(1.1 * first.spacing_highest)
    assert second.spacing_lowest == pytest.approx(first.spacing_lowest)
