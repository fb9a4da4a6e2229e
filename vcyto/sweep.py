"""`vcyto sweep`: a parameter study of the closed sorting loop, point by point, on any executor.

A spec (TOML) has four tables:

- ``[base]``: the run every point starts from, in the words of ``vcyto stream``: ``scenario`` (a scenario file,
  relative to the spec), ``set`` (a list of ``FIELD=VALUE`` overrides, as ``--set``) and any other stream or
  scenario option by its name (``cells``, ``count``, ``mix``, ``rate``, ``lead``, ``pulse``, ``model``, ``seed``,
  ``mesh_h``, ``saw_model``, ...), in the option's unit (ms for times).
- ``[parameters]``: what varies. A name is a ``[base]`` option (``lead``) or a dotted scenario field
  (``saw.streaming_force``, ``channel.inlets.1.v_hat``); its values a list, a range ``{start, stop, num}`` or
  ``{start, stop, step}`` (``log = true`` for geometric spacing), or, with random sampling, a distribution
  ``{uniform = [a, b]}``, ``{log_uniform = [a, b]}`` or ``{integers = [a, b]}``.
- ``[sweep]``: ``metrics`` (columns of the table), ``plot`` (the metric of the summary figure),
  ``sampling = "grid"`` (every combination) or ``"random"`` (``samples`` draws with ``sampling_seed``).

Every point runs with the base seed unless ``seed`` is a parameter (common random numbers: points differ by
their parameters, not by their noise), so a spec determines every result wherever it runs. A point's identity
is a hash of its effective inputs (the scenario as TOML and the stream settings): a re-run skips the points
already in the table. Points sharing a plant run in chunks on one worker, and each worker process keeps the
plants it built, so a plant (mesh, steady flows) is built once per worker and scenario, not once per point.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import csv
import dataclasses
import functools
import hashlib
import io
import itertools
import json
import logging
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.plants import MODELS

from .arguments import MAX_SWEEP_POINTS, Integer, Quantity
from .config import check_input_file, parse_quantity, scenario_to_toml
from .options import stream_run, stream_run_options
from .stream import make_plant, run_stream

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

DEFAULT_MODEL = "rom"
SAMPLINGS = ("grid", "random")
SWEEP_KEYS = ("metrics", "plot", "sampling", "samples", "sampling_seed")
RANGE_KEYS = ("start", "stop", "num", "step", "log")
DISTRIBUTIONS = ("uniform", "log_uniform", "integers")
STATISTICS = ("yield", "purity", "abort_rate", "aborts", "misclassified", "undetected", "throughput_cells_per_s",
              "cells", "purity_of_sorting", "offered", "events", "event_rate_per_s", "rejected_at_inlet", "sorted",
              "co_deflected",
              "co_deflected_unexpected", "not_injected", "yield_estimate")
RUN_FIGURES = ("simulated_time_ms", "idt_on_time_ms", "wall_time_s")
DEFAULT_METRICS = ("yield", "purity", "abort_rate", "outlets")
RESULTS, FIGURE, SUMMARY = "results.csv", "summary.png", "sweep.json"
PLANTS_PER_WORKER = 2
FAILURES_SHOWN = 5
SCHEDULER_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")
CONNECT_TIMEOUT_S = 10
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


ROW_STATUSES = ("ok", "failed", "truncated")   # truncated: the run hit a cap before its sample ended


class SweepError(ValueError):
    """A bad spec or sweep option; ``str(error)`` is one line naming what is wrong."""


# --- the spec -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Parameter:
    name: str
    values: tuple = ()                 # a list or a range
    distribution: tuple | None = None  # ("uniform" | "log_uniform" | "integers", low, high): random sampling only

    def draw(self, rng: np.random.Generator):
        if self.distribution is None:
            return self.values[int(rng.integers(len(self.values)))]
        kind, low, high = self.distribution
        if kind == "integers":
            return int(rng.integers(low, high + 1))
        if kind == "log_uniform":
            return _rounded(math.exp(rng.uniform(math.log(low), math.log(high))))
        return _rounded(rng.uniform(low, high))


@dataclass(frozen=True)
class Point:
    values: tuple                      # ((parameter name, value as given), ...)
    scenario: object                   # sim.scenario.Scenario
    settings: object                   # vcyto.stream.StreamSettings
    id: str                            # digest of the inputs and of the code (version, schema)
    inputs: str = ""                   # digest of the inputs alone (scenario TOML and settings)

    @property
    def label(self) -> str:
        return ", ".join(f"{name}={value}" for name, value in self.values)

    @property
    def plant_key(self):
        return (self.settings.model, self.settings.control_period, self.scenario)


@dataclass(frozen=True)
class Sweep:
    path: str
    parameters: tuple[Parameter, ...]
    metrics: tuple[str, ...]
    plot: str
    sampling: str
    points: tuple[Point, ...]

    @property
    def columns(self) -> list[str]:
        names = [parameter.name for parameter in self.parameters]
        metrics = [metric for metric in self.metrics if metric != "wall_time_s"]
        return ["point", "status", *names, *([] if "seed" in names else ["seed"]), *metrics, "wall_time_s", "error",
                "inputs", "vcyto"]


def load_sweep(path: str | os.PathLike) -> Sweep:
    """The sweep the spec file at ``path`` describes, every point built and checked (no plant is built)."""
    try:
        check_input_file(path, "sweep spec", field="spec")
    except ValueError as error:
        raise SweepError(str(error)) from None
    try:
        with open(path, "rb") as file:
            document = tomllib.load(file)
    except RecursionError:
        raise SweepError(f"sweep spec '{os.fspath(path)}' nests tables or arrays too deeply") from None
    except FileNotFoundError:
        raise SweepError(f"sweep spec '{os.fspath(path)}' does not exist; check the path") from None
    except OSError as error:
        raise SweepError(f"cannot read sweep spec '{os.fspath(path)}': {error.strerror}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise SweepError(f"sweep spec '{os.fspath(path)}' is not valid TOML: {_one_line(error)}") from None
    return parse_sweep(document, Path(path).parent, name=os.fspath(path))


def parse_sweep(document: dict, directory: Path = Path("."), name: str = "spec") -> Sweep:
    """The sweep of a parsed spec; ``directory`` resolves a relative ``[base] scenario`` file."""
    _known(document, ("base", "parameters", "sweep"), "", "tables")
    options = _options()
    base = _base_arguments(_table(document, "base"), options, directory)
    parameters = tuple(_parameter(key, value, options) for key, value in _flat(_table(document, "parameters")))
    if not parameters:
        raise SweepError("parameters: no parameter to vary; add one, e.g. lead = [0.25, 0.5, 0.75]")
    sweep = _table(document, "sweep")
    _known(sweep, SWEEP_KEYS, "sweep", "keys")
    sampling = sweep.get("sampling", "grid")
    if sampling not in SAMPLINGS:
        raise SweepError(f"sweep.sampling: must be one of {', '.join(SAMPLINGS)} (got {sampling!r})")
    _check_size(parameters, sampling, sweep)
    combinations = _grid(parameters) if sampling == "grid" else _random(parameters, sweep)
    points = _points(combinations, base, options)
    metrics = _metrics(sweep.get("metrics", list(DEFAULT_METRICS)), points[0].scenario)
    plot = sweep.get("plot", metrics[0])
    if plot not in metrics:
        raise SweepError(f"sweep.plot: {plot!r} is not one of the metrics ({', '.join(metrics)})")
    return Sweep(name, parameters, metrics, plot, sampling, points)


def _table(document: dict, key: str) -> dict:
    value = document.get(key, {})
    if not isinstance(value, dict):
        raise SweepError(f"{key}: must be a table [{key}]")
    return value


def _flat(table: dict, prefix: str = ""):
    """(dotted name, values) pairs: TOML reads an unquoted ``saw.streaming_force = [...]`` as nested tables."""
    for key, value in table.items():
        if isinstance(value, dict) and not any(k in value for k in RANGE_KEYS + DISTRIBUTIONS):
            yield from _flat(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _known(table: dict, allowed, where: str, kind: str):
    for key in table:
        if key not in allowed:
            raise SweepError(f"{where + '.' if where else ''}{key}: unknown; known {kind}: {', '.join(allowed)}")


def _options() -> dict[str, argparse.Action]:
    """The options of ``vcyto stream`` a sweep can set, by name (their argparse actions: types, defaults)."""
    actions = {action.dest: action for action in stream_run_options()._actions if action.dest != "help"}
    actions["set"] = actions.pop("overrides")
    return actions


def _base_arguments(table: dict, options: dict, directory: Path) -> argparse.Namespace:
    """The options of the base run: ``vcyto stream``'s defaults (model: ``DEFAULT_MODEL``), then ``[base]``."""
    arguments = stream_run_options().parse_args([])
    arguments.model = DEFAULT_MODEL
    for key, value in table.items():
        if key not in options:
            raise SweepError(f"base.{key}: unknown option; known: {', '.join(sorted(options))}")
        if key in ("scenario", "controller"):          # files beside (or below) the spec
            setattr(arguments, key, str(_beside_spec(_checked_text(value, f"base.{key}"), directory)))
        elif key == "set":
            if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
                raise SweepError('base.set: must be a list of "FIELD=VALUE" strings, e.g. ["saw.model=streaming"]')
            arguments.overrides = list(value)
        else:
            setattr(arguments, key, _option_value(options[key], value, f"base.{key}"))
    return arguments


