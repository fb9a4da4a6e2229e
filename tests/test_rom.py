"""The reduced plant `rom`: contract, gridded flows against the FE field, outlets against the FE-IB plant,
walls, determinism, the grouped closed loop against the period-by-period one, and the real-time bench."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from controller.detector import DetectorSettings
from controller.events import TYPE_II
from controller.sorter import ControllerSettings
from sim.method.fluid import NavierStokes
from sim.method.streamline import trace
from sim.method.transfer import PointLocator
from sim.model.arrivals import Arrivals
from sim.model.scenario import UM, Scenario
from sim.plants.rom import JET_RESPONSE_TIME, RomFlows, RomPlant, area_mean_rule, measure_response_time
from sim.plants.streamline import StreamlinePlant
from vcyto.outcomes import SORTED_OUTLET
from vcyto.stream import StreamSettings, run_stream

# The FE-IB plant on the paper's scenarios (docs/results.md, `vcyto paper 1`, `vcyto paper 2`): outlet and exit
# ordinate.
FEIB_SCENARIO_I = ("lower", 72.2 * UM)        # RBC, IDT off
FEIB_SCENARIO_II = ("upper", 140.8 * UM)      # melanoma, IDT on


@pytest.fixture(scope="module")
def flows(paper_scenario, paper_solver):
    return RomFlows.of(paper_scenario, fluid=paper_solver)


@pytest.fixture(scope="module")
def plant(paper_scenario, flows):
    return RomPlant(paper_scenario, flows=flows)


def run_alone(plant, name, drive=1.0):
    """One cell from the injection inlet to its fate at a constant drive; its ground truth."""
    plant.reset([(0.0, name)])
    for _ in range(round(20e-3 / plant.control_period)):
        if plant.done:
            break
        plant.step(drive)
    return plant.truth().cells[0]


def stream(scenario, plant, sinks=(), **options):
    arrivals = options.pop("arrivals", None) or Arrivals(cells=tuple(options.pop("cells", ())))
    return run_stream(scenario, StreamSettings(arrivals, model="rom", **options), plant=plant, sinks=sinks)


def test_gridded_flows_match_the_exact_fe_interpolation(paper_scenario, paper_solver, flows):
    locator = PointLocator(paper_solver.space.cmesh, paper_solver.space.velocity_basis.element_dofs)
    off, on = paper_solver.steady(0.0).velocity, paper_solver.steady(1.0).velocity
    points = np.random.default_rng(0).uniform([0, 0], [300 * UM, 220 * UM], size=(5000, 2))
    for level, exact_field in ((0.0, off), (1.0, on)):
        exact = locator.interpolate(exact_field, points)
        error = np.linalg.norm(flows.velocity(points, level) - exact) / np.linalg.norm(exact)
        assert error < 2e-3, (level, error)            # measured 5.7e-4 (off), 1.25e-3 (on) at 1 um
    # the injection streamline leaves where the exact field puts it (measured: within 0.002 um)
    channel, h, start = paper_scenario.channel, paper_scenario.numerics.mesh_h, np.array([1 * UM, 115 * UM])
    for level, exact_field in ((0.0, off), (1.0, on)):
        exact = trace(locator, exact_field, channel, start, h, fraction=0.05)
        gridded = _trace_on_grid(flows, level, start, h)
        assert abs(gridded - exact.exit_y) < 0.05 * UM, (level, gridded, exact.exit_y)


def _trace_on_grid(flows, level, point, h):
    """RK4 through the gridded point field; the exit ordinate at x = 300 um."""
    def velocity(p):
        return flows.velocity(p[None], level)[0]
    while True:
        k1 = velocity(point)
        dt = 0.05 * h / np.hypot(*k1)
        k2 = velocity(point + dt / 2 * k1)
        k3 = velocity(point + dt / 2 * k2)
        k4 = velocity(point + dt * k3)
        new = point + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if new[0] >= 300 * UM:
            return point[1] + (300 * UM - point[0]) / (new[0] - point[0]) * (new[1] - point[1])
        point = new


def test_area_mean_rule_is_exact_for_quadratics_and_converged_on_the_flow(flows, paper_scenario, paper_solver):
    offsets, weights = area_mean_rule((3.0, 2.0))
    assert weights.sum() == pytest.approx(1.0)
    assert weights @ offsets[:, 0] ** 2 == pytest.approx(9.0 / 4) and weights @ offsets[:, 1] ** 2 == pytest.approx(1.0)
    assert weights @ offsets[:, 0] ** 4 == pytest.approx(81.0 / 8)
    # a finer rule changes the melanoma's area-mean flow by < 0.1 % (relative L2 over the admissible region)
    locator = PointLocator(paper_solver.space.cmesh, paper_solver.space.velocity_basis.element_dofs)
    on = paper_solver.steady(1.0).velocity
    centres = np.random.default_rng(1).uniform([8 * UM, 8 * UM], [292 * UM, 212 * UM], size=(300, 2))
    means = {}
    for rings, spokes in ((3, 8), (8, 24)):
        offsets, weights = area_mean_rule((8 * UM, 8 * UM), rings, spokes)
        samples = locator.interpolate(on, (centres[:, None, :] + offsets[None]).reshape(-1, 2))
        means[rings] = np.einsum("q,nqc->nc", weights, samples.reshape(len(centres), len(weights), 2))
    assert np.linalg.norm(means[3] - means[8]) / np.linalg.norm(means[8]) < 1e-3
    gridded = flows.velocity(centres, 1.0, "melanoma")
    assert np.linalg.norm(gridded - means[8]) / np.linalg.norm(means[8]) < 3e-3


def test_paper_scenarios_leave_by_the_feib_plants_outlets(paper_scenario, flows):
    instant = RomPlant(paper_scenario, flows=flows, response_time=0.0)   # the paper's runs start in steady flow
    rbc, melanoma = run_alone(instant, "RBC", 0.0), run_alone(instant, "melanoma", 1.0)
    assert (rbc.fate, melanoma.fate) == (FEIB_SCENARIO_I[0], FEIB_SCENARIO_II[0])
    assert abs(rbc.exit_y - FEIB_SCENARIO_I[1]) < 1 * UM           # measured 71.9 um
    assert abs(melanoma.exit_y - FEIB_SCENARIO_II[1]) < 1 * UM     # measured 141.1 um
    # the finite size matters: the melanoma's area-mean flow is not the point flow at its centroid
    assert not np.allclose(flows.velocity([[150 * UM, 110 * UM]], 1.0, "melanoma"),
                           flows.velocity([[150 * UM, 110 * UM]], 1.0), rtol=1e-3)


def test_isolated_cells_in_the_closed_loop_agree_with_the_feib_and_streamline_plants(paper_scenario, paper_solver,
                                                                                     plant):
    # FE-IB in the loop (tests/test_stream.py, docs/results.md): RBC passed -> lower, melanoma sorted -> upper
    streamline = StreamlinePlant(paper_scenario, fluid=paper_solver)
    for name, expected in (("RBC", ("pass", "lower")), ("melanoma", ("sort", "upper"))):
        rom = stream(paper_scenario, plant, cells=(name,))["cells"][0]
        line = run_stream(paper_scenario, StreamSettings(Arrivals(cells=(name,)), model="streamline"),
                          plant=streamline)["cells"][0]
        assert (rom["decision"], rom["outlet"]) == expected == (line["decision"], line["outlet"])
        assert abs(rom["detection_time_ms"] - line["detection_time_ms"]) < 0.05
    melanoma = stream(paper_scenario, plant, cells=("melanoma",), controller=ControllerSettings(enabled=False))
    assert melanoma["cells"][0]["outlet"] == "lower"


def test_a_cell_pushed_into_a_wall_slides_along_it_and_sticks_in_a_corner():
    scenario = Scenario()
    down_right = RomFlows.uniform(scenario, off=(0.05, -0.05), on=(0.05, -0.05))
    plant = RomPlant(scenario, flows=down_right, response_time=0.0, stall_time=0.2e-3)
    a, b = scenario.cell_type("RBC").semi_axes
    plant.reset([(0.0, "RBC")])
    for _ in range(200):                       # 4 ms: it reaches the lower wall after 2.25 ms
        plant.step(0.0)
    (cell,) = plant.observe().cells
    assert cell.y == pytest.approx(b, abs=1e-15)                       # held off by its semi-axis
    assert cell.x == pytest.approx(a + 1 * UM + 0.05 * 4e-3, rel=1e-9)  # and still moving along the wall
    assert plant.diagnostics()["wall_contacts"] > 0
    while not plant.done:                      # it slides into the corner with the outlet-side wall and stops
        plant.step(0.0)
    (truth,) = plant.truth().cells
    assert truth.fate == "wall"
    assert truth.x == pytest.approx(300 * UM - a) and truth.exit_y == pytest.approx(b)
    slide_end = (300 * UM - a - (a + 1 * UM)) / 0.05                   # time to reach the corner
    assert slide_end < truth.exit_time < slide_end + 0.2e-3 + 2 * plant.control_period


def _divider_run(catch_on_divider, inlet_span):
    # the injection inlet moved to ``inlet_span`` (um) and a flow straight to the right: a melanoma (radius
    # 8 um) runs towards the outlet plane at the inlet's middle; the wall between the outlets spans 100-120 um
    paper = Scenario()
    inlets = (paper.channel.inlets[0], replace(paper.channel.inlets[1], span=tuple(v * UM for v in inlet_span)),
              paper.channel.inlets[2])
    scenario = replace(paper, channel=replace(paper.channel, inlets=inlets))
    plant = RomPlant(scenario, flows=RomFlows.uniform(scenario, off=(0.1, 0.0), on=(0.1, 0.0)), response_time=0.0,
                     catch_on_divider=catch_on_divider)
    plant.reset([(0.0, "melanoma")])
    while not plant.done:
        plant.step(0.0)
    (truth,) = plant.truth().cells
    return plant, truth


@pytest.mark.parametrize("catch_on_divider", [False, True])
def test_a_cell_at_an_outlet_edge_is_steered_round_the_corner_into_the_outlet(catch_on_divider):
    # it starts at y = 97 um, 3 um below the divider's end (300, 100) um: its outline meets the end, its
    # centroid passes outside the divider's span, as an FE-IB cell's would (the divider rule leaves it alone)
    plant, truth = _divider_run(catch_on_divider, (84, 110))
    assert truth.fate == "lower"
    assert truth.exit_y == pytest.approx(92 * UM, abs=0.2 * UM)    # its outline just clears the corner
    assert plant.diagnostics()["wall_contacts"] > 0


def test_a_cell_pressed_on_the_divider_settles_on_it():
    # it starts at y = 105 um, in the divider's span: with the divider rule (the default) it settles on the
    # face when it reaches it, where an FE-IB cell's centroid would leave through the wall (fate wall);
    # without, it is held on the face (this flow has no component along it) until the stall rule's 1 ms
    plant, truth = _divider_run(True, (92, 118))
    assert truth.fate == "wall" and truth.exit_y == pytest.approx(105 * UM, abs=1e-9)
    assert truth.x == pytest.approx(300 * UM - 8 * UM, abs=1e-9) and truth.exit_time < 3e-3
    _, held = _divider_run(False, (92, 118))
    assert held.fate == "wall" and held.exit_time >= truth.exit_time + 1e-3 - plant.control_period


def test_same_seed_same_stream_other_seed_other_stream(paper_scenario, plant):
    arrivals = Arrivals(count=60, mix=(("RBC", 0.7), ("melanoma", 0.3)), rate=2000.0, process="poisson", min_spacing=0)
    first, second, other = (stream(paper_scenario, plant, arrivals=arrivals, seed=seed) for seed in (5, 5, 6))
    assert first["cells"] == second["cells"]
    assert first["cells"] != other["cells"]


class _EveryPeriod:
    """A sink that records nothing: its presence makes the loop step the plant period by period."""

    def on_step(self, record):
        pass


@pytest.mark.parametrize("window, mode", [((30 * UM, 60 * UM), "purity"), ((5 * UM, 12 * UM), "yield")])
def test_grouped_periods_give_the_same_stream_as_period_by_period(paper_scenario, plant, window, mode):
    # (5, 12) um: melanomas start inside the window (x = 9 um), RBCs just before it, and cross both edges fast
    arrivals = Arrivals(count=80, mix=(("RBC", 0.7), ("melanoma", 0.3)), rate=2000.0, process="poisson", min_spacing=0)
    options = dict(arrivals=arrivals, seed=2, detector=DetectorSettings(window=window),
                   controller=ControllerSettings(mode=mode))
    grouped = stream(paper_scenario, plant, **options)
    stepped = stream(paper_scenario, plant, sinks=[_EveryPeriod()], **options)
    assert grouped["cells"] == stepped["cells"]
    assert grouped["simulated_time_ms"] == stepped["simulated_time_ms"]
    assert {c["decision"] for c in grouped["cells"]} >= ({"sort", "pass", "abort"} if mode == "purity" else {"sort"})


def test_mixed_stream_statistics_equal_counts_by_hand(paper_scenario, plant):
    arrivals = Arrivals(count=200, mix=(("RBC", 0.8), ("melanoma", 0.2)), rate=1000.0, process="poisson", min_spacing=0)
    result = stream(paper_scenario, plant, arrivals=arrivals, seed=11, max_time=1.0)
    cells, stats = result["cells"], result["statistics"]
    upper = [c for c in cells if c["outlet"] == SORTED_OUTLET]
    wanted = [c for c in cells if c["true_class"] == TYPE_II]
    detected = [c for c in cells if c["detected_class"] == TYPE_II]
    assert stats["cells"] == 200 and stats["undetected"] == 0
    assert stats["purity"] == sum(c["true_class"] == TYPE_II for c in upper) / len(upper)
    assert stats["yield"] == sum(c["outlet"] == SORTED_OUTLET for c in wanted) / len(wanted)
    assert stats["abort_rate"] == sum(c["decision"] == "abort" for c in cells) / len(detected)
    assert stats["outlets"] == {o: sum(c["outlet"] == o for c in cells) for o in {c["outlet"] for c in cells}}
    assert set(stats["outlets"]) <= {"lower", "upper"}
    # what the controller sorts goes up, and an RBC that no pulse touched goes down
    for cell in cells:
        if cell["decision"] == "sort" and cell["true_class"] == TYPE_II:
            assert cell["outlet"] == SORTED_OUTLET, cell
    pulses = [(c["exit_time_ms"] - 3, c["exit_time_ms"] + 3) for c in cells if c["decision"] == "sort"]
    for cell in cells:
        if cell["type"] == "RBC" and not any(low < cell["exit_time_ms"] < high for low, high in pulses):
            assert cell["outlet"] == "lower", cell


def test_realtime_bench_reports_the_real_time_factor():
    command = [sys.executable, "-m", "vcyto.cli", "bench", "realtime", "--duration", "30ms", "--repeats", "1",
               "--json", "--mesh-h", "5um"]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["cells"] == 30 and report["model"] == "rom"
    assert report["real_time_factor"] == pytest.approx(report["device_time_s"] / report["loop_wall_s"])
    assert report["device_time_s"] > 0.01 and report["setup_s"] > 0 and report["control_period_us"] == 20
    assert sum(report["outlets"].values()) == 30


@pytest.mark.slow
def test_the_lag_is_the_measured_response_of_the_fe_flow():
    fluid = NavierStokes(Scenario().with_numerics(dt=10e-6))
    assert measure_response_time(fluid) == pytest.approx(JET_RESPONSE_TIME, rel=0.1)


@pytest.mark.slow
def test_rom_and_feib_agree_on_the_outlet_of_every_isolated_cell_scene():
    """Each cell type alone with the IDT off, on, and in the closed loop (passed, sorted, a misclassified RBC
    sorted): the same outlet from both plants, and at a constant drive exit ordinates within 1 um
    (measured: 0.3-0.8 um; exit times within 2 %)."""
    from sim.plants.feib import FeibPlant
    scenario = Scenario().with_numerics(dt=10e-6)        # stable for both cell types (docs/results.md, stability)
    feib = FeibPlant(scenario)
    rom = RomPlant(scenario, flows=RomFlows.of(scenario, fluid=feib.ib.fluid))
    for name in ("RBC", "melanoma"):
        for drive in (0.0, 1.0):
            full, reduced = (run_alone(plant, name, drive) for plant in (feib, rom))
            assert full.fate == reduced.fate, (name, drive)
            assert abs(full.exit_y - reduced.exit_y) < 1 * UM, (name, drive, full.exit_y, reduced.exit_y)
        for detector in (DetectorSettings(), DetectorSettings(gate=0.0)):    # gate 0: every cell is sorted
            settings = {model: StreamSettings(Arrivals(cells=(name,)), detector=detector, model=model)
                        for model in ("feib", "rom")}
            full, reduced = (run_stream(scenario, settings[model], plant=plant)["cells"][0]
                             for model, plant in (("feib", feib), ("rom", rom)))
            assert (full["decision"], full["outlet"]) == (reduced["decision"], reduced["outlet"]), (name, detector)


def test_the_plants_fast_views_and_truths_are_the_dataclasses_own():
    """The views, truths and observations the plant builds without the frozen dataclasses' ``__init__`` are the
    objects it would build: equal, with the same fields in the same order, repr, pickle and immutability."""
    import dataclasses
    import pickle

    from sim.plants import rom
    from sim.plants.contract import CellTruth, CellView, Observation
    made = [(rom._view(3, 1e-5, 2e-5, 3e-11, 1.0), CellView(3, 1e-5, 2e-5, 3e-11, 1.0)),
            (rom._truth(7, "RBC", 0.1, "upper", 0.2, 1.4e-4, 3e-4, 1.4e-4),
             CellTruth(7, "RBC", 0.1, "upper", 0.2, 1.4e-4, 3e-4, 1.4e-4, 1.0)),
            (rom._observation(0.5, (CellView(1, 0.0, 0.0, 1.0, 0.0),)),
             Observation(0.5, (CellView(1, 0.0, 0.0, 1.0, 0.0),)))]
    for fast, own in made:
        assert type(fast) is type(own) and fast == own and repr(fast) == repr(own)
        assert list(vars(fast)) == [f.name for f in dataclasses.fields(own)] == list(vars(own))
        assert pickle.loads(pickle.dumps(fast)) == own and hash(fast) == hash(own)
        with pytest.raises(dataclasses.FrozenInstanceError):
            fast.time = 0.0
