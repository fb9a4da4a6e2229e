"""The command line as a user meets it: exit codes, one-line errors, no tracebacks, JSON output."""

import json
import subprocess
import sys

import pytest


def vcyto(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "vcyto.cli", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=600)


@pytest.mark.parametrize("args, field", [
    (["--set", "fluid.viscosity=-1"], "fluid.viscosity"),
    (["--dt", "0"], "numerics.dt"),
    (["--set", "channel.inlets.0.span=[-10um, 20um]"], "channel.inlets[0].span"),
    (["--set", "channel.outlets.1.span=[90um, 200um]"], "channel.outlets"),
    (["--mesh-h", "20um"], "numerics.mesh_h"),
    (["--set", "fluid.viscocity=1"], "fluid.viscocity"),
    (["--set", "numerics.dt=fast"], "numerics.dt"),
    (["--scenario", "no-such-file.toml"], "no-such-file.toml"),
])
def test_bad_scenario_input_is_one_line_exit_2_no_traceback(args, field):
    result = vcyto("flow", *args)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vcyto: error: ") and field in lines[0]


def test_malformed_toml_names_the_file_and_line(tmp_path):
    scenario = tmp_path / "broken.toml"
    scenario.write_text("[fluid]\nviscosity = = 3\n")
    result = vcyto("flow", "--scenario", str(scenario))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "broken.toml" in result.stderr and "line 2" in result.stderr
    assert result.stderr.startswith("vcyto: error: --scenario: ")      # the option, not the API's argument name


def test_unwritable_png_is_refused_before_any_work(tmp_path):
    result = vcyto("flow", "--png", str(tmp_path / "missing-dir" / "flow.png"))
    assert result.returncode == 2
    assert "--png: cannot write" in result.stderr and "is not an existing directory" in result.stderr
    assert "Traceback" not in result.stderr


def test_flow_json_on_a_coarse_mesh(tmp_path):
    png = tmp_path / "flow.png"
    result = vcyto("flow", "--mesh-h", "5um", "--json", "--png", str(png))
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["idt_off"]["outlet"] == "lower"
    assert summary["idt_on"]["outlet"] == "upper"
    assert png.stat().st_size > 10_000


