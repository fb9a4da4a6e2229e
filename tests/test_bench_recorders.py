"""`vcyto bench recorders`: each part of a recorded rom run timed by itself, on the sample the loop sorts."""

import json

from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario
from vcyto.bench.recorders import PARTS, bench_recorders
from vcyto.recording.replay import happenings
from vcyto.stream import StreamSettings, run_stream


def test_the_recorders_are_timed_on_the_records_of_the_sort_the_loop_runs(tmp_path, monkeypatch):
    """The bench's events are those of the same sort run by ``run_stream``; every part takes time; the MCAP the
    bench writes holds every event and outcome of that sort."""
    import vcyto.bench.recorders as recorders
    kept = {}

    class Directory:                               # the recorders' files kept for the check
        def __enter__(self):
            return str(tmp_path)

        def __exit__(self, *exc):
            kept["mcap"] = happenings(tmp_path / "run.mcap")
            return False

    monkeypatch.setattr(recorders.tempfile, "TemporaryDirectory", Directory)
    result = bench_recorders(Scenario(), count=400, repeats=1, seed=5)
    settings = StreamSettings(Arrivals(count=400, mix=(("RBC", 0.9), ("melanoma", 0.1)), rate=2000.0,
                                       process="poisson"), model="rom", seed=5)
    reference = run_stream(Scenario(), settings)
    assert result["events"] == reference["statistics"]["events"] > 100
    assert result["records"] >= result["events"]
    assert all(result["us_per_event"][part] > 0 for part in PARTS)
    assert len(kept["mcap"]["/detector/event"]) == result["events"]
    assert len(kept["mcap"]["/outcome"]) == len(reference["cells"])
    json.dumps(result, allow_nan=False)
