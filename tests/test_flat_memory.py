"""A long recorded sort holds what the cells in the channel need, not what the cells that passed left behind.

The closed loop with the rom plant, the MCAP recorder, the Rerun view (saved to a file) and the sort report is run
cell after cell; every few stops each container reachable from the loop (the plant, the controller and its ledger,
the detector, the report, the sinks) is measured: elements of every dict, list, set and deque, bytes of every array.
None may hold more in the second half of the run than in the first. The bounds that keep them flat (the plant's
window of cells, the latest events and decisions the controller, the report and the MCAP keep, the latest
latencies, the rows the view sends at once) are set small here so that a short run reaches them; the run's own
transit times of the yield estimate are per-cell by design (16 bytes a cell of the first ``TRANSIT_CELLS``) and
are left out. The sample itself is drawn a chunk at a time: a loop holds no array with a byte for each cell it was
offered, at any length (``test_a_loop_holds_no_array_of_the_cells_offered``). ``vcyto bench sort`` checks the same
at 10^5 and 10^6 events in the process's peak memory.
"""

import collections
import json

import numpy as np

from controller import sorter
from sim.model import arrivals
from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario
from vcyto import control, sortreport
from vcyto.recording import mcap, rerunlog
from vcyto.recording.mcap import McapRecorder
from vcyto.recording.rerunlog import RerunSink
from vcyto.stream import Loop, StreamSettings, make_plant

SETTINGS = StreamSettings(Arrivals(count=1600, mix=(("RBC", 0.8), ("melanoma", 0.2)), rate=2000.0,
                                   process="poisson"), model="rom", seed=5)


def held(root, skip) -> collections.Counter:
    """What each container reachable from ``root`` holds, by its path (objects' attributes, containers' items: the
    items of one container share a path): elements of dicts, lists, sets and deques, bytes of arrays; not through
    modules, classes, functions or the objects in ``skip``."""
    seen, sizes, stack = set(skip), collections.Counter(), [("loop", root)]
    while stack:
        path, item = stack.pop()
        if id(item) in seen or isinstance(item, (str, bytes, int, float, type, type(np), type(held))):
            continue
        seen.add(id(item))
        if isinstance(item, np.ndarray):
            sizes[path] += item.nbytes if item.base is None else 0
        elif isinstance(item, dict):
            sizes[path] += len(item)
            stack += [(f"{path}[]", value) for pair in item.items() for value in pair]
        elif isinstance(item, (list, tuple, set, frozenset, collections.deque)):
            sizes[path] += len(item)
            stack += [(f"{path}[]", value) for value in item]
        elif hasattr(item, "__dict__") and type(item).__module__.split(".")[0] in ("vcyto", "sim", "controller"):
            stack += [(f"{path}.{name}", value) for name, value in vars(item).items()]
    return sizes


def test_a_long_recorded_sort_holds_no_more_in_its_second_half_than_in_its_first(tmp_path, monkeypatch):
    for module in (sortreport, mcap):
        monkeypatch.setattr(module, "EVENT_NAMES", 32)
    monkeypatch.setattr(sortreport, "SORTS_KEPT", 16)
    monkeypatch.setattr(sortreport, "KEEP_CELLS", 100)      # the summary lists the cells of short runs only
    monkeypatch.setattr(control, "KNOWN_EVENTS", 16)
    monkeypatch.setattr(control, "LATENCY_SAMPLES", 64)
    monkeypatch.setattr(sorter, "RECENT_DECISIONS", 16)
    monkeypatch.setattr(rerunlog, "FILE_BATCH_ROWS", 500)   # rows the view keeps before it sends them
    scenario = Scenario()
    plant = make_plant(scenario, SETTINGS)
    plant.window = 64                                     # cells whose state the plant holds at once
    recorder = McapRecorder(tmp_path / "run.mcap", {"seed": SETTINGS.seed}, flush_every=50, scenario=scenario)
    view = RerunSink(scenario, SETTINGS.detector.window, ("save", tmp_path / "run.rrd"), field_every=0,
                     membranes=False)
    try:
        loop = Loop(scenario, SETTINGS, plant=plant, sinks=[recorder, view])
        per_cell = [loop.report.samples, scenario]
        sizes, stops = [], 0
        while loop.proceed:
            loop.step()
            stops += 1
            if stops % 25 == 0:
                sizes.append((loop.report.tally.counts["cells"], held(loop, [id(item) for item in per_cell])))
        loop.finish()
        summary = loop.summary()
    finally:
        recorder.close()
        view.close()
    assert summary["status"] == "complete" and summary["statistics"]["cells"] > 700
    left = summary["statistics"]["cells"]
    # each container: what it holds in the second half at most what it held in the first (cells in the channel vary)
    first, second = collections.Counter(), collections.Counter()
    for cells, held_then in sizes:
        if left / 8 <= cells <= left / 2 or cells > left / 2:
            (first if cells <= left / 2 else second).update({path: 0 for path in held_then})
            later = first if cells <= left / 2 else second
            for path, size in held_then.items():
                later[path] = max(later[path], size)
    grew = {path: (first[path], size) for path, size in second.items() if size > 1.2 * first[path] + 16}
    assert not grew
    assert plant._base > 0 and len(plant._born) == 64


