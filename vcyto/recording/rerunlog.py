"""What a run shows in Rerun, live (``RerunSink``, a sink of the closed loop) or replayed (``vcyto.recording.replay``).

Coordinates are the plant's, in micrometres, y up (0 = lower wall): every entity under ``device`` is logged in
them, and a static transform on ``device`` (y -> height - y) shows them y up in Rerun's 2D view, whose y axis
points down. Entities:

- static: ``device/outline``, ``device/inlets``, ``device/outlets``, ``device/saw_window``,
  ``device/detection_window``, the annotation context of the classes, and the series' styles (drive and pulses
  drawn as steps: ``SeriesLines`` with step-after interpolation, one value per edge);
- every step shown: ``device/cells`` (every cell in the channel: its centroid, labelled with its key),
  ``device/membranes`` (the membranes of models that have them) and ``area/<key>`` (each membrane's area /
  initial area, named "cell <key> (<type>)"; the area panel is in the view only for models with membranes);
- ``idt``: the IDT drive, one value per edge at the edge's time (the pulses the controller kept: a pulse is
  logged once its start has passed, so an aborted one never shows); ``pulses/scheduled``, ``pulses/aborted``: each
  pulse the controller scheduled, or aborted, as 1 at its start and 0 at its end;
- ``sort/purity``, ``sort/yield``, ``sort/abort_rate``: the sort's figures so far, as an operator watches them
  (``SortFigures``: purity of the sorted outlet, targets sorted over the targets that left, aborts over type-II
  events), updated as cells leave, drawn as steps with a marker at each value (``blueprint``'s overrides);
- ``device/paths/<slot>``: a cell's centroid path when it leaves, in slot ``key % PATH_SLOTS``, coloured by its
  outcome class, labelled "key: outcome class" (hidden, shown on hover: drawn, they piled up where the cells
  leave): the view shows the paths of the last ``PATH_SLOTS`` cells (the MCAP keeps them all);
- ``device/events``: the newest ``RECENT_EVENTS`` detector events as markers where the cells were, at each
  event's time, coloured by class, their labels hidden (shown on hover; the log has each event's line);
- ``log``: detector events, decisions with their reasons, outcomes; ``device/flow/speed_mm_s``: the flow speed in
  mm/s as a scalar image (``DepthImage``, meter = 1, so hovering a pixel reads the speed in mm/s; viridis from 0 to
  the fixed ``speed_max_mm_s``), 1 pixel = 1 um, at the field cadence, with a colour bar ``device/legend`` above
  the channel once a field is shown.

Cells, paths and events are coloured by class through the annotation context: the outcome classes of
``vcyto.outcomes`` once a cell has left, provisional classes while it is in the channel (``vcyto.classes``).
Timelines: ``sim_time`` (simulated seconds) and ``step``.

Cost: the logger keeps rows in memory and sends each entity's rows in one columnar call (``send_columns``)
per batch (``batch_rows`` rows, or ``batch_seconds`` of wall time, whichever comes first), with the Arrow arrays
built directly from numpy. A view saved to a file (nobody watches it live) is sent in larger batches
(``FILE_BATCH_ROWS``, ``FILE_BATCH_SECONDS``): Rerun's file writer keeps about 1 KB per chunk sent (one chunk per
entity per batch) until the file is finished, so the batches set how that memory grows with the run. The number
of entities is bounded (the slots), so a run of 10^5 cells costs a bounded number of calls per batch, and the state
is bounded by the cells in the channel and one batch.
"""

from __future__ import annotations

import collections
import functools
import math
import time

import numpy as np

from sim.model.scenario import UM, Scenario

from ..classes import CLASS_COLOURS, CLASS_IDS, CLASS_NAMES, CellClasses
from ..outcomes import outcome_text
from ..trace import TracedRows, joined, stretches
from .foxglove import speed_grid
from .viewer import finish_stream, import_rerun, speed_scale_mm_s

