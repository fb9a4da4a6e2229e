"""Finding, starting and reaching a Rerun viewer, and the layout (blueprint) it shows a run in.

What a run logs to the viewer (entities, colours, batching) is ``vcyto.recording.rerunlog``.
"""

from __future__ import annotations

import functools
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from sim.model.scenario import Scenario

from ..arrowshim import ready_pyarrow, spare_pandas_import  # noqa: F401  (spare_pandas_import: vcyto.cli's)

# the Rerun SDK logs connection trouble as multi-line Rust log records; vcyto reports it in one line instead
# (set RUST_LOG to see them)
os.environ.setdefault("RUST_LOG", "off")


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform in ("darwin", "win32")


def _accepts(family: int, address, timeout: float = 0.5) -> bool:
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.settimeout(timeout)
            probe.connect(address)
            return True
    except (OSError, ValueError):
        return False


def display_problem() -> str | None:
    """Why the display the environment names cannot be used (None: it can, or this platform has no such check).

    A viewer started without a reachable display exits, but only once it tries to open its window, which on a
    busy machine can take longer than the grace ``start_viewer`` gives it; so the display server itself is
    asked first: the Wayland socket, else the X server of ``DISPLAY`` (its Unix socket, abstract or in
    /tmp/.X11-unix, or TCP port 6000 + n for a remote one such as ssh's forwarding)."""
    if sys.platform in ("darwin", "win32"):
        return None
    wayland = os.environ.get("WAYLAND_DISPLAY")
    if wayland:
        path = wayland if os.path.isabs(wayland) else os.path.join(os.environ.get("XDG_RUNTIME_DIR", ""), wayland)
        if _accepts(socket.AF_UNIX, path):
            return None
    display = os.environ.get("DISPLAY", "")
    host, _, number = display.rpartition(":")
    number = number.split(".")[0]
    if number.isdigit():
        if host in ("", "unix"):
            socket_path = f"/tmp/.X11-unix/X{number}"
            if _accepts(socket.AF_UNIX, "\0" + socket_path) or _accepts(socket.AF_UNIX, socket_path):
                return None
        elif _accepts(socket.AF_INET, (host, 6000 + int(number))):
            return None
    elif display:
        return None                       # a form we do not parse (a launchd path...): let the viewer try
    shown = ", ".join(f"{name}={os.environ[name]}" for name in ("DISPLAY", "WAYLAND_DISPLAY") if os.environ.get(name))
    return f"no display server answers at {shown or 'the display named'}"


# --- finding, starting and reaching a viewer (the view itself is below) -------------------------------

VIEWER_PORT = 9876
VIEWER_START_TIMEOUT = 15.0     # s until the spawned viewer listens
VIEWER_GRACE = 1.0              # s it must then stay alive (a viewer without a usable display exits at once)
PROBE_SECONDS = 1.0             # s a viewer has to answer the handshake
FLUSH_SECONDS = 0.25            # s the run waits at its end for a viewer to take what is queued, and again to close
# the client's opening of HTTP/2, on which gRPC (and so the Rerun viewer's server) runs: the connection preface
# and an empty SETTINGS frame; a gRPC server answers with its own SETTINGS frame (RFC 9113, section 3.4)
_HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_SETTINGS = 4
URL_SCHEMES = ("rerun", "rerun+http", "rerun+https")


class ViewerUnavailable(Exception):
    """No viewer could be started or reached; ``str(error)`` says why in a few words."""


def find_viewer() -> Path | None:
    """The Rerun viewer binary that belongs to the installed rerun-sdk (its ``rerun_cli`` package, else the
    ``rerun`` script beside this Python), never whatever ``rerun`` comes first on PATH."""
    import importlib.util
    suffix = ".exe" if sys.platform.startswith("win") else ""
    candidates = []
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin:
        package = Path(spec.origin).parent
        candidates += [package / "Rerun.app" / "Contents" / "MacOS" / "Rerun", package / f"rerun{suffix}"]
    candidates.append(Path(sys.executable).parent / f"rerun{suffix}")
    return next((path for path in candidates if path.is_file() and os.access(path, os.X_OK)), None)


