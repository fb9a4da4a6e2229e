"""Controllers in another process (vcyto.wire, docs/wire-protocol.md): the framing and messages, the reference
controllers in Python and C against the built-in one, missed decisions in paced real time, and every failure of a
controller as one line, a non-zero exit and a finalised recording, never a hang."""

import json
import math
import shlex
import shutil
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from controller.protocol import ControllerError, DeviceFacts
from controller.sorter import ControllerSettings
from vcyto import wire
from vcyto.control import Timing
from vcyto.wire import framing, messages

ROOT = Path(__file__).resolve().parents[1]
PURITY_PY = ROOT / "examples" / "controllers" / "purity_server.py"
PURITY_C = ROOT / "examples" / "controllers" / "purity_server.c"
SERVERS = Path(__file__).resolve().parent / "wire_servers.py"
POISSON = ["--model", "rom", "--count", "1000", "--mix", "RBC:0.7,melanoma:0.3", "--rate", "1000",
           "--arrivals", "poisson", "--min-spacing", "0.1ms", "--seed", "7"]
FACTS = DeviceFacts.from_settings(ControllerSettings(), 2.5e-6, (30e-6, 60e-6))


def python_server(*args) -> str:
    return shlex.join([sys.executable, str(SERVERS if args else PURITY_PY), *args])


def vcyto(*args, timeout=240):
    return subprocess.run([sys.executable, "-m", "vcyto.cli", *args], capture_output=True, text=True,
                          timeout=timeout)


def finalised_mcap(path: Path) -> dict:
    """The run_end metadata of an MCAP file that has its summary section (written when it is closed)."""
    from mcap.reader import make_reader
    with open(path, "rb") as handle:
        reader = make_reader(handle)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, f"{path} was not finalised"
        return {m.name: dict(m.metadata) for m in reader.iter_metadata()}.get("run_end", {})


# --- frames and messages -------------------------------------------------------------------------------------

def test_a_frame_is_a_big_endian_length_and_one_json_object():
    data = framing.encode({"type": "bye"})
    assert data[:4] == struct.pack(">I", len(data) - 4) and json.loads(data[4:]) == {"type": "bye"}
    frames = framing.Frames()
    for byte in data * 2:                       # byte by byte: whole messages only
        frames.feed(bytes([byte]))
    assert frames.pop() == {"type": "bye"} and frames.pop() == {"type": "bye"} and frames.pop() is None


@pytest.mark.parametrize("data, words", [
    (struct.pack(">I", (1 << 20) + 1), "oversized message: a frame of 1048577 bytes"),
    (b"HTTP/1.1 200 OK\r\n", "oversized message"),
    (struct.pack(">I", 0), "empty frame"),
    (struct.pack(">I", 4) + b"\xff\xfe\x00\x01", "not UTF-8"),
    (struct.pack(">I", 5) + b"hello", "not JSON"),
    (struct.pack(">I", 3) + b"NaN", "not JSON"),
    (struct.pack(">I", 23) + b'{"type": "x", "a": NaN}', "not JSON"),
    (struct.pack(">I", 2) + b"[]", "a JSON object with a string \"type\""),
    (struct.pack(">I", 11) + b'{"type": 1}', "a JSON object with a string \"type\""),
])
def test_malformed_and_oversized_frames_are_refused_naming_the_cause(data, words):
    frames = framing.Frames()
    with pytest.raises(framing.WireError, match=words.replace("(", r"\(")) as error:
        frames.feed(data)
        frames.pop()
    assert "\n" not in str(error.value)


def test_a_message_vcyto_would_send_beyond_the_limit_or_with_nan_is_refused():
    with pytest.raises(framing.WireError, match="longer than"):
        framing.encode({"type": "error", "message": "x" * (1 << 20)})
    from controller.events import DetectorEvent
    with pytest.raises(framing.WireError, match="not a finite number"):
        messages.event(DetectorEvent(3, 1e-3, 1.0, 100.0, math.nan, "II", 3), 1.2e-3, 1e-3)


def test_the_hello_carries_the_protocol_version_capabilities_and_facts_in_si():
    hello = messages.hello(FACTS, Timing(realtime=True, factor=0.5))
    assert (hello["protocol"], hello["version"]) == ("vcyto-controller", 1)
    assert hello["capabilities"] == ["decisions", "drive"]
    assert hello["facts"]["sort_delay"] == 0.553e-3 and hello["facts"]["envelope"] == [-0.21e-3, 0.2025e-3]
    assert hello["timing"] == {"mode": "realtime", "factor": 0.5}
    assert framing.decode(framing.encode(hello)[4:]) == hello


