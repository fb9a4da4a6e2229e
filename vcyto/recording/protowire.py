"""Protobuf's wire format written directly, for the Foxglove messages a long recording writes per event and per step.

Building a message through the protobuf classes costs tens of microseconds for a scene entity (each nested
message is built, then copied into its parent); a recording writes one per detector event and per cell that
leaves, and a point cloud per recorded step. The functions here write the same messages as bytes: the fields
that never change are serialised once by the protobuf classes, the rest written in the wire format
(https://protobuf.dev/programming-guides/encoding/): a field is its key (number << 3 | wire type), then a varint,
8 bytes of a double, or a length and the bytes of a string or nested message. Fields are written in field-number
order, and a message's parts may be concatenated (protobuf reads a concatenation as the merged message), which is
how the fixed parts are joined to the varying ones. ``tests/test_recording_formats.py`` holds every message built
here equal to the one the protobuf classes build.
"""

from __future__ import annotations

import functools
import math
import struct

import numpy as np

VARINT, FIXED64, LENGTH = 0, 1, 2
_DOUBLE = struct.Struct("<d")
_BYTE = [bytes((value,)) for value in range(0x80)]      # the one-byte varints


def varint(value: int) -> bytes:
    """A non-negative integer as a varint (7 bits a byte, lowest first, the high bit set on all but the last)."""
    if value < 0x80:
        return _BYTE[value]
    if value < 0x4000:
        return bytes((value & 0x7F | 0x80, value >> 7))
    if value < 0x200000:
        return bytes((value & 0x7F | 0x80, value >> 7 & 0x7F | 0x80, value >> 14))
    if value < 0x10000000:
        return bytes((value & 0x7F | 0x80, value >> 7 & 0x7F | 0x80, value >> 14 & 0x7F | 0x80, value >> 21))
    if value < 0x800000000:                      # a timestamp's nanoseconds or seconds
        return bytes((value & 0x7F | 0x80, value >> 7 & 0x7F | 0x80, value >> 14 & 0x7F | 0x80,
                      value >> 21 & 0x7F | 0x80, value >> 28))
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def key(number: int, wire_type: int) -> bytes:
    tag = number << 3 | wire_type
    return _BYTE[tag] if tag < 0x80 else varint(tag)


def field(number: int, data: bytes) -> bytes:
    """A length-delimited field: a string, bytes or a nested message's serialisation (written even when empty: a
    nested message that is present)."""
    tag, size = number << 3 | LENGTH, len(data)
    return ((_BYTE[tag] if tag < 0x80 else varint(tag)) + (_BYTE[size] if size < 0x80 else varint(size))) + data


def text(number: int, value: str) -> bytes:
    """A string field (left out when empty)."""
    return field(number, value.encode()) if value else b""


def data(number: int, value: bytes) -> bytes:
    """A bytes field (left out when empty)."""
    return field(number, value) if value else b""


def double(number: int, value: float) -> bytes:
    """A double field (left out when it is +0.0, as proto3 serialises a message)."""
    return key(number, FIXED64) + _DOUBLE.pack(value) if value or math.copysign(1.0, value) < 0 else b""


def integer(number: int, value: int) -> bytes:
    """A non-negative integer field (int32, int64, uint32, an enum; left out when it is 0)."""
    return key(number, VARINT) + varint(value) if value else b""


def timestamp(unix_ns: int) -> bytes:
    """A ``google.protobuf.Timestamp`` (seconds 1, nanos 2) of a time in ns since the epoch (>= 0)."""
    seconds, nanos = divmod(unix_ns, 1_000_000_000)
    return _seconds(seconds) + integer(2, nanos)


def stamp(number: int, unix_ns: int) -> bytes:
    """``timestamp(unix_ns)`` as field ``number`` (< 16) of its message: ``field(number, timestamp(unix_ns))`` in
    fewer calls (a recording writes one per step and per log line)."""
    seconds, nanos = divmod(unix_ns, 1_000_000_000)
    body = _seconds(seconds) + (b"\x10" + varint(nanos) if nanos else b"")
    return bytes((number << 3 | LENGTH, len(body))) + body       # the body: at most 16 bytes


@functools.lru_cache(maxsize=4)
def _seconds(seconds: int) -> bytes:
    """Field 1 of a Timestamp (the same for every message of a second)."""
    return integer(1, seconds)


# one repeated ``foxglove.Point3`` field element per row: key, length 18, then x and y (doubles; z = 0 left out)
_POINT3 = np.dtype([("key", "u1"), ("length", "u1"), ("x_key", "u1"), ("x", "<f8"), ("y_key", "u1"), ("y", "<f8")])
POINT3_BYTES = _POINT3.itemsize           # a point's bytes (unless a coordinate is +0.0)


def points(number: int, xy: np.ndarray) -> bytes:
    """A repeated ``Point3`` field ``number`` (< 16) of the (n, 2) array ``xy`` (z = 0), written as arrays; a point
    with a coordinate +0.0, which proto3 leaves out, is written point by point."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if ((xy == 0) & ~np.signbit(xy)).any():
        return b"".join(field(number, double(1, x) + double(2, y)) for x, y in xy.tolist())
    rows = np.zeros(len(xy), dtype=_POINT3)
    rows["key"], rows["length"] = number << 3 | LENGTH, _POINT3.itemsize - 2
    rows["x_key"], rows["y_key"] = 0x09, 0x11
    rows["x"], rows["y"] = xy[:, 0], xy[:, 1]
    return rows.tobytes()
