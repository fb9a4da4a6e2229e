"""Foxglove well-known messages (protobuf encoding) of a run, for the MCAP recording.

Any tool that knows the Foxglove schemas draws these with no vcyto installed: Foxglove's 3D panel (scene and
point cloud), Image panel (speed), Log panel (events); Rerun's MCAP importer turns ``foxglove.PointCloud`` into
``Points3D``, ``foxglove.RawImage`` into ``Image`` and ``foxglove.Log`` into ``TextLog``. Coordinates are the
plant's in metres, as Foxglove's conventions have them, y up (frame ``channel``: x along the channel, y across
it, z = 0); the functions here take micrometres (the plant's figures read in um) and write metres. Detector
markers and cell paths have lifetimes (``MARKER_LIFETIME``, ``PATH_LIFETIME`` of simulated time, which is the
recording's timeline), so the 3D panel shows the recent ones, not every cell of a long run.
"""

from __future__ import annotations

import base64
import functools
import struct

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp

from ..classes import CLASS_COLOURS, CLASS_NAMES
from . import protowire as wire

FRAME = "channel"
TOPICS = {"/foxglove/scene": SceneUpdate, "/foxglove/membranes": PointCloud, "/foxglove/speed": RawImage,
          "/foxglove/log": Log}
POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                  ("alpha", "u1"), ("key", "<u4"), ("class", "u1")])
_NUMERIC = {"<f4": PackedElementField.FLOAT32, "|u1": PackedElementField.UINT8, "<u4": PackedElementField.UINT32}
_POINT = struct.Struct("<fffBBBBIB")                 # one row of POINT
POINT_FIELDS = [PackedElementField(name=name, offset=POINT.fields[name][1], type=_NUMERIC[POINT.fields[name][0].str])
                for name in POINT.names]
SPEED_PIXEL_UM = 2.0
METRE = 1e-6                                     # metres per micrometre: what the functions write
MARKER_LIFETIME = Duration(nanos=2_000_000)      # 2 ms of simulated time
PATH_LIFETIME = Duration(nanos=10_000_000)       # 10 ms
_CLASS_RGB = np.array([CLASS_COLOURS[name] for name in CLASS_NAMES], dtype=np.uint8).reshape(-1, 3)
_CLASS_RGBA = np.column_stack([_CLASS_RGB, np.full(len(_CLASS_RGB), 255, np.uint8)])
_COLOUR_BYTES = slice(POINT.fields["red"][1], POINT.fields["alpha"][1] + 1)      # red, green, blue, alpha: adjacent
LEVELS = {"INFO": Log.INFO, "WARN": Log.WARNING, "WARNING": Log.WARNING, "ERROR": Log.ERROR}


def stamp(unix_ns: int) -> Timestamp:
    return Timestamp(seconds=unix_ns // 1_000_000_000, nanos=unix_ns % 1_000_000_000)


def _binary(values_um):
    """Micrometres in metres, rounded to 1/1024 um (about 1 nm), as float32 (an array, or a tuple of Python floats
    for a tuple)."""
    if isinstance(values_um, tuple):
        return tuple(round(value * 1024.0) / 1024.0 * METRE for value in values_um)
    return (np.round(np.asarray(values_um, dtype=float) * 1024.0) / 1024.0 * METRE).astype(np.float32)


# a pose with every field set: Rerun's MCAP importer reads an absent position as a column it cannot decode
_UPRIGHT = Quaternion(w=1.0)
_IDENTITY = Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=_UPRIGHT)
_SPHERE = Vector3(x=4.0 * METRE, y=4.0 * METRE, z=4.0 * METRE)
# the messages below are built for every detector event and every cell that leaves: their constant parts are made
# once (a message given to another is copied into it)


def membranes(unix_ns: int, cells) -> PointCloud:
    """Every cell's membrane points (or its centroid for point-like models) with its key, class id and colour.

    ``cells``: (key, class id, RGB, points in um: an (n, 2) array, or an (x, y) pair for a point-like cell)."""
    return PointCloud.FromString(Membranes().message(unix_ns, cells))