def test_a_long_runs_fcs_is_finished_from_its_checkpoint_with_the_events_of_its_table(tmp_path, monkeypatch, capsys):
    """A run longer than a summary lists (no cells in it): its FCS events are those of the checkpoints written as it
    went and the rest, copied rather than read back, and they are the events its per-cell table gives."""
    from vcyto import celltable
    from vcyto.cli import main
    from vcyto.recording import checkpoint, fcs
    monkeypatch.setattr(sortreport, "KEEP_CELLS", 100)
    monkeypatch.setattr(checkpoint.Checkpoint, "due", lambda self: True)          # a checkpoint at every stop
    copied = []
    finish = checkpoint.Checkpoint.finish_events
    monkeypatch.setattr(checkpoint.Checkpoint, "finish_events",
                        lambda self, *args: copied.append(self.count) or finish(self, *args))
    assert main(["stream", "--model", "rom", "--count", "600", "--rate", "2000", "--arrivals", "poisson",
                 "--mix", "RBC:0.8,melanoma:0.2", "--seed", "2", "--json", "--quiet", "--no-viewer",
                 "--output", str(tmp_path)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert "cells" not in result and copied and copied[0] > 100       # most events were in the file already
    records = list(celltable.records(result["cell_table"]["path"]))
    names, events, keywords = fcs.read_fcs(next(tmp_path.glob("*.fcs")))
    assert len(events) == result["statistics"]["events"] > 250 and keywords["vcyto_status"] == "complete"
    np.testing.assert_array_equal(events, fcs.event_table({"cells": records}))


def test_a_loop_holds_no_array_of_the_cells_offered(monkeypatch):
    """The same loop (the rom plant, the controller, the sort report and the sample) offered 4,000 and 40,000 cells,
    looked at when 1,500 cells have left: the longer holds less than a quarter of a byte more for each cell more it
    was offered (the arrays of running counts of its chunks of 1,024 cells), where an array of the
    sample would add 8 bytes an admitted cell for its times, one for its types, one for a flag per cell (about half
    an admitted cell an offered one at this rate)."""
    monkeypatch.setattr(arrivals, "CHUNK", 1024)
    monkeypatch.setattr(sortreport, "KEEP_CELLS", 100)      # neither run lists its cells in the summary
    scenario = Scenario()
    plant = make_plant(scenario, SETTINGS)
    plant.window = 64

    def held_at(count):
        settings = StreamSettings(Arrivals(count=count, mix=(("RBC", 0.8), ("melanoma", 0.2)), rate=2000.0,
                                           process="poisson"), model="rom", seed=5)
        loop = Loop(scenario, settings, plant=plant)
        while loop.report.tally.counts["cells"] < 1500:
            loop.step()
        return sum(held(loop, [id(scenario), id(loop.report.samples)]).values())

    short, long = held_at(4_000), held_at(40_000)
    assert long - short < 0.25 * (40_000 - 4_000), (short, long)
