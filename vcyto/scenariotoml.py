"""A ``Scenario`` written as a TOML document that ``vcyto.config.load_scenario`` reads back to the same scenario.

The tables mirror the dataclasses of ``sim.model.scenario`` (``vcyto.config``'s docstring); numbers are plain SI,
floats written as the shortest text that reads back to the same float. ``vcyto scenario`` prints it, the
recordings and the sweep's point identities store it.
"""

from __future__ import annotations

import dataclasses
import numbers

from sim.model.scenario import Scenario


def scenario_to_toml(scenario: Scenario) -> str:
    """A complete TOML document, in plain SI numbers, that ``load_scenario`` reads back to ``scenario``."""
    lines = ["# vcyto scenario; SI units (m, s, kg/m^3, Pa s, Hz, rad)"]
    _write_table(scenario, "", lines)
    return "\n".join(lines) + "\n"


def _write_table(obj, path: str, lines: list[str]) -> None:
    """Append to ``lines`` the key/value pairs of the dataclass ``obj``, then its sub-tables and arrays of tables."""
    sections = []
    for name in _init_fields(type(obj)):
        value = getattr(obj, name)
        if dataclasses.is_dataclass(value) or _is_table_array(value):
            sections.append((_join(path, name), value))
        elif value is not None:
            lines.append(f"{name} = {_toml_value(value)}")
    for section_path, value in sections:
        for entry in (value if _is_table_array(value) else [value]):
            lines += ["", f"[[{section_path}]]" if _is_table_array(value) else f"[{section_path}]"]
            _write_table(entry, section_path, lines)


def _toml_value(value) -> str:
    """``value`` (bool, number, string or a sequence of them) as a TOML value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        return repr(float(value))  # shortest text that reads back to the same float; inf and nan are TOML too
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    raise TypeError(f"cannot write {value!r} as a TOML value")


def _toml_string(text: str) -> str:
    """``text`` as a TOML basic string, with quotes, backslashes and control characters escaped."""
    def escaped(char: str) -> str:
        if char in '"\\':
            return "\\" + char
        if ord(char) < 0x20 or ord(char) == 0x7F:
            return f"\\u{ord(char):04x}"
        return char
    return '"' + "".join(map(escaped, text)) + '"'


def _is_table_array(value) -> bool:
    """Whether ``value`` is a non-empty sequence of dataclass instances, written as [[...]] tables."""
    return isinstance(value, (tuple, list)) and bool(value) and all(dataclasses.is_dataclass(item) for item in value)


def _init_fields(cls: type) -> dict[str, dataclasses.Field]:
    """The fields of the dataclass ``cls`` that its constructor takes, by name, in declaration order."""
    return {spec.name: spec for spec in dataclasses.fields(cls) if spec.init}


def _join(where: str, name: str) -> str:
    """The dotted path of ``name`` inside ``where`` (just ``name`` at the top)."""
    return f"{where}.{name}" if where else name
