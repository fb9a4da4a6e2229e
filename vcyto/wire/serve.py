"""A Python controller served over the wire protocol: ``python -m vcyto.wire.serve --listen ADDRESS``.

The controller end of ``WirePort`` for any object implementing ``controller.protocol.Controller`` (and
``Drives``: it then offers the ``drive`` capability and answers each ``period``): by default
the built-in ``SortController``, its settings taken from the device facts of the hello (``--mode``: purity
unless told), or a controller of one's own (``--controller FILE.py:NAME``, as ``vcyto stream --controller-from``).
It lets a Python controller run in a process, or on a machine, of its own; ``vcyto bench wire`` times the loop
through it. It listens on 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import sys
import time

from controller.events import DetectorEvent
from controller.protocol import DeviceFacts, Drives, Starts
from controller.sorter import MODES, ControllerSettings, SortController

from .framing import Frames, WireError, encode
from .messages import DRIVE, PROTOCOL, REQUIRED, VERSION
from .port import ENV_ADDRESS, parse_address, readable

EVENT_FIELDS = ("event_id", "time", "fluorescence", "scatter", "velocity", "classification", "key")


def facts_of(hello: dict) -> DeviceFacts:
    facts = dict(hello["facts"])
    facts["envelope"], facts["detection_window"] = tuple(facts["envelope"]), tuple(facts["detection_window"])
    return DeviceFacts(**facts)


def settings_of(facts: DeviceFacts, mode: str = "purity") -> ControllerSettings:
    """The built-in controller's settings that the device facts describe."""
    return ControllerSettings(delay=facts.sort_delay, reference_velocity=facts.reference_velocity, lead=facts.lead,
                              pulse=facts.pulse, mode=mode, envelope=facts.envelope, timing_error=facts.timing_error)


def _decision(decision) -> dict:
    def seconds(value):
        return value if math.isfinite(value) else None
    return {"event_id": decision.event_id, "action": decision.action, "arrival": seconds(decision.arrival),
            "pulse_on": seconds(decision.pulse_on), "pulse_off": seconds(decision.pulse_off),
            "reason": decision.reason}


def _messages(sock: socket.socket, spin: float = 0.0):
    """The messages off ``sock``; ``spin``: seconds to poll for the next one before sleeping in ``recv``."""
    frames = Frames()
    while True:
        while (message := frames.pop()) is not None:
            yield message
        if spin > 0:
            _poll(sock, spin)
        data = sock.recv(1 << 16)
        if not data:
            return
        frames.feed(data)


def _poll(sock: socket.socket, spin: float) -> None:
    """Busy-wait up to ``spin`` s for ``sock`` to have something to read: a processor that never idles wakes at
    once (a virtual machine's idle processor can take milliseconds to be scheduled again)."""
    end = time.perf_counter() + spin
    while time.perf_counter() < end:
        if readable(sock, 0.0):
            return


def serve_connection(sock: socket.socket, make, spin: float = 0.0) -> None:
    """One run: answer the hello, then each event with ``make(facts)``'s decisions, until ``end`` (``spin``: see
    ``_poll``)."""
    controller = None
    for message in _messages(sock, spin):
        kind = message["type"]
        if kind == "hello":
            if message.get("protocol") != PROTOCOL or message.get("version") != VERSION:
                sock.sendall(encode({"type": "error", "message": f"this controller speaks {PROTOCOL} {VERSION}"}))
                return
            facts = facts_of(message)
            controller = make(facts)
            if isinstance(controller, Starts):
                controller.start(facts)
            offers = [REQUIRED, DRIVE] if isinstance(controller, Drives) else [REQUIRED]
            sock.sendall(encode({"type": "welcome", "protocol": PROTOCOL, "version": VERSION,
                                 "name": getattr(controller, "name", type(controller).__name__),
                                 "software": "vcyto.wire.serve", "capabilities": offers}))
        elif kind == "event" and controller is not None:
            event = DetectorEvent(*(message[name] for name in EVENT_FIELDS))
            answer = controller.on_event(event, message["clock"]) or ()
            sock.sendall(encode({"type": "decisions", "event_id": event.event_id,
                                 "decisions": [_decision(decision) for decision in answer]}))
        elif kind == "period" and isinstance(controller, Drives):
            clock = message["clock"]
            sock.sendall(encode({"type": "drive", "clock": clock, "level": float(controller.drive(clock))}))
        elif kind == "end":
            sock.sendall(encode({"type": "bye"}))
            return
        else:
            sock.sendall(encode({"type": "error", "message": f"unexpected message {kind!r}"}))
            return


def listen(address: str) -> socket.socket:
    parsed = parse_address(address)
    if parsed[0] == "unix":
        if os.path.exists(parsed[1]):
            os.unlink(parsed[1])
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(parsed[1])
    else:
        server = socket.socket(socket.AF_INET6 if ":" in parsed[1] else socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(parsed[1:])
    server.listen(1)
    return server


def factory(spec: str | None, mode: str):
    """``facts -> controller``: the built-in one in ``mode``, or ``spec``'s (``vcyto.plugins``)."""
    if spec is None:
        return lambda facts: SortController(settings_of(facts, mode))
    from .. import plugins
    return lambda facts: plugins.controller(spec, settings_of(facts, mode))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vcyto.wire.serve", description=__doc__.split("\n")[0])
    parser.add_argument("--listen", default=os.environ.get(ENV_ADDRESS, "tcp:127.0.0.1:7070"), metavar="ADDRESS",
                        help=f"tcp:HOST:PORT or unix:PATH (default ${ENV_ADDRESS}, else tcp:127.0.0.1:7070)")
    parser.add_argument("--controller", metavar="FILE.py:NAME", help="a controller of one's own (default: built-in)")
    parser.add_argument("--mode", choices=MODES, default="purity", help="the built-in controller's mode")
    parser.add_argument("--once", action="store_true", help="exit after one run")
    parser.add_argument("--spin", type=float, default=0.0, metavar="SECONDS",
                        help="after each answer, poll for the next message this long before sleeping (default 0): "
                             "keeps the processor awake for paced real time, at the cost of a busy core")
    args = parser.parse_args(argv)
    try:
        server = listen(args.listen)
    except (ValueError, OSError) as error:
        print(f"vcyto.wire.serve: error: --listen: {error}", file=sys.stderr)
        return 2
    make = factory(args.controller, args.mode)
    while True:
        connection, _ = server.accept()
        if connection.family != socket.AF_UNIX:
            connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with connection:
            try:
                serve_connection(connection, make, args.spin)
            except (OSError, WireError, KeyError, TypeError, ValueError) as error:
                print(f"vcyto.wire.serve: {type(error).__name__}: {error}", file=sys.stderr)
        if args.once:
            return 0


if __name__ == "__main__":
    sys.exit(main())
