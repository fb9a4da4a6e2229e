"""A sorting controller in its own process: purity mode over vcyto's wire protocol (docs/wire-protocol.md).

Standard library only; it imports nothing of vcyto, so it shows what a controller in any language must do:
listen, answer the handshake, answer each event with its decisions, say bye. Run it and point vcyto at it:

    python3 examples/controllers/purity_server.py --listen tcp:127.0.0.1:7070 &
    vcyto stream --model rom --count 100 --controller-connect tcp:127.0.0.1:7070

or let vcyto start it (vcyto says where to listen through {address} and VCYTO_CONTROLLER_ADDRESS):

    vcyto stream --model rom --count 100 --controller-exec "python3 examples/controllers/purity_server.py --once"

It listens on 127.0.0.1 unless told otherwise (an open port lets anyone who reaches it drive the sorter).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import struct
import sys

PROTOCOL, VERSION = "vcyto-controller", 1
MAX_MESSAGE = 1 << 20                  # bytes of JSON in one frame
HEADER = struct.Struct(">I")
REORDER_SLACK = 1e-3                   # s: recent events are kept this much beyond the envelope's reach


class Purity:
    """Purity mode: sort each type-II event unless a type-I event's predicted arrival falls in the envelope
    widened by twice the timing error; a type-I event aborts the earlier sorts whose widened envelope holds it,
    if their pulse has not started by its detection."""

    def __init__(self, facts: dict):
        self.delay, self.velocity = facts["sort_delay"], facts["reference_velocity"]
        self.lead, self.pulse = facts["lead"], facts["pulse"]
        widen = 2 * facts["timing_error"]
        self.low, self.high = facts["envelope"][0] - widen, facts["envelope"][1] + widen
        self.reach = max(self.high, -self.low, 0.0)
        self.recent = []               # [event_id, classification, arrival, decision dict], oldest first

    def on_event(self, event: dict) -> list[dict]:
        time = event["time"]
        arrival = time + self.delay * self.velocity / max(event["velocity"], 1e-9)
        self.recent = [entry for entry in self.recent if entry[2] >= arrival - self.reach - REORDER_SLACK]
        if event["classification"] == "II":
            answer = [self._sort(event["event_id"], time, arrival)]
        else:
            answer = self._aborts(event["event_id"], time, arrival)
            answer.append(_decision(event["event_id"], "pass", arrival))
        self.recent.append([event["event_id"], event["classification"], arrival, answer[-1]])
        return answer

    def _sort(self, event_id: int, time: float, arrival: float) -> dict:
        for other_id, classification, other_arrival, _ in self.recent:
            if classification == "I" and self.low <= other_arrival - arrival <= self.high:
                return _decision(event_id, "abort", arrival, reason=f"type-I event {other_id} inside the envelope")
        on = arrival - self.lead
        off = on + self.pulse
        if off <= time:
            return _decision(event_id, "abort", arrival, reason="too late: the pulse would be over")
        return _decision(event_id, "sort", arrival, on, off)

    def _aborts(self, event_id: int, time: float, arrival: float) -> list[dict]:
        aborts = []
        for entry in self.recent:
            decided = entry[3]
            if decided["action"] == "sort" and decided["pulse_on"] > time \
                    and self.low <= arrival - entry[2] <= self.high:
                entry[3] = _decision(entry[0], "abort", entry[2], reason=f"type-I event {event_id} inside its envelope")
                aborts.append(entry[3])
        return aborts


def _decision(event_id, action, arrival, pulse_on=None, pulse_off=None, reason=""):
    return {"event_id": event_id, "action": action, "arrival": arrival, "pulse_on": pulse_on, "pulse_off": pulse_off,
            "reason": reason}


def send(sock: socket.socket, message: dict) -> None:
    body = json.dumps(message, separators=(",", ":"), allow_nan=False).encode()
    sock.sendall(HEADER.pack(len(body)) + body)


def receive(stream) -> dict | None:
    """The next message (None when vcyto closed the connection)."""
    header = stream.read(HEADER.size)
    if len(header) < HEADER.size:
        return None
    (length,) = HEADER.unpack(header)
    if not 0 < length <= MAX_MESSAGE:
        raise ValueError(f"a frame of {length} bytes (at most {MAX_MESSAGE})")
    body = stream.read(length)
    if len(body) < length:
        return None
    return json.loads(body)


def serve_connection(sock: socket.socket, make=Purity) -> None:
    """One run: the handshake, then an answer to each event until vcyto says end."""
    stream = sock.makefile("rb")
    controller = None
    while (message := receive(stream)) is not None:
        kind = message.get("type")
        if kind == "hello":
            if message.get("protocol") != PROTOCOL or message.get("version") != VERSION:
                send(sock, {"type": "error", "message": f"this controller speaks {PROTOCOL} version {VERSION}"})
                return
            controller = make(message["facts"])
            send(sock, {"type": "welcome", "protocol": PROTOCOL, "version": VERSION, "name": "purity_server.py",
                        "software": "1.0", "capabilities": ["decisions"]})
        elif kind == "event" and controller is not None:
            send(sock, {"type": "decisions", "event_id": message["event_id"],
                        "decisions": controller.on_event(message)})
        elif kind == "end":
            send(sock, {"type": "bye"})
            return
        elif kind == "error":
            print(f"purity_server: vcyto reported an error: {message.get('message')}", file=sys.stderr)
            return
        else:
            send(sock, {"type": "error", "message": f"unexpected message {kind!r}"})
            return


def listen(address: str) -> socket.socket:
    kind, _, rest = address.partition(":")
    if kind == "unix":
        if os.path.exists(rest):
            os.unlink(rest)
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(rest)
    elif kind == "tcp":
        host, _, port = rest.rpartition(":")
        server = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind((host.strip("[]") or "127.0.0.1", int(port)))
    else:
        raise SystemExit(f"purity_server: an address is tcp:HOST:PORT or unix:PATH (got {address!r})")
    server.listen(1)
    return server


def main(argv=None, make=Purity) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--listen", default=os.environ.get("VCYTO_CONTROLLER_ADDRESS", "tcp:127.0.0.1:7070"),
                        help="tcp:HOST:PORT or unix:PATH (default $VCYTO_CONTROLLER_ADDRESS, else tcp:127.0.0.1:7070)")
    parser.add_argument("--once", action="store_true", help="exit after one run")
    args = parser.parse_args(argv)
    server = listen(args.listen)
    while True:
        connection, _ = server.accept()
        if connection.family != socket.AF_UNIX:
            connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with connection:
            try:
                serve_connection(connection, make)
            except (OSError, ValueError, KeyError) as error:
                print(f"purity_server: {type(error).__name__}: {error}", file=sys.stderr)
        if args.once:
            return


if __name__ == "__main__":
    main()