def _beside_spec(text: str, directory: Path) -> Path:
    """The scenario file ``text`` names, relative to the spec's folder and inside it (a spec shared with you
    cannot make vcyto read files elsewhere)."""
    path = (directory / text).resolve()
    if Path(text).is_absolute() or not path.is_relative_to(directory.resolve()):
        raise SweepError(f"base.scenario: must name a file in the spec's folder or below it, relative to the spec "
                         f"(got {text!r}); copy the scenario next to the spec")
    return path


def _check_size(parameters, sampling: str, sweep: dict) -> None:
    """Refuse, before any point is built, a sweep of more than ``MAX_SWEEP_POINTS`` points, saying how many."""
    if sampling == "random":
        count = sweep.get("samples")
        count = count if isinstance(count, int) and not isinstance(count, bool) else 0
    else:
        count = math.prod(len(p.values) for p in parameters if p.distribution is None)
    if count > MAX_SWEEP_POINTS:
        per_point = 0.5 if DEFAULT_MODEL == "rom" else 30.0
        raise SweepError(f"{'sweep.samples' if sampling == 'random' else 'parameters'}: {count:,} points (at "
                         f"least ~{count * per_point / 3600:,.0f} CPU hours); a sweep has at most "
                         f"{MAX_SWEEP_POINTS:,} points: use fewer values or a random sample")


