"""The `auto` plant (rom, FE-IB while cells are close) and `vcyto tradeoff` (speed against accuracy)."""

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from sim.model.scenario import UM, Scenario
from sim.plants.auto import AutoPlant
from sim.plants.feib import FeibPlant
from vcyto.studies.tradeoff import SCENES, TOLERANCE_UM, Scene, compare, run_scene

CLOSE_PAIR = SCENES[2]


@pytest.fixture(scope="module")
def coarse():
    scenario = Scenario().with_numerics(mesh_h=20 * UM / 3, dt=10e-6)
    return scenario, AutoPlant(scenario, grid_spacing=2 * UM), FeibPlant(scenario)


def test_an_isolated_cell_never_needs_the_feib_model(coarse):
    _, auto, _ = coarse
    run = run_scene(auto, SCENES[0])
    assert run["cells"][0]["fate"] == "lower"
    assert auto.switches == [(0.0, "rom", "start: no cells close together")] and auto.feib_steps == 0


def test_a_close_pair_runs_in_feib_while_close_and_is_within_tolerance_where_rom_is_not(coarse):
    scenario, _, feib = coarse
    auto = AutoPlant(scenario, grid_spacing=2 * UM, stiff_capillary=0.0)     # the distance rule alone
    reference = run_scene(feib, CLOSE_PAIR)
    result = compare(run_scene(auto, CLOSE_PAIR), reference)
    models = [model for _, model, _ in auto.switches]
    assert models[:3] == ["rom", "feib", "rom"]                  # switched to feib and back when apart
    assert "within" in auto.switches[1][2] and "no two cells" in auto.switches[2][2]
    assert 0 < auto.feib_steps < auto.steps
    assert result["outlets_agree"] == 2 and result["path_mean_um"] < TOLERANCE_UM
    from sim.plants.rom import RomPlant
    rom = compare(run_scene(RomPlant(scenario, control_period=20e-6, flows=auto.rom.flows), CLOSE_PAIR), reference)
    assert rom["path_mean_um"] > 2 * result["path_mean_um"]


def test_the_capillary_numbers_put_the_melanoma_among_stiff_cells_and_the_rbc_among_soft_ones(coarse):
    scenario, auto, _ = coarse
    off, on = (flow.velocity for flow in auto._steady)
    saw_speed = np.abs(np.hypot(*(on - off))).max()
    assert 0.3 < saw_speed < 1.5                                  # m/s: the IDT's jet (docs/results.md: 0.66 m/s)
    for cell in scenario.cell_types:
        assert auto.capillary[cell.name] == pytest.approx(scenario.fluid.viscosity * saw_speed / cell.kappa_e)
    assert auto.capillary["melanoma"] < auto.stiff_capillary < auto.capillary["RBC"]
    with pytest.raises(ValueError, match="stiff_capillary"):
        AutoPlant(scenario, grid_spacing=2 * UM, stiff_capillary=-1.0)


def test_a_stiff_cell_with_company_runs_in_feib_at_any_distance_and_rom_once_it_is_alone(coarse):
    scenario, auto, _ = coarse
    scene = Scene("melanoma, RBC 1 ms later", ((0.0, "melanoma"), (1.0e-3, "RBC")))
    run = run_scene(auto, scene)
    times = [t for t, _, _ in auto.switches]
    assert [model for _, model, _ in auto.switches][:3] == ["rom", "feib", "rom"]
    assert "cell 0 (melanoma, Ca = " in auto.switches[1][2] and "shares the channel with cell 1" in auto.switches[1][2]
    assert times[1] == pytest.approx(1.0e-3, abs=1.5 * scenario.numerics.dt)      # when the RBC came in: far apart
    exit_melanoma = run["cells"][0]["exit_time"]
    assert exit_melanoma < times[2] <= exit_melanoma + auto.dwell + 2 * scenario.numerics.dt
    assert "no stiff cell" in auto.switches[2][2]


def test_soft_cells_further_apart_than_the_coupling_distance_stay_in_rom(coarse):
    _, auto, _ = coarse
    run_scene(auto, Scene("two RBCs 1 ms apart", ((0.0, "RBC"), (1.0e-3, "RBC"))))
    assert [model for _, model, _ in auto.switches] == ["rom"] and auto.feib_steps == 0


@pytest.fixture(scope="module")
def windowed():
    """A 5 um mesh: the auto plant's windows run on its default 6.67 um mesh, its rom flows come from 5 um."""
    scenario = Scenario().with_numerics(mesh_h=5 * UM, dt=10e-6)
    return scenario, AutoPlant(scenario, grid_spacing=2 * UM), FeibPlant(scenario)


