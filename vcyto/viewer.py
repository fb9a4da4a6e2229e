"""The Rerun view of a run, live (a sink of the closed loop) or replayed from an MCAP recording.

Entities (2D, micrometres, y up as in the paper: logged as (x, height - y) because Rerun's 2D y axis
points down): ``device/outline``, ``device/inlets``, ``device/outlets``, ``device/saw_window``,
``device/detection_window`` (static); ``device/flow`` (the speed as an image, at the field cadence);
``device/cells/<key>`` (membrane line strips), ``device/paths/<key>`` (centroid paths); ``idt`` (the IDT
drive, a time series); ``area/<key>`` (each membrane's area / initial area, a time series); ``log`` (detector events, decisions and outcomes as text). Timeline: ``sim_time``
(simulated seconds) and ``step``. A blueprint lays out the channel, the IDT plot and the log.
"""

from __future__ import annotations

import base64
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from sim.scenario import UM, Scenario

TYPE_COLOURS = {"RBC": (220, 40, 40), "melanoma": (250, 200, 30)}
# the Rerun SDK logs connection trouble as multi-line Rust log records; vcyto reports it in one line instead
# (set RUST_LOG to see them)
os.environ.setdefault("RUST_LOG", "off")


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform in ("darwin", "win32")


# --- finding, starting and reaching a viewer (the view itself is below) -------------------------------

VIEWER_PORT = 9876
VIEWER_START_TIMEOUT = 15.0     # s until the spawned viewer listens
VIEWER_GRACE = 1.0              # s it must then stay alive (a viewer without a usable display exits at once)
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


def start_viewer(bind: str = "127.0.0.1", port: int = VIEWER_PORT) -> tuple[str, str]:
    """Start the installed Rerun viewer listening on ``bind``:``port`` (detached: it outlives the run), or find
    the one already listening there; (its URL, what was done). Raises ``ViewerUnavailable`` if it cannot be
    started, does not listen within ``VIEWER_START_TIMEOUT`` or exits at once (no usable display)."""
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if listening("127.0.0.1", port, timeout=0.5):
        return url, f"streaming to the viewer already listening on port {port}"
    binary = find_viewer()
    if binary is None:
        raise ViewerUnavailable("the rerun-sdk installation has no viewer binary")
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


def blueprint():
    import rerun.blueprint as rrb
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin="device", name="channel"),
            rrb.Vertical(rrb.TimeSeriesView(origin="idt", name="IDT drive"),
                         rrb.TimeSeriesView(origin="area", name="area / initial area"),
                         rrb.TextLogView(origin="log", name="events")),
            column_shares=[3, 2]),
        collapse_panels=True)


