"""`vcyto bench realtime`: the real-time factor of the closed loop with the ``rom`` plant (device time simulated
over loop wall time) on a Poisson stream, detector and controller in the loop, no recording; the set-up apart."""

from __future__ import annotations

import statistics
import time

from sim.model.scenario import UM, Scenario


def bench_realtime(scenario: Scenario, rate: float = 1000.0, duration: float = 1.0,
                   mix=(("RBC", 0.9), ("melanoma", 0.1)), repeats: int = 3, control_period: float | None = None,
                   seed: int = 0, progress=lambda message: None) -> dict:
    """Real-time factor of the closed loop with the ``rom`` plant: a Poisson stream of ``rate`` x ``duration``
    cells (no dead time), detector and controller in the loop, no recording.

    Set-up (the two steady FE solves, sampling the grid, loading the kernels) is timed once; then the same
    stream runs ``repeats`` times on that plant. Loop wall = the run's wall time minus its own set-up
    (schedule, reset); real-time factor = device time simulated / loop wall; the median over repeats.
    """
    from sim.model.arrivals import Arrivals

    from ..stream import StreamSettings, make_plant, run_stream

    arrivals = Arrivals(count=max(1, round(rate * duration)), mix=tuple(mix), rate=rate, process="poisson",
                        min_spacing=0.0)
    settings = StreamSettings(arrivals, model="rom", seed=seed, control_period=control_period,
                              max_time=2 * duration + 20e-3)
    progress("set-up: steady flows with the IDT off and on, sampled on the grid")
    started = time.perf_counter()
    plant = make_plant(scenario, settings)
    setup = time.perf_counter() - started
    runs = []
    for repeat in range(repeats):
        progress(f"run {repeat + 1} of {repeats}")
        result = run_stream(scenario, settings, plant=plant)
        loop = result["wall_time_s"] - result["setup_time_s"]
        runs.append({"loop_wall_s": loop, "device_time_s": result["simulated_time_ms"] * 1e-3,
                     "real_time_factor": result["simulated_time_ms"] * 1e-3 / loop})
    stats = result["statistics"]
    return {
        "model": "rom", "rate_per_s": rate, "duration_s": duration, "cells": arrivals.count,
        "mix": [list(pair) for pair in mix], "seed": seed, "control_period_us": plant.control_period * 1e6,
        "substep_us": plant.control_period / plant.substeps * 1e6, "response_time_us": plant.response_time * 1e6,
        "grid_spacing_um": [s / UM for s in plant.flows.spacing],
        "setup_s": setup, "setup_parts_s": dict(plant.timings),
        "runs": runs, "loop_wall_s": statistics.median(r["loop_wall_s"] for r in runs),
        "device_time_s": runs[-1]["device_time_s"],
        "real_time_factor": statistics.median(r["real_time_factor"] for r in runs),
        "purity": stats["purity"], "yield": stats["yield"], "abort_rate": stats["abort_rate"],
        "outlets": stats["outlets"], "misclassified": stats["misclassified"],
    }


def realtime_lines(result: dict) -> list[str]:
    def percent(value):
        return "n/a" if value is None else f"{100 * value:.1f} %"

    parts = ", ".join(f"{name.removesuffix('_s').replace('_', ' ')} {value:.2f} s"
                      for name, value in result["setup_parts_s"].items())
    factors = ", ".join(f"{run['real_time_factor']:.1f}" for run in result["runs"])
    return [
        f"real time: rom plant, {result['cells']:,} cells at {result['rate_per_s']:g}/s (Poisson, "
        f"{', '.join(f'{name}:{weight:g}' for name, weight in result['mix'])}), control period "
        f"{result['control_period_us']:g} us, detector and controller in the loop, no recording",
        f"  set-up {result['setup_s']:.2f} s ({parts})",
        f"  loop: {result['device_time_s'] * 1e3:.1f} ms of device time in {result['loop_wall_s'] * 1e3:.1f} ms wall "
        f"(median of {len(result['runs'])})",
        f"  real-time factor {result['real_time_factor']:.1f} (runs: {factors}; target >= 10)",
        f"  purity {percent(result['purity'])}, yield {percent(result['yield'])}, abort rate "
        f"{percent(result['abort_rate'])}; outlets: "
        + (", ".join(f"{outlet} {count}" for outlet, count in result["outlets"].items()) or "none"),
    ]
