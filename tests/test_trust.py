"""Runs a user can trust: every bad input a one-line error with exit 1 or 2, units checked for
dimension, strict JSON, run files never overwritten, interrupted and failed runs leaving a complete record,
a desktop without a usable viewer still getting its files."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from guard import assert_one_line_refusal, patch_heavy, vcyto_inline

from vcyto.recording.replay import happenings

REPO = Path(__file__).resolve().parent.parent


def strict_load(text: str):
    """JSON as a strict parser reads it: NaN and Infinity refused."""
    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")
    return json.loads(text, parse_constant=refuse)


@pytest.fixture
def inline(monkeypatch, tmp_path):
    patch_heavy(monkeypatch)
    monkeypatch.chdir(tmp_path)
    return vcyto_inline


# --- every input class of the issue: one line, exit 1 or 2 ---------------------------------------------

BAD_INPUTS = {
    # "exit 3, internal error" in the issue
    "huge count": ["stream", "--count", "1000000000", "--mix", "RBC:1"],
    "nan mix weight": ["stream", "--count", "3", "--mix", "RBC:nan"],
    "negative seed": ["stream", "--seed", "-1"],
    "mesh too fine for memory": ["stream", "--mesh-h", "1nm"],
    "channel of 1e308 m": ["stream", "--set", "channel.length=1e308"],
    "connect to a non-URL": ["stream", "--connect", "not a url"],
    "replay --save onto a directory": ["replay", "REC", "--save", "."],
    # "silent nonsense" in the issue
    "nan rate": ["stream", "--rate", "nan"],
    "inf min spacing": ["stream", "--min-spacing", "inf"],
    "nan max time": ["stream", "--max-time", "nan"],
    "inf gate": ["stream", "--gate", "inf"],
    "inf noise": ["stream", "--noise", "inf"],
    "inf lead": ["stream", "--lead", "inf"],
    "inf delay": ["stream", "--delay", "inf"],
    "a cell wider than the inlet": ["stream", "--set", "cell_types.1.semi_axes=[250um, 250um]"],
    "no cell types": ["stream", "--scenario", "EMPTY_TYPES"],
    "no cell types (flow)": ["flow", "--scenario", "EMPTY_TYPES"],
    "count 0": ["stream", "--count", "0"],
    "negative flush interval": ["stream", "--flush-every", "-5"],
    # units
    "time step in um": ["stream", "--dt", "3um"],
    "mesh size in us": ["stream", "--mesh-h", "2.5us"],
    "viscosity in MHz": ["stream", "--set", "fluid.viscosity=6MHz"],
    "three detection window edges": ["stream", "--detection-window", "30um,60um,90um"],
    # files
    "scenario from /dev/zero": ["flow", "--scenario", "/dev/zero"],
    "scenario nested 5000 deep": ["flow", "--scenario", "DEEP"],
    "sweep of 1e8 points": ["sweep", "HUGE_SWEEP"],
    "sweep scenario outside the spec's folder": ["sweep", "ESCAPING_SWEEP"],
    "scheduler that is not an address": ["sweep", "GOOD_SWEEP", "--scheduler", "http://example.org"],
    # argparse
    "unknown option": ["stream", "--bogus"],
    "missing value": ["stream", "--rate"],
    "not an integer": ["stream", "--count", "1.5"],
}


@pytest.fixture
def files(tmp_path):
    """The files some bad inputs name."""
    deep = tmp_path / "deep.toml"
    deep.write_text("x = " + "[" * 5000 + "]" * 5000 + "\n")
    empty_types = tmp_path / "empty.toml"
    empty_types.write_text("cell_types = []\n")
    huge = tmp_path / "huge.toml"
    huge.write_text('[parameters]\nlead = {start = 0.0, stop = 1.0, num = 100000000}\n')
    escaping = tmp_path / "sub" / "escape.toml"
    escaping.parent.mkdir()
    escaping.write_text('[base]\nscenario = "../empty.toml"\n[parameters]\nlead = [0.5]\n')
    good = tmp_path / "good.toml"
    good.write_text('[parameters]\nlead = [0.25, 0.5]\n')
    recording = tmp_path / "rec.mcap"
    recording.write_bytes(b"\x89MCAP0\r\n")
    return {"DEEP": deep, "EMPTY_TYPES": empty_types, "HUGE_SWEEP": huge, "ESCAPING_SWEEP": escaping,
            "GOOD_SWEEP": good, "REC": recording}


@pytest.mark.parametrize("name", BAD_INPUTS)
def test_each_bad_input_class_is_one_line_with_exit_1_or_2(name, inline, files):
    argv = [str(files.get(arg, arg)) for arg in BAD_INPUTS[name]]
    status, _, stderr = inline(argv)
    assert_one_line_refusal(status, stderr)


def test_debug_mode_adds_the_traceback_and_keeps_the_exit_status(inline, monkeypatch):
    monkeypatch.setenv("VCYTO_DEBUG", "1")
    status, _, stderr = inline(["stream", "--model", "rom", "--dt", "3um", "--cells", "RBC"])
    assert status == 2, stderr                         # bad input stays bad input
    assert "Traceback (most recent call last)" in stderr
    assert stderr.strip().splitlines()[-1].startswith("vcyto: error: numerics.dt: ")


@pytest.mark.parametrize("argv, words", [
    (["stream", "--dt", "3um"], "is a length, but numerics.dt is a time"),
    (["stream", "--set", "fluid.viscosity=6MHz"], "fluid.viscosity is a viscosity"),
    (["stream", "--lead", "3um"], "--lead: '3um' is a length, but --lead is a time"),
    (["stream", "--delay", "3um"], "--delay: '3um' is a length, but --delay is a time"),
    (["stream", "--rate", "5ms"], "--rate: '5ms' is a time, but --rate is a frequency"),
    (["stream", "--window-h", "3us"], "--window-h: '3us' is a time, but --window-h is a length"),
    (["stream", "--tolerance", "3us"], "--tolerance: '3us' is a time, but --tolerance is a length"),
    (["stream", "--detection-window", "3us,4us"], "error: --detection-window: '3us' is a time, but"),
    (["bench", "realtime", "--duration", "3um"], "--duration: '3um' is a length, but --duration is a time"),
    (["calibrate", "--pulse-step", "3um"], "--pulse-step: '3um' is a length, but --pulse-step is a time"),
])
def test_wrong_units_name_the_field_and_the_dimension(argv, words, inline):
    status, _, stderr = inline(argv)
    assert_one_line_refusal(status, stderr, allowed=(2,))
    assert words in stderr


@pytest.mark.parametrize("argv, option", [
    (["stream", "--count", "5"], "--count: needs --mix"),
    (["stream", "--cells", ""], "--cells: "),
    (["stability", "--cells", ","], "--cells: "),
    (["stream", "--envelope", "1"], "--envelope: "),
    (["stream", "--count", "5", "--mix", "RBC:1", "--rate", "5000", "--min-spacing", "1"],
     "--cells/--count/--mix/--rate/--min-spacing: regular arrivals"),
    (["stream", "--output", "A_FILE/sub"], "--output: cannot create the directory"),
    (["sweep", "SPEC", "--output", "A_FILE/sub"], "--output: cannot create the directory"),
    (["flow", "--png", "A_FILE/flow.png"], "--png: cannot write"),
    (["flow", "--png", "A_FILE"], "--png: "),                         # exists: never overwritten
    (["replay", "NO_FILE"], "FILE: "),
    (["bench", "sort", "--counts", "x"], "--counts: "),
    (["bench", "sweep", "--workers", "x"], "--workers: "),
    (["calibrate", "--pulse", "0.4", "--output", ""], "--pulse/--lead: "),
    (["tradeoff", "--pair-gap", "3", "--output", ""], "--pair-gap: "),
    (["stream", "--tolerance", "nan"], "--tolerance: 'nan' is not a finite length"),
    (["stream", "--bogus"], "--bogus: unknown option"),
    (["sweep"], "SPEC: missing"),
])
def test_bad_input_names_its_option_first(argv, option, inline, tmp_path):
    (tmp_path / "a-file").write_text("")
    (tmp_path / "spec.toml").write_text("[parameters]\nlead = [0.25]\n")
    names = {"A_FILE": str(tmp_path / "a-file"), "NO_FILE": str(tmp_path / "none.mcap"),
             "SPEC": str(tmp_path / "spec.toml")}
    for placeholder, path in names.items():
        argv = [arg.replace(placeholder, path) for arg in argv]
    status, _, stderr = inline(argv)
    assert_one_line_refusal(status, stderr, allowed=(2,))
    assert stderr.startswith(f"vcyto: error: {option}"), stderr


@pytest.mark.parametrize("argv", [
    ["stream", "--max-time", "5ms", "--model", "rom"],
    ["stream", "--pulse", "150us"],
    ["stream", "--rate", "1kHz", "--count", "5", "--mix", "RBC:1"],
    ["stream", "--dt", "25µs"],
    ["stream", "--detection-window", "30um,60um"],
    ["stream", "--lead", "-0"],
    ["stream", "--set", "fluid.viscosity=6 mPa s"],
])
def test_units_of_the_right_dimension_are_accepted(argv, inline):
    status, _, stderr = inline([*argv, "--output", "", "--no-viewer"])
    assert status is None, stderr          # reached the run


def test_option_values_reach_the_settings_in_si(monkeypatch):
    from vcyto import cli, options
    args = cli.build_parser().parse_args(["stream", "--max-time", "5ms", "--pulse", "150us", "--rate", "1kHz",
                                          "--lead", "0.25", "--detection-window", "30um,0.06mm"])
    settings = options.stream_settings(args, options.scenario_from(args))
    assert settings.max_time == pytest.approx(5e-3)
    assert settings.controller.pulse == pytest.approx(150e-6)
    assert settings.controller.lead == pytest.approx(0.25e-3)
    assert settings.arrivals.rate == pytest.approx(1000.0)
    assert settings.detector.window == pytest.approx((30e-6, 60e-6))


def test_strict_json_has_null_for_undefined_values():
    from vcyto.outputs import strict_json
    text = strict_json({"purity": float("nan"), "yield": float("inf"), "list": (1.0, float("-inf"))})
    assert strict_load(text) == {"purity": None, "yield": None, "list": [1.0, None]}


# --- sweeps: the code version is part of a point's identity --------------------------------------------

def _fake_simulator(scenario, settings):
    return {"statistics": {"yield": 1.0, "purity": float("nan"), "abort_rate": None, "outlets": {"lower": 1}},
            "cells": [], "simulated_time_ms": 1.0, "idt_on_time_ms": 0.0, "wall_time_s": 0.0}


def _run(spec, output, **options):
    from concurrent.futures import ThreadPoolExecutor

    from vcyto import sweep
    output.mkdir(exist_ok=True)
    with ThreadPoolExecutor(1) as pool:
        return sweep.run_sweep(sweep.load_sweep(spec), output, pool, simulator=_fake_simulator, **options)


def test_upgrading_the_version_recomputes_a_finished_sweep(tmp_path, monkeypatch):
    import vcyto
    spec = tmp_path / "spec.toml"
    spec.write_text('[parameters]\nlead = [0.25, 0.5]\n')
    first = _run(spec, tmp_path / "out")
    assert first["ran"] == 2
    assert _run(spec, tmp_path / "out")["ran"] == 0              # same code: nothing to do
    monkeypatch.setattr(vcyto, "__version__", "99.0.0")
    upgraded = _run(spec, tmp_path / "out")
    assert upgraded["ran"] == 2 and upgraded["stale_rows"] == 2   # recomputed; the old rows are kept, ignored
    rows = (tmp_path / "out" / "results.csv").read_text().splitlines()
    assert sum(",99.0.0" in row for row in rows) == 2


def test_keep_old_rows_reuses_the_rows_of_another_version_and_says_so(tmp_path, monkeypatch):
    import vcyto
    spec = tmp_path / "spec.toml"
    spec.write_text('[parameters]\nlead = [0.25, 0.5]\n')
    _run(spec, tmp_path / "out")
    monkeypatch.setattr(vcyto, "__version__", "99.0.0")
    kept = _run(spec, tmp_path / "out", keep_old_rows=True)
    assert kept["ran"] == 0 and kept["kept_old_rows"] == 2 and kept["ok"] == 2


def test_a_scheduler_that_is_not_dask_fails_within_its_timeout_in_one_line(tmp_path):
    """A server that greets with a banner (as SSH does) made Dask allocate exabytes; now: one line, exit 2."""
    import socket
    import threading
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen()
    port = server.getsockname()[1]

    def greet():
        connection, _ = server.accept()
        connection.sendall(b"SSH-2.0-OpenSSH_8.9p1 Ubuntu-3ubuntu0.1\r\n" * 4)
        time.sleep(15)
        connection.close()
    threading.Thread(target=greet, daemon=True).start()
    spec = tmp_path / "spec.toml"
    spec.write_text('[parameters]\nlead = [0.25]\n')
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "vcyto.cli", "sweep", str(spec), "--output", str(tmp_path / "o"),
                             "--scheduler", f"tcp://127.0.0.1:{port}"], capture_output=True, text=True, timeout=120)
    assert_one_line_refusal(result.returncode, result.stderr, allowed=(2,))
    assert "cannot reach a Dask scheduler" in result.stderr
    assert time.monotonic() - started < 60
    server.close()


# --- whole runs (subprocesses): desktop without a viewer, two at once, signals, failure ---------------

def vcyto(*args, env=None, **kwargs):
    return subprocess.run([sys.executable, "-m", "vcyto.cli", *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, **(env or {})}, **kwargs)


def run_files(directory: Path) -> dict[str, list[Path]]:
    return {suffix: sorted(directory.glob(f"*.{suffix}")) for suffix in ("mcap", "json", "fcs", "rrd")}


def finalised_mcap(path: Path) -> int:
    """Messages in an MCAP file that has its summary section (written by ``finish``)."""
    from mcap.reader import make_reader
    with open(path, "rb") as handle:
        summary = make_reader(handle).get_summary()
    assert summary is not None and summary.statistics is not None, f"{path} was not finalised"
    return summary.statistics.message_count


def recorded_steps(path: Path) -> int:
    """The steps in the ``/loop/steps`` columns of the MCAP at ``path``."""
    from mcap.reader import make_reader
    with open(path, "rb") as handle:
        return sum(len(json.loads(message.data)["time"])
                   for _, _, message in make_reader(handle).iter_messages(topics=["/loop/steps"]))


def test_a_desktop_without_a_usable_viewer_still_gets_every_file(tmp_path):
    """DISPLAY set, no X server: vcyto sees no display server, starts no viewer, says so, saves the .rrd, exits 0."""
    result = vcyto("stream", "--cells", "RBC,melanoma", "--model", "rom", "--mesh-h", "10um", "--output", str(tmp_path),
                   "--quiet",
                   env={"DISPLAY": ":99", "WAYLAND_DISPLAY": ""})
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert "saving the view to an .rrd file instead" in result.stderr
    found = run_files(tmp_path)
    assert all(len(paths) == 1 for paths in found.values()), found
    assert "saved to " + str(found["rrd"][0]) in result.stdout
    assert finalised_mcap(found["mcap"][0]) > 0 and recorded_steps(found["mcap"][0]) > 10    # rom: every 0.25 ms
    assert [outcome["type"] for outcome in happenings(found["mcap"][0])["/outcome"]] == ["RBC", "melanoma"]
    summary = strict_load(found["json"][0].read_text())
    assert summary["status"] == "complete" and [c["outlet"] for c in summary["cells"]] == ["lower", "upper"]
    from rerun.chunk import RrdReader
    assert RrdReader(str(found["rrd"][0])) is not None
    from vcyto.recording.fcs import read_fcs
    channels, events, _ = read_fcs(found["fcs"][0])
    assert events.shape == (2, len(channels))


def test_two_streams_started_together_write_distinct_readable_files(tmp_path):
    command = [sys.executable, "-m", "vcyto.cli", "stream", "--cells", "RBC", "--model", "streamline", "--mesh-h",
               "10um",
               "--output", str(tmp_path), "--quiet", "--json"]
    processes = [subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for _ in range(2)]
    outputs = [process.communicate(timeout=600) for process in processes]
    assert all(process.returncode == 0 for process in processes), outputs
    summaries = [strict_load(out) for out, _ in outputs]
    paths = [set(summary["files"].values()) for summary in summaries]
    assert not paths[0] & paths[1]                                  # no file shared
    found = run_files(tmp_path)
    assert [len(found[suffix]) for suffix in ("mcap", "json", "fcs", "rrd")] == [2, 2, 2, 2]
    for path in found["mcap"]:
        assert finalised_mcap(path) > 10
    for path in found["json"]:
        assert strict_load(path.read_text())["status"] == "complete"


def test_a_name_that_is_taken_is_refused_before_any_work(tmp_path):
    (tmp_path / "mine.json").write_text("{}")
    result = vcyto("stream", "--name", "mine", "--output", str(tmp_path), "--no-viewer")
    assert_one_line_refusal(result.returncode, result.stderr, allowed=(2,))
    assert "already exists" in result.stderr and (tmp_path / "mine.json").read_text() == "{}"
    assert not (tmp_path / "mine.mcap").exists()


def _interrupt(tmp_path, signum):
    process = subprocess.Popen([sys.executable, "-m", "vcyto.cli", "stream", "--count", "3000", "--mix",
                                "RBC:0.9,melanoma:0.1", "--model", "rom", "--max-time", "10s", "--output",
                                str(tmp_path), "--no-viewer", "--name", "run"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:                 # wait until the loop is stepping (the MCAP grows)
        mcap = tmp_path / "run.mcap"
        if mcap.exists() and mcap.stat().st_size > 50_000:
            break
        time.sleep(0.2)
    process.send_signal(signum)
    out, err = process.communicate(timeout=300)
    return process.returncode, out, err


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_run_leaves_a_complete_record(tmp_path, signum, status):
    returncode, out, err = _interrupt(tmp_path, signum)
    assert returncode == status, err
    assert "Traceback" not in err
    name = signal.Signals(signum).name
    assert f"interrupted by {name}" in err and str(tmp_path / "run.json") in err
    assert finalised_mcap(tmp_path / "run.mcap") > 100
    summary = strict_load((tmp_path / "run.json").read_text())
    assert summary["status"] == "interrupted" and name in summary["reason"]
    assert 0 < summary["simulated_time_ms"] < 10_000
    from vcyto.recording.fcs import read_fcs
    _, events, keywords = read_fcs(tmp_path / "run.fcs")
    assert len(events) == sum(cell["detected_class"] is not None for cell in summary["cells"]) > 0
    assert keywords.get("vcyto_status") == "interrupted"


def test_a_numerical_failure_says_where_its_partial_record_is(tmp_path):
    """dt = 1 ms blows the FE-IB run up at once: exit 1, the reason, and the files of what ran."""
    result = vcyto("stream", "--cells", "melanoma", "--mesh-h", "10um", "--dt", "1ms", "--output", str(tmp_path),
                   "--no-viewer", "--name", "boom", "--quiet")
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vcyto: error: the run failed in the step after t = ")
    assert str(tmp_path / "boom.json") in lines[0] and "Traceback" not in result.stderr
    summary = strict_load((tmp_path / "boom.json").read_text())
    assert summary["status"] == "failed" and summary["reason"]
    assert finalised_mcap(tmp_path / "boom.mcap") >= 0
    assert (tmp_path / "boom.fcs").stat().st_size > 0


def test_a_disk_filling_up_mid_run_is_one_line_exit_1(tmp_path, monkeypatch):
    """The MCAP writer hits ENOSPC after a few steps: the run stops with the cause in one line, exit 1."""
    import errno

    from guard import vcyto_inline

    from vcyto.recording import mcap as recording
    written = {"steps": 0}
    original = recording.McapRecorder.on_steps

    def filling(self, records):
        written["steps"] += len(records)
        if written["steps"] > 20:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path))
        return original(self, records)
    monkeypatch.setattr(recording.McapRecorder, "on_steps", filling)
    monkeypatch.delenv("DISPLAY", raising=False)
    status, _, stderr = vcyto_inline(["stream", "--cells", "RBC", "--model", "streamline", "--mesh-h", "10um",
                                      "--output", str(tmp_path), "--no-viewer", "--quiet", "--name", "full"])
    assert_one_line_refusal(status, stderr, allowed=(1,))
    assert "No space left on device" in stderr and "full.mcap" in stderr
    summary = strict_load((tmp_path / "full.json").read_text())     # written (room is left), marked failed
    assert summary["status"] == "failed" and "full.mcap" in summary["reason"]
    assert "kept (what ran up to the failure" in stderr and str(tmp_path / "full.json") in stderr


# --- the viewer: the installed one, bound to this machine, never breaking a run --------------------------

def test_the_viewer_is_the_one_installed_with_rerun_sdk_not_the_first_on_path(tmp_path, monkeypatch):
    from vcyto.recording import viewer
    impostor = tmp_path / "rerun"
    impostor.write_text("#!/bin/sh\nexit 7\n")
    impostor.chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}:{os.environ['PATH']}")
    found = viewer.find_viewer()
    assert found is not None and found != impostor and os.access(found, os.X_OK)
    assert "rerun_cli" in str(found) or found.parent == Path(sys.executable).parent


FAKE_VIEWER = """#!{python}
import os, socket, sys, time
args = sys.argv[1:]
bind, port = args[args.index("--bind") + 1], int(args[args.index("--port") + 1])
server = socket.socket()
server.bind((bind, port))
server.listen()
open({record!r}, "w").write(" ".join(args) + "\\n" + str(os.getpid()))
time.sleep(60)
"""


def test_a_started_viewer_listens_on_localhost_only_unless_asked(tmp_path, monkeypatch):
    import socket

    from vcyto.recording import viewer
    fake, record = tmp_path / "fake-rerun", tmp_path / "args.txt"
    fake.write_text(FAKE_VIEWER.format(python=sys.executable, record=str(record)))
    fake.chmod(0o755)
    monkeypatch.setattr(viewer, "find_viewer", lambda: fake)
    monkeypatch.setattr(viewer, "VIEWER_GRACE", 0.2)
    monkeypatch.setattr(viewer, "display_problem", lambda: None)     # the fake viewer needs no display
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    for asked, bind in ((None, "127.0.0.1"), ("0.0.0.0", "0.0.0.0")):
        url, done = viewer.start_viewer(port=port) if asked is None else viewer.start_viewer(bind=asked, port=port)
        try:
            assert url == f"rerun+http://127.0.0.1:{port}/proxy" and bind in done
            args = record.read_text().splitlines()[0]
            assert f"--bind {bind}" in args and f"--port {port}" in args
        finally:
            os.kill(int(record.read_text().splitlines()[1]), signal.SIGTERM)
        deadline = time.monotonic() + 10
        while viewer.listening("127.0.0.1", port, 0.2) and time.monotonic() < deadline:
            time.sleep(0.1)


def test_an_unreachable_viewer_means_an_rrd_and_a_finished_run(tmp_path):
    result = vcyto("stream", "--cells", "RBC", "--model", "streamline", "--mesh-h", "10um", "--quiet",
                   "--connect", "rerun+http://127.0.0.1:9/proxy", "--output", str(tmp_path), "--name", "r")
    assert result.returncode == 0, result.stderr
    assert result.stderr.strip().splitlines() == ["vcyto: no Rerun viewer answers at rerun+http://127.0.0.1:9/proxy: "
                                                  "no connection (Connection refused); saving the view to an .rrd "
                                                  "file instead"]
    assert (tmp_path / "r.rrd").stat().st_size > 1000 and finalised_mcap(tmp_path / "r.mcap") > 10


def test_a_viewer_that_goes_away_mid_run_does_not_break_it(tmp_path):
    """A real Rerun gRPC server (headless) receives the run and is killed half-way: the run still finishes."""
    import socket

    from vcyto.recording import viewer
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen([str(viewer.find_viewer()), "--serve-grpc", "--port", str(port), "--bind", "127.0.0.1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while not viewer.listening("127.0.0.1", port, 0.2) and time.monotonic() < deadline:
            time.sleep(0.1)
        run = subprocess.Popen([sys.executable, "-m", "vcyto.cli", "stream", "--count", "400", "--mix", "RBC:1",
                                "--model", "rom", "--mesh-h", "10um", "--max-time", "1s", "--quiet", "--name", "v",
                                "--connect", f"rerun+http://127.0.0.1:{port}/proxy", "--output", str(tmp_path)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        while time.monotonic() < deadline + 240:
            mcap = tmp_path / "v.mcap"
            if run.poll() is not None or (mcap.exists() and mcap.stat().st_size > 100_000):
                break
            time.sleep(0.2)
    finally:
        server.kill()
        server.wait()
    out, err = run.communicate(timeout=300)
    assert run.returncode == 0, err
    assert "Traceback" not in err and len(err.strip().splitlines()) <= 1
    assert strict_load((tmp_path / "v.json").read_text())["status"] == "complete"
    assert finalised_mcap(tmp_path / "v.mcap") > 1000


def test_no_viewer_binary_at_all_means_an_rrd(monkeypatch, capsys):
    import argparse

    from vcyto.recording import runfiles, viewer
    monkeypatch.setenv("DISPLAY", ":99")
    monkeypatch.setattr(viewer, "find_viewer", lambda: None)
    monkeypatch.setattr(viewer, "listening", lambda *args, **kwargs: False)
    args = argparse.Namespace(no_viewer=False, save=None, connect=None, spawn=False, viewer_bind="127.0.0.1")
    view = runfiles.choose_view(args, True, spawn_by_default=True, error=ValueError)
    assert view.kind == "save" and view.path is None                 # the run's own NAME.rrd
    assert capsys.readouterr().err.strip() == ("vcyto: cannot start a Rerun viewer: the rerun-sdk installation has no "
                                               "viewer binary; saving the view to an .rrd file instead")


def test_a_second_paper_run_never_overwrites_the_first_figure(tmp_path):
    """The default figure gets a new name; a figure named by the user that exists is refused in one line."""
    args = ["paper", "2", "--mesh-h", "6.67um", "--quiet"]
    for _ in range(2):
        assert vcyto(*args, cwd=tmp_path).returncode == 0
    assert sorted(p.name for p in (tmp_path / "recordings").iterdir()) == ["paper2-2.png", "paper2.png"]
    refused = vcyto(*args, "--png", str(tmp_path / "recordings" / "paper2.png"), cwd=tmp_path)
    assert refused.returncode == 2 and "never overwrites" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("argv", [["stream", "--dt", "1ns"], ["paper", "1", "--dt", "1ns"],
                                  ["stream", "--count", "100000", "--mix", "RBC:1", "--rate", "1000"]])
def test_runs_that_would_take_days_are_refused_with_the_estimate(argv, inline):
    status, _, stderr = inline(argv)
    assert_one_line_refusal(status, stderr)
    assert "FE-IB steps" in stderr and " h on this machine" in stderr and "--allow-long" in stderr


def test_every_mcap_json_message_is_strict_json(tmp_path):
    """A rom stream's recording, JSON channels read back with a parser that refuses NaN and infinities."""
    from mcap.reader import make_reader
    done = vcyto("stream", "--model", "rom", "--mesh-h", "10um", "--count", "30", "--mix", "RBC:0.8,melanoma:0.2",
                 "--rate", "1000", "--no-viewer", "--quiet", "--output", str(tmp_path), "--name", "s")
    assert done.returncode == 0, done.stderr
    with open(tmp_path / "s.mcap", "rb") as handle:
        reader = make_reader(handle)
        texts = [message.data for _, channel, message in reader.iter_messages() if channel.message_encoding == "json"]
        texts += [value for record in reader.iter_metadata() for value in record.metadata.values()
                  if value.startswith(("{", "["))]       # metadata: plain strings, containers as JSON text
    for text in texts:
        strict_load(text)
    assert len(happenings(tmp_path / "s.mcap")["/outcome"]) == 30 and recorded_steps(tmp_path / "s.mcap") > 50