class RerunLogger:
    """Logs the pieces of a run to one Rerun recording stream."""

    def __init__(self, scenario: Scenario, detection_window=None, target=("save", "run.rrd"), application_id="vcyto",
                 batch_rows: int = 200):
        import rerun as rr
        self.rr = rr
        self.height_um = scenario.channel.height / UM
        self.stream = rr.RecordingStream(application_id)
        kind = target[0]
        if kind == "save":
            self.stream.save(str(target[1]), default_blueprint=blueprint())
        elif kind == "spawn":
            self.stream.spawn(default_blueprint=blueprint())
        elif kind == "connect":
            self.stream.connect_grpc(target[1], default_blueprint=blueprint()) if target[1] else \
                self.stream.connect_grpc(default_blueprint=blueprint())
        else:
            raise ValueError(f"unknown Rerun target {kind!r}")
        self.paths: dict[int, list] = {}
        self.batch_rows = batch_rows
        self._pending: dict[str, tuple] = {}
        self._rows = 0
        self._now = (0.0, None)
        self._device(scenario, detection_window)

    def _flip(self, points_um):
        points = np.asarray(points_um, dtype=float).reshape(-1, 2)
        return np.column_stack([points[:, 0], self.height_um - points[:, 1]])

    def _device(self, scenario, detection_window):
        rr, channel = self.rr, scenario.channel
        length, height = channel.length / UM, channel.height / UM
        outline = [[0, 0], [length, 0], [length, height], [0, height], [0, 0]]
        self.stream.log("device/outline", rr.LineStrips2D([self._flip(outline)], colors=[(200, 200, 200)]), static=True)
        inlets = [self._flip([[0, i.span[0] / UM], [0, i.span[1] / UM]]) for i in channel.inlets]
        self.stream.log("device/inlets", rr.LineStrips2D(inlets, colors=[(0, 190, 255)], radii=1.5,
                                                         labels=[i.name for i in channel.inlets]), static=True)
        outlets = [self._flip([[length, o.span[0] / UM], [length, o.span[1] / UM]]) for o in channel.outlets]
        self.stream.log("device/outlets", rr.LineStrips2D(outlets, colors=[(255, 140, 0)], radii=1.5,
                                                          labels=[o.name for o in channel.outlets]), static=True)
        window = np.array(channel.saw_window.span) / UM
        self.stream.log("device/saw_window", rr.LineStrips2D([self._flip([[window[0], 0], [window[1], 0]])],
                                                             colors=[(255, 0, 0)], radii=2.0, labels=["SAW"]), static=True)
        if detection_window is not None:
            x0, x1 = np.array(detection_window) / UM
            box = [[x0, 0], [x1, 0], [x1, height], [x0, height], [x0, 0]]
            self.stream.log("device/detection_window", rr.LineStrips2D([self._flip(box)], colors=[(120, 255, 120)]),
                            static=True)

    def time(self, time_s: float, step: int | None = None):
        self.stream.set_time("sim_time", duration=time_s)
        if step is not None:
            self.stream.set_time("step", sequence=step)
        if self._rows >= self.batch_rows:             # a new step begins: send the batch of the ones before
            self.send_pending()
        self._now = (time_s, step)

    def idt(self, drive: float):
        self._add("idt", drive)

    def cells(self, cells: list[dict]):
        """Cells as in the MCAP ``/cells`` payload (um; the membrane as nested lists or an array)."""
        rr = self.rr
        for cell in cells:
            key = cell["key"]
            entity = f"device/cells/{key}"
            if cell["fate"] != "in_channel":
                self._send(entity)
                self.stream.log(entity, rr.Clear(recursive=False))
                continue
            membrane = np.asarray(cell["membrane_um"], dtype=float).reshape(-1, 2)
            if not len(membrane):
                membrane = np.array([[cell["x_um"], cell["y_um"]]])
            self._add(entity, self._flip(np.vstack([membrane, membrane[:1]])), cell["type"])
            if cell.get("perimeter_um") is not None:            # a membrane model: how much area it keeps
                self._add(f"area/{key}", cell["area_ratio"])
            path = self.paths.setdefault(key, [])
            path.append((cell["x_um"], cell["y_um"]))
            if len(path) % 10 == 1:
                colour = TYPE_COLOURS.get(cell["type"], (255, 255, 255))
                self.stream.log(f"device/paths/{key}", rr.LineStrips2D([self._flip(path)], colors=[colour], radii=0.3))

    # Per-step values (IDT drive, area ratios, membranes) are sent in batches of ``batch`` steps through
    # Rerun's columnar API (one call per entity per batch instead of one archetype per entity per step:
    # about 5x cheaper); every step still becomes one row on the timelines.
    def _add(self, entity: str, value, kind=None):
        rows = self._pending.setdefault(entity, ([], [], [], kind))
        rows[0].append(self._now[0])
        rows[1].append(self._now[1])
        rows[2].append(value)
        self._rows += 1

    def _send(self, entity: str):
        rows = self._pending.pop(entity, None)
        if not rows or not rows[0]:
            return
        rr = self.rr
        times, steps, values, kind = rows
        indexes = [rr.TimeColumn("sim_time", duration=np.array(times))]
        if all(step is not None for step in steps):
            indexes.append(rr.TimeColumn("step", sequence=np.array(steps)))
        if entity.startswith("device/cells/"):
            colour = TYPE_COLOURS.get(kind, (255, 255, 255))
            columns = rr.LineStrips2D.columns(strips=values, colors=[colour] * len(values),
                                              radii=[0.4] * len(values)).partition([1] * len(values))
        else:
            columns = rr.Scalars.columns(scalars=np.array(values, dtype=float))
        self.stream.send_columns(entity, indexes=indexes, columns=columns)

    def send_pending(self):
        for entity in list(self._pending):
            self._send(entity)
        self._rows = 0

    def text(self, message: str, level: str = "INFO"):
        self.stream.log("log", self.rr.TextLog(message, level=level))

    def field(self, payload: dict):
        """The speed image from an MCAP ``/flow/velocity`` payload."""
        rows, columns = payload["shape"]
        vx = np.frombuffer(base64.b64decode(payload["vx_f32_b64"]), dtype=np.float32).reshape(rows, columns)
        vy = np.frombuffer(base64.b64decode(payload["vy_f32_b64"]), dtype=np.float32).reshape(rows, columns)
        speed = np.hypot(vx, vy)[::-1]                      # first row at the top: y = height
        image = _resample_uniform(speed, np.asarray(payload["x_um"]), np.asarray(payload["y_um"])[::-1])
        from matplotlib import colormaps
        rgb = (colormaps["viridis"](image / max(float(image.max()), 1e-12))[:, :, :3] * 255).astype(np.uint8)
        self.stream.log("device/flow", self.rr.Image(rgb))     # 1 pixel = 1 um, top row at y = height

    def close(self):
        self.send_pending()
        self.stream.flush()
        self.stream.disconnect()


