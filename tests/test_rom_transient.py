"""The rom plant's transient modes: the fit, the FE step response they reproduce, and the flows they make."""

import numpy as np
import pytest

from sim.method.fluid import NavierStokes
from sim.model.scenario import UM
from sim.plants.rom import RomFlows, RomPlant
from sim.plants.rom_transient import TRANSIENT_LAGS, fit_modes, step_response, transient_scenario


def test_the_fit_recovers_a_sum_of_exponentials():
    rng = np.random.default_rng(4)
    lags = (0.0, 30e-6, 150e-6)
    modes = rng.normal(size=(3, 7))
    times = np.arange(1, 121) * 10e-6
    design = np.array([[1.0 if tau == 0 else 1 - np.exp(-t / tau) for tau in lags] for t in times])
    fitted, residual = fit_modes(times, design @ modes, modes.sum(axis=0), lags)
    np.testing.assert_allclose(fitted, modes, atol=1e-9)
    assert residual.max() < 1e-9
    # with other time constants the same data leave a residual the fit reports
    assert fit_modes(times, design @ modes, modes.sum(axis=0), (0.0, 60e-6))[1].max() > 0.01


@pytest.fixture(scope="module")
def response(coarse_scenario):
    fluid = NavierStokes(transient_scenario(coarse_scenario))
    return step_response(fluid, 1.2e-3)


def test_three_modes_reproduce_the_fe_step_response_and_one_lag_does_not(response):
    times, responses, change = response
    _, residual = fit_modes(times, responses, change, TRANSIENT_LAGS)
    assert residual.max() < 0.06 and np.sqrt(np.mean(residual**2)) < 0.02       # measured: 4.9 % and 1.3 %
    single = np.array([(1 - np.exp(-t / 41e-6)) * change for t in times])        # rom's former 41 us lag
    assert (np.linalg.norm(single - responses, axis=1) / np.linalg.norm(change)).max() > 0.5    # measured: 68 %
    # the first step carries most of the change, in another shape than the steady change (not a blend)
    first = responses[0]
    level = first @ change / (change @ change)
    assert 0.7 < level < 0.9 and np.linalg.norm(first - level * change) > 0.1 * np.linalg.norm(change)


def test_the_modes_sum_to_the_steady_change_and_a_given_lag_uses_one(coarse_scenario):
    flows = RomFlows.of(coarse_scenario, spacing=2 * UM)
    assert flows.lags == TRANSIENT_LAGS and flows.fit_residual < 0.06 and flows.cells.shape[-1] == 4 + 2 * 3
    for fields in (flows.point, flows.cells):
        modes = fields[..., 4:].reshape(*fields.shape[:-1], 3, 2).sum(axis=-2)
        np.testing.assert_allclose(modes, fields[..., 2:4], atol=1e-12)
    points = np.array([[150 * UM, 40 * UM], [100 * UM, 100 * UM], [280 * UM, 110 * UM]])
    plain = RomFlows.of(coarse_scenario, spacing=2 * UM, transient=False)
    for level in (0.0, 0.3, 1.0):        # every mode at one level: the blended steady flows
        np.testing.assert_allclose(flows.velocity(points, level), plain.velocity(points, level), atol=1e-12)
    # modes at different levels: another flow than any blend
    assert not np.allclose(flows.velocity(points, (1.0, 0.0, 0.0)), plain.velocity(points, 1.0), atol=1e-3)
    assert RomPlant(coarse_scenario, flows=flows, response_time=41e-6).lags == (41e-6,)
    assert RomPlant(coarse_scenario, flows=flows).lags == TRANSIENT_LAGS