class Membranes:
    """``membranes`` serialised fast, for every step of a recording: the fields that never change (frame, pose,
    point layout) are serialised once, the step's timestamp and points around them in field order (protobuf reads
    the concatenation as one message, and it is the bytes that message serialises to)."""

    def __init__(self):
        self._fixed = PointCloud(frame_id=FRAME, pose=_IDENTITY, point_stride=POINT.itemsize,
                                 fields=POINT_FIELDS).SerializeToString()

    def message(self, unix_ns: int, cells) -> bytes:
        return self.packed(unix_ns, _points(cells))

    def packed(self, unix_ns: int, data: bytes) -> bytes:
        """The message of points already packed as ``POINT`` rows (``centroids``)."""
        return wire.stamp(1, unix_ns) + self._fixed + wire.data(6, data)


def centroids(x_um, y_um, keys, class_ids) -> np.ndarray:
    """Point-like cells as ``POINT`` rows, the rows ``membranes`` writes for them, built as arrays (for many steps'
    cells at once: slices of the result are each step's points)."""
    count = len(keys)
    data = np.zeros(count, dtype=POINT)
    data["x"], data["y"] = _binary(np.array((x_um, y_um), dtype=float).reshape(2, count))
    ids = np.array(class_ids, dtype=np.intp)
    data.view(np.uint8).reshape(count, POINT.itemsize)[:, _COLOUR_BYTES] = _CLASS_RGBA[ids]   # red .. alpha
    data["key"], data["class"] = keys, ids
    return data


def _points(cells) -> bytes:
    """The packed ``POINT`` rows of ``membranes``' cells."""
    if all(isinstance(points, tuple) for _, _, _, points in cells):       # point-like cells: one row each
        return b"".join(_POINT.pack(*_binary(points), 0.0, *colour, 255, key, class_id)
                        for key, class_id, colour, points in cells)
    else:
        arrays = [np.asarray(points, dtype=float).reshape(-1, 2) for _, _, _, points in cells]
        counts = [len(points) for points in arrays]
        data = np.zeros(sum(counts), dtype=POINT)
        points = np.concatenate(arrays)
        data["x"], data["y"] = _binary(points[:, 0]), _binary(points[:, 1])
        colours = np.repeat(np.array([colour for _, _, colour, _ in cells], dtype=np.uint8), counts, axis=0)
        data["red"], data["green"], data["blue"], data["alpha"] = colours[:, 0], colours[:, 1], colours[:, 2], 255
        data["key"] = np.repeat([key for key, _, _, _ in cells], counts)
        data["class"] = np.repeat([class_id for _, class_id, _, _ in cells], counts)
        return data.tobytes()


def membrane_points(message: PointCloud) -> np.ndarray:
    """The structured points of a ``membranes`` message (fields of ``POINT``; x and y in metres, recordings of
    format 2 in um)."""
    return np.frombuffer(message.data, dtype=POINT)


def log(unix_ns: int, text: str, level: str = "INFO") -> Log:
    return Log(timestamp=stamp(unix_ns), level=LEVELS.get(level, Log.INFO), message=text, name="vcyto")


_LOG_LEVELS = {name: wire.integer(2, number) for name, number in LEVELS.items()}
_LOG_NAME = wire.text(4, "vcyto")


def log_line(unix_ns: int, text: str, level: str = "INFO") -> bytes:
    """``log``'s message, serialised, written in the wire format (a recording writes a line per event, decision
    and outcome)."""
    return wire.stamp(1, unix_ns) + _LOG_LEVELS.get(level, _LOG_LEVELS["INFO"]) + wire.text(3, text) + _LOG_NAME


def _colour(rgb, alpha: float = 1.0) -> Color:
    return _colours(tuple(int(value) for value in rgb), alpha)


@functools.lru_cache(maxsize=256)
def _colours(rgb: tuple, alpha: float) -> Color:
    return Color(r=rgb[0] / 255, g=rgb[1] / 255, b=rgb[2] / 255, a=alpha)


