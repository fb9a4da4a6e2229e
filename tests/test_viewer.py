"""Rerun output: the live view saved by `vcyto stream --save` and `vcyto replay`, read back with Rerun's reader."""

import collections
import json
import subprocess
import sys
from pathlib import Path

import pytest
from rerun.chunk import RrdReader

STATIC = {"/device/outline", "/device/inlets", "/device/outlets", "/device/saw_window", "/device/detection_window"}


def vcyto(*args):
    return subprocess.run([sys.executable, "-m", "vcyto.cli", *args], capture_output=True, text=True, timeout=600)


def entities(path, labels_of=None):
    """Static entities, rows per temporal entity (and, if ``labels_of`` names one, every label it showed)."""
    rows, static, labels = collections.Counter(), set(), set()
    for chunk in RrdReader(str(path)).stream():
        if chunk.is_static:
            static.add(chunk.entity_path)
        else:
            rows[chunk.entity_path] += chunk.num_rows
            if chunk.entity_path == labels_of:
                batch = chunk.to_record_batch()
                for name in (n for n in batch.schema.names if n.endswith(":labels")):
                    labels.update(label for row in batch.column(name).to_pylist() for label in row or ())
    return (static, rows, labels) if labels_of else (static, rows)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    directory = tmp_path_factory.mktemp("run")
    result = vcyto("stream", "--model", "streamline", "--cells", "melanoma,RBC", "--json", "--output", str(directory),
                   "--save", str(directory / "live.rrd"))
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    return directory, summary


def steps_in(mcap_path):
    from vcyto.recording.replay import read_recording
    _, messages, _ = read_recording(mcap_path)
    return sum(len(data["step"]) for topic, data in messages if topic == "/loop/steps")


def test_live_view_has_the_device_cells_idt_and_log(run):
    directory, summary = run
    static, rows, shown = entities(directory / "live.rrd", labels_of="/device/cells")
    assert STATIC <= static
    steps = steps_in(summary["files"]["mcap"])
    assert rows["/device/cells"] == steps                  # every step shows the cells in the channel
    kept = sum(cell["decision"] == "sort" for cell in summary["cells"])
    assert 0 < rows["/idt"] <= 1 + 2 * kept                # the drive: a value per edge of the kept pulses
    assert {str(cell["key"]) for cell in summary["cells"]} <= shown
    assert rows["/log"] == 3 * len(summary["cells"])       # an event, a decision and an outcome per cell


def test_replay_relogs_every_step(run, tmp_path):
    directory, summary = run
    result = vcyto("replay", summary["files"]["mcap"], "--save", str(tmp_path / "replay.rrd"), "--json")
    assert result.returncode == 0, result.stderr
    static, rows = entities(tmp_path / "replay.rrd")
    live_static, live_rows = entities(directory / "live.rrd")
    assert static == live_static and rows["/idt"] == live_rows["/idt"] and rows["/log"] == live_rows["/log"]
    assert json.loads(result.stdout)["damaged"] is False


