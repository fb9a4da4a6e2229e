"""MCAP recording of a closed-loop run: Foxglove well-known channels any tool draws, vcyto's typed channels
for analysis and replay, crash safety.

Foxglove channels (protobuf, Foxglove's official schemas; ``vcyto.recording.foxglove``; coordinates in metres, frame
``channel``): ``/foxglove/scene`` (``foxglove.SceneUpdate``: the device once, then per batch a marker per detector
event and each cell's centroid path when it has left, coloured by outcome class, each with a lifetime so that the
scene holds the recent ones), ``/foxglove/membranes`` (``foxglove.PointCloud`` every step shown: the membrane
points of the cells in the channel, with fields key, class and a colour), ``/foxglove/speed``
(``foxglove.RawImage``, 32FC1 in mm/s, at the field cadence) and ``/foxglove/log`` (``foxglove.Log``: events,
decisions with their reasons, outcomes).

vcyto's channels (JSON, each with a JSON Schema stating required fields and units; ``vcyto.recording.schemas.SCHEMAS``).
Every one but the flow field is columns, one message per batch of steps (``flush_every``):
- ``/loop/steps``        per step: time, step, IDT drive, cells the optics see, wall time, plant diagnostics
                         (dt, physics steps, cumulative solver times: wall-clock);
- ``/cells/rows``        per step its row count, then per row (a cell in the channel at that step): key, type,
                         class, centroid (um), area ratio, perimeter and smallest/largest point spacing / h (null
                         for models without membranes); the membranes are in ``/foxglove/membranes``;
- ``/detector/events``   the batch's detector events (fluorescence, scatter, velocity, class);
- ``/controller/decisions`` the batch's decisions (sort / pass / abort, predicted arrival, pulse, reason) and when
                         each was shown;
- ``/outcomes``          the cells that left in the batch (outlet, exit time and ordinate, outcome class);
- ``/flow/velocity``     every ``field_every`` steps (0: never): velocity (m/s) and pressure (Pa) at the mesh
                         vertices (float32, base64) with the grid.
The events, decisions and outcomes of a batch are written before its ``/loop/steps`` message, one message each
(``vcyto.recording.replay`` puts them back among the steps by their times).

Log and publish times are the wall-clock start of the run (``time_origin_unix_ns`` in the metadata) plus the
simulated time, so MCAP tools show a date and a timeline as long as the simulated run; every message also
carries its simulated time. Run metadata (scenario TOML, seed, settings as JSON text, command line, versions) is
an MCAP metadata record named ``run``, every value a plain string.

The writer (the Foxglove SDK's, compiled) is flushed after each batch, so a killed process loses at most the
batch being gathered (and the batches the background thread had not written yet, ``vcyto.recording.sinks``); ``close``
finishes the file (summary and index) and is called on normal exit, Ctrl-C and SIGTERM. State is bounded: the
cells in the channel (their paths until they leave) and one batch.
"""

from __future__ import annotations

import base64
import collections
import dataclasses
import errno
import json
import logging
import math
import operator
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import orjson
from foxglove import Channel, Context, Schema, open_mcap
from foxglove.mcap import MCAPCompression, MCAPWriteOptions
from mcap_protobuf.schema import build_file_descriptor_set

from sim.model.scenario import UM, Scenario

from ..classes import CLASS_COLOURS, CLASS_IDS, CLASS_NAMES, CellClasses
from ..outcomes import outcome_text
from ..outputs import plain
from ..sortreport import EVENT_NAMES, name_cells
from ..trace import TracedRows, joined, stretches
from . import foxglove
from .schemas import SCHEMAS

PER_STEP = ("/loop/steps", "/cells/rows")
# 1: JSON channels only, membranes in /cells; 2: Foxglove channels beside them (um); 3: the per-step channels as
# columns per batch (/loop/steps, /cells/rows), Foxglove coordinates in metres, scene entities with lifetimes
# 4: events, decisions and outcomes as columns per batch (/detector/events, /controller/decisions, /outcomes)
FORMAT = "4"
FULL_BYTES = 1 << 20          # a filesystem with less free space than this is full (for a failed write's cause)


