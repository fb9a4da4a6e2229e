"""`vcyto bench auto`: the same mixed Poisson stream with ``--model auto`` and with ``--model feib``: outlets
cell by cell, exit times, sort statistics and the wall time of each."""

from __future__ import annotations

import numpy as np

from sim.model.scenario import Scenario


def bench_auto(scenario: Scenario, count: int = 100, rate: float = 500.0, mix=(("RBC", 0.8), ("melanoma", 0.2)),
               seed: int = 0, progress=None) -> dict:
    """The same mixed Poisson stream with ``--model auto`` and ``--model feib``: outcomes cell by cell, and
    the wall time of each (set-up apart)."""
    from sim.model.arrivals import Arrivals

    from ..stream import StreamSettings, StreamStopped, run_stream

    arrivals = Arrivals(count=count, mix=tuple(mix), rate=rate, process="poisson")
    results = {}
    for model in ("auto", "feib"):
        if progress:
            progress.note(f"{count}-cell stream with the {model} model")
        try:
            results[model] = run_stream(scenario, StreamSettings(arrivals, model=model, seed=seed))
        except StreamStopped as error:           # reported, not hidden: the comparison cannot be made
            if error.status != "failed":
                raise
            return {"cells": count, "rate": rate, "failed": model, "error": str(error)}
    auto, feib = results["auto"], results["feib"]
    pairs = list(zip(auto["cells"], feib["cells"]))
    differ = [{"key": a["key"], "type": a["type"], "arrival_ms": f["arrival_ms"], "auto": a["outlet"],
               "feib": f["outlet"], "auto_exit_y_um": a["exit_y_um"], "feib_exit_y_um": f["exit_y_um"]}
              for a, f in pairs if a["outlet"] != f["outlet"]]
    exit_errors = [abs(a["exit_time_ms"] - f["exit_time_ms"]) for a, f in pairs
                   if a["exit_time_ms"] is not None and f["exit_time_ms"] is not None]
    run = {model: r["wall_time_s"] - r["setup_time_s"] for model, r in results.items()}
    return {"cells": count, "rate": rate, "mix": [list(m) for m in mix], "seed": seed,
            "simulated_ms": feib["simulated_time_ms"], "outlets_differ": differ,
            "exit_time_error_ms": {"max": max(exit_errors), "median": float(np.median(exit_errors))},
            "statistics": {model: r["statistics"] for model, r in results.items()},
            "wall_s": {model: r["wall_time_s"] for model, r in results.items()},
            "setup_s": {model: r["setup_time_s"] for model, r in results.items()},
            "run_s": run, "speedup_run": run["feib"] / run["auto"],
            "speedup_total": results["feib"]["wall_time_s"] / results["auto"]["wall_time_s"],
            "feib_fraction": auto.get("auto", {}).get("feib_fraction"),
            "switches": len(auto.get("auto", {}).get("switches", [])) - 1,
            "outcomes": [{"key": a["key"], "type": a["type"], "auto": a["outlet"], "feib": f["outlet"],
                          "auto_exit_ms": a["exit_time_ms"], "feib_exit_ms": f["exit_time_ms"]} for a, f in pairs]}


def _fraction(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def _exit_at(y_um) -> str:
    return f" (exit at y = {y_um:.1f} um)" if y_um is not None else ""


def auto_lines(result: dict) -> list[str]:
    if "failed" in result:
        return [f"{result['cells']}-cell stream: the {result['failed']} run stopped: {result['error']}"]
    stats = result["statistics"]
    differ = "".join(f"; cell {d['key']} ({d['type']}, arrived {d['arrival_ms']:.3f} ms): auto {d['auto']}"
                     f"{_exit_at(d['auto_exit_y_um'])}, feib {d['feib']}{_exit_at(d['feib_exit_y_um'])}"
                     for d in result["outlets_differ"])
    return [f"{result['cells']}-cell Poisson stream at {result['rate']:g}/s ({result['simulated_ms']:.1f} ms of device "
            f"time), seed {result['seed']}: auto against feib",
            f"  outlets that differ: {len(result['outlets_differ'])} of {result['cells']}{differ}",
            f"  exit time difference: median {result['exit_time_error_ms']['median'] * 1e3:.1f} us, "
            f"max {result['exit_time_error_ms']['max'] * 1e3:.1f} us",
            f"  purity / yield: auto {_fraction(stats['auto']['purity'])} / {_fraction(stats['auto']['yield'])}, "
            f"feib {_fraction(stats['feib']['purity'])} / {_fraction(stats['feib']['yield'])}",
            f"  wall: auto {result['wall_s']['auto']:.1f} s (set-up {result['setup_s']['auto']:.1f} s), feib "
            f"{result['wall_s']['feib']:.1f} s (set-up {result['setup_s']['feib']:.1f} s): "
            f"{result['speedup_run']:.1f}x "
            f"faster without set-up, {result['speedup_total']:.1f}x with",
            f"  auto ran feib for {100 * result['feib_fraction']:.1f} % of the periods ({result['switches']} switches)"]