def test_truncated_recording_replays_what_survives(run, tmp_path):
    _, summary = run
    data = open(summary["files"]["mcap"], "rb").read()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[: len(data) // 2])
    result = vcyto("replay", str(truncated), "--save", str(tmp_path / "t.rrd"))
    assert result.returncode == 0 and "Traceback" not in result.stderr
    assert "damaged or truncated" in result.stdout
    _, rows = entities(tmp_path / "t.rrd")
    assert 0 < rows["/idt"] < steps_in(summary["files"]["mcap"])


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all" * 10])
def test_garbage_is_refused_in_one_line(tmp_path, content):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    result = vcyto("replay", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "bad.mcap" in result.stderr


def test_missing_recording_is_refused():
    result = vcyto("replay", "no-such-run.mcap")
    assert result.returncode == 2 and "does not exist" in result.stderr


def test_a_long_sort_logs_a_bounded_set_of_entities_and_every_path_once(tmp_path):
    """300 cells through rom: the view's entities do not grow with the cells (16 path slots, one cells entity),
    while every cell's path is logged once, in its slot (key mod 16)."""
    result = vcyto("stream", "--model", "rom", "--count", "300", "--rate", "1000", "--arrivals", "poisson",
                   "--mix", "RBC:0.9,melanoma:0.1", "--json", "--quiet", "--output", str(tmp_path),
                   "--save", str(tmp_path / "live.rrd"))
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    left = [cell for cell in summary["cells"] if cell["outlet"] not in ("not_injected",)]
    paths = collections.Counter()
    temporal = set()
    for chunk in RrdReader(str(tmp_path / "live.rrd")).stream():
        if chunk.is_static:
            continue
        temporal.add(chunk.entity_path)
        if chunk.entity_path.startswith("/device/paths/"):
            paths[int(chunk.entity_path.rsplit("/", 1)[1])] += chunk.num_rows
    assert len([e for e in temporal if e.startswith("/device/paths/")]) == 16
    assert len(temporal) <= 16 + 11       # slots + idt, cells, events, pulses (2), log, flow, sort figures (3)
    assert paths == collections.Counter(cell["key"] % 16 for cell in left)


def test_a_display_without_a_server_is_seen_before_the_viewer_is_started(monkeypatch, tmp_path):
    """A viewer started without a reachable display exits only once it opens its window (on a busy machine
    after the start's grace): so vcyto asks the display server first. No server at DISPLAY=:n or at a remote
    one: a one-line reason and no viewer started; a listening X socket (abstract, as Linux's X servers make) or
    Wayland socket: usable."""
    import os
    import socket

    from vcyto.recording import viewer
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    number = 700 + os.getpid() % 200                  # a display no X server on this machine is using
    monkeypatch.setenv("DISPLAY", f":{number}")
    assert viewer.display_problem() == f"no display server answers at DISPLAY=:{number}"
    monkeypatch.setattr(viewer, "find_viewer", lambda: Path(sys.executable))     # a binary it would start
    with pytest.raises(viewer.ViewerUnavailable, match="no display server answers"):
        viewer.start_viewer(port=1)                   # nothing listens on port 1: it would start one
    monkeypatch.setenv("DISPLAY", f"127.0.0.1:{number}.0")
    assert viewer.display_problem() is not None
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(f"\0/tmp/.X11-unix/X{number}")
        server.listen()
        monkeypatch.setenv("DISPLAY", f":{number}.0")
        assert viewer.display_problem() is None
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(str(tmp_path / "wayland-0"))
        server.listen()
        monkeypatch.setenv("DISPLAY", f":{number}")
        monkeypatch.setenv("WAYLAND_DISPLAY", str(tmp_path / "wayland-0"))
        assert viewer.display_problem() is None


# --- a program on the viewer's port that is not a viewer ---------------------------------------------------------

def never_reading(greeting: bytes = b""):
    """A TCP server on a free port that accepts every connection, sends it ``greeting`` and never reads from it;
    yields its port."""
    import socket
    import threading
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    held = []

    def accept():
        while True:
            try:
                connection = server.accept()[0]
            except OSError:
                return
            held.append(connection)
            connection.sendall(greeting)

    threading.Thread(target=accept, daemon=True).start()
    yield server.getsockname()[1]
    server.close()
    for connection in held:
        connection.close()


@pytest.fixture
def deaf_listener():
    """A plain TCP listener that accepts every connection and never reads from it (nor answers)."""
    yield from never_reading()


@pytest.fixture
def stalled_viewer():
    """A server that answers the handshake as a gRPC server (an empty SETTINGS frame) and then never reads: a
    viewer that has hung."""
    yield from never_reading(bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))


def vcyto_on_port(port: int, *args, env=None, **options):
    """``vcyto ARGS`` in a new process whose viewer port (``vcyto.recording.viewer.VIEWER_PORT``, 9876) is ``port``."""
    code = (f"import sys, vcyto.recording.viewer as v; v.VIEWER_PORT = {port}; sys.argv = ['vcyto', *sys.argv[1:]]; "
            "from vcyto.__main__ import run; run()")
    return subprocess.Popen([sys.executable, "-c", code, *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **options)


def test_a_program_on_the_viewer_port_that_never_reads_cannot_hold_the_run(deaf_listener, tmp_path):
    import os
    import time
    env = {**os.environ, "DISPLAY": ":0", "RUST_LOG": "off"}
    started = time.monotonic()
    process = vcyto_on_port(deaf_listener, "stream", "--model", "streamline", "--cells", "RBC,melanoma", "--output",
                            str(tmp_path), "--name", "run", "--quiet", env=env)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "is not a Rerun viewer" in lines[0] and "did not answer the gRPC handshake" in lines[0]
    assert "saving the view to an .rrd file instead" in lines[0], err
    static, rows = entities(tmp_path / "run.rrd")
    assert STATIC <= static and rows["/idt"] > 0
    assert (tmp_path / "run.json").stat().st_size > 0 and (tmp_path / "run.mcap").stat().st_size > 0
    assert time.monotonic() - started < 120


def test_a_viewer_address_that_never_answers_is_not_connected_to(deaf_listener, tmp_path):
    process = vcyto_on_port(deaf_listener, "stream", "--model", "streamline", "--cells", "RBC", "--output",
                            str(tmp_path), "--name", "run", "--quiet", "--connect",
                            f"rerun+http://127.0.0.1:{deaf_listener}/proxy")
    _, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    assert "no Rerun viewer answers at" in err and "gRPC handshake" in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "run.rrd").stat().st_size > 0


@pytest.fixture
def rerun_server():
    """The port of Rerun's own gRPC server (``rerun --serve-grpc``, what a viewer listens with), once it listens."""
    import socket
    import time

    from vcyto.recording import viewer
    binary = viewer.find_viewer()
    if binary is None:
        pytest.skip("no Rerun viewer binary installed")
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    server = subprocess.Popen([str(binary), "--serve-grpc", "--port", str(port)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while not viewer.listening("127.0.0.1", port, timeout=0.2) and time.monotonic() < deadline:
            time.sleep(0.1)
        yield port
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_the_handshake_tells_a_grpc_server_from_a_deaf_port(deaf_listener, rerun_server):
    """A real gRPC server of Rerun's answers the handshake; the deaf listener does not."""
    from vcyto.recording import viewer
    assert "did not answer" in viewer.viewer_problem("127.0.0.1", deaf_listener, timeout=0.3)
    assert viewer.viewer_problem("127.0.0.1", rerun_server) is None


def test_a_viewer_that_stops_taking_the_view_is_left_within_the_bound(stalled_viewer, tmp_path):
    """The run ends, the close waits ``FLUSH_SECONDS`` for the viewer, and says so in a note instead of waiting
    without end (nor when the process frees the stream)."""
    import time
    started = time.monotonic()
    process = vcyto_on_port(stalled_viewer, "stream", "--model", "streamline", "--cells", "RBC,melanoma", "--output",
                            str(tmp_path), "--name", "run", "--quiet", "--connect",
                            f"rerun+http://127.0.0.1:{stalled_viewer}/proxy")
    try:
        _, err = process.communicate(timeout=300)
    finally:
        process.kill()
    assert process.returncode == 0, err
    assert "the Rerun viewer stopped receiving (the viewer did not" in err, err
    assert (tmp_path / "run.json").stat().st_size > 0 and time.monotonic() - started < 120


def test_sigterm_ends_a_run_streaming_to_a_stalled_viewer_at_once(stalled_viewer, tmp_path):
    """SIGTERM mid-run with the viewer no longer reading: the run finishes its files and the process ends within
    three seconds on a loaded machine (0.6-0.7 s measured: the viewer's two bounds and the files), exit 143."""
    import time

    from guard import terminated_within
    # 10^5 cells offered at 500/s: a loop of tens of seconds, still running when the signal comes
    process = vcyto_on_port(stalled_viewer, "stream", "--model", "rom", "--count", "100000", "--mix",
                            "RBC:0.9,melanoma:0.1", "--rate", "500", "--output", str(tmp_path), "--name", "run",
                            "--quiet", "--connect", f"rerun+http://127.0.0.1:{stalled_viewer}/proxy")
    try:
        deadline = time.monotonic() + 120
        recording = tmp_path / "run.mcap"
        while time.monotonic() < deadline and not (recording.exists() and recording.stat().st_size > 10_000):
            time.sleep(0.2)
        time.sleep(2.0)                               # well into the loop
        terminated_within(process, 3.0)
    finally:
        process.kill()
    assert json.loads((tmp_path / "run.json").read_text())["status"] == "interrupted"


def test_a_real_rerun_server_takes_the_whole_run_without_a_note(rerun_server, tmp_path):
    """The handshake and the bounded close cost a real viewer's server nothing: the run streams to
    ``rerun --serve-grpc`` and ends without a note."""
    result = vcyto("stream", "--model", "streamline", "--cells", "RBC,melanoma", "--output", str(tmp_path),
                   "--name", "run", "--quiet", "--connect", f"rerun+http://127.0.0.1:{rerun_server}/proxy")
    assert result.returncode == 0 and result.stderr == "", result.stderr
    assert f"streamed to the viewer at rerun+http://127.0.0.1:{rerun_server}/proxy" in result.stdout


SLOW_VIEW = """
import sys, time
from vcyto.recording import rerunlog
step, delay = rerunlog.RerunSink.on_step, float(sys.argv[1])
def slow_step(self, record):
    time.sleep(delay)
    step(self, record)
rerunlog.RerunSink.on_step = slow_step
sys.argv = ["vcyto", *sys.argv[2:]]
from vcyto.__main__ import run
run()
"""


def test_a_view_that_does_not_keep_up_drops_frames_and_never_holds_the_run(stalled_viewer, tmp_path):
    """The live view is fed through its own bounded queue: with a view made slow (20 ms a step, far slower than
    the rom loop) the run ends in the time the loop takes, not in frames x 20 ms, and the summary (JSON and its
    Rerun line) and the recording's ``run_end`` count the frames dropped."""
    from vcyto.recording.replay import read_metadata
    slow = 0.02
    done = subprocess.run([sys.executable, "-c", SLOW_VIEW, str(slow), "stream", "--model", "rom", "--count", "300",
                           "--mix", "RBC:0.9,melanoma:0.1", "--rate", "2000", "--output", str(tmp_path), "--name",
                           "run", "--quiet", "--connect", f"rerun+http://127.0.0.1:{stalled_viewer}/proxy"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    summary = json.loads((tmp_path / "run.json").read_text())
    frames, dropped = summary["view"]["frames"], summary["view"]["frames_dropped"]
    assert 0 < dropped < frames
    assert summary["wall_time_s"] - summary["setup_time_s"] < 0.5 * frames * slow, summary["wall_time_s"]
    assert f"{dropped:,} of its {frames:,} frames dropped (the view did not keep up" in done.stdout
    ending = read_metadata(tmp_path / "run.mcap")[0]["_run_end"]
    assert int(ending["view_frames"]) == frames and int(ending["view_frames_dropped"]) == dropped


def test_a_view_that_keeps_up_drops_nothing(tmp_path):
    """A sink faster than the batches it is handed: every frame is drawn, none dropped."""
    from vcyto.recording.sinks import LiveView

    class Counting:
        def __init__(self):
            self.steps, self.closed = [], False

        def on_step(self, record):
            self.steps.append(record)

        def close(self):
            self.closed = True
    counting = Counting()
    live = LiveView(counting)
    for batch in range(50):
        live.on_steps(list(range(batch * 4, batch * 4 + 4)))
        while not live._queue.empty():
            time_passes()
    assert live.settle() == {"view_frames": 200, "view_frames_dropped": 0}
    live.close()
    assert counting.steps == list(range(200)) and counting.closed


def time_passes():
    import time
    time.sleep(0.001)