@pytest.mark.parametrize("welcome, words", [
    ({"type": "welcome", "protocol": "vcyto-controller", "version": 2, "name": "x", "capabilities": ["decisions"]},
     "version mismatch: the controller speaks version 2"),
    ({"type": "welcome", "protocol": "other", "version": 1, "name": "x", "capabilities": ["decisions"]},
     "protocol 'other'"),
    ({"type": "welcome", "protocol": "vcyto-controller", "version": 1, "name": "x", "capabilities": []},
     "does not offer 'decisions'"),
    ({"type": "welcome", "protocol": "vcyto-controller", "version": 1, "name": "", "capabilities": ["decisions"]},
     "name must be a non-empty string"),
    ({"type": "error", "message": "no such mode"}, "refused the handshake: no such mode"),
    ({"type": "decisions"}, "expected a welcome"),
])
def test_a_wrong_welcome_is_refused_naming_the_cause(welcome, words):
    with pytest.raises(ControllerError, match=words):
        messages.check_welcome(welcome)


@pytest.mark.parametrize("answer, words", [
    ({"type": "decisions", "event_id": "3", "decisions": []}, "event_id must be an integer"),
    ({"type": "decisions", "event_id": 3}, "needs a list"),
    ({"type": "decisions", "event_id": 3, "decisions": [{"event_id": 3, "action": 5}]}, "action must be a string"),
    ({"type": "decisions", "event_id": 3, "decisions": [{"event_id": 3, "action": "sort", "pulse_on": "1"}]},
     "pulse_on must be a finite number"),
    ({"type": "decisions", "event_id": 3, "decisions": [{"event_id": 3, "action": "pass", "reason": 1}]},
     "reason must be a string"),
])
def test_a_malformed_decision_is_refused_naming_the_field(answer, words):
    with pytest.raises(ControllerError, match=words):
        messages.decisions(answer)


def test_null_pulse_times_mean_none_given():
    event_id, decisions = messages.decisions({"type": "decisions", "event_id": 4, "decisions": [
        {"event_id": 4, "action": "pass", "arrival": 1.5e-3, "pulse_on": None, "pulse_off": None}]})
    assert event_id == 4 and decisions[0].action == "pass" and math.isnan(decisions[0].pulse_on)


@pytest.mark.parametrize("text", ["tcp:127.0.0.1", "tcp:127.0.0.1:0", "tcp::7070", "udp:1.2.3.4:5", "unix:", "7070"])
def test_a_bad_address_is_refused_with_the_forms(text):
    with pytest.raises(ValueError, match=r"tcp:HOST:PORT .* or unix:PATH"):
        wire.parse_address(text)


def test_nothing_listening_is_a_connection_error_within_the_timeout(tmp_path):
    started = time.monotonic()
    with pytest.raises(ConnectionError, match="cannot connect to the controller at unix:"):
        wire.connect(f"unix:{tmp_path}/nobody.sock", timeout=1.0)
    with pytest.raises(ConnectionError, match="exited with status 3 before listening"):
        wire.launch(shlex.join([sys.executable, "-c", "raise SystemExit(3)"]), timeout=5.0)
    with pytest.raises(ConnectionError, match="did not listen"):
        wire.launch(shlex.join([sys.executable, "-c", "import time; time.sleep(60)"]), timeout=1.0)
    assert time.monotonic() - started < 30


# --- the reference controllers against the built-in one ------------------------------------------------------

def _run(argv, controller=None):
    from vcyto.cli import build_parser
    from vcyto.options import scenario_from, stream_settings
    from vcyto.stream import run_stream
    args = build_parser().parse_args(["stream", *argv])
    scenario = scenario_from(args)
    try:
        return run_stream(scenario, stream_settings(args, scenario), controller=controller)
    finally:
        if hasattr(controller, "close"):
            controller.close()


def _outcomes(result) -> list[tuple]:
    return [(c["event_id"], c["decision"], c["pulse_ms"], c["predicted_arrival_ms"], c["outlet"], c["outcome"])
            for c in result["cells"]]