def _line(points_um, rgb, thickness: float = METRE, loop: bool = False) -> LinePrimitive:
    return LinePrimitive(type=LinePrimitive.LINE_LOOP if loop else LinePrimitive.LINE_STRIP, thickness=thickness,
                         pose=_IDENTITY, color=_colour(rgb),
                         points=[Point3(x=x * METRE, y=y * METRE, z=0.0)
                                 for x, y in np.asarray(points_um, dtype=float).tolist()])


def _text(x: float, y: float, text: str, rgb=(230, 230, 230)) -> TextPrimitive:
    """A label at (x, y) um."""
    return TextPrimitive(pose=Pose(position=Vector3(x=x * METRE, y=y * METRE, z=0.0), orientation=_UPRIGHT),
                         billboard=True, font_size=12.0, scale_invariant=True, color=_colour(rgb), text=text)


def device(unix_ns: int, outlines) -> SceneUpdate:
    """The device drawn once (entities without a lifetime stay): ``outlines`` is (id, points in um, RGB, label)."""
    entities = []
    for entity_id, points, rgb, label in outlines:
        points = np.asarray(points, dtype=float)
        texts = [_text(float(points[:, 0].mean()), float(points[:, 1].max()) + 4.0, label, rgb)] if label else []
        entities.append(SceneEntity(timestamp=stamp(unix_ns), frame_id=FRAME, id=entity_id,
                                    lines=[_line(points, rgb)], texts=texts))
    return SceneUpdate(entities=entities)


def marker(unix_ns: int, entity_id: str, x_um: float, y_um: float, rgb, label: str) -> SceneEntity:
    """A detector event: a sphere where the cell was when it was detected, with its label, for
    ``MARKER_LIFETIME`` (the message ``Entities`` writes as bytes)."""
    sphere = SpherePrimitive(pose=Pose(position=Vector3(x=x_um * METRE, y=y_um * METRE, z=0.0),
                                       orientation=_UPRIGHT), size=_SPHERE, color=_colour(rgb, 0.8))
    return SceneEntity(timestamp=stamp(unix_ns), frame_id=FRAME, id=entity_id, lifetime=MARKER_LIFETIME,
                       spheres=[sphere], texts=[_text(x_um, y_um + 5.0, label, rgb)])


def path(unix_ns: int, key: int, points_um, rgb, label: str) -> SceneEntity:
    """A cell's centroid path, drawn when it has left, in the colour of its outcome class, for
    ``PATH_LIFETIME`` (the message ``Entities`` writes as bytes)."""
    points = np.asarray(points_um, dtype=float).reshape(-1, 2)
    return SceneEntity(timestamp=stamp(unix_ns), frame_id=FRAME, id=f"path/{key}", lifetime=PATH_LIFETIME,
                       lines=[_line(points, rgb, thickness=0.5 * METRE)],
                       texts=[_text(float(points[-1, 0]), float(points[-1, 1]), label, rgb)])


