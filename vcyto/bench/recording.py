"""`vcyto bench recording`: the wall-time overhead of recording an FE-IB stream (MCAP + Rerun .rrd on the
background sink thread) against the same stream unrecorded, in interleaved pairs; the files' sizes."""

from __future__ import annotations

import time

import numpy as np

from sim.model.scenario import Scenario


def bench_recording(scenario: Scenario, cells=("RBC", "melanoma"), repeats: int = 3, progress=None) -> dict:
    """The same FE-IB stream without and with the default recording (MCAP + Rerun .rrd, written on the
    background thread of ``vcyto.recording.sinks``), in ``repeats`` interleaved pairs: the median overhead."""
    import tempfile
    from pathlib import Path

    from controller.detector import DetectorSettings
    from sim.model.arrivals import Arrivals
    from sim.plants.feib import FeibPlant

    from ..recording.mcap import McapRecorder
    from ..recording.rerunlog import RerunSink
    from ..recording.sinks import BackgroundSinks
    from ..stream import StreamSettings, run_stream

    settings = StreamSettings(Arrivals(cells=tuple(cells)))
    plant = FeibPlant(scenario)
    run_stream(scenario, settings.__class__(Arrivals(cells=tuple(cells[:1])), max_time=50e-6), plant=plant)  # warm-up
    pairs = []
    with tempfile.TemporaryDirectory() as directory:
        for repeat in range(repeats):
            walls = {}
            for mode in ("without", "with"):
                if progress:
                    progress.note(f"pair {repeat + 1}/{repeats}: stream {mode} recording")
                sinks = []
                if mode == "with":
                    sinks = [BackgroundSinks([McapRecorder(Path(directory) / "run.mcap", {"benchmark": "recording"},
                                                           scenario=scenario,
                                                           detection_window=DetectorSettings().window),
                                              RerunSink(scenario, DetectorSettings().window,
                                                        ("save", Path(directory) / "run.rrd"))])]
                started = time.perf_counter()
                result = run_stream(scenario, settings, plant=plant, sinks=sinks)
                for sink in sinks:
                    sink.close()
                walls[mode] = time.perf_counter() - started
            pairs.append(walls)
        sizes = {name: (Path(directory) / name).stat().st_size for name in ("run.mcap", "run.rrd")}
    steps = round(result["simulated_time_ms"] * 1e-3 / scenario.numerics.dt)
    overheads = [pair["with"] / pair["without"] - 1 for pair in pairs]
    return {"cells": list(cells), "steps": steps, "pairs_s": pairs, "overheads": overheads,
            "overhead": float(np.median(overheads)), "file_bytes": sizes}


def recording_lines(result: dict) -> list[str]:
    pairs = "; ".join(f"{p['without']:.1f} s / {p['with']:.1f} s" for p in result["pairs_s"])
    return [f"recording overhead: stream {','.join(result['cells'])}, {result['steps']} steps (FE-IB)",
            f"  without / with MCAP + Rerun, interleaved pairs: {pairs}",
            f"  overhead per pair {', '.join(f'{100 * o:.1f} %' for o in result['overheads'])}: "
            f"median {100 * result['overhead']:.1f} % (target <= 10 %)",
            f"  files: MCAP {result['file_bytes']['run.mcap'] / 1e6:.2f} MB, "
            f"Rerun {result['file_bytes']['run.rrd'] / 1e6:.2f} MB"]
