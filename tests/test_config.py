"""Tests of vcyto.config: scenario files, overrides, units, the TOML writer and the error messages."""

import math
import sys
from dataclasses import replace

import pytest

from sim.model.scenario import Inlet, Outlet, Scenario, ScenarioError
from vcyto.config import load_scenario, scenario_to_toml

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

UM = 1e-6


@pytest.fixture
def write_toml(tmp_path):
    """A function writing its text to a scenario file and returning the file's path."""
    def write(text, name="scenario.toml"):
        path = tmp_path / name
        path.write_text(text, encoding="utf-8")
        return path
    return write


def scenario_error(path=None, overrides=()):
    """The ScenarioError that load_scenario raises for ``path`` and ``overrides`` (checked to be one line)."""
    with pytest.raises(ScenarioError) as caught:
        load_scenario(path, overrides)
    message = str(caught.value)
    assert "\n" not in message and "\r" not in message
    return caught.value


# --- defaults and files -------------------------------------------------------------------------


def test_no_path_gives_the_defaults():
    assert load_scenario() == Scenario()
    assert load_scenario(None, []) == Scenario()


def test_an_empty_file_gives_the_defaults(write_toml):
    assert load_scenario(write_toml("")) == Scenario()


def test_file_values_with_units_become_si_numbers(write_toml):
    path = write_toml(
        """
        [fluid]
        viscosity = "1.5 mPa s"

        [numerics]
        dt = "25 us"
        mesh_h = "2.5um"
        convection = "oseen"
        max_nonlinear_iterations = 12

        [saw]
        frequency = "50 MHz"
        amplitude = "2 nm"

        [channel]
        length = "0.4 mm"

        [channel.saw_window]
        span = ["140 um", "160 um"]
        """)
    scenario = load_scenario(path)
    defaults = Scenario()
    assert scenario.fluid.viscosity == pytest.approx(1.5e-3)
    assert scenario.fluid.density == defaults.fluid.density
    assert scenario.numerics.dt == pytest.approx(25e-6)
    assert scenario.numerics.mesh_h == pytest.approx(2.5e-6)
    assert scenario.numerics.convection == "oseen"
    assert scenario.numerics.max_nonlinear_iterations == 12
    assert type(scenario.numerics.max_nonlinear_iterations) is int
    assert scenario.saw.frequency == pytest.approx(50e6)
    assert scenario.saw.amplitude == pytest.approx(2e-9)
    assert scenario.saw.model == defaults.saw.model
    assert scenario.channel.length == pytest.approx(400e-6)
    assert scenario.channel.saw_window.span == pytest.approx((140e-6, 160e-6))
    assert isinstance(scenario.channel.saw_window.span, tuple)
    assert scenario.channel.saw_window.cutoff == defaults.channel.saw_window.cutoff
    assert scenario.channel.inlets == defaults.channel.inlets


def test_file_inlets_and_outlets_replace_the_default_lists(write_toml):
    path = write_toml(
        """
        [channel]
        injection_inlet = "sample"

        [[channel.inlets]]
        name = "sheath"
        span = ["20 um", "90 um"]
        v_hat = 0.04
        tilt = "10 deg"

        [[channel.inlets]]
        name = "sample"
        span = [1.1e-4, 1.5e-4]
        v_hat = "0.02"
        cutoff = "2 um"

        [[channel.outlets]]
        name = "waste"
        span = ["10 um", "200 um"]
        """)
    channel = load_scenario(path).channel
    assert [inlet.name for inlet in channel.inlets] == ["sheath", "sample"]
    assert isinstance(channel.inlets, tuple)
    sheath, sample = channel.inlets
    assert sheath.span == pytest.approx((20e-6, 90e-6))
    assert sheath.tilt == pytest.approx(math.radians(10))
    assert sheath.cutoff == Inlet("x", (0.1, 0.2), 0.0).cutoff
    assert sample.v_hat == pytest.approx(0.02)
    assert sample.tilt == 0.0
    assert sample.cutoff == pytest.approx(2e-6)
    assert channel.outlets == (Outlet("waste", (10e-6, 200e-6)),)


