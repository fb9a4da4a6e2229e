"""MCAP recording of a closed-loop run: typed JSON channels, log time = simulated time, crash safety.

Topics (JSON, each with a JSON Schema):
- ``/loop/step``         every control period: time, step, IDT drive, cells in the channel, wall time,
                         plant diagnostics (dt, physics steps, cumulative solver times: wall-clock);
- ``/cells``             every control period: each cell's key, type, centroid, area ratio, fate, membrane
                         points (um, rounded to 1 nm), perimeter and smallest/largest point spacing / h
                         (null for models without membranes);
- ``/detector/event``    each detector event (fluorescence, scatter, velocity, class);
- ``/controller/decision`` each decision (sort / pass / abort, predicted arrival, pulse);
- ``/outcome``           each cell when it leaves (outlet, exit time and ordinate);
- ``/flow/velocity``     every ``field_every`` control periods (0: never): velocity (m/s) and pressure (Pa) at
                         the mesh vertices (float32, base64) with the grid, for replay as an image.
Run metadata (scenario TOML, seed, command line, versions) is an MCAP metadata record named ``run``.

The writer flushes every ``flush_every`` control periods, so a killed process loses at most that many
steps; ``close`` finishes the file (summary and index) and is called on normal exit, Ctrl-C and SIGTERM.
"""

from __future__ import annotations

import base64
import json
import time
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer

SCHEMAS = {
    "/loop/step": {"type": "object", "properties": {
        "time": {"type": "number"}, "step": {"type": "integer"}, "idt": {"type": "number"},
        "cells_in_channel": {"type": "integer"}, "wall_time": {"type": "number"},
        "diagnostics": {"type": "object", "description": "plant figures: dt, physics steps, cumulative solver "
                                                          "wall times (s, wall-clock), health"}}},
    "/cells": {"type": "object", "properties": {"time": {"type": "number"}, "cells": {"type": "array", "items": {
        "type": "object", "properties": {
            "key": {"type": "integer"}, "type": {"type": "string"}, "x_um": {"type": "number"},
            "y_um": {"type": "number"}, "area_ratio": {"type": "number"}, "fate": {"type": "string"},
            "perimeter_um": {"type": ["number", "null"]},
            "spacing_min_h": {"type": ["number", "null"], "description": "smallest point spacing / mesh h"},
            "spacing_max_h": {"type": ["number", "null"], "description": "largest point spacing / mesh h"},
            "membrane_um": {"type": "array", "items": {"type": "array", "items": {"type": "number"}}}}}}}},
    "/detector/event": {"type": "object", "properties": {
        "event_id": {"type": "integer"}, "time": {"type": "number"}, "fluorescence": {"type": "number"},
        "scatter": {"type": "number"}, "velocity": {"type": "number"}, "classification": {"type": "string"},
        "key": {"type": "integer"}}},
    "/controller/decision": {"type": "object", "properties": {
        "event_id": {"type": "integer"}, "action": {"type": "string"}, "arrival": {"type": "number"},
        "pulse_on": {"type": ["number", "null"]}, "pulse_off": {"type": ["number", "null"]},
        "reason": {"type": "string"}}},
    "/outcome": {"type": "object", "properties": {
        "key": {"type": "integer"}, "type": {"type": "string"}, "outlet": {"type": "string"},
        "exit_time": {"type": "number"}, "exit_y_um": {"type": "number"}}},
    "/flow/velocity": {"type": "object", "properties": {
        "time": {"type": "number"}, "shape": {"type": "array", "items": {"type": "integer"}},
        "x_um": {"type": "array"}, "y_um": {"type": "array"}, "vx_f32_b64": {"type": "string"},
        "vy_f32_b64": {"type": "string"}, "p_f32_b64": {"type": "string"}}},
}
PER_STEP = ("/loop/step", "/cells")


def _nanoseconds(seconds: float) -> int:
    return int(round(seconds * 1e9))


def _rounded(value: float, digits: int):
    return round(value, digits) if np.isfinite(value) else None


def _finite(value):
    """JSON has no NaN: report it as null."""
    return None if value is None or (isinstance(value, float) and not np.isfinite(value)) else value


