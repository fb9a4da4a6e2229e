"""Recordings that open anywhere: the MCAP against its schemas and through Rerun's MCAP importer, the Rerun view
of the sort (plant coordinates, classes, event markers), replay of both recording formats."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from rerun.chunk import RrdReader

from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario
from sim.plants.feib import FeibPlant
from vcyto.classes import CLASS_COLOURS, CLASS_IDS
from vcyto.outcomes import outcome_class
from vcyto.recording.mcap import FORMAT, McapRecorder
from vcyto.recording.replay import happenings
from vcyto.recording.rerunlog import RerunSink
from vcyto.stream import StreamSettings, run_stream

FOXGLOVE = {"/foxglove/scene": "foxglove.SceneUpdate", "/foxglove/membranes": "foxglove.PointCloud",
            "/foxglove/speed": "foxglove.RawImage", "/foxglove/log": "foxglove.Log"}
OLD = Path(__file__).parent / "data" / "format1-streamline.mcap"
# a rom stream of 30 cells recorded in format 3 (one message per event, decision and outcome)
FORMAT3 = Path(__file__).parent / "data" / "format3-rom.mcap"


class Capture:
    """A sink that keeps the plant's membranes (um) per step."""
    field_every = 0

    def __init__(self):
        self.membranes = {}

    def on_step(self, record):
        self.membranes[round(record.time * 1e9)] = {c.key: np.asarray(c.membrane) * 1e6 for c in record.truth.cells
                                                    if c.fate == "in_channel" and c.membrane is not None}

    def close(self):
        pass


def recorded_run(directory, settings, plant=None, field_every=0):
    scenario = Scenario()
    capture = Capture()
    recorder = McapRecorder(directory / "run.mcap", {"seed": settings.seed, "detector": settings.detector},
                            field_every=field_every, scenario=scenario)
    viewer = RerunSink(scenario, settings.detector.window, ("save", directory / "live.rrd"), field_every=field_every)
    try:
        result = run_stream(scenario, settings, plant=plant, sinks=[capture, recorder, viewer])
    finally:
        recorder.close()
        viewer.close()
    return {"dir": directory, "result": result, "capture": capture, "recorder": recorder, "viewer": viewer}


@pytest.fixture(scope="module")
def feib(tmp_path_factory):
    """A short FE-IB run (one cell, 100 steps) with the flow field every 25 steps."""
    settings = StreamSettings(Arrivals(cells=("melanoma",)), model="feib", max_time=0.25e-3)
    return recorded_run(tmp_path_factory.mktemp("feib"), settings, plant=FeibPlant(Scenario()), field_every=25)


@pytest.fixture(scope="module")
def sort(tmp_path_factory):
    """A streamline stream dense enough for coincidences (aborts) and both outlets."""
    settings = StreamSettings(Arrivals(count=14, mix=(("RBC", 0.5), ("melanoma", 0.5)), rate=2500.0,
                                       process="poisson", min_spacing=0.1e-3), model="streamline", seed=3)
    return recorded_run(tmp_path_factory.mktemp("sort"), settings)


def mcap_messages(path):
    with open(path, "rb") as handle:
        reader = make_reader(handle)
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        return metadata, list(reader.iter_messages(log_time_order=False))


def rrd_rows(path):
    """entity -> [(sim_time ns or None, {component: value})] of the non-static rows; and the static components."""
    rows, static = {}, {}
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if ":" in n]
        columns = {n: batch.column(n).to_pylist() for n in names}
        if chunk.is_static:
            static.setdefault(chunk.entity_path, {}).update({n: v[-1] for n, v in columns.items()})
            continue
        times = batch.column("sim_time").cast("int64").to_pylist() if "sim_time" in batch.schema.names \
            else [None] * batch.num_rows
        for row, time_ns in enumerate(times):
            rows.setdefault(chunk.entity_path, []).append((time_ns, {n: columns[n][row] for n in names}))
    for entity in rows:
        rows[entity].sort(key=lambda item: item[0] if item[0] is not None else -1)
    return rows, static


