"""Fuzzing every command with generated bad input (hypothesis): random and boundary values, wrong units,
malformed scenario files and sweep specs, crafted MCAP recordings. Whatever comes in, vcyto either accepts
it (it reaches the point where the work would begin, replaced here by a sentinel) or refuses it with exit
status 1 or 2 and one line on stderr: never a traceback, never an "internal error".

``VCYTO_FUZZ_EXAMPLES`` sets the examples per property (default 40: about 10 s for the whole file); the
examples are the same every run unless ``VCYTO_FUZZ_RANDOM=1`` (new ones each run, to search further)."""

import json
import os
from pathlib import Path

import pytest
from guard import names_what_is_wrong, patch_heavy, vcyto_inline
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

EXAMPLES = int(os.environ.get("VCYTO_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=not os.environ.get("VCYTO_FUZZ_RANDOM"),
                database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

BOUNDARY = ["nan", "-nan", "inf", "-inf", "Infinity", "1e308", "-1e308", "1e999", "0", "-0", "-1", "1e-320",
            "9" * 40, "-" + "9" * 40, "", " ", "0x10", "1_000", "1,5", "--", "-", ".", "e5", "1e", "NaN ms"]
UNITS = ["", "um", "µm", "us", "µs", "ms", "s", "Hz", "kHz", "MHz", "m", "nm", "deg", "mPa s", "N/m^3", "kg", "K",
         "furlong", "m**3", "1/s", "%", "cells/s", "bogons"]
numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                    st.integers(min_value=-10**30, max_value=10**30).map(str),
                    st.sampled_from(BOUNDARY))
quantities = st.one_of(st.tuples(numbers, st.sampled_from(UNITS)).map(lambda pair: pair[0] + pair[1]),
                       st.sampled_from(BOUNDARY),
                       st.text(max_size=12))
values = st.one_of(quantities, st.lists(quantities, min_size=0, max_size=4).map(",".join))

STREAM_OPTIONS = ["--rate", "--min-spacing", "--max-time", "--delay", "--lead", "--pulse", "--envelope", "--gate",
                  "--timing-error", "--mode", "--controller",
                  "--noise", "--count", "--seed", "--detection-window", "--mix", "--cells", "--dt", "--mesh-h",
                  "--flush-every", "--field-every", "--window-h", "--name", "--arrivals", "--model",
                  "--controller-timeout", "--realtime"]
SET_FIELDS = ["fluid.viscosity", "fluid.density", "numerics.dt", "numerics.mesh_h", "channel.length",
              "channel.height", "saw.frequency", "saw.amplitude", "channel.inlets.1.v_hat", "channel.inlets.0.tilt",
              "channel.inlets.0.span", "cell_types.0.semi_axes", "numerics.spacing_band", "numerics.max_stretch",
              "cell_types", "numerics.max_nonlinear_iterations", "numerics.reproducible", "saw.model"]
RELAXATION = Path(__file__).parent.parent / "examples" / "scenarios" / "relaxation.toml"
OTHER_COMMANDS = {
    ("paper", "2"): ["--max-time", "--dt", "--mesh-h"],
    ("stability",): ["--cells", "--mesh-sizes"],
    ("relax", "--scenario", str(RELAXATION)): ["--cell", "--time", "--mesh-sizes", "--mesh-h"],
    ("tradeoff", "--output", ""): ["--coupling", "--stiff-capillary", "--pair-gap", "--lone-rbc"],
    ("extremes",): ["--case"],
    ("flow",): ["--mesh-h", "--dt"],
    ("bench", "realtime"): ["--rate", "--duration", "--control-period", "--repeats", "--seed", "--mix"],
    ("bench", "wire"): ["--rate", "--duration", "--realtime-duration", "--min-spacing", "--repeats", "--seed",
                        "--mix"],
    ("bench", "auto"): ["--count", "--rate", "--mix", "--seed"],
    ("bench", "controller"): ["--events"],
    ("bench", "gym"): ["--count", "--rate", "--min-spacing", "--repeats", "--seed"],
    ("bench", "fluid"): ["--repeats"],
    ("bench", "treatments"): ["--steps"],
    ("bench", "coupling"): ["--steps", "--repeats", "--dt", "--mesh-h"],
    ("bench", "sweep"): ["--workers", "--repeats"],
    ("bench", "sort"): ["--counts", "--rate", "--seed"],
    ("bench", "recorders"): ["--count", "--rate", "--repeats", "--seed"],
    ("calibrate", "--output", ""): ["--model", "--pulse", "--lead", "--pulse-range", "--pulse-step", "--lead-step",
                                    "--offset-step", "--offset-range", "--resolution", "--controller", "--gate"],
    ("sweep", "SPEC"): ["--workers", "--chunk", "--scheduler"],
}


@pytest.fixture
def sandbox(monkeypatch, tmp_path):
    patch_heavy(monkeypatch)
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.toml"
    spec.write_text("[parameters]\nlead = [0.25, 0.5]\n")
    return tmp_path


def check(argv):
    status, _, stderr = vcyto_inline(argv)
    if status is None or status == 0:                  # accepted (the work would begin here)
        assert "Traceback" not in stderr and "internal error" not in stderr, (argv, stderr)
        return
    lines = stderr.strip().splitlines()
    assert status in (1, 2), (argv, status, stderr)
    assert len(lines) == 1 and lines[0].startswith("vcyto: error: "), (argv, stderr)
    assert names_what_is_wrong(lines[0]), (argv, stderr)
    assert "Traceback" not in stderr and "internal error" not in stderr, (argv, stderr)


@FUZZ
@given(options=st.lists(st.tuples(st.sampled_from(STREAM_OPTIONS), values), min_size=1, max_size=3),
       overrides=st.lists(st.tuples(st.sampled_from(SET_FIELDS), values), max_size=2))
def test_stream_options_and_overrides(sandbox, options, overrides):
    argv = ["stream", "--output", str(sandbox / "out"), "--no-viewer", "--model", "rom"]
    for option, value in options:
        argv += [option, value]
    for field, value in overrides:
        argv += ["--set", f"{field}={value}"]
    check(argv)


@FUZZ
@given(command=st.sampled_from(sorted(OTHER_COMMANDS)), data=st.data())
def test_every_other_command(sandbox, command, data):
    options = data.draw(st.lists(st.tuples(st.sampled_from(OTHER_COMMANDS[command]), values), min_size=1, max_size=3))
    argv = [str(sandbox / "spec.toml") if word == "SPEC" else word for word in command]
    for option, value in options:
        argv += [option, value]
    check(argv)


toml_scalars = st.one_of(st.floats(), st.integers(min_value=-10**20, max_value=10**20), st.booleans(),
                         st.text(max_size=10), quantities)
toml_values = st.recursive(toml_scalars, lambda inner: st.lists(inner, max_size=3), max_leaves=6)
SECTIONS = {"channel": ["length", "height", "injection_inlet", "profile_reading", "inlets", "outlets"],
            "fluid": ["density", "viscosity"], "saw": ["model", "frequency", "amplitude", "streaming_force"],
            "numerics": ["mesh_h", "dt", "convection", "membrane_spacing", "spacing_band", "max_stretch"],
            "bogus": ["x"]}


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return {"nan": "nan", "inf": "inf", "-inf": "-inf"}.get(repr(value), repr(value))
    if isinstance(value, list):
        return "[" + ", ".join(_toml(item) for item in value) + "]"
    return json.dumps(value) if isinstance(value, str) else str(value)


@FUZZ
@given(tables=st.dictionaries(st.sampled_from(sorted(SECTIONS)), st.data(), max_size=3),
       garbage=st.one_of(st.none(), st.binary(max_size=64)))
def test_scenario_files(sandbox, tables, garbage):
    path = sandbox / "scenario.toml"
    if garbage is not None:
        path.write_bytes(garbage)
    else:
        lines = []
        for section, data in tables.items():
            lines.append(f"[{section}]")
            for key in data.draw(st.lists(st.sampled_from(SECTIONS[section]), max_size=3, unique=True)):
                lines.append(f"{key} = {_toml(data.draw(toml_values))}")
        path.write_text("\n".join(lines) + "\n")
    check(["stream", "--scenario", str(path), "--output", "", "--no-viewer"])


@FUZZ
@given(parameters=st.dictionaries(st.sampled_from(["lead", "pulse", "rate", "seed", "count", "saw.frequency",
                                                   "fluid.viscosity", "nonsense", "scenario"]),
                                  st.one_of(toml_values,
                                            st.fixed_dictionaries({"start": toml_scalars, "stop": toml_scalars,
                                                                   "num": st.integers(-5, 10**9)}),
                                            st.fixed_dictionaries({"uniform": toml_values})), max_size=3),
       base=st.dictionaries(st.sampled_from(["model", "scenario", "cells", "lead", "set", "max_time", "count"]),
                            toml_values, max_size=2),
       sweep=st.dictionaries(st.sampled_from(["metrics", "plot", "sampling", "samples", "sampling_seed"]),
                             toml_values, max_size=2))
def test_sweep_specs(sandbox, parameters, base, sweep):
    lines = []
    for name, table in (("base", base), ("sweep", sweep)):
        lines.append(f"[{name}]")
        lines += [f"{key} = {_toml(value)}" for key, value in table.items()]
    lines.append("[parameters]")
    for key, value in parameters.items():
        text = ("{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}") if isinstance(value, dict) \
            else _toml(value)
        lines.append(f'"{key}" = {text}')
    spec = sandbox / "fuzzed.toml"
    spec.write_text("\n".join(lines) + "\n")
    check(["sweep", str(spec), "--output", str(sandbox / "sweep-out")])


TOPICS = ["/loop/step", "/cells", "/loop/steps", "/cells/rows", "/detector/event", "/controller/decision", "/outcome",
          "/flow/velocity", "/detector/events", "/controller/decisions", "/outcomes"]
payloads = st.dictionaries(st.sampled_from(["time", "step", "idt", "cells", "key", "classification", "fluorescence",
                                            "event_id", "action", "type", "outlet", "shape", "x_um", "y_um"]),
                           st.one_of(toml_scalars, st.lists(st.integers(-3, 3), max_size=3),
                                     st.lists(st.dictionaries(st.sampled_from(["key", "fate", "x_um"]), toml_scalars),
                                              max_size=2)), max_size=6)


@FUZZ
@given(messages=st.lists(st.tuples(st.sampled_from(TOPICS), payloads), max_size=6),
       metadata=st.dictionaries(st.sampled_from(["scenario_toml", "detector", "seed", "recording_format"]),
                                st.text(max_size=30), max_size=2),
       cut=st.one_of(st.none(), st.integers(0, 400)))
def test_crafted_recordings(sandbox, messages, metadata, cut):
    from mcap.writer import Writer
    path = sandbox / "crafted.mcap"
    with open(path, "wb") as handle:
        writer = Writer(handle)
        writer.start(profile="", library="fuzz")
        channels = {topic: writer.register_channel(topic, "json", writer.register_schema(topic, "jsonschema", b"{}"))
                    for topic in TOPICS}
        writer.add_metadata("run", metadata)
        for index, (topic, payload) in enumerate(messages):
            writer.add_message(channels[topic], log_time=index, publish_time=index,
                               data=json.dumps(payload, allow_nan=True).encode())
        writer.finish()
    if cut is not None:
        path.write_bytes(path.read_bytes()[:cut])
    saved = sandbox / f"view-{len(list(sandbox.glob('view-*')))}.rrd"
    check(["replay", str(path), "--save", str(saved)])


# --- NaN for every quantity option: the same refusal, naming the option ---------------------------------------

STREAM_QUANTITIES = ["--rate", "--min-spacing", "--max-time", "--delay", "--lead", "--pulse", "--timing-error",
                     "--window-h", "--tolerance", "--gate", "--noise"]
NAN_OPTIONS = [("stream", option) for option in STREAM_QUANTITIES] + [
    ("paper", "2", "--tolerance"), ("paper", "2", "--max-time"), ("bench", "realtime", "--duration"),
    ("bench", "realtime", "--control-period"), ("calibrate", "--pulse-step"), ("calibrate", "--resolution")]


@pytest.mark.parametrize("words", NAN_OPTIONS, ids=" ".join)
def test_nan_is_not_a_finite_value_of_the_option_it_was_given_to(sandbox, words):
    *command, option = words
    status, _, stderr = vcyto_inline([*command, option, "nan"])
    assert status == 2 and len(stderr.strip().splitlines()) == 1, stderr
    assert stderr.startswith(f"vcyto: error: {option}: 'nan' is not a finite "), stderr
