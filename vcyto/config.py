"""Scenario files and command-line overrides turned into a validated ``Scenario``.

A scenario file is TOML whose tables mirror the dataclasses of ``sim.model.scenario``: [channel],
[[channel.inlets]], [[channel.outlets]], [channel.saw_window], [fluid], [saw], [numerics]. Omitted keys
keep their defaults; a [[channel.inlets]] or [[channel.outlets]] array replaces the default list.
An override is ``dotted.path=value`` (``numerics.dt=25us``, ``channel.inlets.1.v_hat=0.02``,
``channel.inlets.0.span=[30um, 80um]``); tuple entries are chosen by 0-based index.

Numbers are SI unless written as a string with a unit of the field's dimension ("3.33 um", "2.5 us",
"30 deg"; ``vcyto.units``, the one unit rule). Files are read with their size and depth bounded (``read_toml``).
Every problem is a ``ScenarioError`` whose one-line message names the full dotted field,
e.g. ``channel.inlets[0].span: ...``.

The sections are built generically from ``dataclasses.fields`` and their type hints, so a field added
to a scenario dataclass is read, overridden and written without changes here. Writing a scenario back to
TOML (``scenario_to_toml``) lives in ``vcyto.scenariotoml`` and is re-exported here.
"""

from __future__ import annotations

import dataclasses
import numbers
import os
import re
import stat
import sys
import types
import typing
from collections.abc import Sequence

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

from sim.model.scenario import Scenario, ScenarioError, as_dict

from . import units
from .scenariotoml import _init_fields, _join, scenario_to_toml  # noqa: F401 (scenario_to_toml: re-exported)

# the dimension of every float field of the scenario dataclasses ("Class.field"); a bare number is SI
FIELD_DIMENSIONS = {
    "Channel.length": "length", "Channel.height": "length",
    "Inlet.span": "length", "Inlet.v_hat": "speed", "Inlet.tilt": "angle", "Inlet.cutoff": "length",
    "Outlet.span": "length", "SawWindow.span": "length", "SawWindow.cutoff": "length",
    "Fluid.density": "density", "Fluid.viscosity": "viscosity",
    "Saw.amplitude": "length", "Saw.frequency": "frequency", "Saw.streaming_force": "force density",
    "Saw.attenuation_length": "length", "Saw.spin_up_time": "time",
    "Numerics.mesh_h": "length", "Numerics.dt": "time", "Numerics.nonlinear_tolerance": "dimensionless",
    "Numerics.tolerance": "length",
    "Numerics.membrane_spacing": "dimensionless", "Numerics.max_area_change": "dimensionless",
    "Numerics.spacing_band": "dimensionless", "Numerics.max_stretch": "dimensionless",
    "CellType.kappa_e": "tension", "CellType.kappa_b": "bending modulus", "CellType.semi_axes": "length",
    "CellType.fluorescence": "dimensionless",
    # controller files (vcyto.controllerfile): times carry their unit
    "ControllerSettings.delay": "time", "ControllerSettings.reference_velocity": "speed",
    "ControllerSettings.lead": "time", "ControllerSettings.pulse": "time", "ControllerSettings.envelope": "time",
    "ControllerSettings.timing_error": "time",
}
MAX_FILE_BYTES = 1_000_000          # a scenario, sweep spec or controller file larger than this is refused unread
MAX_DEPTH = 16                      # tables and arrays nested deeper than this (the scenario's deepest: 4) are refused
_INDEX = re.compile(r"\d+", re.ASCII)
_OVERRIDE_FORM = "an override must have the form dotted.path=value, e.g. numerics.dt=25us"


# --- public interface -------------------------------------------------------------------------


