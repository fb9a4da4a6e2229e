"""`vcyto replay FILE.mcap`: re-log a recording to Rerun; damaged files replay what can be recovered.

Reads recordings of the four formats: 1 (JSON channels only, membranes in ``/cells``), 2 (membranes in the
Foxglove point cloud ``/foxglove/membranes``, in um; classes in ``/cells`` and ``/outcome``), 3 (the per-step
channels as columns per batch, ``/loop/steps`` and ``/cells/rows``, written after the batch's events, decisions
and outcomes, which are put back at their steps by their times; point clouds in metres) and 4 (as 3, with the
events, decisions and outcomes as columns per batch too: ``/detector/events``, ``/controller/decisions``,
``/outcomes``, whose rows are replayed as format 3's messages). The replayed view shows what the live one did:
cells coloured by class, detector event markers, pulses, decisions with their reasons.
"""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import numpy as np
import orjson
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Metadata
from mcap.stream_reader import StreamReader

from sim.model.scenario import Scenario

from ..classes import class_of_type, provisional_class
from ..config import scenario_from_toml
from ..outcomes import outcome_class, outcome_text
from .rerunlog import BATCH_ROWS, BATCH_SECONDS, POINT_LIKE, RerunLogger, decision_text

MEMBRANES = "/foxglove/membranes"


MAX_RECORD_BYTES = 64 << 20          # one record as stored (a chunk: compressed); vcyto's chunks are ~1 MB
MAX_CHUNK_BYTES = 256 << 20          # one chunk decompressed, refused before it is decompressed further
MAX_MESSAGE_BYTES = 32 << 20         # one message's payload
MAX_JSON_DEPTH = 1024                # arrays and objects nested in one JSON message (orjson's bound; vcyto's: 3)
# format 4's columnar channels, and the topic of format 3's messages their rows are
COLUMNAR = {"/detector/events": "/detector/event", "/controller/decisions": "/controller/decision",
            "/outcomes": "/outcome"}
VCYTO_TOPICS = ("/loop/step", "/cells", "/loop/steps", "/cells/rows",
                "/detector/event", "/controller/decision", "/outcome", "/flow/velocity",
                MEMBRANES, *COLUMNAR)


MAX_FIELD_PIXELS = 16_000_000      # the flow image at 1 um pixels (the paper's channel: ~0.2 million)


class ReplayError(ValueError):
    """The file is not a vcyto recording at all."""


class TooDeep(ReplayError):
    """A JSON message nested beyond ``MAX_JSON_DEPTH``: no vcyto wrote it, so the file is refused, not replayed."""


class Damaged(Exception):
    """The file cannot be read past this point (truncated, corrupted, or a record beyond the size limits)."""


def _decode(topic: str, data: bytes):
    if len(data) > MAX_MESSAGE_BYTES:
        raise Damaged(f"a {topic} message of {len(data):,} bytes (at most {MAX_MESSAGE_BYTES:,})")
    if topic == MEMBRANES:          # (its time stamp in ns, its points)
        from . import foxglove
        cloud = foxglove.PointCloud.FromString(data)
        return cloud.timestamp.seconds * 1_000_000_000 + cloud.timestamp.nanos, foxglove.membrane_points(cloud)
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError as error:
        if any(word in str(error).lower() for word in ("depth", "recursion")):     # orjson's words for its bound
            raise TooDeep(f"a {topic} message nests its JSON arrays and objects more than {MAX_JSON_DEPTH:,} levels "
                          f"deep (the limit; vcyto writes at most 3): not a recording vcyto wrote") from None
        raise


_DAMAGE = (McapError, ValueError, EOFError, struct.error, zstandard.ZstdError, RuntimeError, Damaged)


def _records(handle):
    """The records of an MCAP stream, chunks opened one at a time with their decompressed size bounded: memory
    stays within a record's and a chunk's limits however long the recording is."""
    for record in StreamReader(handle, skip_magic=False, emit_chunks=True, record_size_limit=MAX_RECORD_BYTES).records:
        if isinstance(record, Chunk):
            yield from _chunk_records(record)
        else:
            yield record


def _chunk_records(chunk: Chunk):
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        raise Damaged(f"a chunk of {chunk.uncompressed_size:,} bytes decompressed (at most {MAX_CHUNK_BYTES:,})")
    if chunk.compression == "zstd":
        data = _zstd(chunk.data, chunk.uncompressed_size + 1)
    elif chunk.compression == "lz4":
        import lz4.frame
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=chunk.uncompressed_size + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise Damaged(f"a chunk compressed with {chunk.compression!r}, which vcyto does not write")
    if len(data) != chunk.uncompressed_size:
        raise Damaged(f"a chunk that decompresses to another size than the {chunk.uncompressed_size:,} bytes it "
                      "claims")
    stream = ReadDataStream(io.BytesIO(data))
    while stream.count < len(data):
        opcode, length = stream.read1(), stream.read8()
        if opcode == Opcode.CHANNEL:
            yield Channel.read(stream)
        elif opcode == Opcode.MESSAGE:
            yield Message.read(stream, length)
        else:
            stream.read(length)