class McapRecorder:
    """A sink of the closed loop that writes every step to an MCAP file."""

    def __init__(self, path: Path, metadata: dict, flush_every: int = 50, field_every: int = 100):
        self.path = Path(path)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="vcyto")
        self._channels = {}
        for topic, schema in SCHEMAS.items():
            schema_id = self._writer.register_schema(topic.strip("/").replace("/", "."), "jsonschema",
                                                     json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic, "json", schema_id)
        self._writer.add_metadata("run", {key: str(value) for key, value in metadata.items()})
        self.flush_every = max(1, flush_every)
        self.field_every = field_every
        self._steps = 0
        self._sequence = 0
        self._settled = set()
        self._writer.flush()
        self.closed = False

    def _write(self, topic: str, time_s: float, payload: dict):
        self._sequence += 1
        stamp = _nanoseconds(time_s)
        self._writer.add_message(self._channels[topic], log_time=stamp, publish_time=stamp,
                                 data=json.dumps(payload, separators=(",", ":")).encode(), sequence=self._sequence)

    def on_step(self, step: int, observation, truth, actuation: float, events, decisions, fields=None,
                diagnostics=None):
        now = observation.time
        self._write("/loop/step", now, {"time": now, "step": step, "idt": actuation,
                                        "cells_in_channel": len(observation.cells), "wall_time": time.time(),
                                        "diagnostics": diagnostics or {}})
        self._write("/cells", now, {"time": now, "cells": [self._cell(cell) for cell in truth.cells
                                                           if cell.fate == "in_channel" or cell.key not in self._settled]})
        for event in events:
            self._write("/detector/event", event.time, {key: getattr(event, key) for key in SCHEMAS["/detector/event"]["properties"]})
        for decision in decisions:
            self._write("/controller/decision", now, {key: _finite(getattr(decision, key))
                                                      for key in SCHEMAS["/controller/decision"]["properties"]})
        for cell in truth.cells:
            if cell.fate != "in_channel" and cell.key not in self._settled:
                self._settled.add(cell.key)
                self._write("/outcome", now, {"key": cell.key, "type": cell.type, "outlet": cell.fate,
                                              "exit_time": _finite(cell.exit_time),
                                              "exit_y_um": _finite(cell.exit_y * 1e6)})
        if fields is not None and self.field_every and step % self.field_every == 0:
            self._write("/flow/velocity", now, fields())
        self._steps += 1
        if self._steps % self.flush_every == 0:
            self._writer.flush()
            self._file.flush()

    @staticmethod
    def _cell(cell) -> dict:
        membrane = np.round(np.asarray(cell.membrane) * 1e6, 3).tolist() if cell.membrane is not None else []
        shape = cell.measures or {}
        return {"key": cell.key, "type": cell.type, "x_um": round(cell.x * 1e6, 4), "y_um": round(cell.y * 1e6, 4),
                "area_ratio": round(cell.area_ratio, 6), "fate": cell.fate, "membrane_um": membrane,
                "perimeter_um": _rounded(shape.get("perimeter", float("nan")) * 1e6, 4),
                "spacing_min_h": _rounded(shape.get("spacing_min", float("nan")), 4),
                "spacing_max_h": _rounded(shape.get("spacing_max", float("nan")), 4)}

    def close(self):
        if not self.closed:
            self.closed = True
            self._writer.finish()
            self._file.close()


def velocity_field(vertices: np.ndarray, velocity: np.ndarray, pressure: np.ndarray, grid_x, grid_y,
                   time_s: float) -> dict:
    """Velocity (m/s) and pressure (Pa) at the mesh vertices as a compact JSON payload (float32, base64)."""
    count = vertices.shape[1]
    order = np.lexsort((vertices[0], vertices[1]))          # rows of constant y, x increasing

    def encoded(values):
        return base64.b64encode(np.asarray(values)[:count][order].astype(np.float32).tobytes()).decode()

    return {"time": time_s, "shape": [len(grid_y), len(grid_x)],
            "x_um": np.round(np.asarray(grid_x) * 1e6, 4).tolist(), "y_um": np.round(np.asarray(grid_y) * 1e6, 4).tolist(),
            "vx_f32_b64": encoded(velocity[0]), "vy_f32_b64": encoded(velocity[1]), "p_f32_b64": encoded(pressure)}
