"""The second-order FE-IB step (numerics.time_scheme = "bdf2"; docs/numerics.md, "A second-order step"):
its order against the paper's first-order step, its history (value_back, carried through a redistribution),
a steady flow kept steady, and the one-line errors of bad choices."""

import subprocess
import sys

import numpy as np
import pytest

from sim.method.feib import ImmersedBoundary
from sim.method.fluid import NavierStokes
from sim.method.membrane import Membrane
from sim.method.openloop import stepping, with_cells
from sim.method.timeschemes import earlier_at, lagrange_weights, value_back
from sim.model.scenario import UM, Scenario, ScenarioError


def final_state(scheme, dt, until=300e-6):
    """An RBC in the channel for ``until`` on a 10 um mesh (the paper's literal membrane: no discrete events)."""
    scenario = Scenario().with_numerics(mesh_h=10 * UM, dt=dt, time_scheme=scheme).with_membrane("paper")
    plant = ImmersedBoundary(scenario)
    state = with_cells(plant, plant.start().flow, [(scenario.cell_type("RBC"), None)])
    for state in stepping(plant.step, state, until=until - 1e-12):
        pass
    assert state.time == pytest.approx(until)
    return state.cells[0].membrane.points, state.flow.velocity


@pytest.mark.parametrize("scheme, order", [("euler", 1), ("bdf2", 2)])
def test_the_error_falls_with_the_order_of_the_scheme(scheme, order):
    """Halving dt divides the error at a fixed time by 2^order (against dt = 1.25 us), for the membrane points
    and the flow; measured 2.1-2.3 (euler) and 4.0-4.3 (bdf2)."""
    reference = final_state(scheme, 1.25e-6)
    errors = []
    for dt in (20e-6, 10e-6, 5e-6):
        points, velocity = final_state(scheme, dt)
        errors.append((np.abs(points - reference[0]).max(), np.abs(velocity - reference[1]).max()))
    for coarse, fine in zip(errors[:-1], errors[1:]):
        for part in range(2):
            assert 0.8 * 2 ** order < coarse[part] / fine[part] < 1.25 * 2 ** order, errors
    if scheme == "bdf2":                        # and far smaller than the first-order error at the same dt
        euler = final_state("euler", 5e-6)[0]
        assert np.abs(euler - reference[0]).max() > 10 * errors[-1][0]


def test_value_back_reuses_an_earlier_value_or_interpolates_to_second_order():
    def f(t):                          # a parabola: interpolated exactly
        return np.array([1.0 + 2.0 * t - 3.0 * t * t, t * t])

    now = 10.0
    assert value_back(now, f(now), [], [], 9.0) is None              # a start: no history
    earlier = [f(9.0), f(8.0)]
    assert value_back(now, f(now), [9.0, 8.0], earlier, 9.0) is earlier[0]     # equal steps
    assert value_back(now, f(now), [9.0, 8.0], earlier, 8.0) is earlier[1]     # one level up after two equal
    assert np.allclose(value_back(now, f(now), [9.0, 8.0], earlier, 9.5), f(9.5), rtol=0, atol=1e-12)
    line = value_back(now, f(now), [9.0], earlier[:1], 9.5)          # two values: the line through them
    assert np.allclose(line, (f(now) + f(9.0)) / 2)


def test_an_earlier_time_is_picked_or_the_parabolas_weights_given():
    """The momentum kernel forms v^{m-1} from weights of (v^m, earlier velocities): an earlier velocity itself where
    its time is the target (``earlier_at``: no arithmetic on the values), else Lagrange weights that reproduce a
    parabola (``lagrange_weights``)."""
    assert earlier_at(10.0, [], 9.0) is None
    assert earlier_at(10.0, [9.0, 8.0], 9.0) == 0
    assert earlier_at(10.0, [9.0, 8.0], 8.0) == 1
    assert earlier_at(10.0, [9.0, 8.0], 9.5) is None
    weights = lagrange_weights([10.0, 9.0, 8.0], 9.5)
    assert sum(weights) == pytest.approx(1.0) and weights == pytest.approx([0.375, 0.75, -0.125])
    times = (10.0, 9.0, 8.0)
    values = [1.0 + 2.0 * t - 3.0 * t * t for t in times]
    assert sum(w * v for w, v in zip(weights, values)) == pytest.approx(1.0 + 2.0 * 9.5 - 3.0 * 9.5 ** 2)
    assert lagrange_weights([10.0, 9.0], 9.5) == pytest.approx([0.5, 0.5])      # the line through two


def test_the_momentum_kernel_gets_an_earlier_velocity_itself_or_the_parabolas_weights():
    """``_momentum_back``: the step's v^{m-1} as the kernel forms it. An earlier velocity whose time is the target is
    passed as it is (weights (0, 1, 0): no arithmetic on its values), the latest or the one before it; otherwise the
    Lagrange weights of v^m and both earlier velocities; euler and a start (no history) get none."""
    from types import SimpleNamespace
    bdf2 = Scenario().with_numerics(time_scheme="bdf2", dt=1.0)
    first, second = np.ones((2, 3)), 2 * np.ones((2, 3))
    flow = SimpleNamespace(time=10.0, history=((9.0, first), (8.0, second)))

    def back(flow, scenario=bdf2):
        return NavierStokes._momentum_back(SimpleNamespace(scenario=scenario), flow)
    weights, (a, _) = back(flow)                                                   # equal steps: the latest
    assert weights == (0.0, 1.0, 0.0) and a is first
    weights, (a, _) = back(flow, bdf2.with_numerics(dt=2.0))                       # one level up: the one before
    assert weights == (0.0, 1.0, 0.0) and a is second
    weights, (a, b) = back(flow, bdf2.with_numerics(dt=0.5))                       # between: the parabola's
    assert weights == pytest.approx((0.375, 0.75, -0.125)) and a is first and b is second
    assert back(SimpleNamespace(time=10.0, history=())) is None
    assert back(flow, bdf2.with_numerics(time_scheme="euler")) is None