def load_scenario(path: str | os.PathLike | None = None, overrides: Sequence[str] = (),
                  field: str = "path") -> Scenario:
    """The scenario the TOML file at ``path`` describes (the defaults without one), with ``overrides`` applied.

    Raises ``ScenarioError`` naming the full dotted field for every problem in the file or overrides, and
    ``field`` (the command line's ``--scenario``) for a file that cannot be read as TOML.
    """
    if isinstance(overrides, str):
        raise TypeError("overrides must be a sequence of 'dotted.path=value' strings, not one string")
    tree = as_dict(Scenario())
    if path is not None:
        _merge(tree, _read_document(path, field))
    for override in overrides:
        try:
            _apply_override(tree, override)
        except RecursionError:
            raise ScenarioError(override.partition("=")[0].strip() or "override", "nested too deeply") from None
    return _build(Scenario, _inherit_sort_class(tree), "")


def scenario_from_toml(text: str, field: str = "scenario") -> Scenario:
    """The scenario a TOML document describes (as written by ``scenario_to_toml``, e.g. into recordings); its size
    and depth are bounded as a scenario file's are."""
    tree = as_dict(Scenario())
    _merge(tree, parse_toml(text, "stored scenario", field))
    return _build(Scenario, _inherit_sort_class(tree), "")


def _inherit_sort_class(tree: dict) -> dict:
    """A ``[[cell_types]]`` entry named like a built-in type and without ``target`` takes the built-in type's sort
    class: files written before ``target`` existed keep sorting the melanoma."""
    builtin = {cell.name: cell.target for cell in Scenario().cell_types}
    types = tree.get("cell_types")
    if isinstance(types, list):
        for entry in types:
            if isinstance(entry, dict) and "target" not in entry and entry.get("name") in builtin:
                entry["target"] = builtin[entry["name"]]
    return tree


def field_dimension(dotted: str) -> str | None:
    """The dimension (of ``units.DIMENSIONS``) of the float scenario field ``dotted`` names
    ("saw.streaming_force", "channel.inlets.1.v_hat"), or None if it names no float field."""
    hint, owner, name = Scenario, None, None
    for segment in re.sub(r"\[(\d+)\]", r".\1", dotted).split("."):
        if _is_dataclass_type(hint) and segment in _init_fields(hint):
            owner, name, hint = hint, segment, typing.get_type_hints(hint)[segment]
        elif typing.get_origin(hint) in (tuple, list) and _INDEX.fullmatch(segment):
            items = _item_hints(hint, int(segment) + 1)
            hint = items[int(segment)] if int(segment) < len(items) else None
        else:
            return None
    return FIELD_DIMENSIONS.get(f"{owner.__name__}.{name}") if owner is not None else None


# --- reading the file ---------------------------------------------------------------------------


def check_input_file(path: str | os.PathLike, what: str, field: str = "path", limit: int = MAX_FILE_BYTES) -> None:
    """Refuse, before it is read, an input file that is missing, not a regular file or larger than ``limit``."""
    name = os.fspath(path)
    try:
        status = os.stat(name)
    except FileNotFoundError:
        raise ScenarioError(field, f"{what} '{name}' does not exist; check the path") from None
    except (OSError, ValueError) as error:
        reason = getattr(error, "strerror", None) or error
        raise ScenarioError(field, f"cannot read {what} '{name}': {reason}") from None
    if not stat.S_ISREG(status.st_mode):
        raise ScenarioError(field, f"{what} '{name}' is not a regular file (a directory or a device); give a TOML file")
    if status.st_size > limit:
        raise ScenarioError(field, f"{what} '{name}' is {status.st_size:,} bytes; a {what} is at most {limit:,} bytes")


def _read_document(path: str | os.PathLike, field: str = "path") -> dict:
    """The parsed contents of the TOML scenario file at ``path``."""
    return read_toml(path, "scenario file", field)


