"""One unit rule for every physical quantity vcyto reads (options, scenario fields, sweep specs).

A quantity is a number with an optional unit: ``25us``, ``0.5 ms``, ``1kHz``, ``30um``, ``25µs``, ``6 mPa s``.
A bare number means the field's documented default unit (``ms`` for ``--lead``, SI for scenario fields). A
unit of another dimension than the field's (``--dt 3um``) is an error naming the field and the expected
dimension; so are NaN, infinity and text that is not a number.

Units are read with pint (names, SI prefixes, products and quotients such as ``N/m^3``); the number itself is
read here (a plain decimal, never an expression), so ``10**10**10`` or ``1e999`` cannot run away. pint evaluates
what it is given (``um^(9^9^9)`` would have it compute an astronomically large power), so a unit reaches it only
once it is read here as names joined by ``*``, ``/``, ``·`` or spaces, each with at most a one-digit integer power
(``m^3``, ``s**-1``, ``m^(-1)``), parentheses one deep: any unit pint then sees costs it a bounded, small work.
A value whose magnitude lies beyond physical sense for its dimension (``MAGNITUDES``: ``1e300 s``, ``1e-300 s``,
a gate of ``1e308``) is refused too, naming the range; zero passes (each field says whether it takes zero).
"""

from __future__ import annotations

import decimal
import functools
import hashlib
import json
import math
import os
import re
import tempfile

# dimension name -> (an SI unit of it, as pint writes it, the example shown in messages)
DIMENSIONS = {
    "length": ("m", "30um"),
    "time": ("s", "25us"),
    "frequency": ("Hz", "1kHz"),
    "speed": ("m/s", "20 mm/s"),
    "angle": ("rad", "30deg"),
    "density": ("kg/m^3", "1000 kg/m^3"),
    "viscosity": ("Pa*s", "6 mPa s"),
    "force density": ("N/m^3", "5.7e7 N/m^3"),
    "tension": ("N/m", "6e-6 N/m"),
    "bending modulus": ("N*m", "2e-19 N m"),
    "dimensionless": ("", "0.5"),
}

# dimension -> (smallest nonzero, largest) magnitude in SI that a value of it can have in any vcyto input: far
# beyond every device, cell and run vcyto models, yet nowhere near the float range a number can overflow in
MAGNITUDES = {
    "length": (1e-15, 1e3),
    "time": (1e-15, 1e7),
    "frequency": (1e-6, 1e15),
    "speed": (1e-12, 1e4),
    "angle": (1e-12, 1e3),
    "density": (1e-6, 1e6),
    "viscosity": (1e-12, 1e6),
    "force density": (1e-12, 1e18),
    "tension": (1e-15, 1e6),
    "bending modulus": (1e-30, 1e-6),
    "dimensionless": (1e-30, 1e15),
}
MAX_TEXT_CHARS = 100                # a quantity's text is read only up to this length

_NUMBER = re.compile(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf|infinity))\s*(.*?)\s*",
                     re.IGNORECASE)
_DECIMAL = decimal.Context(prec=34, traps=[])   # overflow gives inf (refused below), not an exception
_NAME = r"[A-Za-zµμΩ°%_]+"
_POWER = r"\s*(?:\^|\*\*)\s*(?:[-+]?\d|\(\s*[-+]?\d\s*\))"          # one digit: m^3, s**-1, m^(-1)
_JOIN = r"(?:\s*[*/·]\s*|\s+)"
_FLAT = rf"{_NAME}(?:{_POWER})?(?:{_JOIN}{_NAME}(?:{_POWER})?)*"
_FACTOR = rf"(?:{_NAME}|\(\s*{_FLAT}\s*\))(?:{_POWER})?"                     # parentheses one deep
_UNIT_FORM = re.compile(rf"{_FACTOR}(?:{_JOIN}{_FACTOR})*")
_MAX_UNIT_CHARS = 40


class QuantityError(ValueError):
    """A quantity that cannot be read; ``str(error)`` is one line naming the field."""


def parse_quantity(text, dimension: str, default_unit: str = "", field: str = "value") -> float:
    """The SI value of ``text`` (a string, or a number in ``default_unit``) for a ``dimension`` of ``DIMENSIONS``.

    ``default_unit`` is the unit of a bare number ("" or the SI unit: SI). Raises ``QuantityError`` whose
    message names ``field``, the expected dimension and an example when ``text`` is not a finite quantity of
    that dimension.
    """
    if dimension not in DIMENSIONS:
        raise KeyError(f"unknown dimension {dimension!r}")
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        raise QuantityError(f"{field}: must be a {_kind(dimension)} (got {text!r})")
    if isinstance(text, int) and text.bit_length() > 4 * MAX_TEXT_CHARS:       # more digits than a text may have
        raise QuantityError(f"{field}: {_shown(text)} is not a finite {_kind(dimension)}; give a number such as "
                            f"{DIMENSIONS[dimension][1]}")
    number, unit = _split(str(text), dimension, field) if isinstance(text, str) else (decimal.Decimal(repr(text)), "")
    if not number.is_finite():
        raise QuantityError(f"{field}: {_shown(text)} is not a finite {_kind(dimension)}; give a number such as "
                            f"{DIMENSIONS[dimension][1]}")
    factor = _factor(unit or default_unit, dimension, field, text)
    value = float(_DECIMAL.multiply(number, decimal.Decimal(repr(factor))))
    if not math.isfinite(value):
        raise QuantityError(f"{field}: {_shown(text)} is not a finite {_kind(dimension)}; give a number such as "
                            f"{DIMENSIONS[dimension][1]}")
    if number and not value:           # so small that it rounds to zero: refused as too small, not read as 0
        value = math.ulp(0.0)
    return check_magnitude(value, dimension, field, text)


