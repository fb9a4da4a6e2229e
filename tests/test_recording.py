"""MCAP recordings of the closed loop: round trip, crash safety, determinism."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario
from sim.plants.streamline import StreamlinePlant
from vcyto.recording.mcap import PER_STEP, McapRecorder
from vcyto.recording.replay import COLUMNAR, happenings, rows_of
from vcyto.recording.sinks import BackgroundSinks
from vcyto.stream import StreamSettings, StreamStopped, run_stream


@pytest.fixture(scope="module")
def plant():
    return StreamlinePlant(Scenario())


def record(plant, path, seed=0, cells=("melanoma", "RBC", "melanoma"), background=False):
    recorder = McapRecorder(path, {"seed": seed}, flush_every=10, field_every=0)
    sink = BackgroundSinks([recorder]) if background else recorder
    settings = StreamSettings(Arrivals(cells=cells), model="streamline", seed=seed)
    try:
        result = run_stream(Scenario(), settings, plant=plant, sinks=[sink])
    finally:
        sink.close()
    return result


def messages(path):
    """(topic, log time from the run's start in ns, payload) of the JSON channels."""
    with open(path, "rb") as handle:
        reader = make_reader(handle)
        origin = int(next(iter(reader.iter_metadata())).metadata["time_origin_unix_ns"])
        return [(channel.topic, message.log_time - origin, json.loads(message.data))
                for _, channel, message in reader.iter_messages(log_time_order=False)
                if channel.message_encoding == "json"]


def test_round_trip_one_row_per_step_in_batches_monotonic_times_and_outcomes(plant, tmp_path):
    """The per-step channels hold one column entry per step, in batches of ``flush_every`` (10) steps, each
    message at its last step's time; the rows of /cells/rows are the cells in the channel at each step."""
    path = tmp_path / "run.mcap"
    result = record(plant, path)
    recorded = messages(path)
    batches = [m for m in recorded if m[0] == "/loop/steps"]
    steps = [step for m in batches for step in m[2]["step"]]
    times = [t for m in batches for t in m[2]["time"]]
    assert steps == list(range(1, len(steps) + 1)) and len(steps) > 20 and times == sorted(times)
    assert [len(m[2]["step"]) for m in batches[:-1]] == [10] * (len(batches) - 1)
    for topic in PER_STEP:
        batch_times = [m[1] for m in recorded if m[0] == topic]
        assert batch_times == [round(m[2]["time"][-1] * 1e9) for m in batches]
    rows = [m[2] for m in recorded if m[0] == "/cells/rows"]
    assert [t for r in rows for t in r["time"]] == times
    assert [c for r in rows for c in r["count"]] == [n for m in batches for n in m[2]["cells_in_channel"]]
    assert sum(len(r["key"]) for r in rows) == sum(c for r in rows for c in r["count"]) > 0
    written = happenings(path)
    outcomes = {outcome["key"]: outcome["outlet"] for outcome in written["/outcome"]}
    assert outcomes == {cell["key"]: cell["outlet"] for cell in result["cells"]}
    decisions = {decision["event_id"]: decision["action"] for decision in written["/controller/decision"]}
    assert sorted(decisions.values()) == sorted(c["decision"] for c in result["cells"])
    with open(path, "rb") as handle:
        metadata = list(make_reader(handle).iter_metadata())
    assert metadata[0].name == "run" and metadata[0].metadata["seed"] == "0"


def test_the_logs_decision_lines_name_each_events_cell(plant, tmp_path):
    """A decision line of the MCAP log names its detector event's cell, ``event N (cell K): ...``, as the summary's
    reasons do; N and K agree with the /detector/event messages (found by a user trial: event numbers only)."""
    import re

    from mcap_protobuf.decoder import DecoderFactory
    path = tmp_path / "run.mcap"
    record(plant, path, cells=("melanoma", "RBC", "melanoma", "RBC"))
    cells_of = {event["event_id"]: event["key"] for event in happenings(path)["/detector/event"]}
    decode, lines = DecoderFactory(), []
    with open(path, "rb") as handle:
        for schema, channel, message in make_reader(handle).iter_messages(topics=["/foxglove/log"]):
            lines.append(decode.decoder_for(channel.message_encoding, schema)(message.data).message)
    decisions = [re.match(r"event (\d+) \(cell (\d+)\): (pass|sort|abort)", line) for line in lines
                 if line.startswith("event ")]
    assert len(decisions) == len(cells_of) == 4 and all(decisions)
    assert all(cells_of[int(found.group(1))] == int(found.group(2)) for found in decisions)


def test_same_seed_same_messages_apart_from_wall_clock(plant, tmp_path):
    record(plant, tmp_path / "a.mcap", seed=4)
    record(plant, tmp_path / "b.mcap", seed=4)
    assert content(tmp_path / "a.mcap") == content(tmp_path / "b.mcap")


def content(path):
    return [(topic, stamp, {k: v for k, v in data.items() if k not in ("wall_time", "diagnostics")})
            for topic, stamp, data in messages(path)]


def test_sinks_on_the_background_thread_write_the_same_messages_as_inline(plant, tmp_path):
    record(plant, tmp_path / "inline.mcap", seed=2)
    record(plant, tmp_path / "background.mcap", seed=2, background=True)
    assert content(tmp_path / "inline.mcap") == content(tmp_path / "background.mcap")


def test_a_failing_sink_stops_the_run_with_its_error(plant):
    class FullDisk:
        field_every = 0

        def on_step(self, record):
            if record.step == 5:
                raise OSError(28, "No space left on device")

        def close(self):
            self.closed = True

    failing = FullDisk()
    settings = StreamSettings(Arrivals(cells=("RBC",)), model="streamline")
    with pytest.raises(StreamStopped) as stopped:        # a failed run, its partial summary and the write's cause
        sink = BackgroundSinks([failing], batch_steps=1)      # handed over each step: the failure seen at once
        try:
            run_stream(Scenario(), settings, plant=plant, sinks=[sink])
        finally:
            sink.close()
    assert failing.closed
    assert stopped.value.status == "failed" and isinstance(stopped.value.__cause__, OSError)
    assert "No space left" in stopped.value.reason and stopped.value.result["status"] == "failed"
    assert 0 < stopped.value.result["steps"] < 1000


def test_a_deferred_sink_is_built_on_the_sinks_thread_and_writes_the_same_messages(plant, tmp_path):
    """``vcyto stream`` builds its Rerun sink on the sinks' thread (its import overlaps the plant's set-up): a
    ``Deferred`` sink is built there, before any step, and records what the same sink given directly records;
    a sink that cannot be built stops the run with its error, as a failing sink does."""
    import threading

    from vcyto.recording.sinks import Deferred
    settings = StreamSettings(Arrivals(cells=("melanoma", "RBC", "melanoma")), model="streamline")
    built_on = []

    def build():
        built_on.append(threading.current_thread().name)
        return [McapRecorder(tmp_path / "deferred.mcap", {"seed": 0}, flush_every=10, field_every=0)]
    sink = BackgroundSinks([Deferred(build)])
    try:
        run_stream(Scenario(), settings, plant=plant, sinks=[sink])
    finally:
        sink.close()
    record(plant, tmp_path / "direct.mcap", background=True)
    assert built_on == ["vcyto-sinks"]
    assert content(tmp_path / "deferred.mcap") == content(tmp_path / "direct.mcap")

    def unbuildable():
        raise OSError(28, "No space left on device")
    with pytest.raises(StreamStopped, match="No space left"):
        sink = BackgroundSinks([Deferred(unbuildable)])
        try:
            run_stream(Scenario(), StreamSettings(Arrivals(cells=("RBC",)), model="streamline"), plant=plant,
                       sinks=[sink])
        finally:
            sink.close()


def killed_recording(command, directory, size: int, wait: float):
    """Run ``command`` until its MCAP in ``directory`` passes ``size`` bytes, SIGKILL it; the MCAP's messages
    readable up to its torn tail, by topic (JSON, decoded)."""
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    path = None
    deadline = time.time() + wait
    while time.time() < deadline and process.poll() is None:
        files = list(directory.glob("*.mcap"))
        if files and files[0].stat().st_size > size:
            path = files[0]
            break
        time.sleep(0.2)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert path is not None, "the run never wrote enough to kill it mid-way"
    channels, topics = {}, {}
    with open(path, "rb") as handle:
        try:
            for record in StreamReader(handle, skip_magic=False).records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message) and record.channel_id in channels:
                    topic = channels[record.channel_id]
                    if topic in COLUMNAR:
                        topics.setdefault(COLUMNAR[topic], []).extend(rows_of(json.loads(record.data)))
                    elif not topic.startswith("/foxglove/"):
                        topics.setdefault(topic, []).append(json.loads(record.data))
        except McapError:
            pass                                   # the truncated tail: everything before it is intact
    return topics