def _checked_text(value, where: str) -> str:
    if not isinstance(value, str):
        raise SweepError(f"{where}: must be a string (got {value!r})")
    return value


def _option_value(action: argparse.Action, value, where: str):
    """``value`` (TOML data) as the command-line option of ``action`` would read it."""
    if action.nargs == 0:                                      # a flag such as no_controller
        if not isinstance(value, bool):
            raise SweepError(f"{where}: must be true or false (got {value!r})")
        return value
    if isinstance(value, bool):
        raise SweepError(f"{where}: must not be true or false (got {value!r})")
    if isinstance(action.type, Integer):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if not isinstance(value, int):
            raise SweepError(f"{where}: must be an integer (got {value!r})")
        return _typed(action, value, where)
    if isinstance(action.type, Quantity):
        if not isinstance(value, (int, float, str)):
            option = action.dest.replace('_', '-')
            raise SweepError(f"{where}: must be a number in the unit of vcyto stream's --{option}"
                             f" or a text with a unit (got {value!r})")
        return _typed(action, value, where)
    text = _option_text(value)
    choices = MODELS if action.dest == "model" else action.choices
    if choices and text not in choices:
        raise SweepError(f"{where}: must be one of {', '.join(choices)} (got {value!r})")
    return text


def _typed(action: argparse.Action, value, where: str):
    """``value`` read by the option's type (``vcyto.arguments``): SI for quantities, range-checked."""
    try:
        return action.type(value)
    except argparse.ArgumentTypeError as error:
        raise SweepError(f"{where}: {error}") from None


def _option_text(value) -> str:
    """A text option as on the command line: lists joined by commas (cells, detection_window), tables as
    NAME:VALUE pairs (mix)."""
    if isinstance(value, list):
        return ",".join(str(item) for item in value)
    if isinstance(value, dict):
        return ",".join(f"{key}:{item}" for key, item in value.items())
    return repr(value) if isinstance(value, float) else str(value)


def _parameter(name: str, spec, options: dict) -> Parameter:
    where = f"parameters.{name}"
    if "." not in name and (name not in options or name in ("scenario", "set")):
        allowed = sorted(set(options) - {"scenario", "set"})
        raise SweepError(f"{where}: unknown parameter; use an option of vcyto stream ({', '.join(allowed)}) or a "
                         "dotted scenario field such as saw.streaming_force (see vcyto scenario)")
    if isinstance(spec, list):
        if not spec:
            raise SweepError(f"{where}: empty list; give at least one value")
        return Parameter(name, tuple(spec))
    if not isinstance(spec, dict):
        return Parameter(name, (spec,))
    if any(key in spec for key in DISTRIBUTIONS):
        return Parameter(name, distribution=_distribution(spec, where))
    return Parameter(name, _range(spec, where, allow_units="." in name))


def _distribution(spec: dict, where: str) -> tuple:
    if len(spec) != 1:
        raise SweepError(f"{where}: a distribution is one key ({', '.join(DISTRIBUTIONS)}) = [low, high]")
    (kind, bounds), = spec.items()
    if kind not in DISTRIBUTIONS:
        raise SweepError(f"{where}.{kind}: unknown; known distributions: {', '.join(DISTRIBUTIONS)}")
    if not (isinstance(bounds, list) and len(bounds) == 2):
        raise SweepError(f"{where}.{kind}: must be [low, high] (got {bounds!r})")
    low, high = (_number(bound, f"{where}.{kind}", allow_units=True) for bound in bounds)
    if not low <= high or (kind == "log_uniform" and low <= 0):
        raise SweepError(f"{where}.{kind}: empty range [{low:g}, {high:g}]; need low <= high"
                         + (" and low > 0" if kind == "log_uniform" else ""))
    if kind == "integers" and not (float(low).is_integer() and float(high).is_integer()):
        raise SweepError(f"{where}.integers: bounds must be integers (got {bounds!r})")
    return (kind, int(low), int(high)) if kind == "integers" else (kind, low, high)


