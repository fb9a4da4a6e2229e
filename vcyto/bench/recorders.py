"""`vcyto bench recorders`: where a recorded event's time goes, on the ``rom`` plant.

One sample (``count`` cells offered at ``rate``/s, Poisson, the inlet's dead time: the stream `vcyto bench sort`
runs) goes through the loop in this process, and each part of a recorded run is timed by itself, as CPU time of
this process per detector event (``time.process_time``: what the work costs, whatever else the machine runs):

- ``loop``: the loop with no sink (the plant, the detector, the controller, the sort report);
- ``loop_shown``: the loop with a sink that keeps what it is shown, as a recording is (the plant looked at and
  traced every record interval, a record built per stop): the difference from ``loop`` is what a recording costs
  the loop's own thread;
- ``mcap`` and ``rerun``: the MCAP recorder and the Rerun view (saved to a file), each handed the kept records in
  batches of ``BATCH_STEPS`` as the recording's thread hands them over, and closed (their set-up, once a run,
  apart: ``recorder_setup_s``).

Each is measured ``repeats`` times and the median reported. The recorders run on a thread of the loop's process
and share its interpreter lock, so a recorded run's loop wall per event is about ``loop_shown + mcap + rerun``
(``serial``) on any number of cores; `vcyto bench sort` measures the wall itself.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from sim.model.scenario import Scenario

from ..recording.sinks import BATCH_STEPS

PARTS = ("loop", "loop_shown", "mcap", "rerun")


class _Kept:
    """A sink that keeps the records it is shown."""

    def __init__(self):
        self.records = []

    def on_step(self, record):
        self.records.append(record)


def bench_recorders(scenario: Scenario, count: int = 20_000, rate: float = 2000.0, repeats: int = 3, seed: int = 3,
                    progress=lambda message: None) -> dict:
    from sim.model.arrivals import Arrivals

    from ..recording.mcap import McapRecorder
    from ..recording.rerunlog import RerunSink
    from ..stream import StreamSettings, make_plant, run_stream

    settings = StreamSettings(Arrivals(count=count, mix=(("RBC", 0.9), ("melanoma", 0.1)), rate=rate,
                                       process="poisson"), model="rom", seed=seed)
    progress("set-up: the rom plant")
    plant = make_plant(scenario, settings)
    times = {part: [] for part in PARTS}
    openings = {"mcap": [], "rerun": []}           # a recorder's set-up (a file opened, the static scene): once a run
    events = records_shown = None
    for repeat in range(repeats):
        progress(f"run {repeat + 1} of {repeats}: the loop alone, then shown, then each recorder")
        started = time.process_time()
        alone = run_stream(scenario, settings, plant=plant)
        times["loop"].append(time.process_time() - started)
        kept = _Kept()
        started = time.process_time()
        shown = run_stream(scenario, settings, plant=plant, sinks=[kept])
        times["loop_shown"].append(time.process_time() - started)
        if alone["statistics"] != shown["statistics"]:
            raise RuntimeError("the loop shown to a sink sorted otherwise than the loop alone")
        events, records_shown = shown["statistics"]["events"], len(kept.records)
        with tempfile.TemporaryDirectory() as directory:
            for part, sink in (("mcap", lambda: McapRecorder(Path(directory) / "run.mcap", {"seed": seed},
                                                             scenario=scenario,
                                                             detection_window=settings.detector.window)),
                               ("rerun", lambda: RerunSink(scenario, settings.detector.window,
                                                           ("save", Path(directory) / "run.rrd"), membranes=False))):
                started = time.process_time()
                recorder = sink()
                opened = time.process_time()
                records = kept.records
                for start in range(0, len(records), BATCH_STEPS):
                    recorder.on_steps(records[start:start + BATCH_STEPS])
                recorder.close()
                times[part].append(time.process_time() - opened)
                openings[part].append(opened - started)
        del kept
    per_event = {part: statistics.median(values) / max(1, events) * 1e6 for part, values in times.items()}
    per_event["recording_on_the_loop"] = per_event["loop_shown"] - per_event["loop"]
    per_event["serial"] = per_event["loop_shown"] + per_event["mcap"] + per_event["rerun"]
    return {"model": "rom", "offered": count, "rate_per_s": rate, "seed": seed, "events": events,
            "records": records_shown, "repeats": repeats,
            "cpu_s": times, "us_per_event": per_event,
            "recorder_setup_s": {part: statistics.median(values) for part, values in openings.items()}}


def report_lines(result: dict) -> list[str]:
    us = result["us_per_event"]
    lines = [f"recorders on rom: {result['offered']:,} cells offered at {result['rate_per_s']:g}/s, "
             f"{result['events']:,} events ({result['records']:,} records shown), seed {result['seed']}; CPU time "
             f"per event, median of {result['repeats']}:"]
    for name, text in (("loop", "the loop alone (plant, detector, controller, report)"),
                       ("loop_shown", "the loop shown to a recording (its state looked at, records built)"),
                       ("recording_on_the_loop", "  of which the recording's share on the loop's thread"),
                       ("mcap", "the MCAP recorder"), ("rerun", "the Rerun view, saved to a file"),
                       ("serial", "loop shown + both recorders (one interpreter lock: about the recorded wall)")):
        lines.append(f"  {us[name]:8.1f} us  {text}")
    setup = result["recorder_setup_s"]
    lines.append(f"  set-up, once a run: MCAP {setup['mcap']:.3f} s, Rerun {setup['rerun']:.3f} s")
    return lines