def _resample_uniform(speed, x, y):
    """Nearest resampling of a tensor-grid image onto a uniform 1 um pixel grid (the mesh may be graded)."""
    columns = np.clip(np.searchsorted(x, np.arange(x[0], x[-1] + 1e-9, 1.0)), 0, len(x) - 1)
    rows_desc = np.arange(y[0], y[-1] - 1e-9, -1.0)
    rows = np.clip(np.searchsorted(-y, -rows_desc), 0, len(y) - 1)
    return speed[np.ix_(rows, columns)]


def _cell_view(cell) -> dict:
    """What the view needs of a cell's ground truth (as the MCAP payload, the membrane as an array in um)."""
    membrane = np.asarray(cell.membrane) * 1e6 if cell.membrane is not None else np.zeros((0, 2))
    return {"key": cell.key, "type": cell.type, "x_um": cell.x * 1e6, "y_um": cell.y * 1e6, "fate": cell.fate,
            "area_ratio": cell.area_ratio, "membrane_um": membrane,
            "perimeter_um": (cell.measures or {}).get("perimeter")}


class RerunSink:
    """A sink of the closed loop that shows every step in Rerun."""

    def __init__(self, scenario: Scenario, detection_window, target, field_every: int = 200):
        self.logger = RerunLogger(scenario, detection_window, target)
        self.field_every = field_every
        self._settled = set()

    def on_step(self, step, observation, truth, actuation, events, decisions, fields=None, diagnostics=None):
        logger = self.logger
        logger.time(observation.time, step)
        logger.idt(actuation)
        logger.cells([_cell_view(cell) for cell in truth.cells if cell.fate == "in_channel" or cell.key not in self._settled])
        for event in events:
            logger.text(f"cell {event.key}: detected type {event.classification} (fluorescence {event.fluorescence:.2f}, "
                        f"{event.velocity * 1e3:.1f} mm/s)")
        for decision in decisions:
            logger.text(f"event {decision.event_id}: {decision.action}" + (f" ({decision.reason})" if decision.reason else ""),
                        level="WARN" if decision.action == "abort" else "INFO")
        for cell in truth.cells:
            if cell.fate != "in_channel" and cell.key not in self._settled:
                self._settled.add(cell.key)
                logger.text(f"cell {cell.key} ({cell.type}) left by: {cell.fate}")
        if fields is not None and self.field_every and step % self.field_every == 0:
            logger.field(fields())

    def close(self):
        self.logger.close()