POINT_LIKE = ("rom", "streamline")     # plants whose cells have no membrane (their view has no area panel)
RECENT_EVENTS = 16                     # markers shown with each new detector event
REPORTED_KEPT = 64                     # cells that left kept beyond those a record lists (then pruned to those)
PATH_SLOTS = 16                        # the paths of the last this many cells stay in the view
BATCH_ROWS = 2000                      # rows kept before they are sent
BATCH_SECONDS = 0.5                    # wall time after which kept rows are sent (the live view's lag)
FILE_BATCH_ROWS = 1 << 16              # the same for a view saved to a file
FILE_BATCH_SECONDS = 5.0
VIEW_MARGIN_UM = 25.0                  # the channel view's margin around the channel, for the labels outside it
LEGEND_ROOM_UM = 20.0                  # and the room above it for the speed's colour bar
AREA_RANGE = (0.5, 1.1)                # the area panel's axis (area / initial area)
SORT_FIGURES = (("sort/purity", "purity"), ("sort/yield", "yield"), ("sort/abort_rate", "abort rate"))


def viridis(scaled) -> np.ndarray:
    """RGB (uint8, a new array) of float values in [0, 1] on matplotlib's viridis: what
    ``(colormaps["viridis"](scaled)[..., :3] * 255).astype(np.uint8)`` gives for floats (values below 0 or above
    1 take the ends, NaN black; integers are read as floats, not as table indices), read from a 256-entry table
    kept in the set-up cache: a warm process shows the flow without importing matplotlib (whose import, with
    pyparsing and its settings, was 0.1-0.3 s of the Rerun sink's start)."""
    values = np.asarray(scaled, dtype=float)
    index = np.clip(np.nan_to_num(values, nan=0.0, posinf=1.0, neginf=0.0) * 256, 0, 255).astype(np.intp)
    rgb = np.take(_viridis_table(), index, axis=0)          # a copy, also for a single value
    rgb[np.isnan(values)] = 0
    return rgb


@functools.lru_cache(maxsize=1)
def _viridis_table() -> np.ndarray:
    """matplotlib's 256 viridis colours as uint8 RGB, through ``sim.fast.store`` (keyed by matplotlib's version)."""
    from importlib.metadata import version

    from sim.fast.store import reuse

    def build():
        from matplotlib import colormaps
        return {"rgb": (colormaps["viridis"](np.arange(256))[:, :3] * 255).astype(np.uint8)}
    table = reuse("colormap", {"name": "viridis", "matplotlib": version("matplotlib"), "layout": 1}, build)["rgb"]
    table = np.array(table, dtype=np.uint8)
    table.setflags(write=False)                             # shared by every call of the process
    return table


def blueprint(membranes: bool = True, length_um: float | None = None, height_um: float | None = None):
    """The operator's view: the channel (framed with a margin for the labels outside it: inlets, outlets, the SAW
    window, the speed's colour bar above); the drive and pulses; the sort's figures (0 to 1); the areas (models
    with membranes only: no empty panel; 0.5 to 1.1, so that the round-off of a kept area does not fill the
    panel); the log."""
    import_rerun()
    import rerun.blueprint as rrb
    unit = rrb.ScalarAxis(range=(-0.02, 1.02))
    series = [rrb.TimeSeriesView(origin="/", contents=["/idt", "/pulses/**"], name="IDT drive and pulses",
                                 axis_y=unit),
              rrb.TimeSeriesView(origin="sort", name="purity, yield, abort rate (so far)", axis_y=unit,
                                 overrides=_steps_with_markers(SORT_FIGURES))]
    if membranes:
        series.append(rrb.TimeSeriesView(origin="area", name="area / initial area",
                                         axis_y=rrb.ScalarAxis(range=AREA_RANGE)))
    bounds = None
    if length_um is not None and height_um is not None:
        margin = VIEW_MARGIN_UM
        bounds = rrb.VisualBounds2D(x_range=(-margin, length_um + margin),
                                    y_range=(-LEGEND_ROOM_UM - margin, height_um + margin))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin="/", contents="/device/**", name="channel (um, y up)", visual_bounds=bounds),
            rrb.Vertical(*series, rrb.TextLogView(origin="log", name="events and decisions")),
            column_shares=[3, 2]),
        collapse_panels=True)


def _steps_with_markers(series) -> dict:
    """Visualizer overrides that draw each (entity, name) of ``series`` as steps with a marker at each value: the
    sort's figures change only as cells leave, and a lone value (a short run) shows as its marker."""
    rr = import_rerun()
    step_after = rr.components.InterpolationMode.StepAfter
    return {f"/{entity}": [rr.SeriesLines(names=name, interpolation_mode=step_after),
                           rr.SeriesPoints(names=name, marker_sizes=3.0)] for entity, name in series}


