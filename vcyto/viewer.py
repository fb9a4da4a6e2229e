"""The Rerun view of a run, live (a sink of the closed loop) or replayed from an MCAP recording.

Coordinates are the plant's, in micrometres, y up (0 = lower wall): every entity under ``device`` is logged in
them, and a static transform on ``device`` (y -> height - y) shows them y up in Rerun's 2D view, whose y axis
points down. Entities: ``device/outline``, ``device/inlets``, ``device/outlets``, ``device/saw_window``,
``device/detection_window`` (static); ``device/flow`` (the speed as an image on a fixed colour scale, 1 pixel =
1 um, at the field cadence) with its legend ``device/legend``; ``device/cells/<key>`` (membrane line strips) and
``device/paths/<key>`` (centroid paths), coloured by class through the annotation context (the outcome classes
of ``vcyto.outcomes`` once a cell has left, provisional classes while it is in the channel:
``vcyto.classes``); ``device/events`` (a marker where and when each detector event happened, with the recent
ones); ``idt`` (the IDT drive) and ``pulses/scheduled``, ``pulses/aborted`` (the controller's pulses) as time
series; ``area/<key>`` (each membrane's area / initial area); ``log`` (detector events, decisions with their
reasons, outcomes). Timelines: ``sim_time`` (simulated seconds) and ``step``. A blueprint lays out the
channel, the IDT and pulse plot, the area plot and the log.
"""

from __future__ import annotations

import collections
import math
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

from sim.scenario import UM, Scenario

from .classes import CLASS_COLOURS, CLASS_IDS, CLASS_NAMES, CellClasses
from .foxglove import speed_grid

RECENT_EVENTS = 16                     # markers shown with each new detector event
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
            rrb.Spatial2DView(origin="/", contents="/device/**", name="channel (um, y up)"),
            rrb.Vertical(rrb.TimeSeriesView(origin="/", contents=["/idt", "/pulses/**"], name="IDT drive and pulses"),
                         rrb.TimeSeriesView(origin="area", name="area / initial area"),
                         rrb.TextLogView(origin="log", name="events and decisions")),
            column_shares=[3, 2]),
        collapse_panels=True)


def speed_scale_mm_s(scenario: Scenario) -> float:
    """The fixed top of the speed colour scale (mm/s): 1.2 x the fastest inflow, rounded up to 1, 2 or 5 x 10^k."""
    from sim.boundary import inflow_velocity
    channel = scenario.channel
    y = np.linspace(0.0, channel.height, 2001)
    fastest = float(np.hypot(*inflow_velocity(channel, y)).max()) * 1e3 * 1.2
    if not fastest > 0:
        return 1.0
    decade = 10.0 ** math.floor(math.log10(fastest))
    return next(step * decade for step in (1, 2, 5, 10) if step * decade >= fastest)


