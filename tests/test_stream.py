"""The closed sorting loop: plant contract, detector, controller, outlets and sort statistics."""

import math
import subprocess
import sys

import numpy as np
import pytest

from controller.detector import DetectorSettings
from controller.sorter import ControllerSettings
from sim.model.arrivals import Arrivals, schedule
from sim.model.scenario import Scenario
from sim.plants.streamline import StreamlinePlant
from vcyto.stream import StreamSettings, run_stream, statistics_of


@pytest.fixture(scope="module")
def scenario():
    return Scenario()


@pytest.fixture(scope="module")
def streamline_plant(scenario):
    return StreamlinePlant(scenario)


def stream(scenario, plant, cells=(), **options):
    arrivals = options.pop("arrivals", None) or Arrivals(cells=tuple(cells))
    settings = StreamSettings(arrivals, model="streamline", **options)
    return run_stream(scenario, settings, plant=plant)


def outcomes(result):
    return [(c["type"], c["detected_class"], c["decision"], c["outlet"]) for c in result["cells"]]


def test_rbc_then_melanoma_are_sorted_by_the_feib_plant(scenario):
    settings = StreamSettings(Arrivals(cells=("RBC", "melanoma")), model="feib")
    result = run_stream(scenario.with_numerics(dt=10e-6), settings)
    assert outcomes(result) == [("RBC", "I", "pass", "lower"), ("melanoma", "II", "sort", "upper")]
    spans = {outlet.name: outlet.span for outlet in scenario.channel.outlets}
    for cell in result["cells"]:                     # where it crossed the exit lies in its outlet
        low, high = spans[cell["outlet"]]
        assert low * 1e6 < cell["exit_y_um"] < high * 1e6


def test_melanoma_rbc_melanoma_and_a_longer_mixed_sequence(scenario, streamline_plant):
    result = stream(scenario, streamline_plant, ("melanoma", "RBC", "melanoma"))
    assert [c["outlet"] for c in result["cells"]] == ["upper", "lower", "upper"]
    names = ("RBC", "melanoma", "melanoma", "RBC", "RBC", "melanoma", "RBC", "melanoma", "RBC", "RBC")
    result = stream(scenario, streamline_plant, names)
    for cell in result["cells"]:
        expected = "upper" if cell["detected_class"] == "II" and cell["true_class"] == "II" else "lower"
        assert cell["outlet"] == expected, cell
    assert result["statistics"]["purity"] == 1.0 and result["statistics"]["yield"] == 1.0


def test_spacing_too_tight_aborts_in_purity_mode_and_never_mis_sorts(scenario, streamline_plant):
    arrivals = Arrivals(cells=("melanoma", "RBC", "melanoma", "RBC"), rate=4000.0, min_spacing=0.2e-3)
    purity = stream(scenario, streamline_plant, arrivals=arrivals)
    assert purity["statistics"]["aborts"] >= 1
    for cell in purity["cells"]:
        if cell["type"] == "RBC":
            assert cell["outlet"] == "lower"
        if cell["decision"] == "abort":
            assert cell["outlet"] == "lower"
    yield_mode = stream(scenario, streamline_plant, arrivals=arrivals, controller=ControllerSettings(mode="yield"))
    assert yield_mode["statistics"]["aborts"] == 0
    assert yield_mode["statistics"]["yield"] == 1.0 and yield_mode["statistics"]["purity"] < 1.0


def test_controller_disabled_sends_every_cell_lower(scenario, streamline_plant):
    result = stream(scenario, streamline_plant, ("melanoma", "RBC", "melanoma"),
                    controller=ControllerSettings(enabled=False))
    assert [c["outlet"] for c in result["cells"]] == ["lower"] * 3


def test_dim_type_ii_cell_is_a_counted_misclassification_and_ends_lower(scenario, streamline_plant):
    result = stream(scenario, streamline_plant, ("melanoma",), detector=DetectorSettings(gate=100.0))
    assert outcomes(result) == [("melanoma", "I", "pass", "lower")]
    assert result["statistics"]["misclassified"] == 1


