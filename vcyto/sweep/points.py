"""A sweep's points as runs: the options of ``vcyto stream`` a spec can set (their types and defaults, from
``vcyto.options``), TOML values read as those options read text, each point's scenario and stream settings, and
its id (a digest of its inputs and of the code)."""

from __future__ import annotations

import argparse
import copy
import dataclasses
import functools
import hashlib
import json
from pathlib import Path

from sim.plants.registry import MODELS

from ..arguments import Integer, Quantity
from ..config import scenario_to_toml
from ..options import stream_run, stream_run_options
from .model import Point, SweepError, one_line

DEFAULT_MODEL = "rom"
WIRE_OPTIONS = ("controller_connect", "controller_exec", "controller_timeout")


def option_actions() -> dict[str, argparse.Action]:
    """The options of ``vcyto stream`` a sweep can set, by name (their argparse actions: types, defaults)."""
    actions = {action.dest: action for action in stream_run_options()._actions if action.dest != "help"}
    actions["set"] = actions.pop("overrides")
    return actions


def base_arguments(table: dict, options: dict, directory: Path) -> argparse.Namespace:
    """The options of the base run: ``vcyto stream``'s defaults (model: ``DEFAULT_MODEL``), then ``[base]``."""
    arguments = stream_run_options().parse_args([])
    arguments.model = DEFAULT_MODEL
    for key, value in table.items():
        if key in WIRE_OPTIONS:
            raise SweepError(f"base.{key}: a controller in another process is given on the command line, not in "
                             f"a spec: vcyto sweep SPEC --{key.replace('_', '-')} ...")
        if key not in options:
            raise SweepError(f"base.{key}: unknown option; known: {', '.join(sorted(options))}")
        if key in ("scenario", "controller"):          # files beside (or below) the spec
            setattr(arguments, key, str(beside_spec(value, directory, f"base.{key}")))
        elif key in ("controller_from", "plant_from"):   # FILE.py:NAME, the file beside (or below) the spec
            where, _, name = _checked_text(value, f"base.{key}").rpartition(":")
            setattr(arguments, key, f"{beside_spec(where, directory, f'base.{key}')}:{name}" if where.endswith(".py")
                    else value)
        elif key == "set":
            if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
                raise SweepError('base.set: must be a list of "FIELD=VALUE" strings, e.g. ["saw.model=streaming"]')
            arguments.overrides = list(value)
        else:
            setattr(arguments, key, _option_value(options[key], value, f"base.{key}"))
    return arguments


def beside_spec(text, directory: Path, where: str) -> Path:
    """The file ``text`` names (a scenario or controller file at ``where`` in the spec), relative to the spec's
    folder and inside it, symbolic links resolved (a spec shared with you cannot make vcyto read files elsewhere)."""
    text = _checked_text(text, where)
    try:
        path = (directory / text).resolve()
    except (OSError, RuntimeError, ValueError):      # a loop of links, a NUL
        path = None
    if path is None or Path(text).is_absolute() or not path.is_relative_to(directory.resolve()):
        raise SweepError(f"{where}: must name a file in the spec's folder or below it, relative to the spec "
                         f"(got {text!r}); copy the file next to the spec")
    return path


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
        return action.type(value, where) if isinstance(action.type, Quantity) else action.type(value)
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


def make_points(combinations, base: argparse.Namespace, options: dict) -> tuple[Point, ...]:
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
        raise SweepError(f"parameters: the point {label or '(the base run)'}: {one_line(error)}") from None
    identity = json.dumps({"scenario": scenario_to_toml(scenario), "settings": repr(settings),
                           "code": [_file_digest(spec) for spec in (settings.controller_from, settings.plant_from)]})
    inputs = hashlib.sha256(identity.encode()).hexdigest()[:16]
    return Point(values, scenario, settings, _point_id(inputs), inputs)


def _file_digest(spec: str | None) -> str | None:
    """The SHA-256 of the file of a ``FILE.py:NAME`` (a point's id changes with the user's code), else None."""
    where = spec.rpartition(":")[0] if spec else ""
    if not where.endswith(".py"):
        return None
    try:
        return hashlib.sha256(Path(where).read_bytes()).hexdigest()
    except OSError as error:
        raise SweepError(f"{where}: cannot read it: {error.strerror}") from None


def code_identity() -> str:
    """The vcyto version and a digest of the scenario and stream-settings schema (field names and types):
    part of every point's id, so results of other code are not taken for this code's."""
    from sim.model.scenario import Scenario

    from .. import __version__
    from ..stream import StreamSettings
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