# --- overrides ----------------------------------------------------------------------------------


def test_overrides_with_units_and_list_indices():
    scenario = load_scenario(overrides=[
        "fluid.viscosity=1e-3",
        "numerics.dt=25us",
        "numerics.convection=oseen",
        "numerics.linear_solver='superlu'",
        "numerics.max_nonlinear_iterations=7",
        "channel.inlets.1.v_hat=0.02",
        "channel.inlets.0.span=[30um, 80um]",
        "channel.inlets[2].tilt=-15 deg",
        "channel.outlets.1.span.0=125 um",
        "saw.frequency = 80 MHz",
    ])
    defaults = Scenario()
    assert scenario.fluid.viscosity == pytest.approx(1e-3)
    assert scenario.numerics.dt == pytest.approx(25e-6)
    assert scenario.numerics.convection == "oseen"
    assert scenario.numerics.linear_solver == "superlu"
    assert scenario.numerics.max_nonlinear_iterations == 7
    assert scenario.channel.inlets[1].v_hat == pytest.approx(0.02)
    assert scenario.channel.inlets[1].span == defaults.channel.inlets[1].span
    assert scenario.channel.inlets[0].span == pytest.approx((30e-6, 80e-6))
    assert scenario.channel.inlets[2].tilt == pytest.approx(-math.radians(15))
    assert scenario.channel.outlets[1].span == pytest.approx((125e-6, defaults.channel.outlets[1].span[1]))
    assert scenario.saw.frequency == pytest.approx(80e6)


def test_overflowing_value_is_rejected_by_validation():
    assert scenario_error(overrides=["fluid.density=1e999"]).field == "fluid.density"


def test_overrides_apply_on_top_of_the_file(write_toml):
    path = write_toml('[numerics]\ndt = "10 us"\nconvection = "implicit"\n')
    scenario = load_scenario(path, ["numerics.dt=5us"])
    assert scenario.numerics.dt == pytest.approx(5e-6)
    assert scenario.numerics.convection == "implicit"


def test_override_can_fix_what_the_file_alone_gets_wrong(write_toml):
    path = write_toml('[numerics]\nmesh_h = "20 um"\n')
    assert scenario_error(path).field == "numerics.mesh_h"
    assert load_scenario(path, ["numerics.mesh_h=5um"]).numerics.mesh_h == pytest.approx(5e-6)


def test_override_indexes_the_inlets_the_file_gives(write_toml):
    path = write_toml('[channel]\ninjection_inlet = "only"\n'
                      '[[channel.inlets]]\nname = "only"\nspan = ["50 um", "150 um"]\nv_hat = 0.01\n')
    scenario = load_scenario(path, ["channel.inlets.0.tilt=5deg"])
    assert scenario.channel.inlets[0].tilt == pytest.approx(math.radians(5))
    assert scenario_error(path, ["channel.inlets.1.v_hat=1"]).field == "channel.inlets[1]"


def test_a_single_string_is_not_taken_for_a_list_of_overrides():
    with pytest.raises(TypeError):
        load_scenario(overrides="fluid.viscosity=1e-3")


# --- round trip ---------------------------------------------------------------------------------


def test_round_trip_of_the_defaults(write_toml):
    text = scenario_to_toml(Scenario())
    assert load_scenario(write_toml(text)) == Scenario()


def test_round_trip_of_a_modified_scenario(write_toml):
    defaults = Scenario()
    channel = replace(
        defaults.channel,
        length=350e-6,
        inlets=(Inlet('side "a" \\ é', (25e-6, 95e-6), 0.033, tilt=0.2, cutoff=1e-6),
                Inlet("core", (1.0 / 9 * 1e-3, 0.17e-3), 0.011)),
        injection_inlet="core",
        profile_reading="peak",
    )
    scenario = replace(defaults, channel=channel,
                       fluid=replace(defaults.fluid, viscosity=1.0 / 3 * 1e-3),
                       saw=replace(defaults.saw, model="streaming", spin_up_time=0.0),
                       numerics=replace(defaults.numerics, dt=1e-5 / 3, convection="oseen",
                                        max_nonlinear_iterations=4))
    text = scenario_to_toml(scenario)
    loaded = load_scenario(write_toml(text))
    assert loaded == scenario
    assert type(loaded.numerics.max_nonlinear_iterations) is int


