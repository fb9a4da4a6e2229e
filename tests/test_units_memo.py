"""The memo of pint's answers (vcyto/units.py ``_UnitMemo``): a warm process gives pint's factors and errors
without importing pint; a corrupted memo is ignored and rewritten."""

import json
import os
import subprocess
import sys

import pytest

from vcyto import units
from vcyto.units import QuantityError, _pint_si_factor, _UnitMemo

CASES = [("us", "time"), ("mPa s", "viscosity"), ("N/m^3", "force density"), ("deg", "angle"), ("cells/s", "frequency")]


@pytest.fixture
def memo_in(tmp_path, monkeypatch):
    """A fresh memo in ``tmp_path``; the module's own memo and lru cache are restored afterwards."""
    monkeypatch.setenv("VCYTO_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("VCYTO_CACHE", "on")
    monkeypatch.setattr(_UnitMemo, "_instance", None)
    units._si_factor.cache_clear()
    yield tmp_path
    units._si_factor.cache_clear()


def memo_file(directory):
    return next((directory / "units").glob("pint-*.json"))


def test_remembered_factors_and_errors_are_pints(memo_in):
    for unit, dimension in CASES:
        assert units._si_factor(unit, dimension) == _pint_si_factor(unit, dimension)
    with pytest.raises(QuantityError, match="is a length, but value is a time"):
        units.parse_quantity("3um", "time")
    with pytest.raises(QuantityError, match="unknown unit 'flibbets'"):
        units.parse_quantity("3 flibbets", "length")
    # a second process reads the memo: same answers, pint never imported
    script = ("import sys, json; from vcyto import units\n"
              f"values = [units._si_factor(u, d) for u, d in {CASES!r}]\n"
              "errors = []\n"
              "for text, dim in (('3um', 'time'), ('3 flibbets', 'length')):\n"
              "    try: units.parse_quantity(text, dim)\n"
              "    except units.QuantityError as e: errors.append(str(e))\n"
              "print(json.dumps([values, errors, 'pint' in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                         env={**os.environ, "VCYTO_CACHE_DIR": str(memo_in)}).stdout
    values, errors, imported = json.loads(out)
    assert values == [_pint_si_factor(u, d) for u, d in CASES]
    assert "is a length, but value is a time" in errors[0] and "unknown unit 'flibbets'" in errors[1]
    assert imported is False


def test_a_corrupted_memo_is_ignored_and_rewritten(memo_in):
    units._si_factor("us", "time")
    path = memo_file(memo_in)
    stored = json.loads(path.read_text())
    stored["entries"]["time|us"] = ["factor", 1.0]           # edited without its checksum: a wrong factor
    path.write_text(json.dumps(stored))
    _UnitMemo._instance = None
    units._si_factor.cache_clear()
    assert units._si_factor("us", "time") == pytest.approx(1e-6, rel=1e-15)
    assert json.loads(path.read_text())["entries"]["time|us"] == ["factor", 1e-6]
    path.write_text("{not json")                              # torn
    _UnitMemo._instance = None
    units._si_factor.cache_clear()
    assert units._si_factor("ms", "time") == pytest.approx(1e-3, rel=1e-15)


def test_cache_off_writes_no_memo(memo_in, monkeypatch):
    monkeypatch.setenv("VCYTO_CACHE", "off")
    assert units._si_factor("ms", "time") == pytest.approx(1e-3, rel=1e-15)
    assert not (memo_in / "units").exists()


def test_the_memo_file_stops_growing_at_its_cap(memo_in, monkeypatch):
    monkeypatch.setattr(units, "MEMO_ENTRIES", 2)
    for unit in ("us", "ms", "s", "ns"):
        units._si_factor(unit, "time")
    stored = json.loads(memo_file(memo_in).read_text())["entries"]
    assert sorted(stored) == ["time|ms", "time|us"]
    assert units._si_factor("ns", "time") == pytest.approx(1e-9, rel=1e-15)        # still answered