def test_windows_run_on_the_coarser_mesh_and_rom_on_the_scenarios_own(windowed):
    scenario, auto, feib = windowed
    assert auto.window_mesh_h == pytest.approx(20 * UM / 3)
    assert auto.diagnostics()["window_mesh_h"] == auto.window_mesh_h
    assert auto.feib.ib.fluid.space.dofs < 0.7 * feib.ib.fluid.space.dofs
    own = AutoPlant(scenario, grid_spacing=2 * UM, window_mesh_h=scenario.numerics.mesh_h)
    assert own.feib.ib.fluid.space.dofs == feib.ib.fluid.space.dofs
    np.testing.assert_array_equal(own.rom.flows.cells, auto.rom.flows.cells)     # rom: the scenario's mesh
    with pytest.raises(ValueError, match="window_mesh_h must be a positive length"):
        AutoPlant(scenario, window_mesh_h=-1.0)


def test_the_hand_over_to_the_coarse_window_keeps_each_cell_where_rom_had_it(windowed):
    _, auto, _ = windowed
    auto.reset([(0.0, "melanoma"), (0.05e-3, "RBC")])
    while auto.model == "rom" and auto.steps < 200:
        auto.step(0.0)
    assert auto.model == "feib"
    rom_now = {cell.key: (cell.x, cell.y) for cell in auto.rom.observe().cells}
    window = auto.feib.observe().cells
    assert sorted(cell.key for cell in window) == sorted(rom_now) == [0, 1]
    for cell in window:                             # the window's membranes, centred on rom's centroids
        assert math.dist((cell.x, cell.y), rom_now[cell.key]) < 1e-3 * UM


def test_a_close_pair_with_coarse_windows_is_within_tolerance_of_feib_on_the_finer_mesh(windowed):
    _, auto, feib = windowed
    result = compare(run_scene(auto, CLOSE_PAIR), run_scene(feib, CLOSE_PAIR))
    assert auto.feib_steps > 0 and result["outlets_agree"] == 2 and result["path_mean_um"] < TOLERANCE_UM


def test_auto_reports_what_it_runs_in_its_diagnostics(coarse):
    _, auto, _ = coarse
    run_scene(auto, Scene("pair", ((0.0, "RBC"), (0.2e-3, "RBC")), max_time=0.5e-3))
    assert auto.diagnostics()["model"] == "feib" and "within" in auto.diagnostics()["reason"]


def test_bench_auto_compares_the_two_models_cell_by_cell(coarse):
    from vcyto.bench.auto import auto_lines, bench_auto
    scenario, _, _ = coarse
    result = bench_auto(scenario, count=3, rate=1000.0, seed=1)
    outcomes = result["outcomes"]
    # cells offered at 1000/s: the inlet's dead time may reject some (sim.model.arrivals); every admitted one is
    # compared
    assert [o["key"] for o in outcomes] == list(range(len(outcomes))) and len(outcomes) >= 2
    assert all(o["auto"] in ("upper", "lower") and o["feib"] in ("upper", "lower") for o in outcomes)
    assert [d["key"] for d in result["outlets_differ"]] == [o["key"] for o in outcomes if o["auto"] != o["feib"]]
    assert result["speedup_run"] == pytest.approx(result["run_s"]["feib"] / result["run_s"]["auto"])
    lines = auto_lines(result)
    assert lines[0].startswith("3-cell Poisson stream at 1000/s") and "outlets that differ" in lines[1]


def test_extra_scenes_are_the_close_pair_with_another_gap_or_without_the_melanoma():
    from vcyto.studies.tradeoff import lone_rbc_scene, pair_scene
    assert pair_scene(0.25e-3).arrivals == CLOSE_PAIR.arrivals and pair_scene(0.25e-3).pulses == CLOSE_PAIR.pulses
    lone = lone_rbc_scene(0.565e-3)
    assert lone.arrivals == ((0.565e-3, "RBC"),) and lone.pulses == CLOSE_PAIR.pulses
    assert [lone.actuation(t) for t in (0.5e-3, 1.0e-3, 2.2e-3)] == [0.0, 1.0, 0.0]