def test_a_redistribution_carries_the_history_to_the_new_points():
    """The history (earlier points) is taken to the new points' spline parameters: a history equal to the
    points is carried to exactly the new points, and a translated one to the translated new points."""
    rbc = Scenario().cell_type("RBC")
    membrane = Membrane.of(rbc, (100 * UM, 100 * UM), 2 * UM)
    stretched = membrane.with_points(membrane.points * np.array([1.6, 0.7]))
    shift = np.array([0.3 * UM, -0.1 * UM])
    new, (same, moved) = stretched.resampled_carrying(1 * UM, (stretched.points, stretched.points + shift))
    assert len(new.points) != len(stretched.points)
    assert np.allclose(same, new.points, rtol=0, atol=1e-18)
    assert np.allclose(moved, new.points + shift, rtol=0, atol=1e-15)


def test_a_steady_flow_stays_steady():
    scenario = Scenario().with_numerics(mesh_h=10 * UM, time_scheme="bdf2", precision="double")
    fluid = NavierStokes(scenario)
    flow = fluid.initial_flow()
    for _ in range(3):
        flow = fluid.step(flow)
    assert len(flow.history) == 2 and flow.history[0][0] == pytest.approx(5e-6)
    scale = np.abs(fluid.initial_flow().velocity).max()
    assert np.abs(flow.velocity - fluid.initial_flow().velocity).max() < 1e-8 * scale


def test_bdf2_needs_a_constant_matrix():
    with pytest.raises(ScenarioError, match="bdf2 needs the convection treatment imex or stokes"):
        Scenario().with_numerics(time_scheme="bdf2", convection="oseen")
    # auto falls back to euler where bdf2 cannot run
    assert Scenario().with_numerics(tolerance=1e-6, convection="oseen").numerics.scheme == "euler"
    assert Scenario().with_numerics(tolerance=1e-6).numerics.scheme == "bdf2"
    assert Scenario().numerics.scheme == "euler"


@pytest.mark.parametrize("arguments, message", [
    (["paper", "2", "--time-scheme", "bdf3"], "vcyto: error: --time-scheme: invalid choice: 'bdf3'"),
    (["stream", "--model", "rom", "--time-scheme", "bdf2"], "--time-scheme: sets the time scheme of the feib step"),
    (["bench", "fluid", "--time-scheme", "bdf2"], "--time-scheme: bench fluid compares convection treatments"),
    (["paper", "2", "--set", "numerics.time_scheme=rk4"], "numerics.time_scheme: must be one of auto, euler, bdf2"),
    (["paper", "2", "--time-scheme", "bdf2", "--convection", "implicit"],
     "numerics.time_scheme: bdf2 needs the convection treatment imex or stokes"),
])
def test_bad_time_schemes_are_one_line_errors(arguments, message):
    result = subprocess.run([sys.executable, "-m", "vcyto.cli", *arguments], capture_output=True, text=True)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and result.stderr.count("\n") == 1 and "Traceback" not in result.stderr


def test_the_tradeoff_ladder_names_the_time_scheme():
    from vcyto.studies.tradeoff import LADDER, Level, tradeoff
    assert Level("feib", 10 * UM / 3, 2.5e-6, tolerance=1e-6).label.endswith("tolerance=1um bdf2")
    assert Level("feib", 10 * UM / 3, 2.5e-6).label == "feib h=3.33um dt=2.5us"           # auto, fixed: euler
    assert [level.label for level in LADDER].count("feib h=3.33um dt=10us bdf2") == 1
    # --time-scheme given: every feib level whose own scheme is auto takes it, and says so
    result = tradeoff(Scenario().with_numerics(time_scheme="bdf2"), ladder=LADDER[:2], scenes=())
    assert result["reference"] == "feib h=3.33um dt=2.5us bdf2" and result["rows"] == []
    from vcyto.studies.tradeoff import resolved_ladder
    labels = [level.label for level in resolved_ladder(Scenario().with_numerics(time_scheme="bdf2"), LADDER)]
    assert len(labels) == len(set(labels)) == len(LADDER) - 2       # the two bdf2 levels are now duplicates
    oseen = resolved_ladder(Scenario().with_numerics(convection="oseen"), LADDER)
    assert not any("bdf2" in level.label for level in oseen)          # explicit bdf2 left out, auto is euler
    # and the implicit coupling's levels too: both need a linear fluid step
    assert not any("implicit" in level.label for level in oseen)
    assert len(oseen) == len(LADDER) - 4 and all(level.scheme in ("euler", "auto") for level in oseen)


def test_the_paper_run_reports_its_time_scheme(tmp_path):
    import json
    runs = {}
    for scheme in ("bdf2", "auto"):
        result = subprocess.run([sys.executable, "-m", "vcyto.cli", "paper", "2", "--no-png", "--json", "--quiet",
                                 "--mesh-h", "10um", "--membrane", "conserving", "--time-scheme", scheme],
                                capture_output=True, text=True,
                                cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        runs[scheme] = json.loads(result.stdout)
    assert runs["bdf2"]["time_scheme"] == "bdf2" and runs["auto"]["time_scheme"] == "euler"
    assert runs["bdf2"]["cells"][0]["outlet"] == runs["auto"]["cells"][0]["outlet"] == "upper"
