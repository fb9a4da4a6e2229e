"""Stability at the extremes (docs/results.md): each extreme setting runs correctly or stops with a specific diagnosis.

The fast variants of `vcyto extremes` (coarse meshes, short runs), one test per case, each asserting its
own outcome; plus the health checks' new diagnoses on hand-made membranes.
"""

import logging

import numpy as np
import pytest

from sim.method.feib import Cell, ImmersedBoundary
from sim.method.health import HealthError, HealthLimits, check_cells, membrane_time_step, under_resolved
from sim.method.membrane import Membrane
from sim.model.scenario import UM, Scenario, ScenarioError
from vcyto.studies import extremes


def run(name):
    case = next(case for case in extremes.CASES if case.name == name)
    return extremes.run_case(case, Scenario(), fast=True)


def test_dt_at_the_measured_limit_runs_and_sorts_the_melanoma_upper():
    row = run("a1")
    assert row["passed"] and row["ran"] and row["dt_us"] == pytest.approx(37.5)
    assert row["cells"][0]["fate"] == "upper"


def test_dt_four_times_the_limit_is_stopped_with_a_smaller_dt_to_try():
    row = run("a2")
    assert row["passed"] and not row["ran"]
    # the dt suggested is the melanoma's limit on this mesh by the stability law, at or below its measured limits
    from sim.method.steplimit import MEASURED, limit_of
    from sim.model.scenario import Scenario
    from vcyto.studies.extremes import PAPER_H
    scenario = Scenario().with_numerics(mesh_h=PAPER_H)
    suggested = limit_of(scenario.cell_type("melanoma"), scenario)
    melanoma = scenario.cell_type("melanoma")
    measured = [m.stable for m in MEASURED if m.kappa_e == melanoma.kappa_e and m.scheme == "euler" and m.reached
                and m.membrane == scenario.membrane_method() and m.h == pytest.approx(PAPER_H)]
    assert measured and all(suggested <= stable * (1 + 1e-9) for stable in measured) and suggested < 150e-6 / 2
    assert "stability limit" in row["diagnosis"] and f"try dt = {suggested * 1e6:.4g} us" in row["diagnosis"]


def test_very_stiff_membrane_at_a_large_dt_is_stopped_and_runs_at_its_estimated_dt():
    stopped, running = run("b1"), run("b2")
    assert stopped["passed"] and "try dt =" in stopped["diagnosis"] and stopped["steps"] < 10
    assert running["passed"] and running["ran"] and running["dt_us"] < 1.0
    assert running["steps"] >= 200 and running["cells"][0]["fate"] == "in_channel"
    assert abs(running["cells"][0]["area_ratio"][0] - 1) < 0.01


def test_very_soft_membrane_keeps_its_spacing_when_conserving_and_its_points_separate_with_the_papers_method():
    conserving, paper = run("b3"), run("b4")
    assert conserving["passed"] and paper["passed"]
    assert conserving["cells"][0]["fate"] == paper["cells"][0]["fate"] == "lower"
    assert conserving["cells"][0]["spacing_over_h"][1] <= 0.7 + 1e-9
    assert paper["cells"][0]["spacing_over_h"][1] > 1.0          # measured 1.64 h


def test_eightfold_inflow_stretches_the_melanoma_but_it_stays_whole():
    row = run("c1")
    assert row["passed"] and row["ran"] and row["cells"][0]["fate"] in ("lower", "upper")
    assert 2.5 < row["max_stretch"] < 10                          # 1.6 at the paper's inflow; measured 4.3


def test_inflow_far_beyond_condition_16_tears_the_membrane_and_says_so_without_blaming_dt():
    row = run("c2")
    assert row["passed"] and not row["ran"]
    assert "torn apart" in row["diagnosis"] and "too fast for this membrane" in row["diagnosis"]
    assert "Remark 2.4" in row["diagnosis"] and "try dt" not in row["diagnosis"]


def test_a_cell_touching_the_lower_wall_slides_along_it_to_the_lower_outlet():
    row = run("d1")
    assert row["passed"] and row["ran"] and row["cells"][0]["fate"] == "lower"


def test_a_cell_driven_into_the_end_wall_ends_as_wall_between_the_outlets():
    row = run("d2")
    assert row["passed"] and row["cells"][0]["fate"] == "wall"
    assert 100 < row["cells"][0]["exit_y_um"] < 120


def test_an_under_resolved_cell_is_warned_about_and_leaves_where_it_does_on_the_papers_mesh():
    row = run("e")
    assert row["passed"] and row["cells"][0]["fate"] == "lower"
    assert any("fewer than two mesh cells" in warning and "mesh_h <= 3.75 um" in warning for warning in row["warnings"])