@pytest.mark.slow
def test_tradeoff_fast_writes_table_csv_plot_and_auto_is_within_tolerance(tmp_path):
    result = subprocess.run([sys.executable, "-m", "vcyto.cli", "tradeoff", "--fast", "--output", str(tmp_path),
                             "--json",
                             "--stiff-capillary", "0", "--pair-gap", "1.0"], capture_output=True, text=True,
                            timeout=1200)
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)["rows"]
    levels = list(dict.fromkeys(row["level"] for row in rows))
    scenes = list(dict.fromkeys(row["scene"] for row in rows))
    assert levels[-1].endswith("stiff Ca<0") and scenes[-1] == "melanoma and RBC 1 ms apart, pulse 0.9-2.1 ms"
    assert len(rows) == len(levels) * len(scenes) == 7 * 4       # FAST_LADDER (with a tolerance level) + 1
    assert {p.name for p in tmp_path.iterdir()} >= {"tradeoff.md", "tradeoff.csv", "tradeoff.png"}
    with open(tmp_path / "tradeoff.csv") as handle:
        assert len(list(csv.DictReader(handle))) == len(rows)
    isolated = [r for r in rows if r["scene"].startswith("isolated")]
    assert all(r["outlets_agree"] == r["cells"] for r in isolated if r["model"] in ("rom", "feib"))
    for row in (r for r in rows if r["model"] == "auto"):
        assert row["outlets_agree"] == row["cells"] and row["path_mean_um"] < TOLERANCE_UM
    auto_wall = sum(r["run_s"] for r in rows if r["model"] == "auto")
    reference_wall = sum(r["run_s"] for r in rows if r["level"] == rows[0]["level"])
    assert auto_wall < reference_wall


@pytest.mark.parametrize("signal_name, status", [("SIGINT", 130), ("SIGTERM", 143)])
def test_an_interrupted_tradeoff_prints_its_finished_rows_as_partial_and_saves_nothing(signal_name, status,
                                                                                      monkeypatch, tmp_path, capsys):
    """Ctrl-C or SIGTERM during the third row: the two rows finished are printed, marked PARTIAL; exit 130 or
    143; no file claims a whole table, and the output directory this run created is removed again."""
    import os
    import signal

    from vcyto.cli import main
    from vcyto.studies import tradeoff
    calls = []

    def fake_run(plant, scene):
        calls.append(scene.name)
        if len(calls) == 3:
            os.kill(os.getpid(), getattr(signal, signal_name))
        return {"wall_s": 0.5, "cells": {0: {"fate": "lower"}}, "failure": None}

    monkeypatch.setattr(tradeoff, "make_plant", lambda scenario, level, flows: None)
    monkeypatch.setattr(tradeoff, "run_scene", fake_run)
    monkeypatch.setattr(tradeoff, "compare", lambda run, reference: {
        "cells": 1, "outlets_agree": 1, "path_max_um": 0.0, "path_mean_um": 0.0, "exit_error_us": 0.0,
        "area_loss_percent": 0.0})
    output = tmp_path / "new" / "tradeoff"
    assert main(["tradeoff", "--fast", "--quiet", "--output", str(output)]) == status
    table = capsys.readouterr().out
    rows = [line for line in table.splitlines() if line.startswith("| ") and "lower" in line]
    assert len(rows) == 2 and all(name in rows[i] for i, name in enumerate(calls[:2]))
    planned = len(tradeoff.FAST_LADDER) * len(tradeoff.SCENES)
    assert f"PARTIAL: interrupted after 2 of {planned} rows" in table
    assert not (tmp_path / "new").exists()


def test_an_interrupt_while_tradeoff_saves_waits_for_its_files(monkeypatch, tmp_path, capsys):
    """Ctrl-C after tradeoff.md is written and before the CSV: the save finishes, the files are listed, exit 130."""
    import os
    import signal

    from vcyto.cli import main
    from vcyto.studies import tradeoff
    monkeypatch.setattr(tradeoff, "make_plant", lambda scenario, level, flows: None)
    monkeypatch.setattr(tradeoff, "run_scene", lambda plant, scene: {
        "wall_s": 0.5, "cells": {0: {"fate": "lower"}}, "failure": None})
    monkeypatch.setattr(tradeoff, "compare", lambda run, reference: {
        "cells": 1, "outlets_agree": 1, "path_max_um": 0.1, "path_mean_um": 0.1, "exit_error_us": 0.0,
        "area_loss_percent": 0.0})
    real_write_whole = __import__("vcyto.outputs", fromlist=["write_whole"]).write_whole

    def interrupted_write(path, write):
        if path.name == "tradeoff.csv":
            os.kill(os.getpid(), signal.SIGINT)
        real_write_whole(path, write)
    monkeypatch.setattr("vcyto.outputs.write_whole", interrupted_write)
    assert main(["tradeoff", "--fast", "--quiet", "--output", str(tmp_path)]) == 130
    assert {p.name for p in tmp_path.iterdir()} == {"tradeoff.md", "tradeoff.csv", "tradeoff.png"}
    assert f"saved {tmp_path / 'tradeoff.md'}" in capsys.readouterr().out
