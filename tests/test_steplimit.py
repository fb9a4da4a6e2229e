"""The stability law (sim/method/steplimit.py): fitted to the measured limits, never above any of them, and recovering a
known law from its own values."""

import math
from dataclasses import replace

import pytest

from sim.method.steplimit import LAW, MEASURED, Law, Measured, implicit_limit, limit_of
from sim.model.scenario import UM, Scenario


def test_the_law_lies_at_or_below_every_measured_limit_and_close_to_those_reached():
    for m in MEASURED:
        if m.coupling == "implicit":                      # its own limit: implicit_limit
            assert implicit_limit(m.membrane) <= m.stable * (1 + 1e-9), m
            continue
        law = LAW.limit(m.h, m.kappa_e, m.scheme, m.membrane)
        assert law <= m.stable * (1 + 1e-9), m
        if m.reached:
            assert law >= 0.7 * m.stable, m              # measured: 0.76-1.0 of each limit reached


def test_a_cells_own_measurement_lifts_the_law_where_it_is_conservative():
    scenario = Scenario().with_numerics(mesh_h=5 * UM / 3)           # euler, conserving
    rbc = scenario.cell_type("RBC")
    assert LAW.limit(5 * UM / 3, rbc.kappa_e, "euler") < 10e-6 and limit_of(rbc, scenario) == pytest.approx(100e-6)
    assert limit_of(rbc, scenario.with_numerics(time_scheme="bdf2", tolerance=1e-6)) < 10e-6   # not measured: law


def test_a_stiffer_cell_has_a_lower_limit_and_the_papers_step_is_no_limit_on_a_finer_mesh():
    scenario = Scenario().with_numerics(mesh_h=20 * UM / 3)
    melanoma = scenario.cell_type("melanoma")
    limits = [limit_of(replace(melanoma, kappa_e=melanoma.kappa_e * k), scenario) for k in (1, 16, 100)]
    assert limits[0] > limits[1] > limits[2] and limits[2] < 25e-6 / 4     # x100 at 25 us: stopped (extremes b1)
    paper = Scenario()
    assert limit_of(melanoma, paper) > 25e-6 > limit_of(melanoma, paper.with_numerics(mesh_h=2.5 * UM))


def test_the_fit_recovers_a_known_law():
    known = Law(40e-6, 3.0, 2.0, 0.1, (("euler", 1.0), ("conserving", 1.0), ("bdf2", 0.5)))
    data = []
    for h in (20 / 3, 10 / 3, 2.5, 5 / 3):
        for scale in (1, 4, 16, 100):
            for scheme in ("euler", "bdf2"):
                limit = known.unbounded(h * UM, 2.8e-4 * scale, scheme, "conserving")
                data.append(Measured("cell", h * UM, 2.8e-4 * scale, scheme, "conserving", limit, 1.2 * limit))
    fitted = Law.fit(tuple(data))
    assert fitted.p == pytest.approx(3.0, abs=1e-3) and fitted.r == pytest.approx(0.1, abs=1e-3)
    assert fitted.mesh_term == pytest.approx(40e-6, rel=1e-3) and fitted.membrane_term == pytest.approx(2.0, rel=1e-3)
    assert dict(fitted.factors)["bdf2"] == pytest.approx(0.5, rel=1e-3)
    assert math.isclose(fitted.limit(1e-6, 1e-3, "bdf2"), known.limit(1e-6, 1e-3, "bdf2"), rel_tol=1e-3)