def test_bench_fluid_reports_every_treatment_and_the_ratio():
    result = vcyto("bench", "fluid", "--mesh-h", "10um", "--repeats", "3", "--rounds", "2", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert set(report["steps_ms"]) == {"imex", "stokes", "oseen", "implicit"}
    assert all(value > 0 for value in report["steps_ms"].values())
    assert report["imex_over_backsolve"] > 0 and report["backsolve_ms"] > 0
    assert report["rounds"] == 2 and len(report["imex_over_fastest_backsolve_rounds"]) == 2
    assert set(report["load_ms"]) == {"euler", "bdf2"} and all(v > 0 for v in report["load_ms"].values())
    if report["linear_solver"] == "pardiso":        # the mixed-precision default against both fastest solves
        assert report["fastest_backsolve_ms"] > 0 and report["fastest_single_backsolve_ms"] > 0
        assert report["double_backsolve_ms"] > 0 and report["corrections_per_step"] >= 1
        assert report["default_factor_nonzeros"] > 0 and report["fastest_factor_nonzeros"] > 0
        assert "M factor entries" in report["default_solver"] and "M factor entries" in report["fastest_backsolve"]
    if "SplitPardiso" in report["default_solver"]:     # the matched halves beside the default
        assert report["matched_backsolve_ms"] > 0 and report["backsolve_over_matched"] > 0
    from sim.fast.supernodal import available
    if "SplitPardiso" in report["default_solver"] and available():   # our own substitutions against PARDISO's
        assert "our own compiled substitutions" in report["default_solver"]
        assert "our own" not in report["pardiso_substitutions_backsolve"]
        assert report["pardiso_substitutions_backsolve_ms"] > 0 and report["backsolve_over_pardiso_substitutions"] > 0


def test_bench_rejects_too_few_repeats():
    result = vcyto("bench", "fluid", "--repeats", "1")
    assert result.returncode == 2 and "--repeats" in result.stderr


def test_paper_2_json_reports_the_upper_outlet_and_a_time_breakdown(tmp_path):
    result = vcyto("paper", "2", "--json", "--png", str(tmp_path / "paper2.png"))
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert [cell["outlet"] for cell in summary["cells"]] == ["upper"]
    assert summary["steps"] > 50 and summary["dofs"] == 54_243
    assert set(summary["wall_time_s"]) >= {"process", "setup", "steady_start", "stepping", "membrane", "fluid_solve"}
    assert (tmp_path / "paper2.png").stat().st_size > 10_000


@pytest.mark.parametrize("args, words", [
    (["--mesh-sizes", "0um"], "--mesh-sizes"),
    (["--mesh-sizes", "20um"], "numerics.mesh_h"),
    (["--cells", "platelet"], "unknown cell type 'platelet'"),
])
def test_stability_rejects_bad_input(args, words):
    result = vcyto("stability", *args)
    assert result.returncode == 2 and words in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("args, words", [
    (["--coupling", "0,2"], "--coupling: needs positive numbers"),
    (["--coupling", "two"], "--coupling: needs positive numbers"),
    (["--pair-gap", "3"], "gaps below 2 ms"),
    (["--pair-gap", "-1"], "--pair-gap: needs positive numbers"),
    (["--lone-rbc", "2.5"], "injection times below 2 ms"),
    (["--lone-rbc", "0,1"], "--lone-rbc: needs positive numbers"),
    (["--stiff-capillary", "-1"], "--stiff-capillary: needs non-negative numbers"),
    (["--stiff-capillary", "inf"], "--stiff-capillary: needs non-negative numbers"),
])
def test_tradeoff_rejects_bad_levels_and_scenes(args, words, tmp_path):
    result = vcyto("tradeoff", "--output", str(tmp_path), *args)
    assert result.returncode == 2 and words in result.stderr and "Traceback" not in result.stderr
    assert not list(tmp_path.iterdir())          # nothing run, nothing written


def test_scenario_json_is_the_effective_scenario_and_the_toml_read_back(tmp_path):
    from vcyto.config import load_scenario
    toml = vcyto("scenario", "--dt", "5us", "--set", "fluid.viscosity=6 mPa s")
    result = vcyto("scenario", "--dt", "5us", "--set", "fluid.viscosity=6 mPa s", "--json")
    assert toml.returncode == 0 and result.returncode == 0, toml.stderr + result.stderr
    tree = json.loads(result.stdout)
    assert tree["numerics"]["dt"] == pytest.approx(5e-6) and tree["fluid"]["viscosity"] == pytest.approx(6e-3)
    (tmp_path / "effective.toml").write_text(toml.stdout)
    assert load_scenario(tmp_path / "effective.toml").numerics.dt == tree["numerics"]["dt"]
    assert [inlet["v_hat"] for inlet in tree["channel"]["inlets"]] == \
        [inlet.v_hat for inlet in load_scenario(tmp_path / "effective.toml").channel.inlets]


def test_the_stream_summary_gives_the_loop_wall_time_beside_the_set_up(tmp_path):
    import re
    result = vcyto("stream", "--model", "streamline", "--mesh-h", "10um", "--cells", "RBC", "--output", "",
                   "--no-viewer", "--quiet")
    assert result.returncode == 0, result.stderr
    found = re.search(r"in ([\d.]+) s wall \(streamline model: set-up ([\d.]+) s, loop ([\d.e+-]+) s\)", result.stdout)
    assert found, result.stdout
    wall, setup, loop = (float(value) for value in found.groups())
    assert loop > 0 and abs(setup + loop - wall) <= 0.1          # rounded to 0.1 s


def test_bench_realtime_prints_the_outlets_as_text():
    from vcyto.bench.realtime import realtime_lines
    result = {"setup_parts_s": {"flows_s": 1.0}, "runs": [{"real_time_factor": 20.0}], "cells": 100,
              "rate_per_s": 1000.0, "mix": [["RBC", 0.9], ["melanoma", 0.1]], "control_period_us": 10.0,
              "setup_s": 1.0, "device_time_s": 0.1, "loop_wall_s": 0.005, "real_time_factor": 20.0, "purity": 1.0,
              "yield": 0.9, "abort_rate": 0.1, "outlets": {"lower": 94, "upper": 6}}
    last = realtime_lines(result)[-1]
    assert last.endswith("outlets: lower 94, upper 6") and "{" not in last, last


def test_stream_help_names_the_controller_defaults_that_run():
    """--help's "default" of each controller option is the shipped calibration (ControllerSettings), in ms."""
    import argparse
    import re

    from controller.sorter import ControllerSettings
    from vcyto.cli import build_parser
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    helps = {a.option_strings[0]: a.help for a in commands.choices["stream"]._actions if a.option_strings}
    shipped = ControllerSettings()
    expected = {"--delay": [shipped.delay], "--lead": [shipped.lead], "--pulse": [shipped.pulse],
                "--timing-error": [shipped.timing_error], "--envelope": list(shipped.envelope)}
    for option, seconds in expected.items():
        stated = re.search(r"default (-?[0-9.]+(?:,-?[0-9.]+)?)", helps[option]).group(1)
        assert [float(v) for v in stated.split(",")] == pytest.approx([s * 1e3 for s in seconds], rel=1e-3), option


def test_hints_name_commands_as_they_can_be_typed(monkeypatch, tmp_path):
    """`replay with: ...` and `open with: ...` give this environment's script by path when PATH does not find
    it (a venv not activated), by name when it does."""
    import os
    from pathlib import Path

    from vcyto.recording import runfiles
    script = Path(sys.executable).parent / "vcyto"
    assert script.is_file()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    assert Path(os.path.abspath(runfiles.typed("vcyto"))).resolve() == script.resolve()
    monkeypatch.setenv("PATH", f"{script.parent}:/usr/bin:/bin")
    assert runfiles.typed("vcyto") == "vcyto"
    assert runfiles.typed("no-such-script") == "no-such-script"


def test_the_latency_line_says_n_a_without_decisions():
    from vcyto.sortreport import _latency_line
    assert _latency_line({}) == "controller latency n/a (no decisions)"
    assert _latency_line({"p99": float("nan")}) == "controller latency n/a (no decisions)"
    assert _latency_line({"p99": 12.345}) == "controller latency p99 12.3 us"


def test_flow_calibration_with_a_png_is_refused_before_the_run(tmp_path):
    result = vcyto("flow", "--calibrate-streaming", "--png", "x.png", cwd=tmp_path)
    assert result.returncode == 2 and result.stderr.startswith("vcyto: error: --png: --calibrate-streaming draws")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args, message", [
    (["--save", "/proc/view.rrd"], "--save: cannot write /proc/view.rrd"),
    (["--save", "view.rrd", "--no-viewer"], "--no-viewer: cannot be combined with --save"),
    (["--spawn", "--no-viewer"], "--no-viewer: cannot be combined with --spawn"),
])
def test_a_view_that_cannot_be_kept_is_refused_before_the_run(args, message, tmp_path):
    result = vcyto("stream", "--model", "rom", "--output", "", *args, cwd=tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [f"vcyto: error: {result.stderr.split('error: ')[1].strip()}"]
    assert message in result.stderr and not list(tmp_path.iterdir())


def test_an_output_directory_refused_for_space_is_not_left_behind(tmp_path, monkeypatch):
    """Too little free space is refused before the run, and the directory made for the run is removed again; a
    command writing small files (sweep, tradeoff, calibrate) asks for less room than a stream's recordings."""
    import shutil
    from collections import namedtuple

    from vcyto.cli import common
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 20 * 10**6, 20 * 10**6))
    with pytest.raises(common.UsageError, match="only 20 MB free"):
        common.output_directory(str(tmp_path / "new" / "run"))
    assert not (tmp_path / "new").exists()
    assert common.output_directory(str(tmp_path / "table"), min_free=common.SMALL_FILES_BYTES).is_dir()


