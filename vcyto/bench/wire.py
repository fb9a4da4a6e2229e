"""`vcyto bench wire`: the closed loop with its controller in another process (``vcyto.wire``), on ``rom``.

Lock-step: the same Poisson stream with the built-in controller in process and served over the wire by a local
Python process (``python -m vcyto.wire.serve``, a Unix socket); the real-time factor of each (device time over
loop wall, no recording; median over repeats) and their ratio. Paced real time: ``--realtime`` at 1x for
``realtime_duration`` of device time with the same client: missed decisions, the controller's latency, and the
plant's lag behind the wall clock. The machine's load (``os.getloadavg``) is reported beside the figures.
"""

from __future__ import annotations

import os
import shlex
import statistics
import sys
import time

from sim.model.scenario import Scenario

LOCKSTEP_TARGET = 5.0          # real-time factor over the wire, lock-step
LAG_TARGET_MS = 1.0            # the plant's lag behind the wall clock, p99, paced real time


def served_command() -> str:
    """The local Python client: the built-in controller served by ``vcyto.wire.serve``, one run."""
    return shlex.join([sys.executable, "-m", "vcyto.wire.serve", "--once", "--spin", "0.005"])


def bench_wire(scenario: Scenario, rate: float = 1000.0, duration: float = 1.0, realtime_duration: float = 100.0,
               mix=(("RBC", 0.7), ("melanoma", 0.3)), min_spacing: float = 0.1e-3, repeats: int = 3, seed: int = 0,
               timeout: float = 10.0, client: str | None = None, progress=lambda message: None) -> dict:
    """Lock-step runs of ``duration`` (in process, then over the wire, ``repeats`` times each) and one paced
    real-time run of ``realtime_duration`` at 1x over the wire; ``client``: the controller's command (started
    by ``vcyto.wire.launch``; default the built-in controller served by ``vcyto.wire.serve``)."""
    from sim.model.arrivals import Arrivals

    from .. import wire
    from ..control import Timing
    from ..stream import StreamSettings, make_plant, run_stream

    def settings(length):
        arrivals = Arrivals(count=max(1, round(rate * length)), mix=tuple(mix), rate=rate, process="poisson",
                            min_spacing=min_spacing)
        return StreamSettings(arrivals, model="rom", seed=seed, max_time=2 * length + 20e-3)

    def run(length, timing=Timing(), over_wire=True):
        port = wire.launch(client, timeout, timing) if over_wire else None
        try:
            result = run_stream(scenario, settings(length), plant=plant, controller=port, timing=timing)
        finally:
            if port is not None:
                port.close()
        loop = result["wall_time_s"] - result["setup_time_s"]
        return result, {"loop_wall_s": loop, "device_time_s": result["simulated_time_ms"] * 1e-3,
                        "real_time_factor": result["simulated_time_ms"] * 1e-3 / loop,
                        "latency_ms": result["control"]["latency_ms"]}

    client = client or served_command()
    progress("set-up: the rom plant")
    plant = make_plant(scenario, settings(duration))
    load_before = os.getloadavg()
    in_process, over_wire = [], []
    for repeat in range(repeats):
        progress(f"lock-step run {repeat + 1} of {repeats}: in process, then over the wire")
        reference, figures = run(duration, over_wire=False)
        in_process.append(figures)
        result, figures = run(duration)
        over_wire.append(figures)
        same = [(c["decision"], c["outlet"]) for c in result["cells"]] == \
            [(c["decision"], c["outlet"]) for c in reference["cells"]]
        figures["same_outcomes_as_in_process"] = same
    progress(f"paced real time: {realtime_duration:g} s of device time at 1x over the wire")
    started = time.perf_counter()
    result, paced = run(realtime_duration, Timing(realtime=True))
    paced["wall_s"] = time.perf_counter() - started
    control = result["control"]
    factor_wire = statistics.median(r["real_time_factor"] for r in over_wire)
    factor_local = statistics.median(r["real_time_factor"] for r in in_process)
    return {
        "model": "rom", "rate_per_s": rate, "mix": [list(pair) for pair in mix], "min_spacing_ms": min_spacing * 1e3,
        "seed": seed, "client": client, "client_name": result["controller_name"],
        "transport": "unix socket in lock-step, TCP loopback in paced real time",
        "load_average": {"before": list(load_before), "after": list(os.getloadavg())}, "cpus": os.cpu_count(),
        "lockstep": {"duration_s": duration, "events": result_events(over_wire), "in_process": in_process,
                     "over_wire": over_wire, "real_time_factor": factor_wire,
                     "real_time_factor_in_process": factor_local, "slowdown": factor_local / factor_wire,
                     "same_outcomes": all(r["same_outcomes_as_in_process"] for r in over_wire),
                     "target": LOCKSTEP_TARGET, "met": factor_wire >= LOCKSTEP_TARGET},
        "realtime": {"device_time_s": paced["device_time_s"], "wall_s": paced["wall_s"],
                     "events": result["statistics"]["events"], "missed_decisions": control["missed_decisions"],
                     "latency_ms": control["latency_ms"], "lag_ms": control["lag_ms"],
                     "deadline_budget_ms": control["deadline_budget_ms"], "status": result["status"],
                     "lag_target_ms": LAG_TARGET_MS,
                     "met": control["missed_decisions"] == 0 and control["lag_ms"].get("p99", 0.0) <= LAG_TARGET_MS},
    }


def result_events(runs) -> int:
    return runs[-1]["latency_ms"].get("count", 0)


def wire_lines(result: dict) -> list[str]:
    lock, paced = result["lockstep"], result["realtime"]
    load = result["load_average"]
    latency, lag = paced["latency_ms"], paced["lag_ms"]

    def met(flag):
        return "met" if flag else "NOT met"
    return [
        f"wire: rom, Poisson {result['rate_per_s']:g}/s, {', '.join(f'{n}:{w:g}' for n, w in result['mix'])}, "
        f"--min-spacing {result['min_spacing_ms']:g} ms; client: {result['client_name']} in a local process "
        f"({result['transport']}); load average {load['before'][0]:.1f} before, {load['after'][0]:.1f} after "
        f"({result['cpus']} CPUs)",
        f"  lock-step, no recording: real-time factor {lock['real_time_factor']:.1f} over the wire (runs: "
        + ", ".join(f"{r['real_time_factor']:.1f}" for r in lock["over_wire"])
        + f"), {lock['real_time_factor_in_process']:.1f} in process ({lock['slowdown']:.1f}x slower over the wire); "
        f"same outcomes: {'yes' if lock['same_outcomes'] else 'NO'}; target >= {lock['target']:g}: {met(lock['met'])}",
        f"  paced real time x1: {paced['device_time_s']:.1f} s of device time in {paced['wall_s']:.1f} s wall, "
        f"{paced['events']} events, {paced['missed_decisions']} missed decisions (deadline "
        f"{paced['deadline_budget_ms']:.3f} ms); latency p50 {latency.get('p50', 0) * 1e3:.0f} us, p99 "
        f"{latency.get('p99', 0) * 1e3:.0f} us, max {latency.get('max', 0) * 1e3:.0f} us; the plant behind the wall "
        f"clock p50 {lag.get('p50', 0):.3f} ms, p99 {lag.get('p99', 0):.3f} ms, max {lag.get('max', 0):.3f} ms; "
        f"target 0 missed and lag p99 <= {paced['lag_target_ms']:g} ms: {met(paced['met'])}",
    ]