def _zstd(data: bytes, limit: int) -> bytes:
    """``data`` decompressed, at most ``limit`` bytes of it (whatever size its frame claims)."""
    reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data))
    parts, size = [], 0
    while size < limit:
        part = reader.read(min(limit - size, 1 << 20))
        if not part:
            break
        parts.append(part)
        size += len(part)
    return b"".join(parts)


def read_metadata(path: Path) -> tuple[dict, dict, str]:
    """(the run's metadata, {channel id: topic} of the channels replay reads, the problem that stopped the
    reading or ""): a first pass over the file that opens no chunk but to find its channels."""
    metadata, channels, problem = {}, {}, ""
    with open(path, "rb") as handle:
        try:
            for record in _records(handle):
                if isinstance(record, Metadata) and record.name == "run":
                    metadata.update(record.metadata)
                elif isinstance(record, Metadata) and record.name == "run_end":      # how the run ended
                    metadata["_run_end"] = dict(record.metadata)
                elif isinstance(record, Channel) and record.topic in VCYTO_TOPICS and \
                        (record.message_encoding == "json" or record.topic == MEMBRANES):
                    channels[record.id] = record.topic
        except _DAMAGE as error:                 # damaged: stop there
            problem = _problem(error)
    if not channels and not metadata:
        why = problem or "none of its channels is one vcyto stream writes, and it has no run metadata"
        raise ReplayError(f"{path}: not a vcyto MCAP recording ({why})")
    return metadata, channels, problem


def messages(path: Path, channels: dict):
    """(topic, decoded data) of each message on ``channels``, one at a time, in file order; a damaged file ends
    with ``Damaged``."""
    with open(path, "rb") as handle:
        try:
            for record in _records(handle):
                if isinstance(record, Message) and record.channel_id in channels:
                    topic = channels[record.channel_id]
                    yield topic, _decode(topic, record.data)
        except TooDeep as error:
            raise TooDeep(f"{path}: {error}") from None
        except _DAMAGE as error:
            raise Damaged(_problem(error)) from None


def read_recording(path: Path):
    """(metadata, [(topic, data)], problem) of a whole (small) recording: for tests and tools; replay streams."""
    metadata, channels, problem = read_metadata(path)
    read = []
    try:
        for item in messages(path, channels):
            read.append(item)
    except Damaged as error:
        problem = problem or str(error)
    return metadata, read, problem


def rows_of(columns: dict) -> list[dict]:
    """The records of a columnar message (``{field: [value per record]}``), one dict each; ValueError for columns
    of unequal lengths (a malformed message)."""
    if not isinstance(columns, dict) or not all(isinstance(values, list) for values in columns.values()):
        raise ValueError("a columnar message that is not an object of arrays")
    lengths = {len(values) for values in columns.values()}
    if len(lengths) > 1:
        raise ValueError(f"a columnar message whose columns have {sorted(lengths)} entries (one length expected)")
    names = list(columns)
    return [dict(zip(names, values)) for values in zip(*columns.values())]


def happenings(path: Path) -> dict:
    """topic -> the events (``/detector/event``), decisions (``/controller/decision``) and outcomes (``/outcome``)
    of the recording at ``path``, one dict each in the file's order, whatever its format: for tests and tools."""
    found = {topic: [] for topic in COLUMNAR.values()}
    _, channels, _ = read_metadata(path)
    for topic, data in messages(path, {key: topic for key, topic in channels.items()
                                       if topic in COLUMNAR or topic in found}):
        if topic in COLUMNAR:
            found[COLUMNAR[topic]] += rows_of(data)
        else:
            found[topic].append(data)
    return found


def _problem(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}".strip() if not isinstance(error, Damaged) else str(error)


def detection_window(metadata: dict):
    """The detector window (m) of the run's metadata: JSON text (format 2) or a Python repr (format 1)."""
    text = metadata.get("detector", "")
    try:
        return tuple(json.loads(text)["window"])
    except (ValueError, KeyError, TypeError):
        pass
    if "window=(" in text:
        return tuple(float(v) for v in text.split("window=(", 1)[1].split(")", 1)[0].split(","))
    return None


