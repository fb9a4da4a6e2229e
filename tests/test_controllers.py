"""Your controller in the loop: the protocol, controllers and plants of one's own (Python and command line), paced
real time and missed decisions, the pytest plugin, the Python API's set-up cache."""

import json
import math
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from controller.events import TYPE_II, Decision, DetectorEvent
from controller.protocol import ControllerError, DeviceFacts, PulseSchedule, check_answer
from controller.sorter import ControllerSettings, SortController
from sim.model.arrivals import Arrivals
from vcyto.control import Timing
from vcyto.stream import StreamSettings, StreamStopped, run_stream
from vcyto.testing import SortRun, assert_outlets, assert_purity, assert_targets_sorted

ROOT = Path(__file__).resolve().parents[1]
THRESHOLD = ROOT / "examples" / "controllers" / "threshold.py"
FOUR = ("RBC", "melanoma", "RBC", "melanoma")


def vcyto(*args, cwd=None, timeout=600):
    return subprocess.run([sys.executable, "-m", "vcyto.cli", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


def one_line_error(result, *words, status=2):
    assert result.returncode == status, result.stderr
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.strip().splitlines() if line.startswith("vcyto: error: ")]
    assert len(errors) == 1, result.stderr
    for word in words:
        assert word in errors[0], errors[0]
    return errors[0]


def settings(cells=FOUR, **options) -> StreamSettings:
    return StreamSettings(Arrivals(cells=cells), model="rom", **options)


# --- the protocol itself ---------------------------------------------------------------------------------------

FACTS = DeviceFacts(0.5e-3, 0.1, 0.3e-3, 0.4e-3, (-0.2e-3, 0.1e-3), 0.02e-3, 10e-6, (30e-6, 60e-6))


def event(n, t, label=TYPE_II, velocity=0.1):
    return DetectorEvent(n, t, 1.0, 40.0, velocity, label, n)


def test_a_deadline_is_the_latest_start_of_the_calibrated_pulse():
    # arrival = t + delay * v_ref / v; deadline = arrival - lead: 0.2 ms after detection at the reference velocity,
    # 0.7 ms at half of it
    assert FACTS.deadline(event(0, 1e-3)) == pytest.approx(1.2e-3)
    assert FACTS.deadline(event(0, 1e-3, velocity=0.05)) == pytest.approx(1.7e-3)


@pytest.mark.parametrize("answer, words", [
    ([Decision(0, "sort", 1e-3, float("nan"), 1e-3)], "finite"),
    ([Decision(0, "sort", 1e-3, 2e-3, 1e-3)], "pulse_on < pulse_off"),
    ([Decision(0, "sort", 1e-3, 0.0, 5.0)], "at most"),
    ([Decision(0, "jump", 1e-3)], "one of sort, pass, abort"),
    ([Decision(7, "pass", 1e-3)], "never told"),
    ([Decision(0, "pass", 1e-3), Decision(0, "pass", 1e-3)], "2 times"),
    ("sort", "Decision objects"),
    (42, "sequence of Decision"),
])
def test_answers_the_protocol_does_not_allow_are_refused_with_what_is_wrong(answer, words):
    with pytest.raises(ControllerError, match=words):
        check_answer(answer, {}, 0)


def test_the_pulse_schedule_is_on_while_any_pulse_is():
    schedule = PulseSchedule()
    schedule.add(0, 1.0, 2.0)
    schedule.add(1, 1.5, 3.0)
    assert schedule.next_change(0.0) == 1.0 and schedule.next_change(1.7) == 2.0
    assert [schedule.actuation(t) for t in (0.5, 1.0, 1.9, 2.5, 3.0)] == [0.0, 1.0, 1.0, 1.0, 0.0]
    assert math.isinf(schedule.next_change(3.0))                       # pulses over are forgotten


# --- controllers of one's own in Python --------------------------------------------------------------------------

class PassAll:
    """Sorts nothing: the targets must leave by the lower outlet."""

    def on_event(self, event, clock):
        return [Decision(event.event_id, "pass", float("nan"))]


class HoldOn:
    """Sets the drive itself: the IDT on all the time, so every cell goes up."""

    name = "hold-on"

    def on_event(self, event, clock):
        return [Decision(event.event_id, "pass", float("nan"))]

    def drive(self, clock):
        return 1.0


class BadPulse:
    def on_event(self, event, clock):
        return [Decision(event.event_id, "sort", 1e-3, float("inf"), 2e-3)]


def test_the_built_in_controller_given_as_an_object_runs_as_the_default(rom_plant, paper_scenario):
    default = run_stream(paper_scenario, settings(), plant=rom_plant)
    given = run_stream(paper_scenario, settings(), plant=rom_plant,
                       controller=SortController(ControllerSettings()))
    assert [c["outlet"] for c in given["cells"]] == [c["outlet"] for c in default["cells"]]
    assert [c["decision"] for c in given["cells"]] == [c["decision"] for c in default["cells"]]
    assert default["controller_name"] == given["controller_name"] == "built-in"
    assert default["model"] == "rom" and default["control"]["timing"] == "lock-step"


def test_a_controller_that_sorts_nothing_sends_every_cell_down_and_the_plugin_says_which(rom_plant, paper_scenario):
    result = run_stream(paper_scenario, settings(), plant=rom_plant, controller=PassAll())
    assert [c["outlet"] for c in result["cells"]] == ["lower"] * 4
    assert result["controller_name"].endswith("PassAll")
    with pytest.raises(AssertionError, match=r"2 of 2 melanoma cells did not leave by the upper outlet"):
        assert_outlets(SortRun(result), melanoma="upper")
    with pytest.raises(AssertionError, match="cell 1 .melanoma"):
        assert_targets_sorted(SortRun(result))
    with pytest.raises(AssertionError, match="purity is undefined"):
        assert_purity(SortRun(result), at_least=0.9)


def test_a_controller_that_drives_the_idt_itself_is_stepped_period_by_period(rom_plant, paper_scenario):
    result = run_stream(paper_scenario, settings(cells=("RBC",)), plant=rom_plant, controller=HoldOn())
    assert result["cells"][0]["outlet"] == "upper"                  # the drive held on: the RBC deflected
    assert result["controller_name"] == "hold-on"
    assert result["idt_on_time_ms"] == pytest.approx(result["simulated_time_ms"], rel=0.02)


def test_a_controller_that_breaks_the_protocol_stops_the_run_saying_why(rom_plant, paper_scenario):
    with pytest.raises(StreamStopped, match="controller: the sort of event 0 needs a pulse") as stopped:
        run_stream(paper_scenario, settings(), plant=rom_plant, controller=BadPulse())
    assert stopped.value.status == "failed" and stopped.value.result["status"] == "failed"


def test_late_answers_in_paced_real_time_are_missed_decisions_and_their_targets_go_down(rom_plant, paper_scenario):
    """At a real-time factor of 0.02 the 0.253 ms budget is 12.6 ms of wall time; every third answer takes 60 ms."""
    class Slow(SortController):
        def on_event(self, event, clock):
            if event.event_id % 3 == 2:
                time.sleep(0.06)
            return super().on_event(event, clock)

    cells = ("melanoma",) * 9
    result = run_stream(paper_scenario, settings(cells=cells), plant=rom_plant,
                        controller=Slow(ControllerSettings()), timing=Timing(realtime=True, factor=0.02))
    missed = [c["event_id"] for c in result["cells"] if c["decision"] == "missed"]
    assert missed == [2, 5, 8]
    assert result["statistics"]["missed_decisions"] == 3 == result["control"]["missed_decisions"]
    assert all(c["outlet"] == ("lower" if c["event_id"] in missed else "upper") for c in result["cells"])
    histogram = result["control"]["latency_histogram"]
    assert sum(histogram["counts"]) == 9
    assert sum(count for edge, count in zip(histogram["edges_us"], histogram["counts"]) if edge >= 10_000) == 3
    assert result["control"]["lag_ms"]["count"] > 0


# --- the command line ---------------------------------------------------------------------------------------------

def test_a_controller_of_ones_own_file_sorts_on_the_command_line(tmp_path):
    result = vcyto("stream", "--model", "rom", "--cells", ",".join(FOUR), "--controller-from",
                   f"{THRESHOLD}:Threshold", "--no-viewer", "--output", str(tmp_path), "--name", "mine", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert [c["outlet"] for c in summary["cells"]] == ["lower", "upper", "lower", "upper"]
    assert summary["controller_name"] == "threshold" and summary["model"] == "rom"
    assert json.loads((tmp_path / "mine.json").read_text())["controller_name"] == "threshold"


@pytest.mark.slow
def test_a_controller_of_ones_own_file_sorts_on_feib(tmp_path):
    result = vcyto("stream", "--cells", ",".join(FOUR), "--controller-from", f"{THRESHOLD}:Threshold",
                   "--no-viewer", "--output", "", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert [c["outlet"] for c in summary["cells"]] == ["lower", "upper", "lower", "upper"]
    assert summary["model"] == "feib"


def test_a_plant_of_ones_own_runs_and_the_summary_names_it(tmp_path):
    (tmp_path / "myplant.py").write_text(textwrap.dedent("""
        from sim.plants.rom import RomPlant

        class Mine(RomPlant):
            name = "my-plant"
    """))
    result = vcyto("stream", "--plant-from", f"{tmp_path / 'myplant.py'}:Mine", "--cells", "RBC,melanoma",
                   "--no-viewer", "--output", "", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["model"] == "my-plant"
    assert [c["outlet"] for c in summary["cells"]] == ["lower", "upper"]


@pytest.mark.parametrize("source, spec, words", [
    (None, "{dir}/absent.py:X", "no such file"),
    ("def broken(:\n", "{file}:X", "SyntaxError (line 1)"),
    ("X = 1\n", "{file}:Y", "has no 'Y'"),
    ("class X:\n    def __init__(self, settings):\n        raise RuntimeError('no device')\n", "{file}:X",
     "building the controller failed: RuntimeError: no device"),
    ("class X:\n    def __init__(self, settings):\n        pass\n", "{file}:X", "no on_event"),
    ("X = 1\n", "{file}", "FILE.py:NAME"),
    (None, "no_such_module_here:X", "cannot import no_such_module_here"),
])
def test_a_controller_that_cannot_be_loaded_is_a_one_line_usage_error(tmp_path, source, spec, words):
    path = tmp_path / "mine.py"
    if source is not None:
        path.write_text(source)
    result = vcyto("stream", "--model", "rom", "--controller-from", spec.format(dir=tmp_path, file=path),
                   "--no-viewer", "--output", "")
    one_line_error(result, "--controller-from", words)


def test_a_plant_option_pair_that_contradicts_itself_is_refused(tmp_path):
    path = tmp_path / "p.py"
    path.write_text("def Plant(scenario):\n    return object()\n")
    one_line_error(vcyto("stream", "--plant-from", f"{path}:Plant", "--model", "rom", "--output", ""),
                   "--plant-from", "give one of them")
    one_line_error(vcyto("stream", "--plant-from", f"{path}:Plant", "--no-viewer", "--output", ""),
                   "--plant-from", "not a plant", "lacks reset")


def test_a_controller_breaking_the_protocol_mid_run_exits_1_with_its_files_kept(tmp_path):
    path = tmp_path / "bad.py"
    path.write_text("from controller.events import Decision\n\nclass Bad:\n    def __init__(self, settings):\n"
                    "        pass\n\n    def on_event(self, event, clock):\n"
                    "        return [Decision(event.event_id, 'sort', 0.0, 2e-3, 1e-3)]\n")
    result = vcyto("stream", "--model", "rom", "--controller-from", f"{path}:Bad", "--no-viewer",
                   "--output", str(tmp_path), "--name", "bad")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert "controller: the sort of event 0 needs a pulse" in result.stderr
    assert json.loads((tmp_path / "bad.json").read_text())["status"] == "failed"
    assert (tmp_path / "bad.mcap").stat().st_size > 0


# --- the pytest plugin and the Python API ----------------------------------------------------------------------------

def test_the_users_example_test_of_their_controller_passes_through_the_plugin():
    result = subprocess.run([sys.executable, "-m", "pytest", str(ROOT / "examples" / "test_my_controller.py"), "-q",
                             "-p", "no:cacheprovider"], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "2 passed" in result.stdout


def test_the_python_api_uses_the_set_up_cache_by_default(tmp_path):
    code = ("import vcyto, sim.fast.store as s; from sim.model.arrivals import Arrivals; "
            "vcyto.make_plant(vcyto.Scenario(), vcyto.StreamSettings(Arrivals(cells=('RBC',)), model='streamline'));"
            " print(type(s.installed()).__name__)")
    env = {**__import__("os").environ, "VCYTO_CACHE_DIR": str(tmp_path)}
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert shown.stdout.strip() == "DiskCache", shown.stderr
    env["VCYTO_CACHE"] = "off"
    off = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert off.stdout.strip() == "NoneType", off.stderr


def test_a_sweep_runs_a_controller_of_ones_own_beside_its_spec(tmp_path):
    """A controller that sorts nothing: yield 0 at every point (the built-in one sorts this sample fully)."""
    (tmp_path / "never.py").write_text("from controller.events import Decision\n\nclass Never:\n"
                                       "    def __init__(self, settings):\n        pass\n\n"
                                       "    def on_event(self, event, clock):\n"
                                       "        return [Decision(event.event_id, 'pass', float('nan'))]\n")
    spec = tmp_path / "spec.toml"
    spec.write_text('[base]\nmodel = "rom"\ncells = ["RBC", "melanoma"]\ncontroller_from = "never.py:Never"\n'
                    '[parameters]\nlead = [0.25, 0.3]\n[sweep]\nmetrics = ["purity", "yield"]\n')
    result = vcyto("sweep", str(spec), "--output", str(tmp_path / "out"), "--workers", "1", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["ok"] == 2
    with open(tmp_path / "out" / "results.csv", newline="") as file:
        rows = list(__import__("csv").DictReader(file))
    assert len(rows) == 2 and all(float(row["yield"]) == 0.0 for row in rows)
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    spec.write_text(f'[base]\nmodel = "rom"\ncontroller_from = "{THRESHOLD}:Threshold"\n[parameters]\nlead = [0.25]\n')
    one_line_error(vcyto("sweep", str(spec), "--output", str(tmp_path / "out2")), "spec's folder")


def test_calibrate_checks_a_controller_of_ones_own_with_the_new_calibration(tmp_path):
    result = vcyto("calibrate", "--controller-from", f"{THRESHOLD}:Threshold", "--pulse", "0.4", "--lead", "0.3",
                   "--offset-step", "0.1", "--resolution", "0.02", "--output", "", "--json")
    assert result.returncode == 0, result.stderr
    check = json.loads(result.stdout)["check"]
    assert check["controller"] == "threshold" and check["sorted_right"] == 4
    assert [c["outlet"] for c in check["cells"]] == ["lower", "upper", "lower", "upper"]
    one_line_error(vcyto("calibrate", "--plant-from", f"{THRESHOLD}:Threshold", "--output", ""),
                   "--plant-from", "not a plant")


def test_calibrate_checks_a_controller_in_another_process_with_the_new_calibration():
    """``vcyto calibrate --controller-exec CMD``: the served built-in controller gets the new calibration's
    device facts in its hello and sorts the check's cells; a dead one is one line and exit 1."""
    served = f"{sys.executable} -m vcyto.wire.serve --once"
    result = vcyto("calibrate", "--controller-exec", served, "--pulse", "0.4", "--lead", "0.3",
                   "--offset-step", "0.1", "--resolution", "0.02", "--output", "", "--json")
    assert result.returncode == 0, result.stderr
    check = json.loads(result.stdout)["check"]
    assert "wire" in check["controller"] and check["sorted_right"] == 4
    assert [c["outlet"] for c in check["cells"]] == ["lower", "upper", "lower", "upper"]
    dead = vcyto("calibrate", "--controller-exec", f"{sys.executable} -c pass", "--pulse", "0.4", "--lead", "0.3",
                 "--offset-step", "0.1", "--resolution", "0.02", "--output", "", "--quiet")
    assert dead.returncode == 1 and "--controller-exec" in dead.stderr and "exited" in dead.stderr
    assert len(dead.stderr.strip().splitlines()) == 1