def test_statistics_agree_with_counts_made_from_the_outcomes():
    cells = [
        {"true_class": "II", "detected_class": "II", "decision": "sort", "outlet": "upper", "exit_time_ms": 2.0},
        {"true_class": "II", "detected_class": "II", "decision": "abort", "outlet": "lower", "exit_time_ms": 3.0},
        {"true_class": "I", "detected_class": "I", "decision": "pass", "outlet": "upper", "exit_time_ms": 3.5},
        {"true_class": "I", "detected_class": "II", "decision": "sort", "outlet": "upper", "exit_time_ms": 4.0},
    ]
    stats = statistics_of(cells, 4e-3)
    assert stats["purity"] == pytest.approx(1 / 3)
    assert stats["yield"] == pytest.approx(1 / 2)
    assert stats["abort_rate"] == pytest.approx(1 / 3)
    assert stats["misclassified"] == 1
    assert stats["throughput_cells_per_s"] == pytest.approx(4 / 4e-3)


def test_poisson_abort_rate_matches_the_coincidence_estimate(scenario, streamline_plant):
    """Pure Poisson arrivals (no dead time): a sort is aborted when a type-I cell's predicted arrival falls in the
    controller's widened envelope before the pulse starts, a window of width W, so the abort rate is
    1 - exp(-rate * share_I * W). W ends at the look-ahead: a cell detected after the pulse started cannot
    abort it (detection to arrival about 0.55 ms, minus the 0.3 ms lead)."""
    rate, share_i = 1000.0, 0.5
    arrivals = Arrivals(count=500, mix=(("RBC", share_i), ("melanoma", 1 - share_i)), rate=rate, process="poisson",
                        min_spacing=0.0, first=0.0)
    result = stream(scenario, streamline_plant, arrivals=arrivals, seed=3)
    low, high = ControllerSettings().window()
    rbcs = [c for c in result["cells"] if c["type"] == "RBC" and c["detection_time_ms"] is not None]
    lookahead = np.median([c["predicted_arrival_ms"] - c["detection_time_ms"] for c in rbcs]) * 1e-3
    high = min(high, lookahead - ControllerSettings().lead)
    sorts = [c for c in result["cells"] if c["detected_class"] == "II"]
    measured = result["statistics"]["abort_rate"]
    expected = 1 - math.exp(-rate * share_i * (high - low))
    sigma = math.sqrt(expected * (1 - expected) / len(sorts))
    assert abs(measured - expected) < 3 * sigma, (measured, expected, sigma)


def test_same_seed_same_stream(scenario, streamline_plant):
    arrivals = Arrivals(count=20, mix=(("RBC", 0.7), ("melanoma", 0.3)), rate=2000.0, process="poisson")
    first = stream(scenario, streamline_plant, arrivals=arrivals, seed=5)
    second = stream(scenario, streamline_plant, arrivals=arrivals, seed=5)
    other = stream(scenario, streamline_plant, arrivals=arrivals, seed=6)
    assert first["cells"] == second["cells"]
    assert first["cells"] != other["cells"]


def test_arrivals_keep_the_minimum_spacing():
    planned = schedule(Arrivals(count=200, mix=(("RBC", 1.0),), rate=5000.0, process="poisson", min_spacing=0.3e-3),
                       np.random.default_rng(0))
    gaps = np.diff([t for t, _ in planned])
    assert gaps.min() >= 0.3e-3 - 1e-15
    assert np.mean(gaps < 0.3e-3 + 1e-6) < 0.02          # drawn, not clipped: nothing piles up at the minimum