def _range(spec: dict, where: str, allow_units: bool) -> tuple:
    """The values of ``{start, stop, num}`` (both ends included) or ``{start, stop, step}`` (stop included when
    a whole number of steps reaches it); ``log = true`` spaces them geometrically."""
    _known(spec, RANGE_KEYS, where, "range keys (or a distribution: uniform, log_uniform, integers)")
    if "start" not in spec or "stop" not in spec or ("num" in spec) == ("step" in spec):
        raise SweepError(f"{where}: a range needs start, stop and one of num or step, e.g. {{start = 0, stop = 1, "
                         "num = 5}")
    start, stop = (_number(spec[key], f"{where}.{key}", allow_units) for key in ("start", "stop"))
    log = spec.get("log", False)
    if log and (start <= 0 or stop <= 0):
        raise SweepError(f"{where}: a log range needs positive start and stop")
    if "num" in spec:
        num = spec["num"]
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise SweepError(f"{where}.num: empty range; num must be an integer >= 1 (got {num!r})")
        if num > MAX_SWEEP_POINTS:
            raise SweepError(f"{where}.num: {num:,} values; a sweep has at most {MAX_SWEEP_POINTS:,} points")
        values = np.geomspace(start, stop, num) if log else np.linspace(start, stop, num)
        return tuple(_rounded(value) for value in values)
    step = _number(spec["step"], f"{where}.step", allow_units)
    if log:
        raise SweepError(f"{where}: a log range takes num, not step")
    ratio = (stop - start) / step if step else -1.0
    if not math.isfinite(ratio) or ratio > MAX_SWEEP_POINTS:
        raise SweepError(f"{where}.step: more than {MAX_SWEEP_POINTS:,} values; a sweep has at most "
                         f"{MAX_SWEEP_POINTS:,} points")
    count = math.floor(ratio + 1e-9) + 1
    if count > MAX_SWEEP_POINTS:
        raise SweepError(f"{where}.step: {count:,} values; a sweep has at most {MAX_SWEEP_POINTS:,} points")
    if count < 1:
        raise SweepError(f"{where}: empty range: step {step:g} never goes from {start:g} to {stop:g}")
    integers = all(isinstance(spec[key], int) for key in ("start", "stop", "step"))
    return tuple(int(start + i * step) if integers else _rounded(start + i * step) for i in range(count))


def _number(value, where: str, allow_units: bool) -> float:
    if isinstance(value, str) and allow_units:
        try:
            return parse_quantity(value)
        except ValueError as error:
            raise SweepError(f"{where}: {error}") from None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SweepError(f"{where}: must be a finite number (got {value!r})")
    return value


def _rounded(value) -> float:
    """``value`` to 12 significant digits: 0.3, not 0.30000000000000004, in tables and hashes."""
    return float(f"{float(value):.12g}")


def _grid(parameters) -> list[tuple]:
    for parameter in parameters:
        if parameter.distribution is not None:
            raise SweepError(f"parameters.{parameter.name}: {parameter.distribution[0]} needs sampling = \"random\" "
                             "in [sweep]")
    names = [parameter.name for parameter in parameters]
    return [tuple(zip(names, values)) for values in itertools.product(*(p.values for p in parameters))]


def _random(parameters, sweep: dict) -> list[tuple]:
    samples, seed = sweep.get("samples"), sweep.get("sampling_seed", 0)
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise SweepError(f"sweep.samples: random sampling needs a number of samples >= 1 (got {samples!r})")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise SweepError(f"sweep.sampling_seed: must be an integer >= 0 (got {seed!r})")
    rng = np.random.default_rng(seed)
    return [tuple((p.name, p.draw(rng)) for p in parameters) for _ in range(samples)]


def _points(combinations, base: argparse.Namespace, options: dict) -> tuple[Point, ...]:
    """A checked point per distinct combination (random draws may repeat one), in spec order."""
    points = {}
    for values in combinations:
        point = _point(values, base, options)
        points.setdefault(point.id, point)
    return tuple(points.values())


def _point(values: tuple, base: argparse.Namespace, options: dict) -> Point:
    arguments = copy.copy(base)
    arguments.overrides = list(base.overrides)
    label = ", ".join(f"{name}={value}" for name, value in values)
    for name, value in values:
        if "." in name:
            arguments.overrides.append(f"{name}={_override_text(value)}")
        else:
            setattr(arguments, name, _option_value(options[name], value, f"parameters.{name}"))
    try:
        scenario, settings = stream_run(arguments)
    except ValueError as error:
        raise SweepError(f"point {label}: {_one_line(error)}") from None
    identity = json.dumps({"scenario": scenario_to_toml(scenario), "settings": repr(settings)})
    inputs = hashlib.sha256(identity.encode()).hexdigest()[:16]
    return Point(values, scenario, settings, _point_id(inputs), inputs)


def code_identity() -> str:
    """The vcyto version and a digest of the scenario and stream-settings schema (field names and types):
    part of every point's id, so results of other code are not taken for this code's."""
    from sim.scenario import Scenario

    from . import __version__
    from .stream import StreamSettings
    return f"{__version__}/{_schema_digest((Scenario, StreamSettings))}"


@functools.lru_cache(maxsize=4)
def _schema_digest(roots) -> str:
    seen, lines, todo = set(), [], list(roots)
    while todo:
        cls = todo.pop(0)
        if cls in seen or not dataclasses.is_dataclass(cls):
            continue
        seen.add(cls)
        for spec in dataclasses.fields(cls):
            lines.append(f"{cls.__name__}.{spec.name}:{spec.type}")
            default = spec.default if spec.default is not dataclasses.MISSING else None
            if spec.default_factory is not dataclasses.MISSING:
                default = spec.default_factory()
            todo += [type(item) for item in (default if isinstance(default, tuple) else (default,))]
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()[:8]


def _point_id(inputs: str) -> str:
    return hashlib.sha256(f"{inputs}/{code_identity()}".encode()).hexdigest()[:16]