class _Replayer:
    """Turns the messages of a recording into the calls the live view makes."""

    def __init__(self, logger: RerunLogger, scenario: Scenario, origin_ns: int = 0, metres: bool = False):
        self.logger = logger
        self.origin_ns, self.scale = origin_ns, 1e6 if metres else 1.0       # point clouds' units to um
        self.batches = metres                 # format 3 and later
        self.columnar = False                 # format 4: events, decisions, outcomes as columns (sorted by time)
        self.waiting: list = []               # format 3: (topic, data) written before their batch's steps
        self.clouds: dict = {}                # format 3: time stamp (ns) -> points of the batch's steps
        self.rows = None                      # format 3: the batch's /cells/rows
        self.true_class = class_of_type(scenario)
        self.membranes = {}                   # key -> points of the step being read (format 2)
        self.detected, self.actions, self.events = {}, {}, {}     # of the cells in the channel (format 1 classes)
        self.pulses = {}

    def on(self, topic: str, data):
        logger = self.logger
        if topic == MEMBRANES:
            self.membranes = _by_key(data[1])
        elif topic == "/cells":
            for cell in data["cells"]:
                if "membrane_um" not in cell and cell["key"] in self.membranes:
                    points = self.membranes[cell["key"]]
                    cell["membrane_um"] = list(zip(points["x"].astype(float) * self.scale,
                                                   points["y"].astype(float) * self.scale))
                cell.setdefault("class", self._provisional(cell["key"]))
            logger.cells(data["cells"])
        elif topic == "/detector/event":
            self._event(data)
        elif topic == "/controller/decision":
            self._decision(data)
        elif topic == "/outcome":
            self.logger.figures.outcome(data["outlet"], self.true_class(data["type"]) == "II")
            name = data.get("class") or self._settle(data)
            logger.outcome(data["key"], name, outcome_text(data["key"], data["type"], data["outlet"], name,
                                                                 data.get("area_restored")))
        elif topic == "/flow/velocity":
            logger.field(_checked_field(data))

    def batched(self, topic: str, data):
        """A message of a format-3 recording: kept until its batch's ``/loop/steps``, which replays them."""
        if topic == "/loop/steps":
            self._steps(data)
        elif topic == "/cells/rows":
            self.rows = data
        elif topic == MEMBRANES:
            self.clouds[data[0]] = data[1]
        elif topic in COLUMNAR:
            self.columnar = True
            self.waiting += [(COLUMNAR[topic], row) for row in rows_of(data)]
        else:
            self.waiting.append((topic, data))

    def on_all_waiting(self):
        if self.columnar:
            self.waiting.sort(key=_time_of)
        for item in self.waiting:
            self.on(*item)
        self.waiting = []

    def _steps(self, steps):
        """A batch's steps in order, each with its cells and then the events, decisions and outcomes shown with it
        (those at or before its time and after the previous step's)."""
        logger, rows, waiting = self.logger, self.rows or {}, self.waiting
        if self.columnar:            # a batch's events, then its decisions, then its outcomes: in time order
            waiting.sort(key=_time_of)
        starts = np.concatenate([[0], np.cumsum(rows.get("count", []))]).astype(int)
        shown = 0
        for n, (time_s, step) in enumerate(zip(steps["time"], steps["step"])):
            logger.time(time_s, step)            # the drive: from the pulses, as the live view
            if n + 1 < len(starts):
                cloud = self.clouds.get(self.origin_ns + int(round(time_s * 1e9)))
                self.membranes = _by_key(cloud) if cloud is not None else {}
                self.on("/cells", {"cells": [_row(rows, index) for index in range(starts[n], starts[n + 1])]})
            last = n + 1 == len(steps["time"])
            outcomes = decided = False
            while shown < len(waiting) and (last or _time_of(waiting[shown]) <= time_s + 1e-12):
                outcomes |= waiting[shown][0] == "/outcome"
                decided |= waiting[shown][0] == "/controller/decision"
                self.on(*waiting[shown])
                shown += 1
            if outcomes or decided:
                logger.sort_figures()
        self.waiting, self.clouds, self.rows = [], {}, None

    def _event(self, data):
        self.logger.figures.event(data["classification"])
        self.detected[data["key"]] = data["classification"]
        self.events[data["event_id"]] = data["key"]
        text = f"cell {data['key']}: detected type {data['classification']} (fluorescence {data['fluorescence']:.2f}"
        text += f", {data['velocity'] * 1e3:.1f} mm/s)" if data.get("velocity") is not None else ")"
        self.logger.event(data["time"], data["key"], self._provisional(data["key"]), text)

    def _decision(self, data):
        key = self.events.get(data["event_id"])
        if key is not None:
            self.actions[key] = data["action"]
        self.logger.figures.decision(data["action"])
        pulsed = data["event_id"] if self.batches else None          # format 3: the drive from the pulses
        self.logger.text(decision_text(data["event_id"], data["action"], data.get("reason")),
                         level="WARN" if data["action"] == "abort" else "INFO")
        if data["action"] == "sort" and data.get("pulse_on") is not None:
            self.pulses[data["event_id"]] = (data["pulse_on"], data["pulse_off"])
            self.logger.pulse(data["pulse_on"], data["pulse_off"], event_id=pulsed)
        elif data["action"] == "abort" and data["event_id"] in self.pulses:
            self.logger.pulse(*self.pulses.pop(data["event_id"]), aborted=True, event_id=pulsed)

    def _provisional(self, key: int) -> str:
        return provisional_class(self.detected.get(key), self.actions.get(key))

    def _settle(self, data) -> str:
        """The outcome class of a format-1 recording's cell, from the events and decisions read so far."""
        key = data["key"]
        for event_id in [e for e, k in self.events.items() if k == key]:
            del self.events[event_id]
        return outcome_class({"outlet": data["outlet"], "true_class": self.true_class(data["type"]),
                              "detected_class": self.detected.pop(key, None), "decision": self.actions.pop(key, None)})