def test_many_cells_at_once_all_leave_by_an_outlet():
    row = run("f")
    assert row["passed"] and len(row["cells"]) == 12
    assert all(cell["fate"] in ("lower", "upper") for cell in row["cells"])
    assert row["step_ms"] > 0


# ---------------------------------------------------------------------------------- the checks themselves
@pytest.fixture
def limits():
    return HealthLimits.of(Scenario().with_numerics(mesh_h=5 * UM, dt=2.5e-6))


def test_a_membrane_stretched_beyond_the_limit_is_torn_apart(limits):
    melanoma = Scenario().cell_type("melanoma")
    membrane = Membrane.of(melanoma, (150 * UM, 110 * UM), 2.5 * UM)
    centre = np.array([150 * UM, 110 * UM])
    stretched = membrane.with_points(centre + (membrane.points - centre) * np.array([36.0, 1 / 36]))   # same area
    with pytest.raises(HealthError, match=r"torn apart: stretched to 2\d\.\d times") as caught:
        check_cells([Cell(3, stretched)], limits, 5, 1e-5)
    assert "v_hat" in str(caught.value) and "try dt" not in str(caught.value)
    check_cells([Cell(3, membrane.with_points(membrane.points * np.array([1.5, 1.0])))], limits, 5, 1e-5)


def test_a_fold_far_below_the_explicit_limit_is_blamed_on_the_flow_not_on_dt(limits):
    rbc = Scenario().cell_type("RBC")
    membrane = Membrane.of(rbc, (150 * UM, 110 * UM), 1 * UM)
    points = membrane.points.copy()
    points[[2, 9]] = points[[9, 2]]                               # two points swapped: the polygon crosses itself
    assert membrane_time_step(membrane, 6e-3) > 100 * limits.dt
    with pytest.raises(HealthError, match="intersects itself") as caught:
        check_cells([Cell(0, membrane.with_points(points))], limits, 1, 1e-5)
    assert "not a time-step instability" in str(caught.value) and "try dt" not in str(caught.value)


def test_under_resolution_is_named_at_cell_creation(caplog):
    rbc = Scenario().cell_type("RBC")
    assert under_resolved(rbc, 3.75 * UM) is None and "fewer than two mesh cells" in under_resolved(rbc, 4 * UM)
    plant = ImmersedBoundary(Scenario().with_numerics(mesh_h=10 * UM))
    with caplog.at_level(logging.WARNING, logger="sim.method.feib"):
        plant.new_cell(rbc, 4, 0.0)
    assert "cell 4: RBC is resolved by fewer than two mesh cells (diameter 7.5 um, h = 10 um)" in caplog.text


def test_max_stretch_is_validated():
    with pytest.raises(ScenarioError, match="max_stretch"):
        Scenario().with_numerics(max_stretch=1.0)
    assert Scenario().numerics.max_stretch == 20.0


def test_an_interrupt_keeps_the_cases_already_finished(monkeypatch):
    """Ctrl-C during a case: the cases finished before it are returned (and printed as a partial table)."""
    from vcyto.studies import extremes
    calls = []

    def fake(case, base, fast):
        calls.append(case.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return {"case": case.name, "setting": "", "expected": "", "passed": True, "observed": "ran", "problems": []}

    monkeypatch.setattr(extremes, "run_case", fake)
    result = extremes.run_cases(None, fast=True)
    assert result["interrupted"] and [row["case"] for row in result["rows"]] == calls[:1]
    assert "PARTIAL: interrupted" in extremes.report_lines(result)[-1]


def test_an_interrupted_stability_map_keeps_its_finished_rows(monkeypatch):
    from sim.method.stability import StabilityResult
    from sim.model.scenario import Scenario
    from vcyto.studies import stabilitymap
    calls = []

    class Quiet:
        def note(self, message):
            pass

    def fake(scenario, cell_type, start=None):
        calls.append(cell_type.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return StabilityResult(cell_type.name, scenario.numerics.mesh_h, 1e-4, float("inf"), 1, "")

    monkeypatch.setattr(stabilitymap, "stable_dt", fake)
    monkeypatch.setattr(stabilitymap, "NavierStokes", lambda scenario: type("F", (), {"steady": lambda s, a: None})())
    result = stabilitymap.stability_map(Scenario(), ["RBC", "melanoma"], [10e-6], Quiet())
    assert result["interrupted"] and [row["cell"] for row in result["rows"]] == ["RBC"]
    assert "PARTIAL: interrupted" in stabilitymap.report_lines(result)[-1]