def read_toml(path: str | os.PathLike, what: str, field: str = "path", limit: int = MAX_FILE_BYTES) -> dict:
    """The TOML document in the file at ``path`` (a ``what``: "scenario file", "sweep spec", ...), its size
    (``limit`` bytes) checked before it is read and its depth (``MAX_DEPTH``) before it is used; every problem a
    ``ScenarioError`` naming ``field`` and the file."""
    name = os.fspath(path)
    check_input_file(path, what, field, limit)
    try:
        with open(path, "rb") as file:
            data = file.read(limit + 1)          # the file may have grown since it was checked
    except FileNotFoundError:
        raise ScenarioError(field, f"{what} '{name}' does not exist; check the path") from None
    except OSError as error:
        raise ScenarioError(field, f"cannot read {what} '{name}': {error.strerror}") from None
    if len(data) > limit:
        raise ScenarioError(field, f"{what} '{name}' is larger than {limit:,} bytes; a {what} is at most that")
    try:
        text = data.decode()
    except UnicodeDecodeError as error:
        raise ScenarioError(field, f"{what} '{name}' is not UTF-8 text: {_one_line(error)}") from None
    return parse_toml(text, f"{what} '{name}'", field, limit)


def parse_toml(text: str, what: str, field: str = "scenario", limit: int = MAX_FILE_BYTES) -> dict:
    """The TOML document ``text`` (a ``what``, named in errors), refused unparsed when longer than ``limit``
    characters and once parsed when nested deeper than ``MAX_DEPTH``: ``ScenarioError`` naming ``field``."""
    if not isinstance(text, str):
        raise ScenarioError(field, f"the {what} is not TOML text (got {type(text).__name__})")
    if len(text) > limit:
        raise ScenarioError(field, f"the {what} is {len(text):,} characters; at most {limit:,} are read")
    try:
        document = tomllib.loads(text)
    except RecursionError:
        raise ScenarioError(field, f"{what} nests tables or arrays too deeply (at most {MAX_DEPTH} levels)") from None
    except ValueError as error:                 # TOMLDecodeError, or an integer of thousands of digits
        raise ScenarioError(field, f"{what} is not valid TOML: {_one_line(error)[:200]}") from None
    if nesting_depth(document) > MAX_DEPTH:
        raise ScenarioError(field, f"{what} nests tables or arrays too deeply (at most {MAX_DEPTH} levels)")
    return document


def nesting_depth(value, stop: int = MAX_DEPTH + 1) -> int:
    """How deeply tables (dicts) and arrays (lists, tuples) nest in ``value`` (a scalar: 0), counted without
    recursion and only up to ``stop``."""
    deepest, level = 0, [(value, 0)]
    while level:
        node, depth = level.pop()
        if isinstance(node, (dict, list, tuple)):
            deepest = max(deepest, depth + 1)
            if deepest >= stop:
                return deepest
            level.extend((item, depth + 1) for item in (node.values() if isinstance(node, dict) else node))
    return deepest


def _merge(base: dict, update: dict) -> None:
    """Merge ``update`` into ``base`` in place: tables merge key by key, anything else (arrays too) replaces."""
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = value


# --- overrides ----------------------------------------------------------------------------------


def _apply_override(tree: dict, override: str) -> None:
    """Set, in the plain-data scenario ``tree``, the field that ``override`` ("dotted.path=value") names."""
    segments, value = _split_override(override)
    node, hint, where = tree, Scenario, ""
    for position, segment in enumerate(segments):
        key, hint, where = _resolve(node, hint, segment, where)
        if position == len(segments) - 1:
            node[key] = value
        elif isinstance(node, dict) and key not in node:
            raise ScenarioError(where, f"is not given, so it cannot be changed in part; set {where} as a whole")
        else:
            node = node[key]


def _split_override(override: str) -> tuple[list[str], object]:
    """The path segments and the parsed value of ``override``; ``name[3]`` is read as ``name.3``."""
    path, separator, text = override.partition("=")
    path = re.sub(r"\[(\d+)\]", r".\1", path.strip())
    segments = [segment.strip() for segment in path.split(".")]
    if not separator or not all(segments):
        raise ScenarioError(override.strip() or "override", _OVERRIDE_FORM)
    return segments, _parse_value(text)


