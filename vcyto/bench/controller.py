"""`vcyto bench controller`: the decision latency of the sorting controller (median, p99, max per call) on a
synthetic Poisson stream of detector events, per event and per control period."""

from __future__ import annotations

import time

import numpy as np


def bench_controller(events: int = 20_000, rate: float = 1000.0, control_period: float = 10e-6, seed: int = 0) -> dict:
    """Decision latency of the sorting controller on a synthetic Poisson stream of detector events.

    Each control period the controller gets the events completed in it, through the loop's end of the protocol
    (``vcyto.control``: the answer checked and applied), then the IDT drive is read; the wall time of each is one
    sample (the decision for an event, the drive for a period).
    """
    from controller.events import TYPE_I, TYPE_II, DetectorEvent
    from controller.protocol import DeviceFacts
    from controller.sorter import ControllerSettings, SortController

    from ..control import Control, InProcess

    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.exponential(1 / rate, size=events))
    settings = ControllerSettings()
    control = Control(InProcess(SortController(settings)), DeviceFacts.from_settings(settings, control_period,
                                                                                       (30e-6, 60e-6)))
    event_samples, drive_samples = [], []
    index, now = 0, 0.0
    while index < events:
        now += control_period
        while index < events and times[index] <= now:
            event = DetectorEvent(index, float(times[index]), float(rng.lognormal()), 50.0, 0.095 * rng.uniform(0.9,
                                                                                                                1.1),
                                  TYPE_II if rng.random() < 0.3 else TYPE_I, index)
            started = time.perf_counter()
            control.deliver((event,), now)
            event_samples.append(time.perf_counter() - started)
            index += 1
        started = time.perf_counter()
        control.actuation(now)
        drive_samples.append(time.perf_counter() - started)

    def summary(samples):
        micro = np.array(samples) * 1e6
        return {"median_us": float(np.median(micro)), "p99_us": float(np.percentile(micro, 99)),
                "max_us": float(micro.max()), "samples": len(micro)}

    return {"events": events, "rate_per_s": rate, "control_period_us": control_period * 1e6,
            "decision": summary(event_samples), "actuation": summary(drive_samples)}


def controller_lines(result: dict) -> list[str]:
    lines = [f"controller latency: {result['events']:,} Poisson events at {result['rate_per_s']:g}/s, control period "
             f"{result['control_period_us']:g} us"]
    for key in ("decision", "actuation"):
        row = result[key]
        lines.append(f"  {key:<10} median {row['median_us']:6.2f} us, p99 {row['p99_us']:6.2f} us, "
                     f"max {row['max_us']:7.1f} us ({row['samples']:,} calls; target p99 <= 50 us)")
    return lines