@pytest.mark.parametrize("run_name", ["feib", "sort"])
def test_every_message_matches_its_channel_schema_and_geometry_is_foxglove(run_name, request):
    run = request.getfixturevalue(run_name)
    metadata, messages = mcap_messages(run["dir"] / "run.mcap")
    validators, decoders, topics = {}, {}, set()
    for schema, channel, message in messages:
        topics.add(channel.topic)
        if channel.message_encoding == "json":
            validator = validators.setdefault(schema.id, Draft202012Validator(json.loads(schema.data)))
            validator.validate(json.loads(message.data))
        else:
            assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
            decoded = decoders.setdefault(schema.id, DecoderFactory().decoder_for("protobuf", schema))(message.data)
            assert schema.name == FOXGLOVE[channel.topic] == decoded.DESCRIPTOR.full_name
            assert decoded.SerializeToString() == message.data        # nothing the schema does not describe
    expected = set(FOXGLOVE) - ({"/foxglove/speed"} if run_name == "sort" else {"/foxglove/log"})   # no event yet
    assert expected <= topics
    run_metadata = metadata["run"]
    assert all(isinstance(value, str) for value in run_metadata.values())
    assert json.loads(run_metadata["detector"])["window"] == [30e-6, 60e-6]
    origin = int(run_metadata["time_origin_unix_ns"])
    assert min(m.log_time for _, _, m in messages) == origin       # the device, at t = 0


def _rerun_cli():
    found = Path(sys.executable).parent / "rerun"
    return str(found) if found.exists() else shutil.which("rerun")


@pytest.mark.skipif(_rerun_cli() is None, reason="the rerun CLI is not installed")
def test_rerun_mcap_importer_draws_membranes_flow_and_log(feib, sort, tmp_path):
    for run, name in ((feib, "feib"), (sort, "sort")):
        converted = tmp_path / f"{name}.rrd"
        done = subprocess.run([_rerun_cli(), "mcap", "convert", "--disable-raw-fallback", "-o", str(converted),
                               str(run["dir"] / "run.mcap")], capture_output=True, text=True, timeout=300,
                              env={"RERUN_ANALYTICS": "0", "PATH": ""})
        assert done.returncode == 0, done.stderr
        verified = subprocess.run([_rerun_cli(), "rrd", "verify", str(converted)], capture_output=True, text=True,
                                  timeout=300, env={"RERUN_ANALYTICS": "0", "PATH": ""})
        assert verified.returncode == 0, verified.stderr[-2000:]      # e.g. a pose without its position
        rows, _ = _components(converted)
        assert "Points3D:positions" in rows["/foxglove/membranes"]
        if name == "feib":
            assert "Image:buffer" in rows["/foxglove/speed"]
            first = next(iter(run["capture"].membranes.values()))[0]
            points = np.array(rows["/foxglove/membranes"]["Points3D:positions"][0])
            assert np.allclose(points[:, :2] * 1e6, first, atol=1e-3) and np.all(points[:, 2] == 0)   # metres
        else:
            cells = run["result"]["cells"]
            detected = sum(c["detected_class"] is not None for c in cells)
            assert "TextLog:text" in rows["/foxglove/log"]
            assert len(rows["/foxglove/log"]["TextLog:text"]) >= 2 * detected + len(cells)


def path_classes(rows) -> dict:
    """cell key -> class ids of its path, from the path slots' rows (labelled "key: class")."""
    found = {}
    for entity, entries in rows.items():
        if entity.startswith("/device/paths/"):
            for _, values in entries:
                key = int(values["LineStrips2D:labels"][0].split(":")[0])
                assert key not in found, f"cell {key}'s path logged twice"
                found[key] = values["LineStrips2D:class_ids"]
    return found


def _components(path):
    """entity -> component -> values of the rows in file order (static and temporal)."""
    found = {}
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if ":" in name:
                found.setdefault(chunk.entity_path, {}).setdefault(name, []).extend(batch.column(name).to_pylist())
    return found, None