class _SdkWarnings(logging.Handler):
    """The Foxglove SDK's warnings (a write that failed: "error logging message: McapError(Io(Os { code: 28 ...")
    kept for the one-line error that names the cause, instead of printed as they come."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.recent: collections.deque = collections.deque(maxlen=4)

    def emit(self, record):
        self.recent.append(record.getMessage())


_SDK_WARNINGS = _SdkWarnings()
_sdk_logger = logging.getLogger("foxglove")
_sdk_logger.addHandler(_SDK_WARNINGS)
_sdk_logger.propagate = False


def write_error(error: RuntimeError, path: Path) -> OSError:
    """The SDK's failure to write the MCAP at ``path`` as an ``OSError`` naming the file and the cause: the
    operating system's error when the SDK's warnings carry its code (28: no space left on device), ENOSPC when
    the file's filesystem has (almost) no space left, else EIO with the SDK's words."""
    said = " ".join([*_SDK_WARNINGS.recent, str(error)])
    code = re.search(r"code: (\d+)", said)
    number = int(code.group(1)) if code else errno.ENOSPC if _full(Path(path).parent) else None
    if number is None:
        return OSError(errno.EIO, f"the MCAP writer failed ({' '.join(str(error).split())})", str(path))
    return OSError(number, os.strerror(number), str(path))


def _full(directory: Path) -> bool:
    try:
        return shutil.disk_usage(directory).free < FULL_BYTES
    except OSError:
        return False




def plain_metadata(metadata: dict) -> dict:
    """Metadata values as plain strings: settings (dataclasses) and containers as JSON text."""
    def text(value):
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return json.dumps(plain(dataclasses.asdict(value)), allow_nan=False)
        if isinstance(value, (dict, list, tuple, bool)) or value is None:
            return json.dumps(plain(value), allow_nan=False)
        return str(value)
    return {key: text(value) for key, value in metadata.items()}


def device_outlines(scenario: Scenario, detection_window=None) -> list:
    """(id, points in um, RGB, label) of the channel, inlets, outlets, SAW window and detection window."""
    channel = scenario.channel
    length, height = channel.length / UM, channel.height / UM
    outlines = [("device/outline", [[0, 0], [length, 0], [length, height], [0, height], [0, 0]], (200, 200, 200), "")]
    outlines += [(f"device/inlet/{i.name}", [[0, i.span[0] / UM], [0, i.span[1] / UM]], (0, 190, 255), i.name)
                 for i in channel.inlets]
    outlines += [(f"device/outlet/{o.name}", [[length, o.span[0] / UM], [length, o.span[1] / UM]], (255, 140, 0),
                  o.name) for o in channel.outlets]
    low, high = np.array(channel.saw_window.span) / UM
    outlines.append(("device/saw_window", [[low, 0], [high, 0]], (255, 0, 0), "SAW"))
    if detection_window is not None:
        x0, x1 = np.array(detection_window) / UM
        outlines.append(("device/detection_window", [[x0, 0], [x1, 0], [x1, height], [x0, height], [x0, 0]],
                         (120, 255, 120), "detector"))
    return outlines


def _scenario_of(metadata: dict) -> Scenario:
    if "scenario_toml" in metadata:
        from ..config import scenario_from_toml
        return scenario_from_toml(str(metadata["scenario_toml"]))
    return Scenario()


class McapRecorder:
    """A sink of the closed loop that writes every step to an MCAP file: the per-step channels as columns, one
    message each per batch of ``flush_every`` steps (then the file is flushed), the events as they come."""

    def __init__(self, path: Path, metadata: dict, flush_every: int = 200, field_every: int = 100,
                 scenario: Scenario | None = None, detection_window=None):
        self.path = Path(path)
        # the Foxglove SDK's MCAP writer (compiled): a message costs a few microseconds instead of ~15 in the pure
        # Python writer; its own context, so that recorders in one process do not share channels
        self._context = Context()
        self.failed = False
        self._writer = self._writing(open_mcap, str(self.path), allow_overwrite=True, context=self._context,
                                     writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd, profile="",
                                                                     compression_threads=0))
        self._channels = {}
        for topic, schema in SCHEMAS.items():
            self._channels[topic] = Channel(topic, message_encoding="json", context=self._context, schema=Schema(
                name=schema["title"], encoding="jsonschema", data=json.dumps(schema).encode()))
        for topic, message_class in foxglove.TOPICS.items():
            described = build_file_descriptor_set(message_class).SerializeToString()
            self._channels[topic] = Channel(topic, message_encoding="protobuf", context=self._context, schema=Schema(
                name=message_class.DESCRIPTOR.full_name, encoding="protobuf", data=described))
        self._log_channel = self._channels["/foxglove/log"]
        self.origin_ns = time.time_ns()
        detection_window = detection_window or getattr(metadata.get("detector"), "window", None)
        scenario = scenario or _scenario_of(metadata)
        self._writing(self._writer.write_metadata, "run", plain_metadata({
            **metadata, "time_origin_unix_ns": self.origin_ns, "recording_format": FORMAT}))
        self.flush_every = max(1, flush_every)
        self.field_every = field_every
        self._classes = CellClasses(scenario)
        self._paths: dict[int, list] = {}        # the cells in the channel: their centroid paths (um), in pieces
        self._kinds: dict[int, tuple] = {}       # traced cells in the channel: (type, area ratio)
        self._entities = foxglove.Entities()
        self._reported: set[int] = set()         # cells that left, while ``truth`` still lists them
        self._keys_by_event: dict[int, int] = {}  # detector events' cells, for the log's decision lines
        self._steps, self._rows = _columns(STEP_COLUMNS), _columns(ROW_COLUMNS)
        self._happened = _happening_columns()    # the batch's events, decisions and outcomes, as columns
        self._scene: list = []                   # the scene's entities of the batch (markers, paths)
        self._leaving: list = []                 # the paths of the cells that left in the batch, to be written
        self._cloud = foxglove.Membranes()
        outlines = device_outlines(scenario, detection_window)
        self._write_proto("/foxglove/scene", 0.0, foxglove.device(self.origin_ns, outlines))
        self._writing(self._writer.flush)
        self.closed = False

    def _writing(self, call, *args, **kwargs):
        """``call`` of the SDK's writer; its failure to write (a full disk) is an ``OSError`` naming the file."""
        try:
            return call(*args, **kwargs)
        except RuntimeError as error:
            self.failed = True
            raise write_error(error, self.path) from None

    def _stamp(self, time_s: float) -> int:
        return self.origin_ns + int(round(time_s * 1e9))

    def _add(self, topic: str, time_s: float, data: bytes):
        self._channels[topic].log(data, log_time=self.origin_ns + int(round(time_s * 1e9)))

    def _write(self, topic: str, time_s: float, payload: dict):
        try:                                   # strict JSON: orjson writes NaN and infinities as null
            data = orjson.dumps(payload, option=orjson.OPT_SERIALIZE_NUMPY)
        except TypeError:                      # a value orjson does not know (outputs.plain makes it plain)
            data = json.dumps(plain(payload), separators=(",", ":"), allow_nan=False).encode()
        self._add(topic, time_s, data)

    def _write_proto(self, topic: str, time_s: float, message):
        self._add(topic, time_s, message if isinstance(message, bytes) else message.SerializeToString())

    def _log(self, time_s: float, text: str, level: str = "INFO"):
        unix_ns = self._stamp(time_s)
        self._log_channel.log(foxglove.log_line(unix_ns, text, level), log_time=unix_ns)

    def on_steps(self, records):
        """Write a batch of steps (``vcyto.recording.sinks.BackgroundSinks`` hands them over together): an
        event-driven plant's recorded steps gathered as arrays (``vcyto.trace.TracedRows``), other steps one by one;
        the file is flushed when ``flush_every`` steps are waiting."""
        for traced, stretch in stretches(records):
            if traced:
                self._traced(stretch)
                self._flush_due()
            else:
                for record in stretch:
                    self._step(record)
                    self._flush_due()

    def _flush_due(self):
        if len(self._steps["time"]) >= self.flush_every:
            self.flush()

    def on_step(self, record):
        """Take one step (``vcyto.steps.StepRecord``): its events, decisions and outcomes are written now, its
        per-step rows with the batch's (every ``flush_every`` steps, then the file is flushed)."""
        self.on_steps([record])

    def _step(self, record):
        """A step of a plant that does not trace (every record a recorded step: its rows, membranes, field)."""
        step, observation, truth, actuation = record.step, record.observation, record.truth, record.actuation
        now = observation.time
        self._classes.observe(record.events, record.decisions)
        in_channel = [cell for cell in truth.cells if cell.fate == "in_channel"]
        _append(self._steps, (now, step, actuation, len(observation.cells), time.time(), record.diagnostics or {},
                              len(in_channel)))
        self._membranes(now, in_channel)
        for cell in in_channel:
            self._cell(now, cell)
        self._happenings(record, in_channel)
        for cell in self._left(truth):
            self._outcome(now, cell, self._classes.settle(cell))
        fields = record.fields
        if fields is not None and self.field_every and step % self.field_every == 0:
            payload = fields()
            self._write("/flow/velocity", now, payload)
            self._write_proto("/foxglove/speed", now, foxglove.speed_image(self._stamp(now), payload))

    def _happenings(self, record, in_channel=None):
        """A record's detector events (a marker where the cell is) and decisions; the pulses that are over are
        forgotten."""
        now = record.observation.time
        if record.events:
            cells = record.truth.cells if in_channel is None else in_channel
            positions = {cell.key: cell for cell in cells if cell.fate == "in_channel"}
            for event in record.events:
                self._event(event, positions.get(event.key))
        decisions = self._happened["/controller/decisions"]
        for decision in record.decisions:
            _append(decisions, (*_DECISION_FIELDS(decision), now))
            reason = f" ({decision.reason})" if decision.reason else ""
            self._log(now, name_cells(f"event {decision.event_id}: {decision.action}{reason}", self._keys_by_event),
                      "WARN" if decision.action == "abort" else "INFO")
        self._classes.forget_pulses(now)          # the pulses that are over (bounded state)

    def _traced(self, records):
        """The recorded steps of an event-driven plant's records (``vcyto.trace``), gathered as arrays: their rows,
        a point cloud per step, the paths; the plant's diagnostics on each record's last step."""
        rows = TracedRows(records)
        x_um, y_um = np.round(rows.x * 1e6, 4), np.round(rows.y * 1e6, 4)
        for key, chunk in rows.by_key(x_um, y_um).items():       # a path is whole when its cell leaves
            self._paths.setdefault(key, []).append(chunk)
        gone, kinds, diagnostics = [], self._kinds, []

        def each(index, record):
            truth = record.truth
            for cell in truth.cells:
                if cell.key not in kinds:
                    kinds[cell.key] = (cell.type, round(cell.area_ratio, 6))
            self._happenings(record)
            now = record.observation.time
            for cell in self._left(truth):
                self._outcome(now, cell, self._classes.settle(cell))
                gone.append(cell.key)
            if len(record.trace):
                diagnostics.extend([{}] * (len(record.trace) - 1) + [record.diagnostics or {}])

        class_ids = rows.classify(self._classes, each)
        count, steps, columns = len(rows), self._steps, self._rows
        keys = rows.keys.tolist()
        for name, values in (("time", rows.times.tolist()), ("step", rows.steps.tolist()),
                             ("idt", rows.drive.tolist()), ("cells_in_channel", rows.counts.tolist()),
                             ("wall_time", [time.time()] * count), ("diagnostics", diagnostics),
                             ("rows", rows.counts.tolist())):
            steps[name].extend(values)
        nothing = [None] * len(keys)
        for name, values in (("key", keys), ("type", [kinds[key][0] for key in keys]),
                             ("class", [CLASS_NAMES[i] for i in class_ids.tolist()]), ("x_um", x_um.tolist()),
                             ("y_um", y_um.tolist()), ("area_ratio", [kinds[key][1] for key in keys]),
                             ("perimeter_um", nothing), ("spacing_min_h", nothing), ("spacing_max_h", nothing)):
            columns[name].extend(values)
        for key in gone:
            kinds.pop(key, None)
        points, size = foxglove.centroids(x_um, y_um, rows.keys, class_ids).tobytes(), foxglove.POINT.itemsize
        channel, packed, stamp = self._channels["/foxglove/membranes"], self._cloud.packed, self._stamp
        ends = np.cumsum(rows.counts)
        for time_s, start, end in zip(rows.times.tolist(), (ends - rows.counts).tolist(), ends.tolist()):
            unix_ns = stamp(time_s)
            channel.log(packed(unix_ns, points[start * size:end * size]), log_time=unix_ns)

    def flush(self):
        """Write the batch's per-step columns and scene entities, then flush the file (a kill keeps this)."""
        self._writing(self._flush)

    def _flush(self):
        steps, happened = self._steps, self._happened
        if any(columns["time"] for columns in happened.values()):
            now = steps["time"][-1] if steps["time"] else max(max(c["time"]) for c in happened.values() if c["time"])
            for topic, columns in happened.items():
                if columns["time"]:
                    self._write(topic, now, columns)
            self._happened = _happening_columns()
        if steps["time"]:
            now = steps["time"][-1]
            self._scene += self._entities.paths(self._leaving)
            if self._scene:
                self._write_proto("/foxglove/scene", now, self._entities.scene(self._scene))
            self._write("/cells/rows", now, {"time": steps["time"], "count": steps["rows"], **self._rows})
            self._write("/loop/steps", now, {key: steps[key] for key in STEP_COLUMNS if key != "rows"})
            self._steps, self._rows, self._scene, self._leaving = _columns(STEP_COLUMNS), _columns(ROW_COLUMNS), [], []
        self._writer.flush()

    def _left(self, truth) -> list:
        """The cells that left since the previous step (each once: ``truth`` may list them again)."""
        left = [cell for cell in truth.cells if cell.fate != "in_channel" and cell.key not in self._reported]
        if left or len(self._reported) > REPORTED_KEPT:
            self._reported &= {cell.key for cell in truth.cells}
            self._reported.update(cell.key for cell in left)
        return left

    def _membranes(self, now: float, cells):
        rows = []
        for cell in cells:
            centroid = (round(cell.x / UM, 4), round(cell.y / UM, 4))
            self._paths.setdefault(cell.key, []).append(centroid)
            name = self._classes.provisional(cell.key)
            points = np.asarray(cell.membrane) / UM if cell.membrane is not None else centroid
            rows.append((cell.key, CLASS_IDS[name], CLASS_COLOURS[name], points))
        self._write_proto("/foxglove/membranes", now, self._cloud.message(self._stamp(now), rows))

    def _event(self, event, cell):
        self._keys_by_event[event.event_id] = event.key
        if len(self._keys_by_event) > 2 * EVENT_NAMES:         # the recent events: a decision names its neighbours
            self._keys_by_event = {e: k for e, k in self._keys_by_event.items() if e > event.event_id - EVENT_NAMES}
        _append(self._happened["/detector/events"], _EVENT_FIELDS(event))
        text = (f"cell {event.key}: detected type {event.classification} (fluorescence {event.fluorescence:.2f}, "
                f"{event.velocity * 1e3:.1f} mm/s)")
        self._log(event.time, text)
        if cell is not None:
            name = self._classes.provisional(event.key)
            self._scene.append(self._entities.marker(self._stamp(event.time), f"event/{event.event_id}", cell.x / UM,
                                               cell.y / UM, CLASS_COLOURS[name],
                                               f"event {event.event_id}: type {event.classification}"))

    def _outcome(self, now: float, cell, name: str):
        restored = (cell.measures or {}).get("area_corrected")
        _append(self._happened["/outcomes"], (cell.key, cell.type, cell.fate, name, cell.exit_time,
                                              cell.exit_y / UM, restored, now))
        self._log(now, outcome_text(cell.key, cell.type, cell.fate, name, restored),
                  "INFO" if name in ("sorted", "passed") else "WARN")
        chunks = self._paths.pop(cell.key, None) or [(cell.x / UM, cell.y / UM)]
        path = joined(chunks)
        self._leaving.append((self._stamp(now), cell.key, path, CLASS_COLOURS[name], f"{cell.key}: {name}"))

    def _cell(self, now: float, cell):
        """A row of ``/cells/rows``: a cell in the channel at this step (null figures for models without
        membranes, and for a missing or non-finite one)."""
        shape = cell.measures or {}
        _append(self._rows, (cell.key, cell.type, self._classes.provisional(cell.key), round(cell.x * 1e6, 4),
                             round(cell.y * 1e6, 4), round(cell.area_ratio, 6),
                             _rounded(shape.get("perimeter"), 1e6), _rounded(shape.get("spacing_min"), 1.0),
                             _rounded(shape.get("spacing_max"), 1.0)))

    def on_end(self, ending: dict):
        """How the run ended (complete, truncated, interrupted, failed; why; its sort figures): the metadata record
        ``run_end``, so that a recording of a partial run says so."""
        self.flush()
        self._writing(self._writer.write_metadata, "run_end", plain_metadata(ending))

    def close(self):
        """Finish the file (its summary and index). After a write that failed (reported then), closing fails too
        and is not reported again: what was flushed before stays readable (readers take a torn tail)."""
        if not self.closed:
            self.closed = True
            failed_before = self.failed
            try:
                if not failed_before:
                    self.flush()
            finally:
                try:
                    self._writing(self._writer.close)
                except OSError:
                    if not failed_before:
                        raise