@pytest.fixture(scope="module")
def c_server(tmp_path_factory):
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler")
    binary = tmp_path_factory.mktemp("purity") / "purity_server"
    subprocess.run([compiler, "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror", "-o", str(binary),
                    str(PURITY_C), "-lm"], check=True, timeout=120)
    return binary


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.slow
def test_the_reference_controllers_sort_as_the_built_in_one_on_a_poisson_stream(c_server):
    """1,000 events at 1,000/s with --min-spacing 0.1ms (aborts matter), lock-step: the Python controller
    (started by vcyto, a Unix socket) and the C one (running already, TCP) decide every event as the built-in
    controller does, with the same pulses, and every cell leaves by the same outlet."""
    built_in = _run(POISSON)
    assert built_in["statistics"]["aborts"] > 10 and built_in["statistics"]["sorted"] > 100
    by_python = _run(POISSON, wire.launch(f"{shlex.join([sys.executable, str(PURITY_PY)])} --once", timeout=30))
    address = f"tcp:127.0.0.1:{_free_port()}"
    server = subprocess.Popen([str(c_server), "--listen", address, "--once"])
    try:
        port = None
        for _ in range(200):
            try:
                port = wire.connect(address, timeout=30)
                break
            except ConnectionError:
                time.sleep(0.02)
        by_c = _run(POISSON, port)
        assert server.wait(timeout=10) == 0              # it said bye and left
    finally:
        server.kill()
    expected = _outcomes(built_in)
    assert len(expected) == built_in["statistics"]["cells"] > 900
    assert _outcomes(by_python) == expected
    assert _outcomes(by_c) == expected
    assert by_python["controller_name"].startswith("purity_server.py") and by_c["controller_name"].startswith(
        "purity_server.c")
    assert by_c["control"]["missed_decisions"] == 0 and by_c["control"]["latency_ms"]["count"] == len(expected)


def test_the_c_controller_polling_for_its_messages_decides_as_the_built_in_one(c_server):
    """``--spin SECONDS`` (poll for the next message before sleeping in read) changes when it reads, not what it
    answers: 100 Poisson events in lock-step decide as the built-in controller; a spin that is not 0-1 s is
    refused with exit 2, naming the option."""
    short = [*POISSON[:3], "100", *POISSON[4:]]
    built_in = _run(short)
    by_c = _run(short, wire.launch(f"{shlex.quote(str(c_server))} --once --spin 0.002", timeout=30))
    assert _outcomes(by_c) == _outcomes(built_in) and len(_outcomes(built_in)) > 80
    for bad in ("x", "5", "-1"):
        done = subprocess.run([str(c_server), "--spin", bad], capture_output=True, text=True, timeout=10)
        assert done.returncode == 2 and "--spin" in done.stderr, (bad, done.stderr)


# --- paced real time: late answers are missed decisions ------------------------------------------------------

def test_late_answers_in_real_time_are_missed_and_their_targets_go_lower(tmp_path):
    """Every third event answered 0.3 s (wall) late, at a real-time factor of 0.01 (deadline budget 25 ms wall):
    exactly those are missed; their melanomas leave by the lower outlet, the others are sorted; the latency
    histogram is in the summary and in the recording."""
    cells = ",".join(["melanoma", "melanoma", "melanoma", "RBC"] * 3)
    result = vcyto("stream", "--model", "rom", "--cells", cells, "--rate", "500", "--realtime", "0.01",
                   "--controller-exec", python_server("late"), "--output", str(tmp_path), "--name", "late",
                   "--no-viewer", "--json", "--quiet", timeout=120)
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    late = [c for c in summary["cells"] if c["event_id"] % 3 == 2]
    on_time = [c for c in summary["cells"] if c["event_id"] % 3 != 2]
    assert len(late) == 4 and len(on_time) == 8
    assert summary["statistics"]["missed_decisions"] == summary["control"]["missed_decisions"] == len(late)
    assert all(c["decision"] == "missed" for c in late)
    assert all(c["decision"] != "missed" for c in on_time)
    assert [c["outlet"] for c in late if c["true_class"] == "II"] == ["lower"] * 3
    assert all(c["outlet"] == ("upper" if c["true_class"] == "II" else "lower") for c in on_time)
    histogram = summary["control"]["latency_histogram"]
    assert sum(histogram["counts"]) == summary["control"]["latency_ms"]["count"] >= len(on_time)
    assert sum(histogram["counts"][histogram["edges_us"].index(100_000):]) >= 1     # a late answer, 0.3 s
    ending = finalised_mcap(tmp_path / "late.mcap")
    recorded = ending["control"]
    recorded = json.loads(recorded) if isinstance(recorded, str) else recorded
    assert recorded["latency_histogram"]["counts"] == histogram["counts"]
    assert int(ending["missed_decisions"]) == len(late)