def _override_text(value) -> str:
    """``value`` (TOML data) as the text after ``--set FIELD=``; strings are quoted, so "5um" keeps its unit."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, list):
        return "[" + ", ".join(_override_text(item) for item in value) + "]"
    return json.dumps(str(value))


def _metrics(names, scenario) -> tuple[str, ...]:
    if isinstance(names, str) or not isinstance(names, list) or not names:
        raise SweepError('sweep.metrics: must be a non-empty list, e.g. ["yield", "purity", "melanoma.upper"]')
    outlets = [outlet.name for outlet in scenario.channel.outlets] + ["wall", "lost"]
    types = [cell.name for cell in scenario.cell_types]
    for name in names:
        group, _, outlet = str(name).partition(".")
        known = name in STATISTICS + RUN_FIGURES + ("outlets",) or (group in ["outlet", *types] and outlet in outlets)
        if not known:
            raise SweepError(f"sweep.metrics: unknown metric {name!r}; known: {', '.join(STATISTICS + RUN_FIGURES)}, "
                             f"outlets, outlet.NAME (cells leaving by outlet NAME: {', '.join(outlets)}) and "
                             f"TYPE.NAME (the fraction of TYPE cells leaving by NAME, TYPE one of {', '.join(types)})")
    return tuple(dict.fromkeys(names))


def metric_value(result: dict, name: str):
    """The metric ``name`` of one ``run_stream`` result (None where it is undefined, e.g. purity of no sort)."""
    if name == "yield_estimate":
        return (result.get("yield_estimate") or {}).get("yield")
    if name in STATISTICS:
        return result["statistics"].get(name)
    if name in RUN_FIGURES:
        return result[name]
    outlets = result["statistics"]["outlets"]
    if name == "outlets":
        return " ".join(f"{outlet}={count}" for outlet, count in outlets.items())
    group, _, outlet = name.partition(".")
    if group == "outlet":
        return outlets.get(outlet, 0)
    cells = [cell for cell in result["cells"] if cell["type"] == group]
    return sum(cell["outlet"] == outlet for cell in cells) / len(cells) if cells else None


# --- one point, on a worker ---------------------------------------------------------------------

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
    that raises is a row with status "failed" and the error in one line; the others still run."""
    rows = []
    for scenario, settings in jobs:
        started = time.perf_counter()
        try:
            result = (simulator or simulate)(scenario, settings)
            if result.get("status", "complete") != "complete":     # a partial run is not a result
                row = {"status": "truncated", "error": _one_line(result.get("reason", ""))}
            else:
                row = {"status": "ok", "error": "", **{name: metric_value(result, name) for name in metrics}}
        except Exception as error:  # noqa: BLE001 - a failed point is data, not the end of the sweep
            if getattr(error, "status", None) == "interrupted":       # Ctrl-C inside the loop: not a result
                raise KeyboardInterrupt from error
            row = {"status": "failed", "error": _one_line(f"{type(error).__name__}: {error}")}
        row["wall_time_s"] = time.perf_counter() - started
        rows.append(row)
    return rows


# --- the results table --------------------------------------------------------------------------


class ResultTable:
    """``results.csv``: a header, then one row per finished point, appended and flushed as points finish."""

    def __init__(self, path: Path, columns: list[str]):
        self.path = path
        self.columns = columns
        self.repaired = 0

    def load(self) -> dict[str, dict]:
        """The rows already written, by point id (the last row of a point wins). A torn last line (a sweep killed
        while writing) is dropped and the file rewritten; a table with other columns is refused."""
        if not self.path.exists() or self.path.stat().st_size == 0:
            self.rewrite([])
            return {}
        text = self.path.read_text()
        lines = text.splitlines(keepends=True)
        header = next(csv.reader([lines[0]]))
        if header != self.columns:
            raise SweepError(f"{self.path} holds the results of a different sweep or of an older vcyto (columns "
                             f"{', '.join(header)}); choose another --output or remove the file")
        rows = {}
        for line in lines[1:]:
            fields = next(csv.reader([line]), [])
            if line.endswith("\n") and len(fields) == len(self.columns) and fields[1] in ROW_STATUSES:
                rows[fields[0]] = dict(zip(self.columns, fields))
            else:
                self.repaired += 1
        if self.repaired:
            self.rewrite(rows.values())
        return rows

    def append(self, rows):
        with open(self.path, "a", newline="") as file:
            writer = csv.writer(file, lineterminator="\n")
            writer.writerows([_cell(row.get(column)) for column in self.columns] for row in rows)
            file.flush()
            os.fsync(file.fileno())

    def rewrite(self, rows):
        """Replace the table by ``rows`` atomically (a temporary file renamed over it)."""
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(self.columns)
        writer.writerows([_cell(row.get(column)) for column in self.columns] for row in rows)
        temporary = self.path.with_suffix(".csv.tmp")
        temporary.write_text(buffer.getvalue())
        os.replace(temporary, self.path)


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return _one_line(str(value))


# --- running a sweep ----------------------------------------------------------------------------


