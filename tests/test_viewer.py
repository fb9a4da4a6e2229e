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
    from vcyto.replay import read_recording
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

    from vcyto import viewer
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
