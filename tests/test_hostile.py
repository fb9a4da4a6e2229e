"""Hostile input to every reader and command: units that would have pint compute without end, magnitudes beyond
physical sense, files nested or sized to exhaust the stack or memory, recordings that decode to gigabytes. Each
is refused in one line (exit 1 or 2) within a bound of time, never accepted silently, never an internal error.

Every source of a quantity is covered (an option, ``--set``, a scenario file, a controller file, a sweep spec's
values, lists, ranges and distributions, a recording's stored scenario), with hypothesis drawing the hostile text.
"""

import json
import os
import time

import pytest
from guard import assert_one_line_refusal, patch_heavy, vcyto_inline
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_fuzz import OTHER_COMMANDS

EXAMPLES = int(os.environ.get("VCYTO_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=not os.environ.get("VCYTO_FUZZ_RANDOM"),
                database=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
BOUND_S = 10.0        # far above the milliseconds a refusal takes; a unit pint evaluated would take for ever

# units with an exponent expression pint would evaluate (9^9^9 has ~370 million digits), nested or repeated
powers = st.sampled_from(["9^9^9", "(9^9^9)", "99", "9**9**9", "(9)^(9)", "-(9^9)", "2^64", "10"])
names = st.sampled_from(["um", "ms", "s", "m", "Hz", "kHz", "N/m", "mPa s", "kg/m", "cells/s"])
exponent_units = st.builds(lambda name, power, joint: f"{name}{joint}{power}", names, powers,
                           st.sampled_from(["^", "**", " ^ "]))
nested_units = st.builds(lambda name, depth: "(" * depth + name + ")" * depth, names, st.integers(2, 30))
long_units = st.builds(lambda name, count: "*".join([name] * count), names, st.integers(12, 400))
hostile_units = st.one_of(exponent_units, nested_units, long_units)
numbers = st.sampled_from(["1", "0.5", "2.5", "30", "-1"])
hostile_quantities = st.one_of(
    st.builds(lambda number, unit, space: f"{number}{space}{unit}", numbers, hostile_units, st.sampled_from(["", " "])),
    # magnitudes beyond physical sense for every dimension (the units being right)
    st.builds(lambda exponent, unit: f"1e{exponent} {unit}", st.sampled_from([300, -300, 30, -40, 200, -200]),
              st.sampled_from(["s", "ms", "um", "m", "Hz", "mPa s", "N/m^3", "m/s"])),
    st.builds(lambda digits: "1" + "0" * digits, st.integers(120, 5000)))


@pytest.fixture
def sandbox(monkeypatch, tmp_path):
    patch_heavy(monkeypatch)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def refused_in_time(argv, allowed=(1, 2)):
    """``vcyto argv`` is refused in one line, fast."""
    started = time.monotonic()
    status, _, stderr = vcyto_inline(argv)
    assert time.monotonic() - started < BOUND_S, argv
    assert status is not None, f"accepted: {argv}"                  # never silently
    assert_one_line_refusal(status, stderr, allowed)
    return stderr


OPTIONS = ["--mesh-h", "--dt", "--lead", "--delay", "--pulse", "--rate", "--min-spacing", "--max-time", "--window-h",
           "--tolerance", "--timing-error"]
FILE_FIELDS = ["numerics.mesh_h", "numerics.dt", "fluid.viscosity", "fluid.density", "saw.frequency",
               "saw.streaming_force", "channel.length", "channel.height"]
SET_FIELDS = ["numerics.mesh_h", "numerics.dt", "fluid.viscosity", "fluid.density", "saw.frequency",
              "saw.streaming_force", "channel.length", "channel.inlets.1.v_hat", "cell_types.0.kappa_b"]
CONTROLLER_FIELDS = ["delay", "lead", "pulse", "timing_error"]


@FUZZ
@given(option=st.sampled_from(OPTIONS), value=hostile_quantities)
def test_options(sandbox, option, value):
    refused_in_time(["stream", "--output", "", "--no-viewer", "--model", "rom", option, value])


@FUZZ
@given(field=st.sampled_from(SET_FIELDS), value=hostile_quantities, command=st.sampled_from(["stream", "scenario"]))
def test_overrides(sandbox, field, value, command):
    extra = ["--output", "", "--no-viewer"] if command == "stream" else []
    refused_in_time([command, *extra, "--set", f"{field}={value}"])


@FUZZ
@given(field=st.sampled_from(FILE_FIELDS), value=hostile_quantities)
def test_scenario_files(sandbox, field, value):
    table, key = field.split(".")
    (sandbox / "scenario.toml").write_text(f'[{table}]\n{key} = "{value}"\n')
    refused_in_time(["scenario", "--scenario", "scenario.toml"])


@FUZZ
@given(field=st.sampled_from(CONTROLLER_FIELDS), value=hostile_quantities)
def test_controller_files(sandbox, field, value):
    (sandbox / "controller.toml").write_text(f'[controller]\n{field} = "{value}"\n')
    refused_in_time(["stream", "--output", "", "--no-viewer", "--model", "rom", "--controller", "controller.toml"])


@FUZZ
@given(name=st.sampled_from(["lead", "delay", "rate", "saw.streaming_force", "fluid.viscosity"]),
       value=hostile_quantities, form=st.sampled_from(["value", "list", "range", "step", "uniform", "log_uniform"]))
def test_sweep_specs(sandbox, name, value, form):
    quoted = json.dumps(value)
    text = {"value": quoted, "list": f"[{quoted}, {quoted}]",
            "range": f"{{start = {quoted}, stop = {quoted}, num = 2}}",
            "step": f"{{start = {quoted}, stop = {quoted}, step = {quoted}}}",
            "uniform": f"{{uniform = [{quoted}, {quoted}]}}",
            "log_uniform": f"{{log_uniform = [{quoted}, {quoted}]}}"}[form]
    sampling = '[sweep]\nsampling = "random"\nsamples = 2\n' if "uniform" in form else ""
    (sandbox / "spec.toml").write_text(f'{sampling}[parameters]\n"{name}" = {text}\n')
    refused_in_time(["sweep", "spec.toml", "--output", str(sandbox / "out")])


@FUZZ
@given(data=st.data(), value=hostile_quantities)
def test_every_other_command(sandbox, data, value):
    """The options of every other command (``test_fuzz.OTHER_COMMANDS``), each given a hostile quantity."""
    (sandbox / "spec.toml").write_text("[parameters]\nlead = [0.25, 0.5]\n")
    command = data.draw(st.sampled_from(sorted(OTHER_COMMANDS)))
    option = data.draw(st.sampled_from(OTHER_COMMANDS[command]))
    argv = [str(sandbox / "spec.toml") if word == "SPEC" else word for word in command]
    refused_in_time([*argv, option, value])


def _recording(path, metadata=None, messages=(), compression="zstd", chunk_size=1 << 20):
    from mcap.writer import CompressionType, Writer
    kinds = {"zstd": CompressionType.ZSTD, "none": CompressionType.NONE}
    with open(path, "wb") as handle:
        writer = Writer(handle, compression=kinds[compression], chunk_size=chunk_size)
        writer.start(profile="", library="test")
        schema = writer.register_schema("step", "jsonschema", b"{}")
        channels = {}
        writer.add_metadata("run", metadata or {})
        for index, (topic, data) in enumerate(messages):
            if topic not in channels:
                channels[topic] = writer.register_channel(topic, "json", schema)
            writer.add_message(channels[topic], log_time=index, publish_time=index, data=data)
        writer.finish()
    return path


@FUZZ
@given(value=hostile_quantities, field=st.sampled_from(["fluid.viscosity", "numerics.mesh_h", "saw.frequency"]))
def test_a_recordings_stored_scenario(sandbox, value, field):
    table, key = field.split(".")
    path = _recording(sandbox / "stored.mcap", {"scenario_toml": f'[{table}]\n{key} = "{value}"\n'},
                      [("/loop/step", b'{"time": 0.0, "step": 0, "idt": 0.0}')])
    saved = sandbox / f"view-{time.monotonic_ns()}.rrd"
    refused_in_time(["replay", str(path), "--save", str(saved)])


# --- depths and sizes ------------------------------------------------------------------------------------------

DEEP = "[" * 3000 + "]" * 3000


@pytest.mark.parametrize("where", ["scenario", "controller", "spec", "stored scenario"])
def test_toml_nested_thousands_deep_is_one_line_from_every_reader(sandbox, where):
    text = f"x = {DEEP}\n"
    if where == "scenario":
        (sandbox / "deep.toml").write_text(f"[fluid]\n{text}")
        argv = ["scenario", "--scenario", "deep.toml"]
    elif where == "controller":
        (sandbox / "deep.toml").write_text(f"[controller]\n{text}")
        argv = ["stream", "--output", "", "--no-viewer", "--controller", "deep.toml"]
    elif where == "spec":
        (sandbox / "deep.toml").write_text(f"[parameters]\nlead = {DEEP}\n")
        argv = ["sweep", "deep.toml", "--output", str(sandbox / "out")]
    else:
        _recording(sandbox / "deep.mcap", {"scenario_toml": text})
        argv = ["replay", "deep.mcap", "--save", str(sandbox / "deep.rrd")]
    assert "too deeply" in refused_in_time(argv)


def test_a_table_nested_beyond_the_bound_is_refused_even_where_python_would_parse_it(sandbox):
    from vcyto.config import MAX_DEPTH
    (sandbox / "deep.toml").write_text(f"[fluid]\nx = {'[' * (MAX_DEPTH + 1)}{']' * (MAX_DEPTH + 1)}\n")
    assert f"at most {MAX_DEPTH} levels" in refused_in_time(["scenario", "--scenario", "deep.toml"])


def test_a_json_message_nested_100000_deep_is_one_line(sandbox):
    deep = b"[" * 100_000 + b"]" * 100_000
    _recording(sandbox / "deep.mcap", {}, [("/loop/step", b'{"time": 0.0, "step": 0, "idt": 0.0}'),
                                          ("/loop/step", deep)])
    stderr = refused_in_time(["replay", "deep.mcap", "--save", str(sandbox / "deep.rrd")])
    assert "/loop/step message nests its JSON" in stderr and "more than 1,024 levels deep (the limit" in stderr
    assert not (sandbox / "deep.rrd").exists()                     # refused, not replayed as "damaged"


def test_a_json_message_at_the_depth_limit_is_read():
    from vcyto.recording.replay import MAX_JSON_DEPTH, _decode
    depth = MAX_JSON_DEPTH
    assert _decode("/loop/step", b"[" * depth + b"]" * depth) is not None


def _one_chunk_recording(path, data: bytes, claimed: int):
    """An MCAP of a header, the run metadata, one zstd chunk of ``data`` claiming ``claimed`` bytes decompressed
    and a footer: written record by record (no writer makes a chunk it did not compress)."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, DataEnd, Footer, Header, Metadata
    builder = RecordBuilder()
    for record in (Header(profile="", library="test"), Metadata(name="run", metadata={}),
                   Chunk(message_start_time=0, message_end_time=0, uncompressed_size=claimed, uncompressed_crc=0,
                         compression="zstd", data=data),
                   DataEnd(data_section_crc=0), Footer(summary_start=0, summary_offset_start=0, summary_crc=0)):
        record.write(builder)
    magic = bytes([0x89]) + b"MCAP0\r\n"
    path.write_bytes(magic + builder.end() + magic)
    return path


def test_a_chunk_that_decompresses_to_gigabytes_is_not_decompressed(sandbox):
    """A gigabyte of zeros compresses to a few tens of kB: the chunk's claimed size, and what its frame yields
    beyond that claim, are checked against the bound before more is decompressed."""
    import tracemalloc

    import zstandard

    from vcyto.recording.replay import MAX_CHUNK_BYTES
    compressor = zstandard.ZstdCompressor(level=1).compressobj()
    block = b"\0" * (16 << 20)
    count = 4 * MAX_CHUNK_BYTES // len(block)
    compressed = b"".join(compressor.compress(block) for _ in range(count)) + compressor.flush()
    for claimed in (count * len(block), 1000):             # the truth, and a lie
        path = _one_chunk_recording(sandbox / f"bomb-{claimed}.mcap", compressed, claimed)
        tracemalloc.start()
        started = time.monotonic()
        status, out, err = vcyto_inline(["replay", str(path), "--save", str(sandbox / f"bomb-{claimed}.rrd")])
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert time.monotonic() - started < 60 and "internal error" not in err and "Traceback" not in err, err
        assert peak < 64 << 20, peak
        assert status in (1, 2) or "damaged" in out, (status, out, err)


def test_a_flow_message_whose_grid_spans_kilometres_is_refused_not_drawn(sandbox):
    zeros = "AAAAAAAAAAAAAAAAAAAAAA=="                     # four float32 zeros
    message = {"time": 0.0, "shape": [2, 2], "x_um": [0.0, 1e9], "y_um": [0.0, 1e9], "vx_f32_b64": zeros,
               "vy_f32_b64": zeros, "p_f32_b64": zeros}
    _recording(sandbox / "wide.mcap", {}, [("/loop/step", b'{"time": 0.0, "step": 0, "idt": 0.0}'),
                                          ("/flow/velocity", json.dumps(message).encode())])
    assert "flow/velocity" in refused_in_time(["replay", "wide.mcap", "--save", str(sandbox / "wide.rrd")])


def test_a_foreign_mcap_is_not_replayed_as_zero_steps(sandbox):
    from mcap.writer import Writer
    with open(sandbox / "foreign.mcap", "wb") as handle:      # no run metadata, a channel vcyto never writes
        writer = Writer(handle)
        writer.start(profile="", library="other")
        channel = writer.register_channel("/camera/info", "json", writer.register_schema("x", "jsonschema", b"{}"))
        writer.add_message(channel, log_time=0, publish_time=0, data=b"{}")
        writer.finish()
    stderr = refused_in_time(["replay", "foreign.mcap", "--save", str(sandbox / "foreign.rrd")])
    assert "not a vcyto MCAP recording" in stderr


def test_replay_memory_does_not_grow_with_the_recordings_length(sandbox):
    """Replay decodes one message at a time: a recording ten times longer costs far less than ten times the Python
    memory (a reader keeping every decoded message holds 3.3 MB at 300 steps and 35 MB at 3,000; this
    reader 1-4 MB, the rest
    being the Rerun view's batches and what other threads of the test process allocate meanwhile)."""
    import tracemalloc

    from vcyto.recording.replay import replay
    def cells(step):          # twenty cells in the channel, each for twenty steps, then it leaves
        return json.dumps({"time": step * 1e-4, "cells": [
            {"key": key, "type": "RBC", "x_um": float(step - key), "y_um": 1.0, "fate": "in_channel",
             "area_ratio": 1.0, "class": "passed"} for key in range(max(0, step - 19), step + 1)]}).encode()
    peaks = []
    for steps in (30, 300, 3000):                       # the first warms up what a replay sets up once
        messages = []
        for step in range(steps):
            messages += [("/loop/step", json.dumps({"time": step * 1e-4, "step": step, "idt": 0.0}).encode()),
                         ("/cells", cells(step))]
            if step >= 20:                              # the cell that leaves now
                messages.append(("/outcome", json.dumps({"key": step - 20, "type": "RBC", "outlet": "lower",
                                                         "class": "passed"}).encode()))
        path = _recording(sandbox / f"long-{steps}.mcap", {}, messages, chunk_size=64 << 10)
        tracemalloc.start()
        result = replay(path, ("save", str(sandbox / f"long-{steps}.rrd")))
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
        assert result["steps"] == steps
    assert peaks[2] < 5 * peaks[1], peaks


def test_a_file_larger_than_the_bound_is_refused_unread(sandbox):
    from vcyto.config import MAX_FILE_BYTES
    (sandbox / "big.toml").write_text("# padding\n" * (MAX_FILE_BYTES // 10 + 1))
    assert "bytes" in refused_in_time(["scenario", "--scenario", "big.toml"])
    assert "bytes" in refused_in_time(["sweep", "big.toml", "--output", str(sandbox / "out")])


# --- the others: each a one-line error, or a documented behaviour ---------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["stream", "--rate", "1e-300"], "--rate: '1e-300' is beyond physical sense for a frequency"),
    (["stream", "--rate", "1e-5"], "of device time"),                       # two cells, 1.2 days: refused
    (["stream", "--model", "rom", "--count", "100000001", "--mix", "RBC:1"], "at most 100,000,000 cells"),
    (["bench", "sort", "--counts", "1000,100000001"], "--counts: wants positive cell counts (at most 100,000,000)"),
    (["stream", "--gate", "1e308"], "--gate: '1e308' is beyond physical sense"),
    (["stream", "--cells", "RBC,,melanoma"], "--cells: an empty entry"),
    (["stream", "--cells", "RBC,"], "--cells: an empty entry"),
    (["stream", "--viewer-bind", "999.1.1.1"], "--viewer-bind: '999.1.1.1' is not an IP address"),
    (["flow", "--png", "x.txt"], "--png: x.txt does not end in .png"),
    (["stream", "--output", "/tmp/" + "x" * 5000], "--output: cannot use the directory"),
])
def test_other_bad_input_is_one_line(sandbox, argv, words):
    if argv[0] == "stream":
        argv = [*argv, *([] if "--output" in argv else ["--output", ""]), "--no-viewer", "--model", "rom"]
    assert words in refused_in_time(argv, allowed=(2,))


@pytest.mark.parametrize("name", ["VCYTO_CACHE", "VCYTO_C_KERNELS", "VCYTO_PREFETCH"])
def test_a_switch_set_to_what_it_does_not_take_is_refused(sandbox, monkeypatch, name):
    monkeypatch.setenv(name, "maybe")
    assert f"{name}: 'maybe' is not a value of this switch" in refused_in_time(["scenario"], allowed=(2,))
    monkeypatch.setenv(name, "0")
    assert vcyto_inline(["scenario"])[0] == 0


@pytest.mark.parametrize("line, words", [
    ('delay = "1e300 s"', "controller.delay: '1e300 s' is beyond physical sense for a time"),
    ('delay = "2 day"', "controller.delay: 1.728e+08 ms is more than 10 ms"),
    ('pulse = "1e-300 s"', "controller.pulse: '1e-300 s' is beyond physical sense"),
    ('envelope = ["-1 s", "1 s"]', "controller.envelope: offsets -1000, 1000 ms reach beyond"),
    ('lead = "0.3 ms^(9^9^9)"', "cannot read the unit"),
])
def test_controller_files_beyond_sense_are_one_line(sandbox, line, words):
    (sandbox / "controller.toml").write_text(f"[controller]\n{line}\n")
    stderr = refused_in_time(["stream", "--output", "", "--no-viewer", "--model", "rom", "--controller",
                              "controller.toml"])
    assert words in stderr, stderr


def test_a_pulse_far_shorter_than_the_drives_spin_up_is_said(sandbox):
    """A pulse the SAW drive cannot follow (a tenth of its spin-up time or less) is accepted, with a note."""
    from controller.sorter import ControllerSettings
    from sim.model.arrivals import Arrivals
    from sim.model.scenario import Scenario
    from vcyto.options import short_pulse_note
    from vcyto.stream import StreamSettings
    scenario = Scenario()
    short = ControllerSettings(pulse=scenario.saw.spin_up_time / 20)
    assert "less than a tenth of the SAW drive's spin-up time" in short_pulse_note(short, scenario)
    assert short_pulse_note(ControllerSettings(), scenario) is None
    assert StreamSettings(Arrivals(cells=("RBC",)))          # the settings themselves take it