class SortFigures:
    """Purity, yield and abort rate so far, from the events, decisions and outcomes a view is shown."""

    def __init__(self):
        self.sorted_out = self.targets_sorted = self.targets_left = self.type_ii = self.aborts = 0

    def event(self, classification: str):
        self.type_ii += classification == "II"

    def decision(self, action: str):
        self.aborts += action == "abort"

    def outcome(self, outlet: str, target: bool):
        from ..outcomes import SORTED_OUTLET
        self.sorted_out += outlet == SORTED_OUTLET
        self.targets_sorted += target and outlet == SORTED_OUTLET
        self.targets_left += target

    def values(self) -> dict:
        """The figures defined so far (a ratio with no denominator yet is left out)."""
        ratios = {"purity": (self.targets_sorted, self.sorted_out), "yield": (self.targets_sorted, self.targets_left),
                  "abort_rate": (self.aborts, self.type_ii)}
        return {name: top / bottom for name, (top, bottom) in ratios.items() if bottom}


class _Rows:
    """The rows of one entity waiting to be sent: times, steps and per-row values (each a list of instances)."""

    __slots__ = ("times", "steps", "values")

    def __init__(self):
        self.times, self.steps, self.values = [], [], []

    def add(self, time_s: float, step, value):
        self.times.append(time_s)
        self.steps.append(step)
        self.values.append(value)


def _strips(rr, strips) -> "object":
    """A LineStrip2D Arrow array from a list of (n, 2) arrays (built directly: Rerun's per-strip conversion is slow)."""
    import pyarrow as pa
    datatype = rr.components.LineStrip2DBatch._ARROW_DATATYPE
    lengths = np.fromiter((len(s) for s in strips), dtype=np.int32, count=len(strips))
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
    flat = (np.concatenate([np.asarray(s, dtype=np.float32).reshape(-1, 2) for s in strips]) if strips
            else np.zeros((0, 2), np.float32))
    inner = pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), type=datatype.value_type)
    return pa.ListArray.from_arrays(pa.array(offsets), inner, type=datatype)