def test_written_toml_holds_plain_si_numbers():
    document = tomllib.loads(scenario_to_toml(Scenario()))
    assert set(document) == {"channel", "fluid", "saw", "numerics", "cell_types"}
    assert document["fluid"]["viscosity"] == Scenario().fluid.viscosity
    assert document["numerics"]["max_nonlinear_iterations"] == Scenario().numerics.max_nonlinear_iterations
    assert all(isinstance(value, float) for value in document["channel"]["inlets"][0]["span"])
    assert len(document["channel"]["inlets"]) == len(Scenario().channel.inlets)


# --- errors: files, keys, values, types, indices ------------------------------------------------


def test_unknown_key_in_file_names_the_field_and_the_known_ones(write_toml):
    error = scenario_error(write_toml("[fluid]\nviscocity = 1e-3\n"))
    assert str(error) == "fluid.viscocity: unknown field; known fields: density, viscosity"


def test_unknown_override_key_gives_the_same_message():
    error = scenario_error(overrides=["fluid.viscocity=1e-3"])
    assert str(error) == "fluid.viscocity: unknown field; known fields: density, viscosity"


@pytest.mark.parametrize("text, field, words", [
    ("[fluids]\ndensity = 1\n", "fluids", "unknown field"),
    ("[channel.saw_window]\nwidth = 1\n", "channel.saw_window.width", "known fields: cutoff, span"),
    ('[[channel.inlets]]\nname = "a"\nspan = [1e-5, 2e-5]\nv_hat = 0.1\nvhat = 1\n', "channel.inlets[0].vhat",
     "unknown field"),
    ('[[channel.inlets]]\nname = "a"\nspan = [1e-5, 2e-5]\n', "channel.inlets[0].v_hat", "missing"),
    ('[fluid]\ndensity = "heavy"\n', "fluid.density", "cannot read 'heavy' as a number"),
    ('[fluid]\ndensity = true\n', "fluid.density", "must be a number"),
    ('[numerics]\ndt = "25 parsec"\n', "numerics.dt", "is a length, but numerics.dt is a time"),
    ('[numerics]\nmax_nonlinear_iterations = "many"\n', "numerics.max_nonlinear_iterations", "integer"),
    ('[numerics]\nconvection = 3\n', "numerics.convection", "must be a string"),
    ('[channel.saw_window]\nspan = ["140 um"]\n', "channel.saw_window.span", "must have 2 entries"),
    ('[channel.saw_window]\nspan = "140 um"\n', "channel.saw_window.span", "must be an array"),
    ('[channel.saw_window]\nspan = ["140 um", "x"]\n', "channel.saw_window.span[1]", "cannot read 'x'"),
    ("fluid = 3\n", "fluid", "must be a table"),
    ("[channel]\ninlets = 3\n", "channel.inlets", "must be an array"),
])
def test_file_errors_name_the_full_field(write_toml, text, field, words):
    error = scenario_error(write_toml(text))
    assert error.field == field
    assert str(error).startswith(f"{field}: ")
    assert words in str(error)