def _resolve(node, hint, segment: str, where: str) -> tuple[object, object, str]:
    """The key ``segment`` selects in ``node`` (of type ``hint``, at path ``where``), its type and its path."""
    if _is_dataclass_type(hint):
        if not isinstance(node, dict):
            raise ScenarioError(where, f"must be a table (got {_shown(node)})")
        if segment not in _init_fields(hint):
            raise ScenarioError(_join(where, segment), _unknown_field(hint))
        return segment, typing.get_type_hints(hint)[segment], _join(where, segment)
    if typing.get_origin(hint) in (tuple, list):
        return _resolve_index(node, hint, segment, where)
    raise ScenarioError(where, f"is a single value and has no part {segment!r}; remove '.{segment}'")


def _resolve_index(node, hint, segment: str, where: str) -> tuple[int, object, str]:
    """The 0-based index ``segment`` selects in the array ``node`` at ``where``, with the entry's type and path."""
    if not isinstance(node, list):
        raise ScenarioError(where, f"must be an array (got {_shown(node)})")
    if not _INDEX.fullmatch(segment):
        raise ScenarioError(where,
                            f"is an array; select an entry by its 0-based index, e.g. {where}.0 (got {segment!r})")
    index = int(segment)
    if index >= len(node):
        valid = f" (indices 0 to {len(node) - 1})" if node else ""
        raise ScenarioError(f"{where}[{index}]", f"index out of range; {where} has {len(node)} entries{valid}")
    item_hints = _item_hints(hint, len(node))
    item_hint = item_hints[index] if index < len(item_hints) else typing.Any
    return index, item_hint, f"{where}[{index}]"


def _parse_value(text: str):
    """The value an override's text stands for: a TOML literal, else a list of such items, else the bare text.

    Bare text stays a string, so unit-suffixed numbers ("25us") are read when the field's type is known.
    """
    text = text.strip()
    value = _toml_literal(text)
    if value is not None:
        return value
    if text.startswith("[") and text.endswith("]"):
        items = text[1:-1].split(",")
        if len(items) > 1 and not items[-1].strip():
            items = items[:-1]  # a trailing comma, as TOML allows
        return [_parse_value(item) for item in items] if text[1:-1].strip() else []
    return text


def _toml_literal(text: str):
    """``text`` read as a TOML value (number, bool, string, array, inline table), or None if it is not one."""
    if "\n" in text or "\r" in text:
        return None
    try:
        value = tomllib.loads(f"value = {text}")["value"]
    except (ValueError, RecursionError):       # not TOML (TOMLDecodeError), or an integer of thousands of digits
        return None
    return value if isinstance(value, (bool, int, float, str, list, dict)) else None


# --- building the dataclasses -------------------------------------------------------------------


def _build(cls: type, data, where: str):
    """An instance of the dataclass ``cls`` from the table ``data`` at path ``where``; omitted fields keep defaults."""
    known = _init_fields(cls)
    if not isinstance(data, dict):
        raise ScenarioError(where or "scenario", f"must be a table of {', '.join(sorted(known))} (got {_shown(data)})")
    for key in data:
        if key not in known:
            raise ScenarioError(_join(where, key), _unknown_field(cls))
    required = [name for name, spec in known.items() if _is_required(spec)]
    for name in required:
        if name not in data:
            raise ScenarioError(_join(where, name), f"missing; each {cls.__name__} needs {', '.join(required)}")
    hints = typing.get_type_hints(cls)
    values = {name: _coerce(data[name], hints[name], _join(where, name), FIELD_DIMENSIONS.get(f"{cls.__name__}.{name}"))
              for name in known if name in data}
    try:
        return cls(**values)
    except ScenarioError as error:
        raise (error.within(where) if where else error) from None