# --- a controller that fails: one line, exit non-zero, the recording finalised, never a hang ------------------

@pytest.mark.parametrize("mode, words", [
    ("die", "lost the connection to the controller at unix:"),
    ("garbage", "malformed message: its 12 bytes are not UTF-8"),
    ("oversized", "oversized message: a frame of 2097152 bytes"),
    ("version", "version mismatch: the controller speaks version 2 of vcyto-controller, vcyto speaks 1"),
    ("silent", "the controller did not answer within 2 s (--controller-timeout): no answer came"),
])
def test_a_failing_controller_stops_the_run_in_one_line_with_a_finalised_recording(mode, words, tmp_path):
    started = time.monotonic()
    result = vcyto("stream", "--model", "rom", "--count", "20", "--mix", "RBC:0.7,melanoma:0.3", "--rate", "1000",
                   "--controller-exec", python_server(mode), "--controller-timeout", "2", "--output", str(tmp_path),
                   "--name", mode, "--no-viewer", "--quiet", timeout=120)
    assert time.monotonic() - started < 100
    assert result.returncode == 1, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert lines[0].startswith("vcyto: error: the run failed") and words in lines[0], lines[0]
    ending = finalised_mcap(tmp_path / f"{mode}.mcap")
    assert ending["status"] == "failed" and words in ending["reason"]
    summary = json.loads((tmp_path / f"{mode}.json").read_text())
    assert summary["status"] == "failed" and words in summary["reason"]
    replayed = vcyto("replay", str(tmp_path / f"{mode}.mcap"), "--save", str(tmp_path / f"{mode}.rrd"), timeout=120)
    assert replayed.returncode == 0, replayed.stderr
    assert "the recorded run is partial: it ended failed" in replayed.stdout


def test_the_controller_options_exclude_each_other_and_check_the_address(tmp_path):
    for argv, words in [
        (["--controller-connect", "tcp:127.0.0.1:9", "--no-controller"], "--controller-connect: --no-controller"),
        (["--controller-exec", "x", "--controller-connect", "tcp:127.0.0.1:9"],
         "--controller-connect: --controller-exec names the controller too"),
        (["--controller-connect", "localhost:7070"], "--controller-connect: a controller address is tcp:HOST:PORT"),
        (["--controller-exec", "'unclosed"], "--controller-exec: the controller command"),
        (["--controller-timeout", "3"], "--controller-timeout: applies to a controller in another process"),
    ]:
        result = vcyto("stream", "--model", "rom", "--cells", "RBC", "--output", "", "--no-viewer", *argv)
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1 and words in lines[0], result.stderr
    refused = vcyto("stream", "--model", "rom", "--cells", "RBC", "--output", str(tmp_path), "--no-viewer",
                    "--controller-connect", f"unix:{tmp_path}/nobody.sock")
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 1 and len(lines) == 1 and "cannot connect to the controller" in lines[0]
    assert not list(tmp_path.iterdir())            # nothing reserved before the controller was reached



def test_a_python_controller_served_over_the_wire_sorts_as_in_process():
    """python -m vcyto.wire.serve: the built-in controller in a process of its own, its settings from the hello's
    facts, decides as in process (200 events with coincidences)."""
    stream = [*POISSON[:3], "200", *POISSON[4:]]
    in_process = _run(stream)
    served = _run(stream, wire.launch(shlex.join([sys.executable, "-m", "vcyto.wire.serve", "--once"]), timeout=60))
    assert in_process["statistics"]["aborts"] > 0
    assert _outcomes(served) == _outcomes(in_process)
    assert served["controller_name"] == "built-in vcyto.wire.serve (wire, started by vcyto)"


def test_bench_wire_reports_both_timing_modes_with_the_load(tmp_path):
    result = vcyto("bench", "wire", "--duration", "0.05", "--realtime-duration", "0.05", "--repeats", "1", "--json",
                   timeout=300)
    assert result.returncode == 0, result.stderr
    bench = json.loads(result.stdout)
    lock, paced = bench["lockstep"], bench["realtime"]
    assert lock["same_outcomes"] and lock["over_wire"][0]["latency_ms"]["count"] == lock["events"] > 20
    assert lock["real_time_factor"] == lock["over_wire"][0]["real_time_factor"] > 0
    assert paced["device_time_s"] > 0.03 and paced["events"] > 20 and paced["missed_decisions"] >= 0
    assert paced["lag_ms"]["count"] > 0 and paced["met"] == (paced["missed_decisions"] == 0
                                                             and paced["lag_ms"]["p99"] <= paced["lag_target_ms"])
    assert len(bench["load_average"]["before"]) == 3


