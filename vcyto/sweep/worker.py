"""One chunk of points on a worker: each worker thread keeps the plants it built (mesh, steady flows), so a plant
is built once per worker and scenario, not once per point; a point that fails is a row, not the sweep's end."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

from sim.fast import speed

from ..speedsettings import from_environment
from ..stream import make_plant, run_stream
from .metrics import metric_value
from .model import one_line

PLANTS_PER_WORKER = 2


_worker = threading.local()


def worker_plant(scenario, settings):
    """This worker thread's plant for (model, control period, scenario): built on first use, the last
    ``PLANTS_PER_WORKER`` kept. A plant is stateful, so each thread has its own. A plant that failed to build
    fails the next points of its scenario at once (with the same error) instead of being built again."""
    plants = getattr(_worker, "plants", None)
    if plants is None:
        plants = _worker.plants = OrderedDict()
    key = (settings.model, settings.control_period, scenario)
    plant = plants.pop(key, None)
    if plant is None:
        try:
            plant = make_plant(scenario, settings)
        except Exception as error:  # noqa: BLE001 - remembered, raised again for each point
            plant = error
    plants[key] = plant
    while len(plants) > PLANTS_PER_WORKER:
        plants.popitem(last=False)
    if isinstance(plant, Exception):
        raise plant
    return plant


def simulate(scenario, settings) -> dict:
    """One point: the closed loop on this worker's plant for the scenario."""
    return run_stream(scenario, settings, plant=worker_plant(scenario, settings))


def evaluate(jobs, metrics, simulator=None) -> list[dict]:
    """Run the points ``jobs`` ((scenario, settings), ...) one after the other; a row of metrics each. A point
    that raises is a row with status "failed" and the error in one line; the others still run. The simulator's
    speed settings are this worker's environment's (``vcyto.sweep.executors``: no prefetch helper thread)."""
    with speed.using(from_environment()):
        return [_evaluate_one(scenario, settings, metrics, simulator) for scenario, settings in jobs]


def _evaluate_one(scenario, settings, metrics, simulator) -> dict:
    started = time.perf_counter()
    try:
        result = (simulator or simulate)(scenario, settings)
        if result.get("status", "complete") != "complete":     # a partial run is not a result
            row = {"status": "truncated", "error": one_line(result.get("reason", ""))}
        else:
            row = {"status": "ok", "error": "", **{name: metric_value(result, name) for name in metrics}}
    except Exception as error:  # noqa: BLE001 - a failed point is data, not the end of the sweep
        if getattr(error, "status", None) == "interrupted":       # Ctrl-C inside the loop: not a result
            raise KeyboardInterrupt from error
        row = {"status": "failed", "error": one_line(f"{type(error).__name__}: {error}")}
    row["wall_time_s"] = time.perf_counter() - started
    return row
