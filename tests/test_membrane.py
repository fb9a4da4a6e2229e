"""Periodic cubic spline membranes: interpolation order, energy, forces (paper section 3.1)."""

import math

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from sim.method.membrane import Membrane, ellipse_by_arc_length
from sim.model.scenario import MELANOMA, RBC, CellType

ELLIPSE = CellType("test", kappa_e=1e-5, kappa_b=1e-17, semi_axes=(6e-6, 3e-6))


def test_spline_interpolation_of_an_ellipse_converges_at_fourth_order():
    a, b = ELLIPSE.semi_axes
    errors, spacings = [], []
    for count in (16, 32, 64, 128):
        angles = 2 * np.pi * np.arange(count) / count
        membrane = Membrane(np.column_stack([a * np.cos(angles), b * np.sin(angles)]), ELLIPSE,
                            reference_length=2 * np.pi)          # q = the ellipse's angle
        halfway = membrane.evaluate(samples_per_interval=2)[1::2]
        middle = angles + np.pi / count
        exact = np.column_stack([a * np.cos(middle), b * np.sin(middle)])
        errors.append(np.abs(halfway - exact).max())
        spacings.append(2 * np.pi / count)
    rate = np.polyfit(np.log(spacings), np.log(errors), 1)[0]
    assert rate == pytest.approx(4.0, abs=0.2)


def independent_energy(membrane, points):
    """E_h from scipy's periodic cubic spline and dense quadrature (no shared code with sim.method.membrane)."""
    q = np.arange(membrane.count + 1) * membrane.dq
    closed = np.vstack([points, points[:1]])
    spline = CubicSpline(q, closed, bc_type="periodic")
    fine = np.linspace(0, q[-1], 200 * membrane.count + 1)
    first, second = spline(fine, 1), spline(fine, 2)
    kind = membrane.cell_type
    elastic = 0.5 * kind.kappa_e * np.trapezoid(np.sum(first**2, axis=1) - 1, fine)
    bending = 0.5 * kind.kappa_b * np.trapezoid(np.sum(second**2, axis=1), fine)
    return elastic + bending


def test_energy_matches_an_independent_spline():
    membrane = Membrane.of(ELLIPSE, (0.0, 0.0), 1e-6)
    rng = np.random.default_rng(0)
    points = membrane.points + 2e-7 * rng.standard_normal(membrane.points.shape)
    assert membrane.energy(points) == pytest.approx(independent_energy(membrane, points), rel=1e-6)


def test_force_is_minus_the_gradient_of_the_energy_taylor_test():
    membrane = Membrane.of(ELLIPSE, (0.0, 0.0), 1e-6)
    rng = np.random.default_rng(1)
    points = membrane.points + 2e-7 * rng.standard_normal(membrane.points.shape)
    direction = rng.standard_normal(points.shape) * 1e-7
    force = membrane.forces(points)
    residuals = []
    for epsilon in (1e-1, 5e-2, 2.5e-2, 1.25e-2):
        change = independent_energy(membrane, points + epsilon * direction) - independent_energy(membrane, points)
        residuals.append(abs(change + epsilon * np.sum(force * direction)))
    # first-order Taylor remainder of a smooth function falls as epsilon^2
    rates = np.log2(np.array(residuals[:-1]) / residuals[1:])
    assert np.all(rates > 1.8)


def test_a_stretched_circle_has_inward_forces_and_positive_energy():
    membrane = Membrane.of(MELANOMA, (0.0, 0.0), 1e-6)
    radius = MELANOMA.semi_axes[0]
    # unstretched (|X_q| = 1): only the bending energy of a circle, kappa_b / 2 * 2 pi r / r^2
    assert membrane.energy() == pytest.approx(math.pi * MELANOMA.kappa_b / radius, rel=1e-3)
    stretched = 1.1 * membrane.points
    forces = membrane.forces(stretched)
    radial = np.sum(forces * stretched, axis=1)
    assert np.all(radial < 0)
    assert membrane.energy(stretched) > 0


def test_rbc_shape_has_the_papers_diameter_and_perimeter():
    assert RBC.diameter == pytest.approx(7.5e-6)
    assert RBC.perimeter == pytest.approx(19.8e-6, rel=0.01)
    membrane = Membrane.of(RBC, (50e-6, 115e-6), 0.5e-6)
    assert membrane.area() == pytest.approx(math.pi * 3.75e-6 * 2.5e-6, rel=1e-4)
    assert membrane.perimeter() == pytest.approx(RBC.perimeter, rel=1e-4)
    assert np.allclose(membrane.centroid(), (50e-6, 115e-6), atol=1e-12)


def test_points_are_equally_spaced_in_arc_length():
    points = ellipse_by_arc_length(6e-6, 3e-6, 64)
    gaps = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    assert gaps.max() / gaps.min() < 1.01