def test_closing_is_bounded_even_for_a_controller_that_ignores_end_and_sigterm():
    """No bye, SIGTERM ignored: close() waits 2 s for the bye, 2 s for the exit, 2 s after SIGTERM, then kills."""
    port = wire.launch(python_server("stubborn"), timeout=30)
    port.start(FACTS)
    process = port._process
    started = time.monotonic()
    port.close()
    assert time.monotonic() - started < 15
    assert process.returncode == -9                 # SIGKILL: it is gone
    port.close()                                    # twice: nothing more to do


# --- a controller that sets the drive itself, over the wire -------------------------------------------------

DRIVER = '''
import math
from controller.events import Decision


class WindowDriver:
    """Sets the drive itself: on for the calibrated pulse around each type II cell's predicted arrival."""

    name = "window driver"

    def __init__(self, settings):
        self.settings, self.windows = settings, []

    def on_event(self, event, clock):
        if event.classification == "II":
            s = self.settings
            arrival = event.time + s.delay * s.reference_velocity / event.velocity
            self.windows.append((arrival - s.lead, arrival - s.lead + s.pulse))
        return [Decision(event.event_id, "pass", math.nan)]

    def drive(self, clock):
        return 1.0 if any(on <= clock < off for on, off in self.windows) else 0.0
'''


def test_a_controller_that_sets_the_drive_itself_over_the_wire_sorts_as_in_process(tmp_path):
    """The ``drive`` capability: a controller served over the wire that sets the drive each period (lock-step)
    gives the outcomes, decisions and IDT on-time of the same controller in process; it sorts the melanomas."""
    from vcyto import plugins
    path = tmp_path / "driver.py"
    path.write_text(DRIVER)
    stream = ["--model", "rom", "--cells", "RBC,melanoma,RBC,melanoma", "--rate", "300", "--seed", "3"]
    in_process = _run(stream, plugins.controller(f"{path}:WindowDriver", ControllerSettings()))
    served = wire.launch(shlex.join([sys.executable, "-m", "vcyto.wire.serve", "--once", "--controller",
                                     f"{path}:WindowDriver"]), timeout=60)
    over_wire = _run(stream, served)
    assert served.drives and "drive" in served.capabilities
    assert [c["outlet"] for c in in_process["cells"]] == ["lower", "upper", "lower", "upper"]
    assert _outcomes(over_wire) == _outcomes(in_process)
    assert over_wire["idt_on_time_ms"] == in_process["idt_on_time_ms"] > 0


def test_a_drive_answer_out_of_range_or_for_no_period_is_refused_naming_the_field():
    with pytest.raises(framing.WireError, match=r"level must be in \[0, 1\]"):
        messages.drive({"type": "drive", "clock": 0.0, "level": 1.5})
    with pytest.raises(framing.WireError, match="clock must be a finite number"):
        messages.drive({"type": "drive", "clock": None, "level": 1.0})
    assert messages.drive({"type": "drive", "clock": 2.5e-5, "level": 1}) == (2.5e-5, 1.0)


def test_a_driving_controller_in_paced_real_time_holds_the_drive_it_last_set(tmp_path):
    """Paced real time (x0.05): each period's drive is the level the controller last set by then; a controller
    that holds the IDT on deflects an RBC, and the IDT is on for nearly the whole run."""
    path = tmp_path / "hold.py"
    path.write_text("from controller.events import Decision\n\n\n"
                    "class HoldOn:\n    name = 'hold on'\n\n    def __init__(self, settings):\n        pass\n\n"
                    "    def on_event(self, event, clock):\n"
                    "        return [Decision(event.event_id, 'pass', float('nan'))]\n\n"
                    "    def drive(self, clock):\n        return 1.0\n")
    command = shlex.join([sys.executable, "-m", "vcyto.wire.serve", "--once", "--controller", f"{path}:HoldOn"])
    result = vcyto("stream", "--model", "rom", "--cells", "RBC", "--realtime", "0.05", "--controller-exec", command,
                   "--output", str(tmp_path), "--no-viewer", "--json", "--quiet", timeout=120)
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["cells"][0]["outlet"] == "upper"
    assert 0.5 * summary["simulated_time_ms"] < summary["idt_on_time_ms"] <= summary["simulated_time_ms"]