def _by_key(points) -> dict:
    """A point cloud's points by cell key."""
    return {key: points[points["key"] == key] for key in set(points["key"].tolist())}


def _row(rows: dict, index: int) -> dict:
    """Row ``index`` of a ``/cells/rows`` message as a ``/cells`` cell."""
    cell = {name: column[index] for name, column in rows.items() if name not in ("time", "count")}
    cell["fate"] = "in_channel"
    return cell


def _time_of(item) -> float:
    """The simulated time of a waiting message (events: detection; decisions and outcomes: when shown)."""
    topic, data = item
    return data.get("time", 0.0) if data.get("time") is not None else 0.0


def _checked_field(data: dict) -> dict:
    """A ``/flow/velocity`` payload whose image (1 um pixels over its grid's extent) is at most
    ``MAX_FIELD_PIXELS``, with as many samples as its shape says; ValueError otherwise (a malformed message)."""
    x, y = (np.asarray(data[key], dtype=float) for key in ("x_um", "y_um"))
    rows, columns = data["shape"]
    if x.ndim != 1 or y.ndim != 1 or (rows, columns) != (len(y), len(x)) or len(x) < 2 or len(y) < 2 \
            or not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("a /flow/velocity message whose grid does not match its shape")
    pixels = (x[-1] - x[0]) * (y[-1] - y[0])
    if not 0 < pixels <= MAX_FIELD_PIXELS or not 0 < rows * columns <= MAX_FIELD_PIXELS:
        raise ValueError(f"a /flow/velocity message of {pixels:.3g} square um (at most {MAX_FIELD_PIXELS:,})")
    return data


def replay(path: Path, target, progress=None) -> dict:
    """Re-log the recording at ``path`` to the Rerun ``target``, message by message (memory independent of the
    recording's length); a damaged file replays what comes before the damage."""
    metadata, channels, problem = read_metadata(path)
    scenario = scenario_from_toml(metadata["scenario_toml"], "scenario_toml") if "scenario_toml" in metadata \
        else Scenario()
    columns = metadata.get("recording_format", "1") >= "3"
    # the live loop's small batches whatever the target: what a replay holds stays small
    logger = RerunLogger(scenario, detection_window(metadata), target, batch_rows=BATCH_ROWS,
                         batch_seconds=BATCH_SECONDS, membranes=metadata.get("model") not in POINT_LIKE)
    replayer = _Replayer(logger, scenario, int(metadata.get("time_origin_unix_ns", 0)), metres=columns)
    steps = count = 0
    last_time = 0.0
    try:
        for topic, data in messages(path, channels):
            count += 1
            if columns:
                if topic == "/loop/steps" and data["time"]:
                    steps += len(data["time"])
                    last_time = data["time"][-1]
                replayer.batched(topic, data)
            elif topic == "/loop/step":
                steps += 1
                last_time = data["time"]
                logger.time(data["time"], data["step"])
                logger.idt(data["idt"])
            else:
                replayer.on(topic, data)
    except Damaged as error:
        problem = problem or str(error)
    finally:
        if columns and replayer.waiting:         # a torn tail: what came after the last whole batch
            replayer.on_all_waiting()
        logger.close()
    ending = metadata.get("_run_end", {})
    return {"steps": steps, "messages": count, "last_time_ms": last_time * 1e3, "damaged": bool(problem),
            "problem": problem, "format": metadata.get("recording_format", "1"),
            "run_status": ending.get("status"), "run_reason": ending.get("reason", "")}