REPORTED_KEPT = 64            # cells that left kept beyond those ``truth`` lists (then pruned to those)
STEP_COLUMNS = ("time", "step", "idt", "cells_in_channel", "wall_time", "diagnostics", "rows")
ROW_COLUMNS = ("key", "type", "class", "x_um", "y_um", "area_ratio", "perimeter_um", "spacing_min_h", "spacing_max_h")
HAPPENINGS = ("/detector/events", "/controller/decisions", "/outcomes")     # in the order a batch writes them
# the columns of each: the fields of its records (``vcyto.recording.schemas.RECORDS``), in their order, which
# ``_happenings`` and ``_outcome`` append in
HAPPENING_COLUMNS = {topic: tuple(SCHEMAS[topic]["properties"]) for topic in HAPPENINGS}
assert HAPPENING_COLUMNS["/controller/decisions"][-1] == "time" and HAPPENING_COLUMNS["/outcomes"] == (
    "key", "type", "outlet", "class", "exit_time", "exit_y_um", "area_restored", "time")
_EVENT_FIELDS = operator.attrgetter(*HAPPENING_COLUMNS["/detector/events"])
_DECISION_FIELDS = operator.attrgetter(*HAPPENING_COLUMNS["/controller/decisions"][:-1])


def _happening_columns() -> dict:
    return {topic: _columns(HAPPENING_COLUMNS[topic]) for topic in HAPPENINGS}