@pytest.mark.parametrize("override, field, words", [
    ("numerics.dt=fast", "numerics.dt", "cannot read 'fast' as a number"),
    ("numerics.dt=", "numerics.dt", "cannot read '' as a number"),
    ("numerics.dt=[1, 2]", "numerics.dt", "must be a number"),
    ("numerics.max_nonlinear_iterations=2.5", "numerics.max_nonlinear_iterations", "must be an integer"),
    ("numerics.max_nonlinear_iterations=true", "numerics.max_nonlinear_iterations", "must be an integer"),
    ("channel.inlets.0.name=3", "channel.inlets[0].name", "must be a string"),
    ("channel.inlets.0.span=[1um]", "channel.inlets[0].span", "must have 2 entries"),
    ("channel.inlets.3.v_hat=0.1", "channel.inlets[3]", "index out of range; channel.inlets has 3 entries"),
    ("channel.inlets.0.span.2=1um", "channel.inlets[0].span[2]", "index out of range"),
    ("channel.inlets.first.v_hat=0.1", "channel.inlets", "0-based index"),
    ("channel.inlets.0.speed=0.1", "channel.inlets[0].speed", "known fields: cutoff, name, span, tilt, v_hat"),
    ("fluid.density.value=3", "fluid.density", "has no part 'value'"),
    ("saw=3", "saw", "must be a table"),
    ("numerics.dt", "numerics.dt", "dotted.path=value"),
    ("numerics..dt=1", "numerics..dt=1", "dotted.path=value"),
    ("nothing=1", "nothing", "known fields: cell_types, channel, fluid, numerics, saw"),
])
def test_override_errors_name_the_full_field(override, field, words):
    error = scenario_error(overrides=[override])
    assert error.field == field
    assert str(error).startswith(f"{field}: ")
    assert words in str(error)


def test_missing_file_is_named(tmp_path):
    missing = tmp_path / "x.toml"
    error = scenario_error(missing)
    assert f"scenario file '{missing}' does not exist" in str(error)


def test_directory_instead_of_file_is_a_scenario_error(tmp_path):
    error = scenario_error(tmp_path)
    assert str(tmp_path) in str(error)


def test_toml_syntax_error_names_the_file_and_line(write_toml):
    path = write_toml('[fluid]\nviscosity = 1 mPa s\n', name="broken.toml")
    error = scenario_error(path)
    assert "broken.toml" in str(error)
    assert "line 2" in str(error)


def test_file_that_is_not_utf8_is_a_scenario_error(tmp_path):
    path = tmp_path / "latin.toml"
    path.write_bytes(b'[channel]\ninjection_inlet = "\xe9"\n')
    assert "latin.toml" in str(scenario_error(path))


# --- errors from the dataclasses' own validation, with their path ------------------------------


def test_negative_viscosity_is_prefixed():
    error = scenario_error(overrides=["fluid.viscosity=-1"])
    assert str(error) == "fluid.viscosity: must be a positive number (got -1.0)"


@pytest.mark.parametrize("overrides, field", [
    (["numerics.dt=0"], "numerics.dt"),
    (["numerics.dt=-2.5us"], "numerics.dt"),
    (["numerics.convection=explicit"], "numerics.convection"),
    (["channel.inlets.2.span=[150um, 230um]"], "channel.inlets[2].span"),
    (["channel.inlets.0.span=[80um, 30um]"], "channel.inlets[0].span"),
    (["channel.inlets.0.tilt=90deg"], "channel.inlets[0].tilt"),
    (["channel.outlets.1.span=[90um, 200um]"], "channel.outlets"),
    (["channel.inlets.1.span=[100um, 105um]", "channel.inlets.1.cutoff=1um"], "numerics.mesh_h"),
    (["numerics.mesh_h=20um"], "numerics.mesh_h"),
    (["channel.saw_window.cutoff=20um"], "channel.saw_window.cutoff"),
    (["channel.saw_window.span=[0, 100um]"], "channel.saw_window.span"),
    (["channel.injection_inlet=inlet9"], "channel.injection_inlet"),
    (["saw.model=laser"], "saw.model"),
])
def test_validation_errors_carry_the_full_path(overrides, field):
    error = scenario_error(overrides=overrides)
    assert error.field == field
    assert str(error).startswith(f"{field}: ")


def test_inlet_beyond_the_wall_in_a_file_is_prefixed(write_toml):
    path = write_toml('[channel]\nheight = "150 um"\n')  # the default third inlet reaches 200 um
    error = scenario_error(path)
    assert error.field.startswith("channel.inlets")
    assert "outside the wall" in str(error)


def test_overlapping_outlets_in_a_file_are_prefixed(write_toml):
    path = write_toml('[[channel.outlets]]\nname = "a"\nspan = ["20 um", "120 um"]\n'
                      '[[channel.outlets]]\nname = "b"\nspan = ["100 um", "200 um"]\n')
    error = scenario_error(path)
    assert error.field == "channel.outlets"
    assert "overlap" in str(error)