class Entities:
    """The scene entities a recording writes per detector event and per cell that leaves, as serialised bytes equal
    to ``marker``'s and ``path``'s messages, at a fraction of their cost: a marker is a copy of a template with
    its varying fields set; a path is written in protobuf's wire format (``vcyto.recording.protowire``), its
    points as an array (the protobuf classes build a message per point)."""

    def __init__(self):
        self._markers: dict = {}
        self._path_head = wire.text(2, FRAME)
        self._path_lifetime = wire.field(4, PATH_LIFETIME.SerializeToString())
        self._line_head = (wire.integer(1, LinePrimitive.LINE_STRIP) + wire.field(2, _IDENTITY.SerializeToString())
                           + wire.double(3, 0.5 * METRE))
        self._label_template = _text(0.0, 0.0, "x")

    def marker(self, unix_ns: int, entity_id: str, x_um: float, y_um: float, rgb, label: str) -> bytes:
        rgb = rgb if type(rgb) is tuple else tuple(rgb)      # a class colour is a tuple already
        template = self._markers.get(rgb)
        if template is None:
            template = self._markers[rgb] = marker(0, "", 0.0, 0.0, tuple(int(value) for value in rgb), "x")
        entity = SceneEntity()
        entity.CopyFrom(template)
        entity.timestamp.seconds, entity.timestamp.nanos = divmod(unix_ns, 1_000_000_000)
        entity.id = entity_id
        position = entity.spheres[0].pose.position
        position.x, position.y = x_um * METRE, y_um * METRE
        text = entity.texts[0]
        position = text.pose.position
        position.x, position.y = x_um * METRE, (y_um + 5.0) * METRE
        text.text = label
        return entity.SerializeToString()

    def path(self, unix_ns: int, key: int, points_um, rgb, label: str) -> bytes:
        return self.paths([(unix_ns, key, points_um, rgb, label)])[0]

    def paths(self, items) -> list[bytes]:
        """``path``'s entities of (unix_ns, key, points in um, RGB, label) items, their points written as one array."""
        if not items:
            return []
        shapes = [np.asarray(points, dtype=float).reshape(-1, 2) for _, _, points, _, _ in items]
        ends = np.cumsum([len(points) for points in shapes]).tolist()
        every = np.concatenate(shapes) * METRE
        packed = wire.points(5, every)
        size = wire.POINT3_BYTES if len(packed) == len(every) * wire.POINT3_BYTES else None    # else: +0.0s
        entities, start = [], 0
        for (unix_ns, key, _, rgb, label), points, end in zip(items, shapes, ends):
            rgb = tuple(int(value) for value in rgb)
            line = (self._line_head + (packed[start * size:end * size] if size else wire.points(5, every[start:end]))
                    + wire.field(6, _colour_bytes(rgb, 1.0)))
            text = TextPrimitive()
            text.CopyFrom(self._label_template)
            position = text.pose.position
            position.x, position.y = every[end - 1].tolist()
            text.text = label
            text.color.CopyFrom(_colours(rgb, 1.0))
            entities.append(wire.stamp(1, unix_ns) + self._path_head + wire.text(3, f"path/{key}")
                            + self._path_lifetime + wire.field(11, line) + wire.field(13, text.SerializeToString()))
            start = end
        return entities

    @staticmethod
    def scene(entities) -> bytes:
        """A ``SceneUpdate`` of entities written by ``marker`` and ``path``."""
        return b"".join(wire.field(2, entity) for entity in entities)


@functools.lru_cache(maxsize=256)
def _colour_bytes(rgb: tuple, alpha: float) -> bytes:
    return _colours(rgb, alpha).SerializeToString()



def speed_grid(payload: dict, pixel_um: float) -> np.ndarray:
    """Speed (m/s) of a ``/flow/velocity`` payload on a uniform grid of ``pixel_um`` pixels, nearest samples;
    row 0 at y = 0 (rows of increasing y), column 0 at x = 0."""
    rows, columns = payload["shape"]
    vx = np.frombuffer(base64.b64decode(payload["vx_f32_b64"]), dtype=np.float32).reshape(rows, columns)
    vy = np.frombuffer(base64.b64decode(payload["vy_f32_b64"]), dtype=np.float32).reshape(rows, columns)
    speed = np.hypot(vx, vy)
    x, y = np.asarray(payload["x_um"], dtype=float), np.asarray(payload["y_um"], dtype=float)
    centres_x = np.arange(x[0] + pixel_um / 2, x[-1], pixel_um)
    centres_y = np.arange(y[0] + pixel_um / 2, y[-1], pixel_um)
    return speed[np.ix_(_nearest(y, centres_y), _nearest(x, centres_x))]


def _nearest(grid, points):
    index = np.clip(np.searchsorted(grid, points), 1, len(grid) - 1)
    return np.where(points - grid[index - 1] < grid[index] - points, index - 1, index)


def speed_image(unix_ns: int, payload: dict) -> RawImage:
    """The flow speed in mm/s (32FC1, rounded to 1/256 mm/s), 2 um pixels, first row at the top wall (y = height)
    as images are read."""
    speed = np.round(speed_grid(payload, SPEED_PIXEL_UM)[::-1] * 1e3 * 256) / 256
    image = np.ascontiguousarray(speed, dtype="<f4")
    return RawImage(timestamp=stamp(unix_ns), frame_id=FRAME, width=image.shape[1], height=image.shape[0],
                    encoding="32FC1", step=image.shape[1] * 4, data=image.tobytes())
