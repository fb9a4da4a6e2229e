"""Recording an event-driven plant without stopping it: the rom plant traces its cells every record interval in
its kernel (``sim.plants.contract.Traces``) and the loop hands the recorded steps over as columns (``vcyto.trace``). The
recording and the outcomes must be those of the loop that stopped the plant at every recorded step; the run's
memory must not keep what it no longer needs (the sample as arrays, bounded decision logs, the detector's cells)."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from controller.detector import Detector, DetectorSettings
from controller.events import Decision, Sighting
from controller.protocol import DecisionLog
from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario
from sim.plants import rom as rom_module
from vcyto.recording.mcap import McapRecorder
from vcyto.recording.replay import COLUMNAR, rows_of
from vcyto.stream import StreamSettings, make_plant, run_stream

SETTINGS = StreamSettings(Arrivals(count=240, mix=(("RBC", 0.8), ("melanoma", 0.2)), rate=2500.0,
                                   process="poisson", min_spacing=0.2e-3), model="rom", seed=4)


class Untraced:
    """The rom plant without its trace: the loop stops it at every record interval (what recordings did before)."""

    def __init__(self, plant):
        self._plant = plant

    def __getattr__(self, name):
        if name in ("trace", "take_trace"):
            raise AttributeError(name)
        return getattr(self._plant, name)


def recorded(directory, plant):
    recorder = McapRecorder(directory / "run.mcap", {"seed": SETTINGS.seed}, flush_every=50, scenario=Scenario())
    try:
        result = run_stream(Scenario(), SETTINGS, plant=plant, sinks=[recorder])
    finally:
        recorder.close()
    return result, json_topics(directory / "run.mcap")


def json_topics(path) -> dict:
    """topic -> the JSON messages of the recording at ``path``, in the file's order; the rows of the columnar
    events, decisions and outcomes as the records they are (``/detector/event`` ...)."""
    topics = {}
    with open(path, "rb") as handle:
        for _, channel, message in make_reader(handle).iter_messages(log_time_order=False):
            if channel.topic in COLUMNAR:
                topics.setdefault(COLUMNAR[channel.topic], []).extend(rows_of(json.loads(message.data)))
            elif channel.message_encoding == "json":
                topics.setdefault(channel.topic, []).append(json.loads(message.data))
    return topics


def column(topics, topic, name):
    return [value for batch in topics[topic] for value in batch[name]]


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    plant = make_plant(Scenario(), SETTINGS)
    traced = recorded(tmp_path_factory.mktemp("traced"), plant)
    stopped = recorded(tmp_path_factory.mktemp("stopped"), Untraced(plant))
    return traced, stopped


def test_the_traced_recording_is_the_one_of_a_loop_that_stopped_at_every_recorded_step(both):
    (traced, new), (stopped, old) = both
    assert traced["steps"] == stopped["steps"] and traced["statistics"] == stopped["statistics"]
    steps = column(new, "/loop/steps", "step")
    assert len(steps) > 100 and steps == sorted(steps)
    for name in ("time", "step", "idt", "cells_in_channel"):
        assert column(new, "/loop/steps", name) == column(old, "/loop/steps", name), name
    for name in ("time", "count", "key", "type", "class", "x_um", "y_um", "area_ratio"):
        assert column(new, "/cells/rows", name) == column(old, "/cells/rows", name), name
    assert {"in channel", "detected type I"} <= set(column(new, "/cells/rows", "class"))
    for topic in ("/detector/event", "/outcome"):
        assert [{k: v for k, v in m.items() if k != "time" or topic == "/detector/event"} for m in new[topic]] == \
            [{k: v for k, v in m.items() if k != "time" or topic == "/detector/event"} for m in old[topic]]
    # a decision is shown at the loop's stop where it was made, no later than at the next recorded step
    new_decisions, old_decisions = new["/controller/decision"], old["/controller/decision"]
    assert [{k: v for k, v in m.items() if k != "time"} for m in new_decisions] == \
        [{k: v for k, v in m.items() if k != "time"} for m in old_decisions]
    assert all(a["time"] <= b["time"] for a, b in zip(new_decisions, old_decisions))


def test_a_crowd_that_overflows_the_log_and_the_trace_gets_more_room_and_the_same_outcome(monkeypatch):
    """Buffers of two rows: every call grows them (a crowd, or a trace never taken); nothing is lost."""
    scenario = Scenario()
    reference = run_stream(scenario, SETTINGS, sinks=[_Paced()])
    monkeypatch.setattr(rom_module, "LOG_ROWS", 2)
    monkeypatch.setattr(rom_module, "TRACE_ROWS", 2)
    crowded = run_stream(scenario, SETTINGS, sinks=[_Paced()])
    assert crowded["statistics"] == reference["statistics"] and crowded["steps"] == reference["steps"]


class _Paced:
    def on_step(self, record):
        pass


def test_decision_logs_keep_the_latest_events_only():
    log = DecisionLog(keep=10)
    for event_id in range(1000):
        log.record(Decision(event_id, "pass", 0.0))
    kept = [d.event_id for d in log.decisions]
    assert 10 <= len(kept) <= 20 and kept[-1] == 999 and log.decision_for(995).event_id == 995
    assert log.decision_for(0) is None
    unbounded = DecisionLog()
    for event_id in range(1000):
        unbounded.record(Decision(event_id, "pass", 0.0))
    assert len(unbounded.decisions) == 1000


def test_the_detector_forgets_the_cells_that_left():
    detector = Detector(DetectorSettings(), np.random.default_rng(0))
    events = []
    for step, x in enumerate(np.linspace(0.0, 100e-6, 40)):
        events += detector.observe(step * 1e-5, [Sighting(key, x, 100e-6, 50e-12, 1.0) for key in range(3)])
    assert len(events) == 3 and len(detector._passages) == len(detector._previous) == 3
    detector.forget([0, 1, 2])
    assert not detector._passages and not detector._previous


@pytest.mark.parametrize("window", [4, 40])
def test_a_sample_sliding_through_a_small_window_of_cells_is_recorded_as_with_every_cell_held(both, tmp_path, window):
    """The rom plant holds the state of ``window`` cells at once (settled cells are dropped as the sample slides
    through): the recording, the steps and the outcomes are those of the plant that holds every cell."""
    (held, whole), _ = both
    plant = make_plant(Scenario(), SETTINGS)
    plant.window = window                   # read at reset: 4 cells grow it, 40 slide many times
    result, topics = recorded(tmp_path, plant)
    assert plant._base > 0 and len(plant._born) < plant._count
    assert result["statistics"] == held["statistics"] and result["steps"] == held["steps"]
    assert set(topics) == set(whole)
    for topic, batches in whole.items():
        strip = [{k: v for k, v in m.items() if k != "wall_time"} for m in batches]
        assert [{k: v for k, v in m.items() if k != "wall_time"} for m in topics[topic]] == strip, topic


def test_records_written_in_batches_are_the_records_written_one_by_one(both, tmp_path):
    """The recorders take an event-driven plant's records a batch at a time (``vcyto.trace.TracedRows``: the rows'
    classes looked up for the batch at once); the recording is the one of the records taken one by one."""
    from vcyto.recording.sinks import BackgroundSinks
    (_, one_by_one), _ = both
    recorder = McapRecorder(tmp_path / "run.mcap", {"seed": SETTINGS.seed}, flush_every=50, scenario=Scenario())
    sinks = BackgroundSinks([recorder], batch_steps=64, batch_seconds=1e9)
    batches = []
    recorder.on_steps = lambda records, write=recorder.on_steps: (batches.append(len(records)), write(records))
    try:
        run_stream(Scenario(), SETTINGS, plant=make_plant(Scenario(), SETTINGS), sinks=[sinks])
    finally:
        sinks.close()
    topics = json_topics(tmp_path / "run.mcap")
    assert max(batches) == 64 and len(batches) >= 3
    for name in ("time", "step", "idt", "cells_in_channel"):
        assert column(topics, "/loop/steps", name) == column(one_by_one, "/loop/steps", name), name
    for name in ("time", "count", "key", "type", "class", "x_um", "y_um", "area_ratio"):
        assert column(topics, "/cells/rows", name) == column(one_by_one, "/cells/rows", name), name
    assert len(set(column(topics, "/cells/rows", "class"))) >= 3
    for topic in ("/detector/event", "/controller/decision", "/outcome"):
        assert topics[topic] == one_by_one[topic], topic