def test_an_empty_case_list_is_refused_and_cache_takes_quiet():
    empty = vcyto("extremes", "--case", "")
    assert empty.returncode == 2 and empty.stderr.startswith("vcyto: error: --case: unknown case ''")
    assert vcyto("cache", "--quiet").returncode == 0


def test_a_lead_beyond_the_delay_is_run_but_never_silently():
    result = vcyto("stream", "--model", "rom", "--lead", "0.6", "--no-viewer", "--output", "", "--quiet", "--json")
    assert result.returncode == 0, result.stderr
    assert "vcyto: note: the lead 0.6 ms is not shorter than the sort delay 0.553 ms" in result.stderr
    melanoma = next(cell for cell in json.loads(result.stdout)["cells"] if cell["type"] == "melanoma")
    assert melanoma["decision"] == "sort" and "late (lead > delay)" in melanoma["reason"]


@pytest.mark.parametrize("args, message", [
    (["--cells", "RBC,melanoma", "--count", "10"], "--cells: lists the cells one by one"),
    (["--count", "10", "--mix", "RBC:0.9,melanoma:0.1,RBC:0.5"], "--mix: RBC given more than once"),
    # a tenth of melanoma cells meant, nothing but melanoma cells drawn when the shares were normalised
    (["--count", "10", "--mix", "melanoma:0.1"], "--mix: the shares sum to 0.1, not 1"),
    (["--count", "10", "--mix", "RBC:9,melanoma:1"], "--mix: the shares sum to 10, not 1"),
])
def test_arrival_options_that_contradict_each_other_are_refused(args, message):
    result = vcyto("stream", "--model", "rom", *args, "--no-viewer", "--output", "")
    assert result.returncode == 2 and result.stderr.startswith(f"vcyto: error: {message}")


def test_a_command_makes_threads_take_turns_with_the_interpreter_lock_often(monkeypatch, capsys):
    """The recording sinks, the loop and the solvers' helper threads run Python between their kernels: a command
    sets the interpreter's switch interval to 0.2 ms (Python's default 5 ms made the loop wait for the sinks)."""
    from vcyto.cli import SWITCH_INTERVAL_S, main
    before = sys.getswitchinterval()
    monkeypatch.setattr(sys, "setswitchinterval", lambda seconds: calls.append(seconds))
    calls = []
    assert main(["cache", "--json"]) == 0 and json.loads(capsys.readouterr().out)
    assert calls == [SWITCH_INTERVAL_S, before] and SWITCH_INTERVAL_S < 5e-3     # set, then given back