def run_sweep(sweep: Sweep, output: Path, executor, slots: int = 1, progress=None, retry_failed: bool = False,
              simulator=None, chunk: int = 8, keep_old_rows: bool = False) -> dict:
    """Run the points of ``sweep`` not yet in ``output/results.csv`` on ``executor`` (``slots`` workers);
    a JSON-ready summary. Points sharing a plant go in chunks of up to ``chunk`` points, no more than an even
    share per worker. ``simulator(scenario, settings) -> run_stream result`` replaces the closed loop (tests).
    A row counts for a point when its id matches: same inputs and same code (vcyto version, schema); with
    ``keep_old_rows`` an ok row of the same inputs computed by other code counts too (the summary says how many)."""
    started = time.perf_counter()
    table = ResultTable(output / RESULTS, sweep.columns)
    previous = table.load()
    if retry_failed and any(row["status"] != "ok" for row in previous.values()):
        previous = {key: row for key, row in previous.items() if row["status"] == "ok"}
        table.rewrite(previous.values())
    rows = dict(previous)
    kept = _old_rows(sweep, previous) if keep_old_rows else {}
    rows.update(kept)
    todo = [point for point in sweep.points if point.id not in rows]
    tracker = _Tracker(len(sweep.points), len(sweep.points) - len(todo), progress)
    futures = {executor.submit(evaluate, [(p.scenario, p.settings) for p in chunk_points], sweep.metrics, simulator):
               chunk_points for chunk_points in _chunks(todo, slots, chunk)}
    try:                                 # on Ctrl-C the executor's owner (``executor``) stops the workers
        for future in as_completed(futures):
            finished = [_row(point, outcome) for point, outcome in zip(futures[future], _outcomes(future, futures))]
            table.append(finished)
            rows.update((row["point"], row) for row in finished)
            tracker.finished(finished)
    finally:
        tracker.close()
    order = {point.id: index for index, point in enumerate(sweep.points)}
    table.rewrite(sorted((row for key, row in rows.items() if key not in kept),
                         key=lambda row: order.get(row["point"], len(order))))
    summary = _summary(sweep, output, {key: row for key, row in rows.items()}, len(todo), table.repaired,
                       time.perf_counter() - started)
    summary["kept_old_rows"] = len(kept)
    summary["stale_rows"] -= len(kept)
    return summary


def _old_rows(sweep: Sweep, previous: dict) -> dict:
    """Rows of other code (another vcyto version or schema) whose inputs equal those of a point of ``sweep``
    that has no row of its own, by that point's id."""
    by_inputs = {row.get("inputs"): row for row in previous.values() if row.get("status") == "ok"}
    return {point.id: {**by_inputs[point.inputs], "point": point.id} for point in sweep.points
            if point.id not in previous and point.inputs in by_inputs}


def _chunks(points, slots: int, chunk: int) -> list[list[Point]]:
    """Points grouped by plant, in spec order, each group cut in pieces of at most ``chunk`` points and at most
    an even share of the group per worker (so a small sweep still uses every worker)."""
    groups = OrderedDict()
    for point in points:
        groups.setdefault(point.plant_key, []).append(point)
    pieces = []
    for group in groups.values():
        size = max(1, min(chunk, math.ceil(len(group) / max(1, slots))))
        pieces += [group[start:start + size] for start in range(0, len(group), size)]
    return pieces


def _outcomes(future, futures) -> list[dict]:
    try:
        return future.result()
    except Exception as error:  # noqa: BLE001 - the worker died (out of memory, killed): the chunk failed
        message = _one_line(f"the worker running this point died: {type(error).__name__}: {error}")
        return [{"status": "failed", "error": message}] * len(futures[future])


def _row(point: Point, outcome: dict) -> dict:
    from . import __version__
    return {"point": point.id, **dict(point.values), "seed": point.settings.seed, **outcome, "inputs": point.inputs,
            "vcyto": __version__}


class _Tracker:
    """The progress bar on stderr: points done of all, failures as they come, time left."""

    def __init__(self, total: int, done: int, progress):
        self.total, self.done, self.failed, self.progress = total, done, 0, progress
        self.started, self.initial = time.perf_counter(), done
        if progress and done:
            progress.note(f"{done} of {total} points already in the table; running the other {total - done}")

    def finished(self, rows):
        self.done += len(rows)
        for row in rows:
            if row["status"] != "ok":
                self.failed += 1
                if self.progress and self.failed <= FAILURES_SHOWN:
                    more = " (further failures are only counted)" if self.failed == FAILURES_SHOWN else ""
                    self.progress.note(f"point {row['point']} {row['status']}: {row['error']}{more}")
        if self.progress:
            self.progress.update(self.bar())

    def bar(self, width: int = 30) -> str:
        elapsed = time.perf_counter() - self.started
        ran = self.done - self.initial
        left = elapsed / ran * (self.total - self.done) if ran else float("nan")
        filled = int(width * self.done / max(1, self.total))
        return (f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} points, {self.failed} failed, "
                f"{elapsed:.0f} s" + (f", ~{left:.0f} s left" if math.isfinite(left) else ""))

    def close(self):
        if self.progress:
            self.progress.interval = 0.0
            self.progress.update(self.bar())
            self.progress.close()