def test_rerun_view_keeps_the_plants_coordinates(feib):
    rows, static = rrd_rows(feib["dir"] / "live.rrd")
    compared = 0
    for time_ns, values in rows["/device/membranes"]:
        if time_ns in feib["capture"].membranes and values.get("LineStrips2D:strips"):
            strip = np.array(values["LineStrips2D:strips"][0])
            plant = feib["capture"].membranes[time_ns][0]
            assert np.allclose(strip[:-1], plant, atol=1e-4)          # float32 of the plant's um, y up, no flip
            compared += 1
    assert compared >= 90
    flip = static["/device"]
    assert flip["Transform3D:scale"] == [[1.0, -1.0, 1.0]] and flip["Transform3D:translation"][0][1] == 220.0
    assert any("DepthImage:buffer" in values for _, values in rows["/device/flow/speed_mm_s"])


def test_each_cell_is_coloured_by_its_outcome_class(sort):
    rows, _ = rrd_rows(sort["dir"] / "live.rrd")
    recorded = {outcome["key"]: outcome["class"] for outcome in happenings(sort["dir"] / "run.mcap")["/outcome"]}
    paths = path_classes(rows)
    assert len(paths) == len(sort["result"]["cells"])            # each cell's path, once, in a slot
    classes = set()
    for cell in sort["result"]["cells"]:
        expected = outcome_class(cell)
        classes.add(expected)
        assert paths[cell["key"]] == [CLASS_IDS[expected]]
        assert recorded[cell["key"]] == expected
    assert {"sorted", "passed"} <= classes and len(classes) >= 3, classes


def test_every_detector_event_is_a_marker_where_and_when_it_happened(sort):
    rows, _ = rrd_rows(sort["dir"] / "live.rrd")
    markers = rows["/device/events"]
    events = sorted(c["detection_time_ms"] for c in sort["result"]["cells"] if c["detection_time_ms"] is not None)
    assert [t for t, _ in markers] == [round(t * 1e6) for t in events]
    for _, values in markers:
        x, _ = values["Points2D:positions"][-1]                       # the newest marker: this event's cell
        assert 60.0 <= x < 70.0                                       # just past the detection window's end