def _columns(names) -> dict:
    return {name: [] for name in names}


def _append(columns: dict, values):
    for column, value in zip(columns.values(), values):
        column.append(value)


def _rounded(value, scale: float):
    """``value * scale`` to 4 decimals (6 for ratios), None for a missing or non-finite one (JSON null)."""
    if value is None or not math.isfinite(value):
        return None
    return round(value * scale, 4)


def velocity_field(vertices: np.ndarray, velocity: np.ndarray, pressure: np.ndarray, grid_x, grid_y,
                   time_s: float) -> dict:
    """Velocity (m/s) and pressure (Pa) at the mesh vertices as a compact JSON payload (float32, base64)."""
    count = vertices.shape[1]
    order = np.lexsort((vertices[0], vertices[1]))          # rows of constant y, x increasing

    def encoded(values):
        return base64.b64encode(np.asarray(values)[:count][order].astype(np.float32).tobytes()).decode()

    return {"time": time_s, "shape": [len(grid_y), len(grid_x)],
            "x_um": np.round(np.asarray(grid_x) * 1e6, 4).tolist(), "y_um": np.round(np.asarray(grid_y) * 1e6,
                                                                                     4).tolist(),
            "vx_f32_b64": encoded(velocity[0]), "vy_f32_b64": encoded(velocity[1]), "p_f32_b64": encoded(pressure)}
