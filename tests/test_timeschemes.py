"""The registered time schemes (``sim.method.timeschemes``), each of them: consistent coefficients, a membrane update
that solves its own difference equation, and the order of accuracy it claims, measured."""

import numpy as np
import pytest

from sim.method.timeschemes import SCHEMES, scheme_named
from sim.model.scenario import TIME_SCHEMES


def test_the_registry_holds_every_scheme_a_scenario_names():
    assert set(SCHEMES) == set(TIME_SCHEMES) - {"auto"}
    assert all(scheme_named(name).name == name for name in SCHEMES)


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_the_derivative_coefficients_are_consistent(name):
    """sum c_k = 0 and sum c_k (-k) = 1: dt dv/dt exact for constants and straight lines."""
    coefficients = np.array(scheme_named(name).derivative)
    assert coefficients.sum() == pytest.approx(0.0, abs=1e-15)
    assert (coefficients * -np.arange(len(coefficients))).sum() == pytest.approx(1.0, abs=1e-15)
    assert len(coefficients) - 1 == max(scheme_named(name).kept, 1)


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_the_update_solves_the_schemes_difference_equation(name):
    """With a value one step back, c0 X^{m+1} + c1 X^m + c2 X^{m-1} = dt v: the update is the coefficients'."""
    scheme = scheme_named(name)
    rng = np.random.default_rng(3)
    points, before, velocity = rng.normal(size=(3, 8, 2))
    dt = 0.3
    earlier = before if scheme.kept else None
    new = scheme.advanced(points, earlier, dt, velocity)
    values = [new, points, before][:len(scheme.derivative)]
    assert np.allclose(sum(c * v for c, v in zip(scheme.derivative, values)), dt * velocity, rtol=0, atol=1e-13)
    assert np.array_equal(scheme.advanced(points, None, dt, velocity), points + dt * velocity)    # a start: Euler


def _error(scheme, steps: int) -> float:
    """dx/dt = cos(t) from x(0) = 0 to t = 1, the velocity at the new time (as the FE-IB step takes v^{m+1})."""
    dt = 1.0 / steps
    x, history, times = np.zeros(1), (), [0.0]
    for m in range(steps):
        t = m * dt
        before = scheme.back(t, x, times[-2:-4:-1], history, dt)      # earlier times, the latest first
        x_new = scheme.advanced(x, before, dt, np.array([np.cos(t + dt)]))
        history = scheme.carried(x, history)
        times.append(t + dt)
        x = x_new
    return abs(x[0] - np.sin(1.0))


@pytest.mark.parametrize("name", sorted(SCHEMES))
def test_each_scheme_converges_at_its_order(name):
    scheme = scheme_named(name)
    steps = np.array([20, 40, 80, 160])
    errors = [_error(scheme, n) for n in steps]
    rate = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert rate == pytest.approx(scheme.order, abs=0.1)