def _summary(sweep: Sweep, output: Path, rows: dict, ran: int, repaired: int, wall: float) -> dict:
    current = [dict(rows[point.id]) for point in sweep.points if point.id in rows]
    ok = [row for row in current if row["status"] == "ok"]
    scored = [row for row in ok if math.isfinite(_float(row.get(sweep.plot)))]
    best = max(scored, key=lambda row: _float(row[sweep.plot]), default=None)
    return {"spec": sweep.path, "sampling": sweep.sampling, "parameters": [p.name for p in sweep.parameters],
            "metrics": list(sweep.metrics), "plot_metric": sweep.plot, "points": len(sweep.points),
            "ok": len(ok), "failed": sum(row["status"] == "failed" for row in current),
            "truncated": sum(row["status"] == "truncated" for row in current), "ran": ran,
            "done_before": len(sweep.points) - ran,
            "repaired_rows": repaired, "stale_rows": len(rows) - len(current), "wall_time_s": wall,
            "highest": best,
            "files": {"table": str(output / RESULTS)}, "rows": current}


def _float(value) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return float("nan")
    return number if math.isfinite(number) else float("nan")


def report_lines(result: dict) -> list[str]:
    lines = [f"{result['points']} points: {result['ok']} ok, {result['failed']} failed, "
             f"{result['truncated']} truncated (not results: raise max_time or drop it) ({result['ran']} run now, "
             f"{result['done_before']} done before) in {result['wall_time_s']:.1f} s"]
    if result["repaired_rows"]:
        lines.append(f"  {result['repaired_rows']} torn row(s) of an interrupted run dropped; those points ran again")
    if result.get("kept_old_rows"):
        lines.append(f"  {result['kept_old_rows']} row(s) computed by another vcyto version reused (--keep-old-rows)")
    if result["stale_rows"]:
        lines.append(f"  {result['stale_rows']} row(s) of the table belong to no point of this spec or were computed "
                     "by another vcyto version (kept in the table, ignored; --keep-old-rows reuses the latter)")
    best = result["highest"]
    if best:
        where = ", ".join(f"{name}={best[name]}" for name in result["parameters"])
        lines.append(f"  highest {result['plot_metric']} = {best[result['plot_metric']]} at {where}")
    for row in [row for row in result["rows"] if row["status"] != "ok"][:5]:
        lines.append(f"  {row['status']}: {', '.join(f'{n}={row[n]}' for n in result['parameters'])}: {row['error']}")
    lines += [f"  {kind}: {path}" for kind, path in result["files"].items()]
    return lines


# --- executors ----------------------------------------------------------------------------------


@contextlib.contextmanager
def executor(scheduler: str | None, workers: int):
    """A concurrent.futures executor and its number of worker slots: a local process pool (``scheduler`` None),
    a Dask ``LocalCluster`` (``"local"``) or the Dask scheduler at an address. Local worker processes run one
    thread each (OMP/MKL/OpenBLAS/numba), as Dask's nannies do: parallelism is across points."""
    with _one_thread_per_process():
        if scheduler is None:
            with _process_pool(workers) as pool:
                yield pool, workers, f"{workers} local process{'es' if workers > 1 else ''}"
        else:
            with _dask_executor(scheduler, workers) as found:
                yield found


@contextlib.contextmanager
def _one_thread_per_process():
    saved = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _ignore_interrupts():
    """Workers leave Ctrl-C to the parent, which stops them."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _interrupts_ignored():
    """Processes started within ignore Ctrl-C (an ignored signal stays ignored across exec): the parent stops them."""
    try:
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:                   # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _process_pool(workers: int):
    before = set(multiprocessing.active_children())
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_ignore_interrupts)
    try:
        yield pool
    except BaseException:
        pool.shutdown(wait=False)        # pending points fail with BrokenProcessPool once their workers are gone
        for process in set(multiprocessing.active_children()) - before:
            process.terminate()
        raise
    else:
        pool.shutdown(wait=True)


def check_scheduler(address: str) -> str:
    """``address`` if it is ``local`` or a Dask address (tcp://, tls://, ucx://, ws://, wss:// HOST:PORT)."""
    from urllib.parse import urlsplit
    if address == "local":
        return address
    parts = urlsplit(address)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme not in SCHEDULER_SCHEMES or not parts.hostname or port is None or parts.path not in ("", "/"):
        raise SweepError(f"--scheduler: {address!r} is not a Dask scheduler address; write tcp://HOST:PORT (tls:// for "
                         "an encrypted cluster) or 'local'")
    return address


def _connect(Client, scheduler: str):
    """A client of the scheduler at ``scheduler``, or an error within ``CONNECT_TIMEOUT_S``. A server that is not a
    Dask scheduler can answer with bytes that Dask reads as an absurd message length: that is a MemoryError here,
    reported as "cannot reach", not a crash."""
    import dask
    with dask.config.set({"distributed.comm.timeouts.connect": f"{CONNECT_TIMEOUT_S}s"}):
        return Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")


@contextlib.contextmanager
def _dask_executor(scheduler: str, workers: int):
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise SweepError("--scheduler needs Dask: pip install 'vcyto[cluster]' (or pip install distributed)") from None
    cluster = None
    try:
        if scheduler == "local":
            with _interrupts_ignored():
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                                       silence_logs=logging.ERROR)
            client = Client(cluster)
        else:
            client = _connect(Client, scheduler)
    except (OSError, ValueError, MemoryError, TimeoutError) as error:
        if cluster is not None:
            cluster.close()
        raise SweepError(f"--scheduler: cannot reach a Dask scheduler at {scheduler} within {CONNECT_TIMEOUT_S} s "
                         f"({type(error).__name__}: {_one_line(error)[:200]})") from None
    try:
        slots = max(1, sum(client.nthreads().values()))
        where = "a local Dask cluster" if cluster is not None else f"the Dask scheduler at {scheduler}"
        pool = client.get_executor(pure=False)
        yield pool, slots, f"{where} ({slots} worker threads)"
    except BaseException:
        if cluster is None:
            pool.shutdown(wait=False)    # cancels our points on a shared cluster; a LocalCluster just closes
        raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# --- the summary figure -------------------------------------------------------------------------