class RerunLogger:
    """Logs the pieces of a run to one Rerun recording stream."""

    def __init__(self, scenario: Scenario, detection_window=None, target=("save", "run.rrd"), application_id="vcyto",
                 batch_rows: int = 200):
        import rerun as rr
        self.rr = rr
        self.height_um = scenario.channel.height / UM
        self.length_um = scenario.channel.length / UM
        self.speed_max_mm_s = speed_scale_mm_s(scenario)
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
        self.paths: dict[int, list] = {}               # the cells in the channel: centroid paths (um)
        self.positions: dict[int, tuple] = {}          # the cells in the channel: latest centroid (um)
        self.recent_events: collections.deque = collections.deque(maxlen=RECENT_EVENTS)
        self.batch_rows = batch_rows
        self._pending: dict[str, tuple] = {}
        self._rows = 0
        self._now = (0.0, None)
        self._static(scenario, detection_window)

    def _static(self, scenario, detection_window):
        rr = self.rr
        classes = [(CLASS_IDS[name], name, CLASS_COLOURS[name]) for name in CLASS_NAMES]
        self.stream.log("/", rr.AnnotationContext(classes), static=True)
        # plant coordinates (y up) shown in a y-down 2D view: y -> height - y
        self.stream.log("device", rr.Transform3D(translation=[0.0, self.height_um, 0.0], scale=[1.0, -1.0, 1.0]),
                        static=True)
        self._device(scenario, detection_window)
        self._legend()

    def _device(self, scenario, detection_window):
        from .recording import device_outlines
        rr = self.rr
        groups = collections.defaultdict(list)
        for entity, points, colour, label in device_outlines(scenario, detection_window):
            parent = entity.rsplit("/", 1)[0]
            name = {"device/inlet": "device/inlets", "device/outlet": "device/outlets"}.get(parent, entity)
            groups[name].append((np.asarray(points, dtype=float), colour, label))
        for entity, strips in groups.items():
            labels = [s[2] for s in strips] if any(s[2] for s in strips) else None
            self.stream.log(entity, rr.LineStrips2D([s[0] for s in strips], colors=[s[1] for s in strips],
                                                    radii=0.5 if entity.endswith("outline") else 1.5, labels=labels),
                            static=True)

    def _legend(self):
        """A colour bar above the channel: 0 to ``speed_max_mm_s`` (mm/s), faster flow in the top colour."""
        from matplotlib import colormaps
        rr, width = self.rr, 256
        bar = (colormaps["viridis"](np.linspace(0.0, 1.0, width))[:, :3] * 255).astype(np.uint8)
        bar = np.repeat(bar[np.newaxis], 6, axis=0)
        base = self.height_um + 8.0
        self.stream.log("device/legend/bar", rr.Transform3D(translation=[0.0, base, 0.0],
                                                            scale=[self.length_um / width, 1.0, 1.0]), static=True)
        self.stream.log("device/legend/bar", rr.Image(bar), static=True)
        ticks = [0.0, 0.5, 1.0]
        self.stream.log("device/legend/ticks", rr.Points2D(
            [[t * self.length_um, base + 10.0] for t in ticks], radii=0.1,
            labels=[f"{t * self.speed_max_mm_s:g} mm/s" for t in ticks[:-1]] + [f">= {self.speed_max_mm_s:g} mm/s"]),
            static=True)

    def time(self, time_s: float, step: int | None = None):
        self.stream.set_time("sim_time", duration=time_s)
        if step is not None:
            self.stream.set_time("step", sequence=step)
        if self._rows >= self.batch_rows:             # a new step begins: send the batch of the ones before
            self.send_pending()
        self._now = (time_s, step)

    def _at(self, time_s: float, entity: str, archetype):
        """Log at another simulated time than the current step's, then come back to it."""
        self.stream.set_time("sim_time", duration=time_s)
        self.stream.log(entity, archetype)
        self.stream.set_time("sim_time", duration=self._now[0])

    def idt(self, drive: float):
        self._add("idt", drive)

    def cells(self, cells: list[dict]):
        """Cells as in the MCAP ``/cells`` payload (um; the membrane as nested lists or an array; ``class``: the
        provisional class name)."""
        rr = self.rr
        for cell in cells:
            key = cell["key"]
            if cell["fate"] != "in_channel":            # recordings of format 1 list a cell once more as it leaves
                continue
            class_id = CLASS_IDS.get(cell.get("class", "in channel"), CLASS_IDS["in channel"])
            membrane = np.asarray(cell.get("membrane_um", ()), dtype=float).reshape(-1, 2)
            if not len(membrane):
                membrane = np.array([[cell["x_um"], cell["y_um"]]])
            self._add(f"device/cells/{key}", np.vstack([membrane, membrane[:1]]), class_id)
            if cell.get("perimeter_um") is not None:            # a membrane model: how much area it keeps
                self._add(f"area/{key}", cell["area_ratio"])
            self.positions[key] = (cell["x_um"], cell["y_um"])
            path = self.paths.setdefault(key, [])
            path.append((cell["x_um"], cell["y_um"]))
            if len(path) % 10 == 1:
                self.stream.log(f"device/paths/{key}", rr.LineStrips2D([path], class_ids=[class_id], radii=0.3))

    def outcome(self, key: int, class_name: str, text: str):
        """A cell has left: its membrane goes, its path stays in the colour of its outcome class."""
        rr = self.rr
        entity = f"device/cells/{key}"
        self._send(entity)
        self.stream.log(entity, rr.Clear(recursive=False))
        path = self.paths.pop(key, None)
        self.positions.pop(key, None)
        class_id = CLASS_IDS.get(class_name, CLASS_IDS["lost"])
        if path:
            self.stream.log(f"device/paths/{key}", rr.LineStrips2D([path], class_ids=[class_id], radii=0.3,
                                                                   labels=[f"{key}: {class_name}"]))
        self.text(text, "INFO" if class_name in ("sorted", "passed") else "WARN")

    def event(self, time_s: float, key: int, class_name: str, label: str):
        """A detector event: a marker where the cell is, at the event's time, with the recent ones."""
        position = self.positions.get(key)
        if position is not None:
            self.recent_events.append((position, CLASS_IDS[class_name], label))
            rr = self.rr
            self._at(time_s, "device/events", rr.Points2D([e[0] for e in self.recent_events], radii=2.0,
                                                          class_ids=[e[1] for e in self.recent_events],
                                                          labels=[e[2] for e in self.recent_events]))
        self.text(label)

    def pulse(self, on: float, off: float, aborted: bool = False):
        """An IDT pulse the controller scheduled ([on, off], s), or one it aborted, as a 0/1 step in time."""
        rr = self.rr
        edge = 1e-9
        times = np.array([on - edge, on, off, off + edge])
        self.stream.send_columns("pulses/aborted" if aborted else "pulses/scheduled",
                                 indexes=[rr.TimeColumn("sim_time", duration=times)],
                                 columns=rr.Scalars.columns(scalars=np.array([0.0, 1.0, 1.0, 0.0])))

    # Per-step values (IDT drive, area ratios, membranes) are sent in batches of ``batch`` steps through
    # Rerun's columnar API (one call per entity per batch instead of one archetype per entity per step:
    # about 5x cheaper); every step still becomes one row on the timelines.
    def _add(self, entity: str, value, kind=None):
        rows = self._pending.setdefault(entity, ([], [], [], []))
        rows[0].append(self._now[0])
        rows[1].append(self._now[1])
        rows[2].append(value)
        rows[3].append(kind)
        self._rows += 1

    def _send(self, entity: str):
        rows = self._pending.pop(entity, None)
        if not rows or not rows[0]:
            return
        rr = self.rr
        times, steps, values, kinds = rows
        indexes = [rr.TimeColumn("sim_time", duration=np.array(times))]
        if all(step is not None for step in steps):
            indexes.append(rr.TimeColumn("step", sequence=np.array(steps)))
        if entity.startswith("device/cells/"):
            columns = rr.LineStrips2D.columns(strips=values, class_ids=kinds,
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
        """The speed image from an MCAP ``/flow/velocity`` payload: 1 um pixels, row 0 at y = 0 (the transform
        on ``device`` shows it y up), colours on the fixed scale 0 .. ``speed_max_mm_s`` (the legend)."""
        from matplotlib import colormaps
        speed_mm_s = speed_grid(payload, 1.0) * 1e3
        scaled = np.clip(speed_mm_s / self.speed_max_mm_s, 0.0, 1.0)
        rgb = (colormaps["viridis"](scaled)[:, :, :3] * 255).astype(np.uint8)
        self.stream.log("device/flow", self.rr.Image(rgb))

    def close(self):
        self.send_pending()
        self.stream.flush()
        self.stream.disconnect()


def _cell_view(cell, class_name: str) -> dict:
    """What the view needs of a cell's ground truth (as the MCAP payload, the membrane as an array in um)."""
    membrane = np.asarray(cell.membrane) / UM if cell.membrane is not None else np.zeros((0, 2))
    return {"key": cell.key, "type": cell.type, "x_um": cell.x / UM, "y_um": cell.y / UM, "fate": cell.fate,
            "area_ratio": cell.area_ratio, "membrane_um": membrane, "class": class_name,
            "perimeter_um": (cell.measures or {}).get("perimeter")}


def event_text(event) -> str:
    return (f"cell {event.key}: detected type {event.classification} (fluorescence {event.fluorescence:.2f}, "
            f"{event.velocity * 1e3:.1f} mm/s)")


def decision_text(event_id: int, action: str, reason: str | None) -> str:
    return f"event {event_id}: {action}" + (f" ({reason})" if reason else "")


class RerunSink:
    """A sink of the closed loop that shows every step in Rerun (bounded state: the cells in the channel)."""

    def __init__(self, scenario: Scenario, detection_window, target, field_every: int = 200):
        self.logger = RerunLogger(scenario, detection_window, target)
        self.field_every = field_every
        self.classes = CellClasses(scenario)
        self._reported: set[int] = set()

    def on_step(self, step, observation, truth, actuation, events, decisions, fields=None, diagnostics=None):
        logger, classes = self.logger, self.classes
        revised = {d.event_id: classes.pulses.get(d.event_id) for d in decisions if d.action == "abort"}
        classes.observe(events, decisions)
        logger.time(observation.time, step)
        logger.idt(actuation)
        logger.cells([_cell_view(cell, classes.provisional(cell.key)) for cell in truth.cells
                      if cell.fate == "in_channel"])
        for event in events:
            logger.event(event.time, event.key, classes.provisional(event.key), event_text(event))
        for decision in decisions:
            logger.text(decision_text(decision.event_id, decision.action, decision.reason),
                        level="WARN" if decision.action == "abort" else "INFO")
            pulse = (decision.pulse_on, decision.pulse_off) if decision.action == "sort" \
                else revised.get(decision.event_id)
            if pulse and math.isfinite(pulse[0]):
                logger.pulse(*pulse, aborted=decision.action == "abort")
        classes.forget_pulses(observation.time)
        self._reported &= {cell.key for cell in truth.cells}
        for cell in truth.cells:
            if cell.fate != "in_channel" and cell.key not in self._reported:
                self._reported.add(cell.key)
                name = classes.settle(cell)
                logger.outcome(cell.key, name, f"cell {cell.key} ({cell.type}) left by: {cell.fate} ({name})")
        if fields is not None and self.field_every and step % self.field_every == 0:
            logger.field(fields())

    def close(self):
        self.logger.close()