def _coerce(value, hint, where: str, dimension: str | None = None):
    """``value`` (plain TOML data) converted to the type ``hint``; ``where`` is its dotted path for errors and
    ``dimension`` (of ``units.DIMENSIONS``) that of a float field."""
    if _is_dataclass_type(hint):
        return _build(hint, value, where)
    origin = typing.get_origin(hint)
    if origin in (tuple, list):
        return _coerce_sequence(value, hint, where, dimension)
    if origin is typing.Union or origin is types.UnionType:
        return _coerce_union(value, hint, where, dimension)
    if hint is float:
        return _coerce_float(value, where, dimension)
    if hint is bool:
        return _checked(value, bool, where, "true or false")
    if hint is int:
        return _checked(value, int, where, "an integer", reject_bool=True)
    if hint is str:
        return _checked(value, str, where, 'a string (quote it, e.g. "name")')
    return value


def _coerce_sequence(value, hint, where: str, dimension: str | None = None):
    """The array ``value`` as the tuple or list type ``hint``, each entry converted to its item type."""
    if not isinstance(value, (list, tuple)):
        raise ScenarioError(where, f"must be an array, e.g. [1, 2] (got {_shown(value)})")
    item_hints = _item_hints(hint, len(value))
    if len(item_hints) != len(value):
        raise ScenarioError(where, f"must have {len(item_hints)} entries (got {len(value)})")
    items = [_coerce(item, item_hint, f"{where}[{index}]", dimension)
             for index, (item, item_hint) in enumerate(zip(value, item_hints))]
    return tuple(items) if typing.get_origin(hint) is tuple else items


def _coerce_union(value, hint, where: str, dimension: str | None = None):
    """``value`` as the first member of the union ``hint`` (NoneType aside) that accepts it."""
    members = [member for member in typing.get_args(hint) if member is not type(None)]
    for member in members[:-1]:
        try:
            return _coerce(value, member, where, dimension)
        except ScenarioError:
            continue
    return _coerce(value, members[-1], where, dimension)


def _coerce_float(value, where: str, dimension: str | None = None) -> float:
    """``value`` as a finite float in SI units: a number, or a string with a unit of the field's ``dimension``."""
    if isinstance(value, bool) or not isinstance(value, (str, numbers.Real)):
        raise ScenarioError(where, f"must be a number, optionally with a unit such as '2.5 us' (got {_shown(value)})")
    try:
        return units.parse_quantity(value if isinstance(value, (str, int)) else float(value),
                                    dimension or "dimensionless", field=where)
    except units.QuantityError as error:
        raise ScenarioError(where, str(error).split(": ", 1)[1]) from None


def _checked(value, kind: type, where: str, description: str, reject_bool: bool = False):
    """``value`` unchanged if it is a ``kind`` (and not a bool when ``reject_bool``); otherwise a ScenarioError."""
    if not isinstance(value, kind) or (reject_bool and isinstance(value, bool)):
        raise ScenarioError(where, f"must be {description} (got {_shown(value)})")
    return value


def _item_hints(hint, length: int) -> tuple:
    """The entry types of the tuple or list type ``hint`` for a sequence of ``length`` entries."""
    args = typing.get_args(hint) or (typing.Any, ...)
    if typing.get_origin(hint) is list or (len(args) == 2 and args[1] is Ellipsis):
        return (args[0],) * length
    return args


# --- small helpers ------------------------------------------------------------------------------


def _is_required(spec: dataclasses.Field) -> bool:
    """Whether the dataclass field ``spec`` has no default."""
    return spec.default is dataclasses.MISSING and spec.default_factory is dataclasses.MISSING


def _is_dataclass_type(hint) -> bool:
    """Whether the type hint ``hint`` is a dataclass (not a generic alias or an instance)."""
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def _unknown_field(cls: type) -> str:
    """The message for a key that is not a field of ``cls``."""
    return f"unknown field; known fields: {', '.join(sorted(_init_fields(cls)))}"


def _shown(value) -> str:
    """A short description of ``value`` for error messages."""
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, (list, tuple)):
        return "an array"
    return repr(value)


def _one_line(error: Exception) -> str:
    """The text of ``error`` with all whitespace runs (newlines too) collapsed to single spaces."""
    return " ".join(str(error).split())

