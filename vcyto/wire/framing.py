"""Frames of the wire protocol: a 4-byte big-endian length, then that many bytes of one UTF-8 JSON object.

``encode`` makes a frame of a message (a dict with a string ``type``); ``Frames`` takes the bytes as they come
off a socket and gives back whole messages, refusing a frame longer than ``MAX_MESSAGE`` before reading it,
bytes that are not UTF-8 JSON, JSON that is not an object with a string ``type``, and the non-standard
constants NaN and Infinity (``WireError``, one line naming the cause). docs/wire-protocol.md is the spec.
"""

from __future__ import annotations

import struct

import orjson

from controller.protocol import ControllerError

MAX_MESSAGE = 1 << 20              # bytes of JSON in one frame (1 MiB); a longer frame is refused unread
HEADER = struct.Struct(">I")       # the frame's length: 4 bytes, big-endian, unsigned


class WireError(ControllerError):
    """The peer broke the wire protocol (a malformed, oversized or unexpected message, a wrong version)."""


def encode(message: dict) -> bytes:
    """The frame of ``message`` (compact JSON; the messages of ``messages`` hold finite numbers only)."""
    body = orjson.dumps(message)
    if len(body) > MAX_MESSAGE:
        raise WireError(f"a {message.get('type')} message of {len(body)} bytes is longer than the protocol's "
                        f"{MAX_MESSAGE} bytes")
    return HEADER.pack(len(body)) + body


def decode(body: bytes) -> dict:
    """The message in one frame's bytes (``WireError`` if they are not a JSON object with a string ``type``)."""
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise WireError(f"malformed message: its {len(body)} bytes are not UTF-8 ({_preview(body)})") from None
    try:
        message = orjson.loads(text)          # strict RFC 8259: NaN and Infinity are refused
    except orjson.JSONDecodeError as error:
        raise WireError(f"malformed message: not JSON ({' '.join(str(error).split())}: {_preview(body)})") from None
    if not isinstance(message, dict) or not isinstance(message.get("type"), str):
        raise WireError(f"malformed message: a JSON object with a string \"type\" is required ({_preview(body)})")
    return message


def _preview(data: bytes, width: int = 40) -> str:
    shown = data[:width].decode("utf-8", "backslashreplace").encode("unicode_escape").decode("ascii")
    return shown + ("..." if len(data) > width else "")


class Frames:
    """Whole messages out of a byte stream: ``feed(bytes)`` then ``pop()`` until it gives None."""

    def __init__(self, limit: int = MAX_MESSAGE):
        self.limit = limit
        self._buffer = bytearray()

    def feed(self, data: bytes) -> None:
        self._buffer += data
        if len(self._buffer) >= HEADER.size:
            self._check_length()

    def _check_length(self) -> int:
        (length,) = HEADER.unpack_from(self._buffer)
        if length > self.limit:
            raise WireError(f"oversized message: a frame of {length} bytes announced (at most {self.limit}; or the "
                            f"peer does not speak this protocol: it sent {_preview(bytes(self._buffer[:16]), 16)})")
        if length == 0:
            raise WireError("malformed message: an empty frame (length 0)")
        return length

    def pop(self) -> dict | None:
        """The next whole message, or None until more bytes come."""
        if len(self._buffer) < HEADER.size:
            return None
        length = self._check_length()
        end = HEADER.size + length
        if len(self._buffer) < end:
            return None
        body = bytes(self._buffer[HEADER.size:end])
        del self._buffer[:end]
        return decode(body)

    def wanted(self) -> int:
        """Bytes that complete the message begun (its header first), at least 1."""
        if len(self._buffer) < HEADER.size:
            return HEADER.size - len(self._buffer)
        return max(1, HEADER.size + self._check_length() - len(self._buffer))

    @property
    def partial(self) -> int:
        """Bytes of a message begun but not complete (a peer that closes now cut a message short)."""
        return len(self._buffer)
