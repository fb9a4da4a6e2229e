"""Controllers over the wire that misbehave on purpose, for tests/test_wire.py: `python wire_servers.py MODE`.

Each listens where vcyto says (VCYTO_CONTROLLER_ADDRESS), serves one run with the reference purity controller
(examples/controllers/purity_server.py) and breaks the protocol as MODE says:
- late: answers every third event (event_id % 3 == 2) LATE_BY seconds late, the others at once;
- die: kills itself (SIGKILL) on its fifth event;
- garbage: answers its third event with bytes that are not JSON;
- oversized: announces a 2 MiB frame in answer to its third event;
- version: welcomes with version 2 of the protocol;
- silent: welcomes, then never answers;
- stubborn: welcomes, never answers, never says bye, and ignores SIGTERM.
"""

import importlib.util
import json
import os
import signal
import socket
import struct
import sys
import threading
from pathlib import Path

LATE_BY = 0.3          # s (wall) a late answer waits: far beyond the deadline budget of the tests' real-time factor

_spec = importlib.util.spec_from_file_location(
    "purity_server", Path(__file__).resolve().parents[1] / "examples" / "controllers" / "purity_server.py")
purity_server = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(purity_server)


def frame(message: dict) -> bytes:
    body = json.dumps(message).encode()
    return struct.pack(">I", len(body)) + body


def serve(mode: str, sock: socket.socket) -> None:
    stream, lock = sock.makefile("rb"), threading.Lock()
    controller, count = None, 0

    def send(data: bytes):
        with lock:
            try:
                sock.sendall(data)
            except OSError:
                pass
    while (message := purity_server.receive(stream)) is not None:
        kind = message["type"]
        if kind == "hello":
            controller = purity_server.Purity(message["facts"])
            send(frame({"type": "welcome", "protocol": "vcyto-controller", "version": 2 if mode == "version" else 1,
                        "name": f"test server ({mode})", "software": "0", "capabilities": ["decisions"]}))
        elif kind == "event":
            count += 1
            answer = frame({"type": "decisions", "event_id": message["event_id"],
                            "decisions": controller.on_event(message)})
            if mode in ("silent", "stubborn"):
                continue
            if mode == "die" and count == 5:
                os.kill(os.getpid(), signal.SIGKILL)
            if mode == "garbage" and count == 3:
                answer = struct.pack(">I", 12) + b"\xff\x00not JSON!!"
            if mode == "oversized" and count == 3:
                answer = struct.pack(">I", 2 << 20) + b"{" * 1000
            if mode == "late" and message["event_id"] % 3 == 2:
                threading.Timer(LATE_BY, send, (answer,)).start()
            else:
                send(answer)
        elif kind == "end" and mode != "stubborn":
            send(frame({"type": "bye"}))
            return


def main():
    mode = sys.argv[1]
    if mode == "stubborn":
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    server = purity_server.listen(os.environ["VCYTO_CONTROLLER_ADDRESS"])
    connection, _ = server.accept()
    with connection:
        serve(mode, connection)
    while mode == "stubborn":
        signal.pause()


if __name__ == "__main__":
    main()