def test_replay_shows_what_the_live_view_shows(sort, tmp_path):
    replayed = tmp_path / "replay.rrd"
    done = subprocess.run([sys.executable, "-m", "vcyto", "replay", str(sort["dir"] / "run.mcap"), "--save",
                           str(replayed), "--json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    live, _ = rrd_rows(sort["dir"] / "live.rrd")
    again, _ = rrd_rows(replayed)
    for entity in ["/idt", "/log", "/device/events", "/pulses/scheduled"] + [e for e in live if "/paths/" in e]:
        assert [t for t, _ in again[entity]] == [t for t, _ in live[entity]], entity
    assert [v for _, v in again["/log"]] == [v for _, v in live["/log"]]          # velocities and reasons too
    assert any("mm/s" in v["TextLog:text"][0] for _, v in again["/log"])
    assert json.loads(done.stdout)["format"] == FORMAT


def test_a_recording_of_the_first_format_still_replays(tmp_path):
    replayed = tmp_path / "old.rrd"
    done = subprocess.run([sys.executable, "-m", "vcyto", "replay", str(OLD), "--save", str(replayed), "--json"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["format"] == "1" and json.loads(done.stdout)["steps"] > 500
    rows, _ = rrd_rows(replayed)
    final = path_classes(rows)
    assert final == {0: [CLASS_IDS["sorted"]], 1: [CLASS_IDS["passed"]], 2: [CLASS_IDS["sorted"]]}
    assert len(rows["/device/events"]) == 3


def test_a_recording_of_the_third_format_replays_every_event_decision_and_outcome(tmp_path):
    """Format 3 wrote an event, a decision and an outcome as one message each; its replay shows a log line for
    each, a marker per event and a path per cell, as the recording has them."""
    written = happenings(FORMAT3)
    assert len(written["/detector/event"]) >= 20 and len(written["/outcome"]) >= 20
    replayed = tmp_path / "format3.rrd"
    done = subprocess.run([sys.executable, "-m", "vcyto", "replay", str(FORMAT3), "--save", str(replayed), "--json"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["format"] == "3" and not json.loads(done.stdout)["damaged"]
    rows, _ = rrd_rows(replayed)
    lines = [v["TextLog:text"][0] for _, v in rows["/log"]]
    assert len(lines) == sum(len(found) for found in written.values())
    assert sum(line.startswith("cell ") and "detected type" in line for line in lines) == \
        len(written["/detector/event"])
    assert len(rows["/device/events"]) == len(written["/detector/event"])
    assert path_classes(rows) == {outcome["key"]: [CLASS_IDS[outcome["class"]]] for outcome in written["/outcome"]}


def test_sinks_keep_only_the_cells_in_the_channel(sort):
    recorder, viewer = sort["recorder"], sort["viewer"]
    assert recorder._paths == {} and recorder._classes._detected == {} and recorder._classes._event_keys == {}
    assert viewer.logger.paths == {} and viewer.logger.positions == {} and viewer.classes._action == {}


def test_the_flow_colours_are_matplotlibs_viridis_and_a_warm_process_needs_no_matplotlib(tmp_path):
    """The speed image and its legend take matplotlib's viridis colours (the table is kept in the set-up cache):
    the same bytes as matplotlib's colouring, NaN black; a second process opens the Rerun view and shows a field
    without importing matplotlib."""
    from matplotlib import colormaps

    from vcyto.recording.rerunlog import viridis
    values = np.concatenate([np.linspace(0.0, 1.0, 20_001), np.arange(257) / 256, (np.arange(256) + 0.999) / 256,
                             [-0.5, 1.5, np.nan, 1 - 1e-12]])
    expected = (colormaps["viridis"](values)[:, :3] * 255).astype(np.uint8)
    assert viridis(values).dtype == np.uint8 and np.array_equal(viridis(values), expected)
    assert np.array_equal(viridis(values[:20_001].reshape(-1, 3)), expected[:20_001].reshape(-1, 3, 3))  # an image
    black = viridis(float("nan"))            # a single value: its own array, the table untouched
    black[...] = 255
    assert np.array_equal(viridis(values), expected) and viridis(0.0).tolist() == expected[0].tolist()
    script = ("import sys; import vcyto.cache as c; c.install_default(); from sim.model.scenario import Scenario; "
              "from vcyto.recording.rerunlog import RerunLogger; from controller.detector import DetectorSettings; "
              "from vcyto.recording.mcap import velocity_field; import numpy as np; "
              "logger = RerunLogger(Scenario(), DetectorSettings().window, ('save', sys.argv[1])); "
              "x, y = np.linspace(0, 300e-6, 4), np.linspace(0, 220e-6, 3); X, Y = np.meshgrid(x, y); "
              "logger.field(velocity_field(np.array([X.ravel(), Y.ravel()]), np.ones((2, 12)) * 0.05, np.zeros(12), "
              "x, y, 0.0)); logger.close(); print('matplotlib' in sys.modules)")
    environment = {**os.environ, "VCYTO_CACHE_DIR": str(tmp_path / "cache")}
    imported = [subprocess.run([sys.executable, "-c", script, str(tmp_path / f"{n}.rrd")], capture_output=True,
                               text=True, env=environment, timeout=120).stdout.strip() for n in range(2)]
    assert imported == ["True", "False"]


def test_a_rerun_recording_does_not_import_pandas_and_pandas_stays_usable(tmp_path):
    """In the vcyto command's own process (``spare_pandas_import``, which ``vcyto.cli.run`` calls) opening a Rerun
    recording (its blueprint is pyarrow's first conversion) leaves pandas unimported where it is installed
    (``vcyto.recording.viewer.import_rerun``: 0.2-0.3 s of a recorded run); pandas then imports as usual, and pyarrow
    converts to and from it; a process that had imported pandas keeps it. A Python user's process is left alone: pyarrow
    imports pandas as usual and converts a categorical Series to a dictionary array."""
    script = ("import sys\nif sys.argv[2] == 'first': import pandas\n"
              "from vcyto.recording import viewer\nif sys.argv[3] == 'command': viewer.spare_pandas_import()\n"
              "from sim.model.scenario import Scenario; from vcyto.recording.rerunlog import RerunLogger\n"
              "from controller.detector import DetectorSettings\n"
              "logger = RerunLogger(Scenario(), DetectorSettings().window, ('save', sys.argv[1]))\n"
              "logger.text('hello'); logger.close(); print('pandas' in sys.modules)\n"
              "import pandas, pyarrow\n"
              "print(pyarrow.table({'a': [1, 2]}).to_pandas()['a'].sum(), pyarrow.array(pandas.Series([3, 4])).type)\n"
              "print(pyarrow.array(pandas.Series(['x', 'y'], dtype='category')).type)")
    for order, process, expected in (("after", "command", "False"), ("first", "command", "True"),
                                     ("after", "library", "True")):
        done = subprocess.run([sys.executable, "-c", script, str(tmp_path / f"{order}-{process}.rrd"), order,
                               process], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        lines = done.stdout.split("\n")
        assert lines[:2] == [expected, "3 int64"], (order, process)
        if process == "library":
            assert lines[2].startswith("dictionary<"), lines[2]         # pyarrow's own pandas conversion
    assert RrdReader(str(tmp_path / "after-command.rrd")) is not None


def test_the_view_draws_pulses_and_drive_as_steps_with_one_value_per_edge(sort):
    """Each pulse the controller scheduled is two rows (1 at its start, 0 at its end, at those times), the drive
    steps at the kept pulses' edges, both drawn with step-after interpolation; purity, yield and abort rate are
    series; the cells' paths keep their labels hidden (drawn, they piled up at the outlets)."""
    rows, static = rrd_rows(sort["dir"] / "live.rrd")
    pulses = [c for c in sort["result"]["cells"] if c["pulse_ms"]]
    kept = [c["pulse_ms"] for c in pulses if c["decision"] == "sort"]
    scheduled = rows["/pulses/scheduled"]
    assert len(scheduled) == 2 * len(pulses) and kept
    edges = sorted((round(t * 1e6), v) for on, off in kept for t, v in ((on, 1.0), (off, 0.0)))
    assert set(edges) <= {(t, row["Scalars:scalars"][0]) for t, row in scheduled}
    drive = [(t, row["Scalars:scalars"][0]) for t, row in rows["/idt"]]
    assert [v for _, v in drive] == [0.0] + [1.0, 0.0] * (len(drive) // 2)       # one row per change
    assert {t for t, v in drive if v == 1.0} <= {t for t, v in edges if v == 1.0}
    step_after = 2                                                               # InterpolationMode.StepAfter
    for entity in ("/idt", "/pulses/scheduled"):
        assert static[entity]["SeriesLines:interpolation_mode"] == [step_after]
    for name in ("purity", "yield", "abort_rate"):
        assert rows[f"/sort/{name}"], name
    last = {name: rows[f"/sort/{name}"][-1][1]["Scalars:scalars"][0] for name in ("purity", "yield")}
    assert last["purity"] == pytest.approx(sort["result"]["statistics"]["purity"])
    assert all(static[f"/device/paths/{slot}"]["LineStrips2D:show_labels"] == [False] for slot in range(16))


def test_the_speed_field_is_a_scalar_image_in_mm_per_s(feib):
    """The flow speed is a DepthImage of float32 mm/s (hovering reads the value), meter 1, viridis, on the
    legend's scale; a point-like plant (no field) shows no legend."""
    rows, static = rrd_rows(feib["dir"] / "live.rrd")
    image = rows["/device/flow/speed_mm_s"][0][1]
    assert "DepthImage:buffer" in image and image["DepthImage:meter"] == [1.0]
    assert image["DepthImage:depth_range"][0][0] == 0.0 and image["DepthImage:depth_range"][0][1] > 10
    assert "/device/legend/bar" in static


def test_foxglove_scene_is_in_metres_with_lifetimes(sort):
    """Foxglove's conventions: the device outline spans the channel's 300 um as 3e-4 m; markers and paths expire."""
    from mcap_protobuf.decoder import DecoderFactory
    _, messages = mcap_messages(sort["dir"] / "run.mcap")
    decode, entities = DecoderFactory(), []
    for schema, channel, message in messages:
        if channel.topic == "/foxglove/scene":
            entities += decode.decoder_for("protobuf", schema)(message.data).entities
    outline = next(e for e in entities if e.id == "device/outline")
    assert max(p.x for p in outline.lines[0].points) == pytest.approx(300e-6)
    temporary = [e for e in entities if e.id.startswith(("event/", "path/"))]
    assert temporary and all(e.lifetime.ToNanoseconds() > 0 for e in temporary)
    assert not outline.HasField("lifetime")


def test_the_per_cell_table_of_the_command_does_not_import_pandas(tmp_path):
    """The per-cell table's writer makes pyarrow's first conversion of a run without a view (its first row group,
    or a short run's exit: 0.26 s measured): in the command's process pandas stays unimported there too."""
    script = ("import sys\nfrom vcyto.recording import viewer\n"
              "if sys.argv[2] == 'command': viewer.spare_pandas_import()\n"
              "from vcyto.celltable import CellTable\n"
              "table = CellTable(sys.argv[1])\ntable.append_columns({'key': [1], 'outlet': 'lower'}, 1)\n"
              "table.close()\n"
              "print('pandas' in sys.modules)")
    imported = [subprocess.run([sys.executable, "-c", script, str(tmp_path / f"{process}.parquet"), process],
                               capture_output=True, text=True, timeout=120).stdout.strip()
                for process in ("command", "library")]
    assert imported == ["False", "True"]


def test_the_view_frames_the_channel_with_its_labels_and_draws_each_figure_as_steps_with_markers():
    """Looked at in the viewer: the channel view's bounds hold the channel and the labels outside it (inlets,
    outlets, SAW window, the colour bar above); purity, yield and abort rate are steps with a marker at each value
    (a run in which one cell was sorted has one value, which a line alone does not draw); the area panel's axis is
    fixed, so a kept area's round-off (1e-12) does not fill it."""
    from vcyto.recording.rerunlog import AREA_RANGE, blueprint
    view = blueprint(True, 300.0, 220.0)
    channel, series = view.root_container.contents
    bounds = channel.properties["VisualBounds2D"].range.as_arrow_array().to_pylist()[0]
    x_low, x_high = bounds["x_range"]
    y_low, y_high = bounds["y_range"]
    assert x_low < 0 and x_high > 300 and y_low < -20 and y_high > 220      # y down in the view: the bar at y < 0
    sort_view = next(v for v in series.contents if v.origin == "sort")
    for entity in ("/sort/purity", "/sort/yield", "/sort/abort_rate"):
        kinds = [type(v).__name__ for v in sort_view.visualizer_overrides[entity]]
        assert kinds == ["SeriesLines", "SeriesPoints"], (entity, kinds)
    area = next(v for v in series.contents if v.origin == "area")
    assert area.properties["ScalarAxis"].range.as_arrow_array().to_pylist()[0] == list(AREA_RANGE)
    assert [v.origin for v in blueprint(False).root_container.contents[1].contents].count("area") == 0


def test_a_cells_log_line_says_how_much_of_its_area_the_projection_restored():
    from vcyto.outcomes import outcome_text
    assert outcome_text(1, "melanoma", "upper", "sorted", 0.0725) == \
        "cell 1 (melanoma) left by: upper (sorted); the area projection restored 7.25 % of its area"
    for nothing in (None, 0.0):
        assert outcome_text(0, "RBC", "lower", "passed", nothing) == "cell 0 (RBC) left by: lower (passed)"


def test_each_area_series_is_named_by_its_cell_and_type(feib):
    _, static = rrd_rows(feib["dir"] / "live.rrd")
    named = {entity: values["SeriesLines:names"] for entity, values in static.items() if entity.startswith("/area/")}
    assert named == {"/area/0": ["cell 0 (melanoma)"]}, named


@settings(max_examples=150, deadline=None)
@given(unix_ns=st.integers(0, 4_000_000_000_000_000_000), x=st.floats(-1e4, 1e4), y=st.floats(-1e4, 1e4),
       label=st.text(max_size=40), rgb=st.sampled_from(sorted(set(CLASS_COLOURS.values()))),
       path=st.lists(st.tuples(st.floats(-1e4, 1e4), st.sampled_from([0.0, -0.0, 1.5, 250.0])), min_size=1,
                     max_size=30), points=st.binary(max_size=64))
def test_the_messages_written_as_bytes_are_those_the_protobuf_classes_serialise(unix_ns, x, y, label, rgb, path,
                                                                                 points):
    """Markers, paths, point clouds and log lines are written in protobuf's wire format
    (``vcyto.recording.protowire``) for speed; each is byte for byte what the protobuf classes serialise (zeros,
    -0.0 and empty fields included)."""
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    from vcyto.recording import foxglove
    entities = foxglove.Entities()
    marker = entities.marker(unix_ns, f"event/{label}", x, y, rgb, label)
    assert marker == foxglove.marker(unix_ns, f"event/{label}", x, y, rgb, label).SerializeToString()
    line = entities.path(unix_ns, 7, path, rgb, label)
    assert line == foxglove.path(unix_ns, 7, path, rgb, label).SerializeToString()
    several = [(unix_ns + n, n, path[n:] + path[:n], rgb, f"{n}: {label}") for n in range(len(path))]
    assert entities.paths(several) == [foxglove.path(*item).SerializeToString() for item in several]
    scene = SceneUpdate.FromString(entities.scene([marker, line]))
    assert scene == SceneUpdate(entities=[foxglove.marker(unix_ns, f"event/{label}", x, y, rgb, label),
                                          foxglove.path(unix_ns, 7, path, rgb, label)])
    cloud = foxglove.Membranes().packed(unix_ns, points)
    assert cloud == PointCloud(timestamp=foxglove.stamp(unix_ns), frame_id=foxglove.FRAME, pose=foxglove._IDENTITY,
                               point_stride=foxglove.POINT.itemsize, fields=foxglove.POINT_FIELDS,
                               data=points).SerializeToString()
    for level in ("INFO", "WARN", "ERROR"):
        assert foxglove.log_line(unix_ns, label, level) == foxglove.log(unix_ns, label, level).SerializeToString()


@settings(max_examples=300, deadline=None)
@given(value=st.one_of(st.integers(0, 2**64 - 1), st.sampled_from([2**k + d for k in (7, 14, 21, 28, 35, 63)
                                                                  for d in (-1, 0)])))
def test_a_varint_is_protobufs(value):
    """Each of ``protowire.varint``'s branches (1 to 5 bytes, then any length) writes protobuf's varint."""
    from google.protobuf.internal.encoder import _VarintBytes

    from vcyto.recording.protowire import varint
    assert varint(value) == _VarintBytes(value)


def test_each_event_shows_with_the_newest_events_before_it_across_batches(tmp_path):
    """``device/events``: the row of each detector event holds it and the ``RECENT_EVENTS - 1`` events before it, in
    order, also where the events before it were sent in an earlier batch."""
    from vcyto.recording.rerunlog import RECENT_EVENTS, RerunLogger
    logger = RerunLogger(Scenario(), None, ("save", tmp_path / "events.rrd"))
    count = 2 * RECENT_EVENTS + 7
    for n in range(count):
        logger.time(n * 1e-3, n)
        logger.event(n * 1e-3, n, "in channel", f"event {n}", position=(float(n), 1.0))
        if n in (3, RECENT_EVENTS + 2):                      # batches end among the events
            logger.send_pending()
    logger.close()
    rows, _ = rrd_rows(tmp_path / "events.rrd")
    markers = rows["/device/events"]
    assert [t for t, _ in markers] == [round(n * 1e-3 * 1e9) for n in range(count)]
    for n, (_, values) in enumerate(markers):
        shown = list(range(max(0, n + 1 - RECENT_EVENTS), n + 1))
        assert [x for x, _ in values["Points2D:positions"]] == shown
        assert values["Points2D:labels"] == [f"event {k}" for k in shown]