@pytest.mark.parametrize("args, words", [
    (["--cells", "RBC,platelet"], "unknown cell type 'platelet'"),
    (["--cells", ","], "--cells: needs at least one"),
    (["--count", "5", "--mix", "RBC:1", "--rate", "-3"], "--rate: must be positive"),
    (["--envelope", "0.1"], "--envelope: wants two offsets"),
    (["--controller", "/nonexistent.toml"], "is not a file"),
    (["--mode", "greedy"], "--mode"),
    (["--detection-window", "30,400"], "outside the channel"),
    (["--window-h", "5um"], "add --model auto"),
    (["--model", "auto", "--window-h=0"], "--window-h: must be positive"),
    (["--model", "auto", "--window-h", "5 bogons"], "unknown unit"),
    (["--model", "auto", "--window-h", "5 furlongs"], "--window-h: "),
])
def test_stream_rejects_bad_input_in_one_line(args, words):
    result = subprocess.run([sys.executable, "-m", "vcyto.cli", "stream", *args], capture_output=True, text=True)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0]


def test_fcs_export_round_trips(scenario, streamline_plant, tmp_path):
    from vcyto.recording.fcs import CHANNELS, read_fcs, write_fcs
    result = stream(scenario, streamline_plant, ("melanoma", "RBC", "melanoma"))
    path = write_fcs(tmp_path / "events.fcs", result, {"VCYTO_NOTE": "test"})
    names, events, keywords = read_fcs(path)
    assert names == list(CHANNELS)
    assert events.shape == (3, len(CHANNELS))
    detected = sorted(result["cells"], key=lambda c: c["detection_time_ms"])
    tick_ms = float(keywords["timestep"]) * 1e3                       # Time: integer ticks, within half a tick
    assert np.allclose(events[:, 0] * tick_ms, [c["detection_time_ms"] for c in detected], rtol=0, atol=tick_ms / 2)
    assert np.allclose(events[:, 1], [c["fluorescence"] for c in detected], rtol=1e-6)
    assert list(events[:, 6]) == [1.0 if c["outlet"] == "upper" else 0.0 for c in detected]
    assert keywords["vcyto_note"] == "test" and keywords["vcyto_outlet_codes"].startswith("0=lower")
    # a cell still in the channel when a partial run stopped is not coded as lost
    inside = dict(result, cells=[dict(detected[0], outlet="in_channel")] + detected[1:])
    _, events, keywords = read_fcs(write_fcs(tmp_path / "partial.fcs", inside, {}))
    first = int(np.argmin(events[:, 0]))
    assert events[first, 6] == 4.0 and "4=in_channel" in keywords["vcyto_outlet_codes"]


def test_stream_command_writes_fcs_and_summary(tmp_path):
    result = subprocess.run([sys.executable, "-m", "vcyto.cli", "stream", "--model", "streamline", "--json",
                             "--cells", "RBC,melanoma", "--output", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    import json
    summary = json.loads(result.stdout)
    assert [c["outlet"] for c in summary["cells"]] == ["lower", "upper"]
    assert len(list(tmp_path.glob("*.fcs"))) == 1 and len(list(tmp_path.glob("*.json"))) == 1


def test_ready_is_called_once_between_the_set_up_and_the_first_step(scenario, streamline_plant):
    """``run_stream(ready=...)``: called once, the plant reset to the sample and not yet stepped; the run's result is
    the one without it."""
    seen = []
    settings = StreamSettings(Arrivals(cells=("RBC", "melanoma")), model="streamline")
    result = run_stream(scenario, settings, plant=streamline_plant,
                        ready=lambda: seen.append((streamline_plant.truth().time, streamline_plant.done)))
    assert seen == [(0.0, False)] and result["simulated_time_ms"] > 0
    assert outcomes(result) == outcomes(stream(scenario, streamline_plant, ("RBC", "melanoma")))


def test_the_collector_is_settled_in_the_executables_own_process_only():
    """``settle_collector`` leaves a Python user's collector as it is; in the executable's own process it freezes
    what exists and collects the youngest generation less often (run in a process of its own)."""
    code = ("import gc; from vcyto.cli import common; before = gc.get_threshold(); common.settle_collector(); "
            "alone = gc.get_threshold() == before and gc.get_freeze_count() == 0; common.own_process(); "
            "common.settle_collector(); print(alone, gc.get_threshold()[0] == common.COLLECTOR_THRESHOLD, "
            "gc.get_freeze_count() > 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["True", "True", "True"]
