"""The one unit rule (vcyto/units.py): units accepted and converted, wrong dimensions and non-finite values refused."""

import dataclasses
import math
import typing

import pytest

from sim.model import scenario as scenario_module
from vcyto.config import FIELD_DIMENSIONS, load_scenario
from vcyto.units import DIMENSIONS, QuantityError, parse_list, parse_quantity


@pytest.mark.parametrize("text, dimension, unit, expected", [
    ("25us", "time", "s", 25e-6),
    ("25µs", "time", "s", 25e-6),            # micro sign
    ("25μs", "time", "s", 25e-6),            # Greek mu
    ("0.5ms", "time", "s", 0.5e-3),
    ("5ms", "time", "ms", 5e-3),
    ("5", "time", "ms", 5e-3),               # a bare number is in the default unit
    ("150us", "time", "ms", 150e-6),
    ("1kHz", "frequency", "Hz", 1000.0),
    ("500 cells/s", "frequency", "Hz", 500.0),
    ("30um", "length", "um", 30e-6),
    ("30", "length", "um", 30e-6),
    ("6 mPa s", "viscosity", "", 6e-3),
    ("30 deg", "angle", "", math.pi / 6),
    ("5.7e7 N/m^3", "force density", "", 5.7e7),
    ("-1e-3", "time", "s", -1e-3),
])
def test_quantities_with_units_are_read_in_si(text, dimension, unit, expected):
    assert parse_quantity(text, dimension, unit, "field") == pytest.approx(expected, rel=1e-12)


def test_decimal_products_round_once():
    assert parse_quantity("10 um", "length") == 1e-05
    assert parse_quantity("25us", "time") == 2.5e-05


@pytest.mark.parametrize("text, dimension, words", [
    ("3um", "time", "is a length, but --x is a time"),
    ("2.5us", "length", "is a time, but --x is a length"),
    ("6MHz", "viscosity", "is a frequency, but --x is a viscosity"),
    ("1 m**3", "length", "but --x is a length"),
    ("2 deg", "dimensionless", "takes no unit"),
    ("1 furlong/s", "time", "but --x is a time"),
    ("3 parsecs", "frequency", "but --x is a frequency"),
    ("5 bogons", "time", "unknown unit"),
    ("nan", "time", "not a finite time"),
    ("-inf ms", "time", "not a finite time"),
    ("1e999", "length", "not a finite length"),
    ("10**10**10", "time", "cannot read the unit"),
    ("", "time", "cannot read"),
    ("fast", "time", "cannot read"),
])
def test_wrong_dimensions_and_non_finite_values_are_refused_naming_field_and_dimension(text, dimension, words):
    with pytest.raises(QuantityError) as caught:
        parse_quantity(text, dimension, field="--x")
    message = str(caught.value)
    assert message.startswith("--x: ") and words in message and "\n" not in message


def test_lists_take_units_per_entry():
    assert parse_list("30um,60", "length", "um") == pytest.approx([30e-6, 60e-6])
    with pytest.raises(QuantityError):
        parse_list("30um,60us", "length", "um")


def test_every_float_field_of_the_scenario_has_a_dimension():
    """A float field added to a scenario dataclass must say its dimension (else units could not be checked)."""
    missing = []
    for cls in (scenario_module.Channel, scenario_module.Inlet, scenario_module.Outlet, scenario_module.SawWindow,
                scenario_module.Fluid, scenario_module.Saw, scenario_module.Numerics, scenario_module.CellType):
        hints = typing.get_type_hints(cls)
        for spec in dataclasses.fields(cls):
            text = str(hints[spec.name])
            if "float" in text and f"{cls.__name__}.{spec.name}" not in FIELD_DIMENSIONS:
                missing.append(f"{cls.__name__}.{spec.name}")
    assert not missing
    assert set(FIELD_DIMENSIONS.values()) <= set(DIMENSIONS)


@pytest.mark.parametrize("override, value", [
    ("numerics.dt=25µs", 25e-6),
    ("fluid.viscosity=6 mPa s", 6e-3),
    ("saw.frequency=0.1GHz", 1e8),
    ("channel.inlets.0.tilt=30deg", math.pi / 6),
])
def test_scenario_fields_take_units_of_their_dimension(override, value):
    scenario = load_scenario(None, [override])
    field, _ = override.split("=")
    node = scenario
    for part in field.split("."):
        node = node[int(part)] if part.isdigit() else getattr(node, part)
    assert node == pytest.approx(value, rel=1e-12)


@pytest.mark.parametrize("override, words", [
    ("fluid.viscosity=6MHz", "is a frequency, but fluid.viscosity is a viscosity"),
    ("numerics.dt=3um", "is a length, but numerics.dt is a time"),
    ("numerics.mesh_h=2.5us", "is a time, but numerics.mesh_h is a length"),
    ("fluid.density=nan", "not a finite density"),
])
def test_scenario_fields_refuse_other_dimensions(override, words):
    with pytest.raises(scenario_module.ScenarioError) as caught:
        load_scenario(None, [override])
    assert words in str(caught.value)