def test_a_killed_run_keeps_every_step_up_to_the_last_flush(tmp_path):
    command = [sys.executable, "-m", "vcyto.cli", "stream", "--model", "streamline", "--count", "400",
               "--mix", "RBC:0.5,melanoma:0.5", "--rate", "2000", "--quiet", "--output", str(tmp_path),
               "--flush-every", "20"]
    topics = killed_recording(command, tmp_path, 200_000, 120)
    steps = [step for batch in topics.get("/loop/steps", []) for step in batch["step"]]
    assert len(steps) >= 20 and steps == list(range(1, len(steps) + 1))


@pytest.mark.slow
def test_a_killed_million_event_sort_keeps_its_recording_up_to_the_last_flush(tmp_path):
    """A rom sort of 10^6 events (2 x 10^6 offered at 2,000/s) with MCAP and Rerun, killed once its recording
    has grown: the steps up to the last whole batch read back in order, with the events of those steps."""
    command = [sys.executable, "-m", "vcyto.cli", "stream", "--model", "rom", "--count", "2000000", "--rate", "2000",
               "--arrivals", "poisson", "--mix", "RBC:0.9,melanoma:0.1", "--quiet", "--output", str(tmp_path),
               "--save", str(tmp_path / "run.rrd")]
    topics = killed_recording(command, tmp_path, 3_000_000, 600)
    steps = [t for batch in topics.get("/loop/steps", []) for t in batch["time"]]
    events = [event["time"] for event in topics.get("/detector/event", [])]
    assert len(steps) >= 400 and steps == sorted(steps) and len(set(steps)) == len(steps)
    assert len(events) > 100 and events == sorted(events)
