"""Reading a sweep spec (TOML): its tables checked key by key, the parameters' lists, ranges and distributions,
and the points of a grid or a random sample (``vcyto.sweep.points`` turns each into a run)."""

from __future__ import annotations

import itertools
import math
import os
from pathlib import Path

import numpy as np

from sim.model.scenario import ScenarioError

from .. import units
from ..arguments import MAX_SWEEP_POINTS, Quantity
from ..config import field_dimension, read_toml
from .metrics import DEFAULT_METRICS, check_metrics
from .model import Parameter, Sweep, SweepError, rounded
from .points import DEFAULT_MODEL, base_arguments, beside_spec, make_points, option_actions

SAMPLINGS = ("grid", "random")
SWEEP_KEYS = ("metrics", "plot", "sampling", "samples", "sampling_seed")
RANGE_KEYS = ("start", "stop", "num", "step", "log")
DISTRIBUTIONS = ("uniform", "log_uniform", "integers")


def load_sweep(path: str | os.PathLike, controller_wire=None) -> Sweep:
    """The sweep the spec file at ``path`` describes, every point built and checked (no plant is built);
    ``controller_wire``: every point's controller in another process (``vcyto.wire.WireController``; given on
    the command line, never by a spec, which could otherwise make vcyto run a program)."""
    try:
        document = read_toml(path, "sweep spec", field="spec")
    except ScenarioError as error:
        raise SweepError(str(error)) from None
    return parse_sweep(document, Path(path).parent, name=os.fspath(path), controller_wire=controller_wire)


def parse_sweep(document: dict, directory: Path = Path("."), name: str = "spec", controller_wire=None) -> Sweep:
    """The sweep of a parsed spec; ``directory`` resolves a relative ``[base] scenario`` file."""
    check_known(document, ("base", "parameters", "sweep"), "", "tables")
    options = option_actions()
    base = base_arguments(_table(document, "base"), options, directory)
    base.controller_wire = controller_wire
    parameters = tuple(_parameter(key, value, options, directory)
                       for key, value in _flat(_table(document, "parameters")))
    if not parameters:
        raise SweepError("parameters: no parameter to vary; add one, e.g. lead = [0.25, 0.5, 0.75]")
    sweep = _table(document, "sweep")
    check_known(sweep, SWEEP_KEYS, "sweep", "keys")
    sampling = sweep.get("sampling", "grid")
    if sampling not in SAMPLINGS:
        raise SweepError(f"sweep.sampling: must be one of {', '.join(SAMPLINGS)} (got {sampling!r})")
    _check_size(parameters, sampling, sweep)
    combinations = _grid(parameters) if sampling == "grid" else _random(parameters, sweep)
    points = make_points(combinations, base, options)
    metrics = check_metrics(sweep.get("metrics", list(DEFAULT_METRICS)), points[0].scenario)
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


def check_known(table: dict, allowed, where: str, kind: str):
    for key in table:
        if key not in allowed:
            raise SweepError(f"{where + '.' if where else ''}{key}: unknown; known {kind}: {', '.join(allowed)}")


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


def _parameter(name: str, spec, options: dict, directory: Path = Path(".")) -> Parameter:
    where = f"parameters.{name}"
    if "." not in name and (name not in options or name in ("scenario", "set")):
        allowed = sorted(set(options) - {"scenario", "set"})
        raise SweepError(f"{where}: unknown parameter; use an option of vcyto stream ({', '.join(allowed)}) or a "
                         "dotted scenario field such as saw.streaming_force (see vcyto scenario)")
    quantity = _quantity(name, options)
    if isinstance(spec, list):
        if not spec:
            raise SweepError(f"{where}: empty list; give at least one value")
        if name == "controller":                  # files beside (or below) the spec, as [base]'s
            spec = [str(beside_spec(value, directory, where)) for value in spec]
        return Parameter(name, tuple(spec), quantity=quantity)
    if not isinstance(spec, dict):
        return Parameter(name, (str(beside_spec(spec, directory, where)) if name == "controller" else spec,),
                         quantity=quantity)
    if any(key in spec for key in DISTRIBUTIONS):
        return Parameter(name, distribution=_distribution(spec, where, quantity), quantity=quantity)
    return Parameter(name, _range(spec, where, quantity), quantity=quantity)


def _quantity(name: str, options: dict) -> tuple[str, str] | None:
    """(dimension, unit of a bare number) of the parameter ``name``: its option's (``--lead``: time in ms) or its
    scenario field's (SI); None for a parameter that is no quantity (a count, a seed, a name)."""
    action = options.get(name)
    if action is not None:
        return (action.type.dimension, action.type.unit) if isinstance(action.type, Quantity) else None
    dimension = field_dimension(name)
    return (dimension, "") if dimension is not None else None


def _distribution(spec: dict, where: str, quantity) -> tuple:
    if len(spec) != 1:
        raise SweepError(f"{where}: a distribution is one key ({', '.join(DISTRIBUTIONS)}) = [low, high]")
    (kind, bounds), = spec.items()
    if kind not in DISTRIBUTIONS:
        raise SweepError(f"{where}.{kind}: unknown; known distributions: {', '.join(DISTRIBUTIONS)}")
    if not (isinstance(bounds, list) and len(bounds) == 2):
        raise SweepError(f"{where}.{kind}: must be [low, high] (got {bounds!r})")
    low, high = (_number(bound, f"{where}.{kind}", quantity) for bound in bounds)
    if not low <= high or (kind == "log_uniform" and low <= 0):
        raise SweepError(f"{where}.{kind}: empty range [{low:g}, {high:g}]; need low <= high"
                         + (" and low > 0" if kind == "log_uniform" else ""))
    if kind == "integers" and not (float(low).is_integer() and float(high).is_integer()):
        raise SweepError(f"{where}.integers: bounds must be integers (got {bounds!r})")
    return (kind, int(low), int(high)) if kind == "integers" else (kind, low, high)


def _range(spec: dict, where: str, quantity) -> tuple:
    """The values of ``{start, stop, num}`` (both ends included) or ``{start, stop, step}`` (stop included when
    a whole number of steps reaches it); ``log = true`` spaces them geometrically."""
    check_known(spec, RANGE_KEYS, where, "range keys (or a distribution: uniform, log_uniform, integers)")
    if "start" not in spec or "stop" not in spec or ("num" in spec) == ("step" in spec):
        raise SweepError(f"{where}: a range needs start, stop and one of num or step, e.g. {{start = 0, stop = 1, "
                         "num = 5}")
    start, stop = (_number(spec[key], f"{where}.{key}", quantity) for key in ("start", "stop"))
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
        return tuple(rounded(value) for value in values)
    step = _number(spec["step"], f"{where}.step", quantity)
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
    return tuple(int(start + i * step) if integers else rounded(start + i * step) for i in range(count))


def _number(value, where: str, quantity) -> float:
    """An end of a range or distribution: for a ``quantity`` (dimension, unit of a bare number) read by the unit
    rule and given in that unit (``"0.2ms"`` of ``lead``, whose bare numbers are ms: 0.2), else a plain number."""
    if quantity is not None and not isinstance(value, bool) and isinstance(value, (int, float, str)):
        dimension, unit = quantity
        try:
            si = units.parse_quantity(value, dimension, unit, field=where)
        except units.QuantityError as error:
            raise SweepError(str(error)) from None
        if isinstance(value, (int, float)):
            return value                        # as written: bare numbers are in the parameter's own unit
        return rounded(si / units.unit_factor(unit, dimension)) if unit else si
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SweepError(f"{where}: must be a finite number (got {value!r})")
    return value


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