def check_magnitude(value: float, dimension: str, field: str = "value", text=None) -> float:
    """``value`` (SI) if zero or within ``MAGNITUDES[dimension]``; else ``QuantityError`` naming the range."""
    smallest, largest = MAGNITUDES[dimension]
    if value == 0 or smallest <= abs(value) <= largest:
        return value
    unit = DIMENSIONS[dimension][0]
    shown = _shown(text if text is not None else value)
    raise QuantityError(f"{field}: {shown} is beyond physical sense for a {_kind(dimension)}: give 0 or a magnitude "
                        f"from {smallest:g} to {largest:g}{(' ' + unit) if unit else ''}")


def parse_list(text: str, dimension: str, default_unit: str = "", field: str = "value") -> list[float]:
    """Comma-separated quantities (``30um,60um`` or ``30,60``), each as ``parse_quantity``."""
    if not isinstance(text, str):
        raise QuantityError(f"{field}: must be comma-separated values such as "
                            f"{DIMENSIONS[dimension][1]},{DIMENSIONS[dimension][1]} (got {text!r})")
    return [parse_quantity(part, dimension, default_unit, field) for part in text.split(",")]


def unit_factor(unit: str, dimension: str) -> float:
    """The SI value of one ``unit`` of ``dimension`` (``unit_factor("ms", "time")`` = 0.001)."""
    return _factor(unit, dimension, "unit", unit)


def _kind(dimension: str) -> str:
    return "number" if dimension == "dimensionless" else f"{dimension}"


def _split(text: str, dimension: str, field: str) -> tuple[decimal.Decimal, str]:
    if len(text) > MAX_TEXT_CHARS:
        raise QuantityError(f"{field}: {_shown(text)} is {len(text):,} characters long; a {_kind(dimension)} is a "
                            f"number with an optional unit, e.g. {DIMENSIONS[dimension][1]}")
    match = _NUMBER.fullmatch(text)
    if match is None:
        example = DIMENSIONS[dimension][1]
        raise QuantityError(f"{field}: cannot read {_shown(text)} as a number"
                            + (f"; a {dimension} is a number with an optional unit, e.g. {example}"
                               if dimension != "dimensionless" else f", e.g. {example}"))
    number, unit = match.groups()
    if number.strip("+-").lower() in ("nan", "inf", "infinity"):
        raise QuantityError(f"{field}: {_shown(text)} is not a finite {_kind(dimension)}; give a number such as "
                            f"{DIMENSIONS[dimension][1]}")
    return decimal.Decimal(number), unit


def _factor(unit: str, dimension: str, field: str, text) -> float:
    """SI factor of ``unit`` after checking that it has ``dimension``."""
    unit = unit.strip()
    if not unit:
        return 1.0
    if dimension == "dimensionless":
        raise QuantityError(f"{field}: is a plain number and takes no unit (got {_shown(text)})")
    if len(unit) > _MAX_UNIT_CHARS or not _UNIT_FORM.fullmatch(unit):
        raise QuantityError(f"{field}: cannot read the unit {_shown(unit)}; a unit is names with one-digit powers "
                            f"(m^3, s**-1), expected a {dimension} such as {DIMENSIONS[dimension][1]}")
    try:
        return _si_factor(unit, dimension)
    except _WrongDimension as error:
        raise QuantityError(f"{field}: {_shown(text)} is a {error.found}, but {field} is a {dimension} "
                            f"(e.g. {DIMENSIONS[dimension][1]})") from None
    except _UnknownUnit:
        raise QuantityError(f"{field}: unknown unit {_shown(unit)}; expected a {dimension} such as "
                            f"{DIMENSIONS[dimension][1]}") from None


class _WrongDimension(Exception):
    def __init__(self, found: str):
        super().__init__(found)
        self.found = found


class _UnknownUnit(Exception):
    pass


@functools.lru_cache(maxsize=None)
def _registry():
    import pint
    registry = pint.UnitRegistry()
    registry.define("cell = [] = cells")          # "500 cells/s" is a rate
    return registry