class RerunLogger:
    """Logs the pieces of a run to one Rerun recording stream (see the module docstring for the entities)."""

    def __init__(self, scenario: Scenario, detection_window=None, target=("save", "run.rrd"), application_id="vcyto",
                 batch_rows: int | None = None, batch_seconds: float | None = None, membranes: bool = True):
        rr = import_rerun()
        self.rr = rr
        self.height_um = scenario.channel.height / UM
        self.length_um = scenario.channel.length / UM
        self.speed_max_mm_s = speed_scale_mm_s(scenario)
        self.stream = rr.RecordingStream(application_id)
        kind = target[0]
        view = blueprint(membranes, self.length_um, self.height_um)
        self.connected = kind in ("spawn", "connect")
        self.path = target[1] if kind == "save" else None
        if kind == "save":
            self.stream.save(str(target[1]), default_blueprint=view)
        elif kind == "spawn":
            self.stream.spawn(default_blueprint=view)
        elif kind == "connect":
            self.stream.connect_grpc(target[1], default_blueprint=view) if target[1] else \
                self.stream.connect_grpc(default_blueprint=view)
        else:
            raise ValueError(f"unknown Rerun target {kind!r}")
        self.paths: dict[int, list] = {}               # the cells in the channel: centroid paths (um), in pieces
        self.positions: dict[int, tuple] = {}          # the cells in the channel: latest centroid (um)
        self.recent_events: collections.deque = collections.deque(maxlen=RECENT_EVENTS)
        saved = kind == "save"              # a file: larger batches (module docstring)
        self.batch_rows = batch_rows or (FILE_BATCH_ROWS if saved else BATCH_ROWS)
        self.batch_seconds = batch_seconds or (FILE_BATCH_SECONDS if saved else BATCH_SECONDS)
        self._pending: dict[str, _Rows] = collections.defaultdict(_Rows)
        self._traced: dict = {}                        # recorded steps of an event-driven plant, as columns
        self._rows, self._sent_at = 0, time.monotonic()
        self._now = (0.0, None)
        self._membranes = False
        self._named_areas: set = set()                 # the area series named so far (membrane models: few cells)
        self._legend_shown = False
        self._pulses: dict = {}                        # event id -> [on, off, on logged] of the kept pulses
        self._drive = None                             # the drive's last logged level
        self.figures = SortFigures()
        self._static(scenario, detection_window)

    # --- static entities ---------------------------------------------------------------------------------------
    def _static(self, scenario, detection_window):
        rr = self.rr
        classes = [(CLASS_IDS[name], name, CLASS_COLOURS[name]) for name in CLASS_NAMES]
        self.stream.log("/", rr.AnnotationContext(classes), static=True)
        # plant coordinates (y up) shown in a y-down 2D view: y -> height - y
        self.stream.log("device", rr.Transform3D(translation=[0.0, self.height_um, 0.0], scale=[1.0, -1.0, 1.0]),
                        static=True)
        self._device(scenario, detection_window)
        # paths, event markers and membranes keep their labels hidden (shown on hover: drawn, they piled up on the
        # cells' keys and where cells leave)
        for slot in range(PATH_SLOTS):
            self.stream.log(f"device/paths/{slot}", rr.LineStrips2D.from_fields(show_labels=False), static=True)
        self.stream.log("device/events", rr.Points2D.from_fields(show_labels=False), static=True)
        self.stream.log("device/membranes", rr.LineStrips2D.from_fields(show_labels=False), static=True)
        step_after = rr.components.InterpolationMode.StepAfter
        for entity, name in (("idt", "IDT drive"), ("pulses/scheduled", "pulse scheduled"),
                             ("pulses/aborted", "pulse aborted")):
            self.stream.log(entity, rr.SeriesLines(names=name, interpolation_mode=step_after), static=True)
        for entity, name in SORT_FIGURES:
            self.stream.log(entity, rr.SeriesLines(names=name, interpolation_mode=step_after), static=True)

    def _device(self, scenario, detection_window):
        from .mcap import device_outlines
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
        """A colour bar above the channel: 0 to ``speed_max_mm_s`` (mm/s), faster flow in the top colour (shown
        with the first field: a model without one has no legend)."""
        self._legend_shown = True
        rr, width = self.rr, 256
        bar = viridis(np.linspace(0.0, 1.0, width))
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

    # --- rows ------------------------------------------------------------------------------------------------
    def time(self, time_s: float, step: int | None = None):
        """A new step begins (its rows are logged at ``time_s`` and ``step``); the drive's edges up to it."""
        if self._rows >= self.batch_rows or time.monotonic() - self._sent_at > self.batch_seconds:
            self.send_pending()
        self._now = (time_s, step)
        self._edges(time_s)
        if self._drive is None:
            self._drive_at(time_s, 0.0)

    def _edges(self, now: float):
        """Log the drive's edges of the kept pulses up to ``now``, each at its time, one value per edge."""
        edges = sorted((edge, n) for pulse in self._pulses.values() for n, edge in enumerate(pulse[:2])
                       if edge <= now and not (n == 0 and pulse[2]))
        for edge, n in edges:
            if n == 0:
                for pulse in self._pulses.values():
                    if pulse[0] == edge:
                        pulse[2] = True
            else:
                self._pulses = {e: p for e, p in self._pulses.items() if p[1] > edge}
            self._drive_at(edge, 1.0 if any(p[2] and p[0] <= edge < p[1] for p in self._pulses.values()) else 0.0)

    def _drive_at(self, time_s: float, level: float):
        if level != self._drive:
            self._drive = level
            self._add("idt", level, time_s)

    def _add(self, entity: str, value, time_s: float | None = None):
        rows = self._pending[entity]
        if time_s is None:
            rows.add(self._now[0], self._now[1], value)
        else:                                           # at another time than the step's (events, pulses)
            rows.add(time_s, None, value)
        self._rows += 1

    def idt(self, drive: float):
        """The drive at this step (recordings of formats 1 and 2; a value only where it changes)."""
        self._drive_at(self._now[0], float(drive))

    def cells(self, cells: list[dict]):
        """The cells in the channel at this step, as in the MCAP ``/cells`` payload (um; the membrane as nested
        lists or an array, for models that have one; ``class``: the provisional class name)."""
        shown, membranes = [], []
        for cell in cells:
            if cell["fate"] != "in_channel":            # recordings of format 1 list a cell once more as it leaves
                continue
            key = cell["key"]
            class_id = CLASS_IDS.get(cell.get("class", "in channel"), CLASS_IDS["in channel"])
            shown.append((cell["x_um"], cell["y_um"], class_id, key))
            membrane = np.asarray(cell.get("membrane_um", ()), dtype=float).reshape(-1, 2)
            if len(membrane):
                membranes.append((np.vstack([membrane, membrane[:1]]), class_id))
            if cell.get("perimeter_um") is not None:            # a membrane model: how much area it keeps
                if key not in self._named_areas:
                    self._named_areas.add(key)
                    name = f"cell {key}" + (f" ({cell['type']})" if cell.get("type") else "")
                    self.stream.log(f"area/{key}", self.rr.SeriesLines(names=name), static=True)
                self._add(f"area/{key}", cell["area_ratio"])
            self.positions[key] = (cell["x_um"], cell["y_um"])
            self.paths.setdefault(key, []).append((cell["x_um"], cell["y_um"]))
        self._add("device/cells", shown)
        self._membranes = self._membranes or bool(membranes)
        if self._membranes:                             # once a model has shown membranes, every step says which
            self._add("device/membranes", membranes)

    def traced(self, rows, x_um, y_um):
        """The recorded steps of an event-driven plant (``vcyto.trace.TracedRows``, classified) at ``x_um``,
        ``y_um``: the cells at each step, sent as columns. (The caller adds the rows to the cells' paths.)"""
        columns = self._traced
        for name, values in (("times", rows.times), ("steps", rows.steps), ("counts", rows.counts),
                             ("keys", rows.keys), ("x", x_um), ("y", y_um), ("class_ids", rows.class_ids)):
            columns.setdefault(name, []).append(values)
        self._rows += len(rows.keys) + len(rows)

    def _send_traced(self):
        rr = self.rr
        columns = {name: np.concatenate(chunks) for name, chunks in self._traced.items()}
        rows = _Rows()
        rows.times, rows.steps = columns["times"], columns["steps"]
        keys = columns["keys"]
        cells = rr.Points2D.columns(positions=np.column_stack([columns["x"], columns["y"]]).astype(np.float32),
                                    class_ids=columns["class_ids"].astype(np.uint16),
                                    labels=keys.astype(str), radii=np.full(len(keys), 2.0, np.float32))
        self.stream.send_columns("device/cells", indexes=self._indexes(rows),
                                 columns=cells.partition(columns["counts"]))
        self._traced = {}

    def outcome(self, key: int, class_name: str, text: str):
        """A cell has left: its path appears in its slot, in the colour of its outcome class."""
        path = self.paths.pop(key, None)
        self.positions.pop(key, None)
        if path:
            class_id = CLASS_IDS.get(class_name, CLASS_IDS["lost"])
            self._add(f"device/paths/{key % PATH_SLOTS}", (joined(path), class_id, f"{key}: {class_name}"))
        self.text(text, "INFO" if class_name in ("sorted", "passed") else "WARN")

    def sort_figures(self):
        """The sort's figures so far (``self.figures``), at this step."""
        for name, value in self.figures.values().items():
            self._add(f"sort/{name}", value)

    def event(self, time_s: float, key: int, class_name: str, label: str, position=None):
        """A detector event: a marker where the cell is (``position``, um; else its latest shown), at the event's
        time, with the recent ones."""
        position = position or self.positions.get(key)
        if position is not None:
            self._add("device/events", (position, CLASS_IDS[class_name], label), time_s)
        self.text(label)

    def pulse(self, on: float, off: float, aborted: bool = False, event_id: int | None = None):
        """An IDT pulse the controller scheduled ([on, off], s), or one it aborted, as 1 at ``on`` and 0 at ``off``
        (a step-after series: one value per edge). A scheduled pulse drives ``idt`` from its start, unless it is
        aborted (by ``event_id``) before."""
        self._add("pulses/aborted" if aborted else "pulses/scheduled", 1.0, on)
        self._add("pulses/aborted" if aborted else "pulses/scheduled", 0.0, off)
        if aborted:
            self._pulses.pop(event_id, None)
        elif event_id is not None:
            self._pulses[event_id] = [on, off, False]

    def text(self, message: str, level: str = "INFO"):
        self._add("log", (message, level))

    def field(self, payload: dict):
        """The speed image from an MCAP ``/flow/velocity`` payload: 1 um pixels, row 0 at y = 0 (the transform
        on ``device`` shows it y up), colours on the fixed scale 0 .. ``speed_max_mm_s`` (the legend)."""
        if not self._legend_shown:
            self._legend()
        speed_mm_s = (speed_grid(payload, 1.0) * 1e3).astype(np.float32)
        self.stream.set_time("sim_time", duration=self._now[0])
        if self._now[1] is not None:
            self.stream.set_time("step", sequence=self._now[1])
        self.stream.log("device/flow/speed_mm_s", self.rr.DepthImage(speed_mm_s, meter=1.0, colormap="viridis",
                                                                     depth_range=(0.0, self.speed_max_mm_s)))

    # --- sending -------------------------------------------------------------------------------------------
    def send_pending(self):
        if self._traced:
            self._send_traced()
        for entity, rows in self._pending.items():
            if rows.times:
                self.stream.send_columns(entity, indexes=self._indexes(rows), columns=self._columns(entity, rows))
        self._pending.clear()
        self._rows, self._sent_at = 0, time.monotonic()

    def _indexes(self, rows: _Rows) -> list:
        rr = self.rr
        nanoseconds = np.round(np.array(rows.times) * 1e9).astype(np.int64)      # rounded, as ``set_time`` does
        indexes = [rr.TimeColumn("sim_time", duration=nanoseconds.astype("timedelta64[ns]"))]
        if all(step is not None for step in rows.steps):
            indexes.append(rr.TimeColumn("step", sequence=np.array(rows.steps)))
        return indexes

    def _columns(self, entity: str, rows: _Rows):
        rr, values = self.rr, rows.values
        lengths = [len(v) for v in values] if entity in ("device/cells", "device/membranes") else None
        if entity == "device/cells":
            flat = [cell for row in values for cell in row]
            return rr.Points2D.columns(positions=np.array([c[:2] for c in flat], dtype=np.float32).reshape(-1, 2),
                                       class_ids=np.array([c[2] for c in flat], dtype=np.uint16),
                                       labels=[str(c[3]) for c in flat], radii=np.full(len(flat), 2.0, np.float32)
                                       ).partition(lengths)
        if entity == "device/membranes":
            flat = [strip for row in values for strip in row]
            return rr.LineStrips2D.columns(strips=_strips(rr, [s[0] for s in flat]),
                                           class_ids=np.array([s[1] for s in flat], dtype=np.uint16),
                                           radii=np.full(len(flat), 0.4, np.float32)).partition(lengths)
        if entity == "device/events":             # each event's row: it and the ones before it, newest last
            return self._recent_events(values)
        if entity.startswith("device/paths/"):
            return rr.LineStrips2D.columns(strips=_strips(rr, [v[0] for v in values]),
                                           class_ids=np.array([v[1] for v in values], dtype=np.uint16),
                                           labels=[v[2] for v in values], radii=np.full(len(values), 0.3, np.float32))
        if entity == "log":
            return rr.TextLog.columns(text=[v[0] for v in values], level=[v[1] for v in values])
        return rr.Scalars.columns(scalars=np.array(values, dtype=float))

    def _recent_events(self, markers):
        """The rows of ``device/events`` for new ``markers`` (position, class id, label), each the newest
        ``RECENT_EVENTS`` markers as of its own (the ones of earlier batches included), built as arrays."""
        rr, kept = self.rr, list(self.recent_events)
        every = kept + list(markers)
        positions = np.array([m[0] for m in every], dtype=np.float32).reshape(-1, 2)
        class_ids = np.array([m[1] for m in every], dtype=np.uint16)
        labels = np.array([m[2] for m in every], dtype=str)
        newest = np.arange(len(kept), len(every))
        lengths = np.minimum(newest + 1, RECENT_EVENTS)
        firsts = newest + 1 - lengths
        rows = np.repeat(firsts - np.cumsum(lengths) + lengths, lengths) + np.arange(lengths.sum())
        self.recent_events.extend(markers)
        return rr.Points2D.columns(positions=positions[rows], class_ids=class_ids[rows], labels=labels[rows],
                                   radii=np.full(len(rows), 2.0, np.float32)).partition(lengths)

    def close(self):
        self.send_pending()
        finish_stream(self.stream, self.connected, self.path)


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

    def __init__(self, scenario: Scenario, detection_window, target, field_every: int = 200, membranes: bool = True):
        self.logger = RerunLogger(scenario, detection_window, target, membranes=membranes)
        self.field_every = field_every
        self.classes = CellClasses(scenario)
        self._reported: set[int] = set()

    def on_steps(self, records):
        """Show a batch of steps: an event-driven plant's recorded steps gathered as arrays (``vcyto.trace``), other
        steps one by one."""
        for traced, stretch in stretches(records):
            if traced:
                self._traced(stretch)
            else:
                for record in stretch:
                    self._step(record)

    def on_step(self, record):
        """Show one step (``vcyto.steps.StepRecord``)."""
        self.on_steps([record])

    def _step(self, record):
        """A step of a plant that does not trace: its cells and membranes, events, decisions, outcomes, field."""
        classes, logger = self.classes, self.logger
        revised = self._revised(record)
        classes.observe(record.events, record.decisions)
        logger.time(record.observation.time, record.step)
        logger.cells([_cell_view(cell, classes.provisional(cell.key)) for cell in record.truth.cells
                      if cell.fate == "in_channel"])
        self._happenings(record, revised, positions=False)
        fields = record.fields
        if fields is not None and self.field_every and record.step % self.field_every == 0:
            logger.field(fields())

    def _traced(self, records):
        """The recorded steps of an event-driven plant's records as columns; each record's events, decisions and
        outcomes at its time."""
        logger = self.logger
        rows = TracedRows(records)
        x_um, y_um = rows.x / UM, rows.y / UM
        for key, piece in rows.by_key(x_um, y_um).items():        # a path is whole when its cell leaves
            logger.paths.setdefault(key, []).append(piece)
        revised = {}

        def before(index, record):
            revised[index] = self._revised(record)

        def each(index, record):
            logger.time(record.observation.time, record.step)
            self._happenings(record, revised.pop(index), positions=True)

        rows.classify(self.classes, each, before)
        logger.traced(rows, x_um, y_um)

    def _revised(self, record) -> dict:
        """The pulses a record's aborts revise, as scheduled before them."""
        pulses = self.classes.pulses
        return {d.event_id: pulses.get(d.event_id) for d in record.decisions if d.action == "abort"}

    def _happenings(self, record, revised: dict, positions: bool):
        """A record's detector events (a marker where the cell is: at its position in ``truth`` if ``positions``,
        else its latest shown), decisions and pulses, outcomes, and the sort's figures."""
        logger, classes, figures, truth = self.logger, self.classes, self.logger.figures, record.truth
        if record.events:
            where = {cell.key: (cell.x / UM, cell.y / UM) for cell in truth.cells} if positions else {}
            for event in record.events:
                figures.event(event.classification)
                logger.event(event.time, event.key, classes.provisional(event.key), event_text(event),
                             where.get(event.key))
        for decision in record.decisions:
            figures.decision(decision.action)
            logger.text(decision_text(decision.event_id, decision.action, decision.reason),
                        level="WARN" if decision.action == "abort" else "INFO")
            pulse = (decision.pulse_on, decision.pulse_off) if decision.action == "sort" \
                else revised.get(decision.event_id)
            if pulse and math.isfinite(pulse[0]):
                logger.pulse(*pulse, aborted=decision.action == "abort", event_id=decision.event_id)
        classes.forget_pulses(record.observation.time)
        left = [cell for cell in truth.cells if cell.fate != "in_channel" and cell.key not in self._reported]
        if left or len(self._reported) > REPORTED_KEPT:
            self._reported &= {cell.key for cell in truth.cells}
        for cell in left:
            self._reported.add(cell.key)
            name = classes.settle(cell)
            figures.outcome(cell.fate, classes.true_class(cell.type) == "II")
            logger.outcome(cell.key, name, outcome_text(cell.key, cell.type, cell.fate, name,
                                                        (cell.measures or {}).get("area_corrected")))
        if left or record.decisions:
            logger.sort_figures()

    def after_gap(self, record):
        """Steps were not shown before ``record`` (a live view that fell behind: ``vcyto.sinks.LiveView``): forget
        the cells that left meanwhile (their paths, classes and positions), so that what is kept stays bounded."""
        inside = {cell.key for cell in record.truth.cells if cell.fate == "in_channel"}
        logger = self.logger
        logger.paths = {key: path for key, path in logger.paths.items() if key in inside}
        logger.positions = {key: at for key, at in logger.positions.items() if key in inside}
        self.classes.keep_only(inside)

    def close(self):
        self.logger.close()