def save_plot(path: Path, sweep: Sweep, rows: list[dict]) -> None:
    """The plotted metric over the first parameter (a line) or the first two (a heat map; random sampling: a
    scatter coloured by the metric); other parameters are averaged over. Failed points are left out."""
    from .figures import pyplot
    plt = pyplot()
    values = {point.id: dict(point.values) for point in sweep.points}
    names = [parameter.name for parameter in sweep.parameters][:2]
    samples = [([_axis_value(values[row["point"]][name]) for name in names], _float(row.get(sweep.plot)))
               for row in rows if row["status"] == "ok" and row["point"] in values]
    averaged = [parameter.name for parameter in sweep.parameters[2 if len(names) == 2 else 1:]]
    figure, axis = plt.subplots(figsize=(6.4, 4.8))
    if len(names) == 1:
        _line(axis, samples, names[0], sweep.plot)
    elif sweep.sampling == "grid":
        _heat_map(figure, axis, samples, names, sweep.plot)
    else:
        _scatter(figure, axis, samples, names, sweep.plot)
    title = f"{sweep.plot} ({Path(sweep.path).stem})"
    axis.set_title(title + (f"\nmean over {', '.join(averaged)}" if averaged else ""))
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def _axis_value(value):
    """A parameter value as a number on an axis (unit strings in SI), or its text for a categorical axis."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    try:
        return parse_quantity(str(value))
    except ValueError:
        return str(value)


def _axis(values):
    """Sorted distinct values, their positions on an axis (numbers as they are, text as categories 0, 1, ...)
    and tick labels."""
    distinct = sorted(set(values), key=lambda v: (isinstance(v, str), v))
    numeric = all(isinstance(v, float) for v in distinct)
    positions = {v: (v if numeric else float(i)) for i, v in enumerate(distinct)}
    return distinct, positions, [f"{v:.4g}" if isinstance(v, float) else v for v in distinct]


def _means(samples, count: int) -> dict:
    """The mean metric per combination of the first ``count`` coordinates (NaN where every sample is NaN)."""
    table = {}
    for coordinates, metric in samples:
        table.setdefault(tuple(coordinates[:count]), []).append(metric)
    return {key: float(np.mean([m for m in v if math.isfinite(m)])) if any(map(math.isfinite, v)) else math.nan
            for key, v in table.items()}


def _line(axis, samples, name, metric):
    means = _means(samples, 1)
    distinct, positions, labels = _axis([key[0] for key in means])
    axis.plot([positions[v] for v in distinct], [means[(v,)] for v in distinct], "o-")
    if not all(isinstance(v, float) for v in distinct):
        axis.set_xticks([positions[v] for v in distinct], labels)
    axis.set_xlabel(name)
    axis.set_ylabel(metric)
    axis.grid(alpha=0.3)


def _heat_map(figure, axis, samples, names, metric):
    means = _means(samples, 2)
    xs, _, x_labels = _axis([key[0] for key in means])
    ys, _, y_labels = _axis([key[1] for key in means])
    grid = np.full((len(ys), len(xs)), np.nan)
    for (x, y), value in means.items():
        grid[ys.index(y), xs.index(x)] = value
    image = axis.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
    for (row, column), value in np.ndenumerate(grid):
        if math.isfinite(value):
            shade = image.norm(value) if image.norm.vmax > image.norm.vmin else 0.0
            axis.text(column, row, f"{value:.2g}", ha="center", va="center", fontsize=7,
                      color="black" if shade > 0.6 else "white")
    axis.set_xticks(range(len(xs)), x_labels, rotation=45)
    axis.set_yticks(range(len(ys)), y_labels)
    axis.set_xlabel(names[0])
    axis.set_ylabel(names[1])
    figure.colorbar(image, ax=axis, label=metric)


def _scatter(figure, axis, samples, names, metric):
    axes = [_axis([coordinates[i] for coordinates, _ in samples]) for i in (0, 1)]
    points = axis.scatter([axes[0][1][c[0]] for c, _ in samples], [axes[1][1][c[1]] for c, _ in samples],
                          c=[m for _, m in samples], cmap="viridis")
    for (distinct, positions, labels), ticks in zip(axes, (axis.set_xticks, axis.set_yticks)):
        if not all(isinstance(v, float) for v in distinct):
            ticks([positions[v] for v in distinct], labels)
    axis.set_xlabel(names[0])
    axis.set_ylabel(names[1])
    figure.colorbar(points, ax=axis, label=metric)


def _one_line(error) -> str:
    return " ".join(str(error).split())