@functools.lru_cache(maxsize=512)
def _si_factor(unit: str, dimension: str) -> float:
    """The SI factor of ``unit`` as pint reads it, remembered between runs (``_UnitMemo``): a warm process
    never imports pint (0.8-1.5 s of a run's start: its import pulls in dask, its registry parses ~1,000
    definitions)."""
    memo = _UnitMemo.shared()
    known = memo.get(unit, dimension)
    if known is None:
        try:
            known = ["factor", _pint_si_factor(unit, dimension)]
        except _WrongDimension as error:
            known = ["wrong", error.found]
        except _UnknownUnit:
            known = ["unknown"]
        memo.put(unit, dimension, known)
    if known[0] == "wrong":
        raise _WrongDimension(known[1])
    if known[0] == "unknown":
        raise _UnknownUnit()
    return float(known[1])


MEMO_ENTRIES = 2000


class _UnitMemo:
    """What pint said about each (unit, dimension) read before: one JSON file in vcyto's cache directory,
    named by pint's version and a digest of the rule (``_rule_digest``), holding a SHA-256 of its entries (a
    corrupted or edited file is ignored and rewritten). Written to a temporary file and moved in place
    (``os.replace``); ``VCYTO_CACHE=off``: memory only.
    """

    _instance = None

    def __init__(self, path):
        self.path, self.entries = path, {}
        if path is not None:
            self.entries = self._read(path)

    @classmethod
    def shared(cls) -> "_UnitMemo":
        if cls._instance is None:
            from importlib.metadata import version

            from .cache import cache_directory, cache_enabled
            path = cache_directory() / "units" / f"pint-{version('pint')}-{_rule_digest()}.json" \
                if cache_enabled() else None
            cls._instance = cls(path)
        return cls._instance

    @staticmethod
    def _read(path) -> dict:
        try:
            stored = json.loads(path.read_text())
            entries = stored["entries"]
            if stored["sha256"] == _entries_digest(entries) and isinstance(entries, dict):
                return entries
        except (OSError, ValueError, KeyError, TypeError):
            pass
        return {}

    def get(self, unit: str, dimension: str):
        known = self.entries.get(f"{dimension}|{unit}")
        valid = isinstance(known, list) and known and (
            (known[0] == "factor" and len(known) == 2 and isinstance(known[1], float) and math.isfinite(known[1]))
            or (known[0] == "wrong" and len(known) == 2 and isinstance(known[1], str))
            or known == ["unknown"])
        return known if valid else None

    def put(self, unit: str, dimension: str, known: list):
        self.entries[f"{dimension}|{unit}"] = known
        if self.path is None or len(self.entries) > MEMO_ENTRIES:     # a fuzzer's thousand units stay in memory
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            handle, temporary = tempfile.mkstemp(dir=self.path.parent, prefix=".units.", suffix=".tmp")
            with os.fdopen(handle, "w") as file:
                json.dump({"entries": self.entries, "sha256": _entries_digest(self.entries)}, file)
            os.replace(temporary, self.path)
        except OSError:      # a read-only cache costs the next run pint's start-up, nothing else
            pass


def _rule_digest() -> str:
    """A short digest of what the remembered answers depend on besides pint: the dimensions and this module's
    reading of pint's answer (a changed rule starts a new memo)."""
    from sim.fast.store import code_digest
    return hashlib.sha256(repr((DIMENSIONS, code_digest(_pint_si_factor, _describe))).encode()).hexdigest()[:16]


def _entries_digest(entries: dict) -> str:
    return hashlib.sha256(json.dumps(entries, sort_keys=True).encode()).hexdigest()


def _pint_si_factor(unit: str, dimension: str) -> float:
    import pint
    registry = _registry()
    try:
        parsed = registry.parse_units(unit.replace("·", "*"))
    except (pint.errors.UndefinedUnitError, pint.errors.DefinitionSyntaxError, AttributeError, ValueError,
            TypeError, SyntaxError, AssertionError, KeyError):
        raise _UnknownUnit() from None
    expected = registry.parse_units(DIMENSIONS[dimension][0]) if DIMENSIONS[dimension][0] else None
    quantity = registry.Quantity(1, parsed)
    found = quantity.dimensionality
    angle = dimension == "angle"
    if (angle and (found or str(parsed) not in ("radian", "degree", "arcminute", "arcsecond", "turn"))) or \
            (not angle and found != registry.Quantity(1, expected).dimensionality):
        raise _WrongDimension(_describe(found, parsed))
    return float(quantity.to(expected).magnitude) if not angle else float(quantity.to("radian").magnitude)


def _describe(found, parsed) -> str:
    """The dimension name of a pint dimensionality (or its pint form)."""
    registry = _registry()
    for name, (si, _) in DIMENSIONS.items():
        if si and registry.Quantity(1, registry.parse_units(si)).dimensionality == found and name != "angle":
            return name
    return f"quantity of dimension {found}" if found else f"plain number ({parsed})"


def _shown(text) -> str:
    if isinstance(text, int) and text.bit_length() > 1000:
        return f"an integer of {text.bit_length()} bits"
    text = str(text)
    return repr(text if len(text) <= 40 else text[:37] + "...")