def parse_viewer_url(url: str) -> tuple[str, int]:
    """(host, port) of a viewer URL such as rerun+http://127.0.0.1:9876/proxy; ValueError in one line if not one."""
    parts = urlsplit(url.strip())
    try:
        port = parts.port
    except ValueError:
        port = -1
    if parts.scheme not in URL_SCHEMES or not parts.hostname or parts.path != "/proxy" or port == -1:
        raise ValueError(f"not a Rerun viewer URL: {url!r}; write e.g. rerun+http://127.0.0.1:9876/proxy")
    return parts.hostname, port or (443 if parts.scheme == "rerun+https" else VIEWER_PORT)


def listening(host: str, port: int, timeout: float = 2.0) -> bool:
    """Whether something accepts TCP connections at host:port."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except (OSError, ValueError):
        return False


def viewer_problem(host: str, port: int, secure: bool = False, timeout: float = PROBE_SECONDS) -> str | None:
    """Why what listens at host:port is not a Rerun viewer (None: it answers the gRPC handshake as the viewer's
    server does). Asked before a run streams to it: a program that accepts connections and never reads (or
    answers something else) would otherwise take the view and hold the run at its end."""
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection((host, port), timeout=timeout) as connection:
            if secure:
                import ssl
                context = ssl.create_default_context()
                context.set_alpn_protocols(["h2"])
                connection = context.wrap_socket(connection, server_hostname=host)
            connection.sendall(_HTTP2_PREFACE)
            header = b""
            while len(header) < 9:
                connection.settimeout(max(0.01, deadline - time.monotonic()))
                part = connection.recv(9 - len(header))
                if not part:
                    return "it closed the connection without answering the gRPC handshake"
                header += part
    except (socket.timeout, TimeoutError):
        return f"it did not answer the gRPC handshake within {timeout:g} s"
    except (OSError, ValueError) as error:
        return f"no connection ({getattr(error, 'strerror', None) or error})"
    if header[3] != _SETTINGS:
        return "it answered, but not as a gRPC server does"
    return None


def start_viewer(bind: str = "127.0.0.1", port: int | None = None) -> tuple[str, str]:
    """Start the installed Rerun viewer listening on ``bind``:``port`` (detached: it outlives the run), or find
    the one already listening there; (its URL, what was done). Raises ``ViewerUnavailable`` if it cannot be
    started, does not listen within ``VIEWER_START_TIMEOUT`` or exits at once (no usable display)."""
    port = port or VIEWER_PORT
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if listening("127.0.0.1", port, timeout=0.5):
        problem = viewer_problem("127.0.0.1", port)
        if problem is not None:
            raise ViewerUnavailable(f"a program listens on port {port} but is not a Rerun viewer ({problem})")
        return url, f"streaming to the viewer already listening on port {port}"
    binary = find_viewer()
    if binary is None:
        raise ViewerUnavailable("the rerun-sdk installation has no viewer binary")
    problem = display_problem()
    if problem is not None:
        raise ViewerUnavailable(problem)
    command = [str(binary), "--port", str(port), "--bind", bind, "--memory-limit", "75%", "--hide-welcome-screen"]
    try:
        process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL, start_new_session=True,
                                   env={**os.environ, "RERUN_APP_ONLY": "true"})
    except OSError as error:
        raise ViewerUnavailable(f"cannot start {binary}: {error.strerror or error}") from None
    deadline = time.monotonic() + VIEWER_START_TIMEOUT
    while not listening("127.0.0.1", port, timeout=0.2):
        if process.poll() is not None:
            raise ViewerUnavailable(f"the viewer exited at once (status {process.returncode}; no usable display?)")
        if time.monotonic() > deadline:
            process.terminate()
            raise ViewerUnavailable(f"the viewer did not listen on port {port} within {VIEWER_START_TIMEOUT:g} s")
        time.sleep(0.05)
    grace = time.monotonic() + VIEWER_GRACE
    while time.monotonic() < grace:
        if process.poll() is not None:
            raise ViewerUnavailable(f"the viewer exited at once (status {process.returncode}; no usable display?)")
        time.sleep(0.05)
    return url, f"started the Rerun viewer (pid {process.pid}, listening on {bind}:{port})"


_LEFT_BEHIND: list = []        # streams whose viewer stopped reading: kept, since freeing one waits for the viewer


def finish_stream(stream, connected: bool, path=None) -> None:
    """Flush and close a Rerun recording stream; one ``connected`` to a viewer gets ``FLUSH_SECONDS`` to take what
    is queued and as long again to close. A viewer that does not within that time is left: the stream is kept,
    never closed nor freed (closing the connection or dropping the stream would wait for the viewer without end,
    and so would Rerun's own exit handler, which is removed; the process ends without freeing it), and
    ``ConnectionError`` says so. A stream saved to the file ``path`` that cannot be written (a full disk) is an
    ``OSError`` naming it."""
    if not connected:
        try:
            stream.flush()
            stream.disconnect()
        except RuntimeError as error:
            import errno
            raise OSError(errno.EIO, f"Rerun's file writer failed ({' '.join(str(error).split())})",
                          str(path) if path else None) from None
        return
    import threading
    try:
        stream.flush(timeout_sec=FLUSH_SECONDS)
    except RuntimeError as error:
        _leave(stream, f"the viewer did not take the rest of the view within {FLUSH_SECONDS:g} s "
                       f"({' '.join(str(error).split())})")
    closing = threading.Thread(target=stream.disconnect, name="vcyto-viewer-close", daemon=True)
    closing.start()
    closing.join(FLUSH_SECONDS)
    if closing.is_alive():
        _leave(stream, f"the viewer did not close the connection within {FLUSH_SECONDS:g} s")


def _leave(stream, why: str):
    import_rerun().unregister_shutdown()
    _LEFT_BEHIND.append(stream)
    raise ConnectionError(why)


@functools.lru_cache(maxsize=None)
def import_rerun():
    """The ``rerun`` module; in the vcyto command's own process, with pyarrow told once that pandas is not there.

    pyarrow's first conversion of a Python sequence (Rerun makes one for the first thing it logs: the blueprint)
    imports pandas, where it is installed (FlowKit, a dev dependency, brings it), only to recognise pandas objects
    among the values; vcyto gives it none. That import took 0.2-0.3 s of a recorded run (measured), on the sinks'
    thread but holding the interpreter's lock the plant's set-up and steps need. In the command's process
    (``spare_pandas_import``) pyarrow makes that first conversion while pandas cannot be imported, notes that it
    has none (``_PandasAPIShim``: asked once per process), and the finder is removed at once: pandas stays
    importable, and pyarrow's explicit pandas functions (``Table.to_pandas``, ``Table.from_pandas``) import it when
    called; until one of them is, a pandas object given to ``pyarrow.array`` would convert as a plain sequence,
    and nothing in that process gives it one. A Python user's process (vcyto imported as a library) is left
    alone: there pyarrow imports pandas as it always does. A process that imported pandas already keeps it."""
    ready_pyarrow()
    import rerun
    return rerun


def blueprint():
    import_rerun()
    import rerun.blueprint as rrb
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin="/", contents="/device/**", name="channel (um, y up)"),
            rrb.Vertical(rrb.TimeSeriesView(origin="/", contents=["/idt", "/pulses/**"], name="IDT drive and pulses"),
                         rrb.TimeSeriesView(origin="area", name="area / initial area"),
                         rrb.TextLogView(origin="log", name="events and decisions")),
            column_shares=[3, 2]),
        collapse_panels=True)


def speed_scale_mm_s(scenario: Scenario) -> float:
    """The fixed top of the speed colour scale (mm/s): 1.2 x the fastest inflow, rounded up to 1, 2 or 5 x 10^k."""
    from sim.model.boundary import inflow_velocity
    channel = scenario.channel
    y = np.linspace(0.0, channel.height, 2001)
    fastest = float(np.hypot(*inflow_velocity(channel, y)).max()) * 1e3 * 1.2
    if not fastest > 0:
        return 1.0
    decade = 10.0 ** math.floor(math.log10(fastest))
    return next(step * decade for step in (1, 2, 5, 10) if step * decade >= fastest)
