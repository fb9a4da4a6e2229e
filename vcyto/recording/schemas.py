"""JSON Schemas (draft 2020-12) of vcyto's own MCAP channels: every field typed, the required ones listed, units
in each description and in a ``unit`` annotation (SI or um as named), base64 fields marked as such.

``SCHEMAS``: the channels a recording has; ``RECORDS``: a detector event, a decision and an outcome, the rows of the
columnar ``/detector/events``, ``/controller/decisions`` and ``/outcomes`` (and the messages of format-3
recordings, which ``vcyto.recording.replay`` reads)."""

from __future__ import annotations

DRAFT = "https://json-schema.org/draft/2020-12/schema"


def _number(description: str, unit: str | None = None, nullable: bool = False) -> dict:
    schema = {"type": ["number", "null"] if nullable else "number",
              "description": f"{description} ({unit})" if unit else description}
    if unit:
        schema["unit"] = unit
    return schema


def _integer(description: str) -> dict:
    return {"type": "integer", "minimum": 0, "description": description}


def _string(description: str, values=None) -> dict:
    schema = {"type": "string", "description": description}
    if values:
        schema["enum"] = list(values)
    return schema


def _array(items: dict) -> dict:
    return {"type": "array", "items": items, "description": f"per row: {items.get('description', '')}"}


def _object(title: str, description: str, properties: dict, optional=()) -> dict:
    return {"$schema": DRAFT, "title": title, "description": description, "type": "object",
            "properties": properties, "required": [key for key in properties if key not in optional]}


TIME = _number("simulated time", "s")
CELL = {"type": "object", "required": ["key", "type", "class", "x_um", "y_um", "area_ratio", "fate"], "properties": {
    "key": _integer("the cell's key (its index in the run's schedule)"),
    "type": _string("cell type (scenario name)"),
    "class": _string("provisional class of a cell in the channel (see /outcome for the final one)"),
    "x_um": _number("centroid abscissa", "um"), "y_um": _number("centroid ordinate (y up, 0 = lower wall)", "um"),
    "area_ratio": _number("membrane area / initial area", "1"),
    "fate": _string("in_channel, an outlet name, wall or lost"),
    "perimeter_um": _number("membrane perimeter; null without a membrane", "um", nullable=True),
    "spacing_min_h": _number("smallest membrane point spacing / mesh size h", "1", nullable=True),
    "spacing_max_h": _number("largest membrane point spacing / mesh size h", "1", nullable=True),
    "membrane_um": {"type": "array", "description": "membrane points (um); only in recordings of format 1",
                    "items": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}}}}
B64 = {"type": "string", "contentEncoding": "base64", "contentMediaType": "application/octet-stream"}

# the records of events, decisions and outcomes: one message each in recordings of format 3, the rows of their
# columnar channels since format 4
RECORDS = {
    "/detector/event": _object("vcyto.DetectorEvent", "a cell's passage through the detection window", {
        "event_id": _integer("event number"), "time": _number("when the cell left the window", "s"),
        "fluorescence": _number("measured fluorescence", "a.u."),
        "scatter": _number("forward scatter (the cell's area with noise)", "um^2"),
        "velocity": _number("window length / transit time", "m/s"),
        "classification": _string("class by the gate", ("I", "II")), "key": _integer("the cell's key")}),
    "/controller/decision": _object("vcyto.Decision", "the controller's decision on an event (made or revised)", {
        "event_id": _integer("event number"), "action": _string(
            "what the controller does (missed: its answer came after its deadline)",
            ("sort", "pass", "abort", "missed")),
        "arrival": _number("predicted arrival at the SAW window", "s"),
        "pulse_on": _number("IDT pulse start; null without a pulse", "s", nullable=True),
        "pulse_off": _number("IDT pulse end; null without a pulse", "s", nullable=True),
        "reason": _string("why (empty for a plain sort or pass)"),
        "time": _number("when the decision was shown (made or revised by then)", "s")}, optional=("time",)),
    "/outcome": _object("vcyto.Outcome", "a cell that has left the channel", {
        "key": _integer("the cell's key"), "type": _string("cell type"),
        "outlet": _string("outlet name, wall or lost"),
        "class": _string("outcome class (vcyto.outcomes.OUTCOME_CLASSES)"),
        "exit_time": _number("when it left", "s", nullable=True),
        "exit_y_um": _number("ordinate where it left", "um", nullable=True),
        "area_restored": _number("area the projection restored over its transit / initial area (vcyto.restored); "
                                 "null without a membrane", "1", nullable=True),
        "time": _number("when its leaving was shown", "s")}, optional=("class", "time", "area_restored")),
}


def _columnar(title: str, description: str, record: dict) -> dict:
    """A channel of ``record``'s fields as columns, one entry per record of a batch (every field required)."""
    return _object(title, f"{description}, as columns (one entry per record of a batch)",
                   {name: _array(schema) for name, schema in record["properties"].items()})


SCHEMAS = {
    "/loop/steps": _object("vcyto.LoopSteps", "the steps of a batch as columns (one entry per step)", {
        "time": _array(TIME), "step": _array(_integer("steps (control periods) since the start")),
        "idt": _array(_number("IDT drive (0 off, 1 on)", "1")),
        "cells_in_channel": _array(_integer("cells the optics see")),
        "wall_time": _array(_number("wall-clock time when the step was recorded (Unix epoch)", "s")),
        "diagnostics": _array({"type": "object", "description": "plant figures: dt (s), physics steps, cumulative "
                                                                "solver wall times (s, wall-clock), health"})}),
    "/cells/rows": _object("vcyto.CellRows", "the cells in the channel at each step of a batch, as columns: the "
                           "first count[0] rows belong to time[0], the next count[1] to time[1] ... (membranes: "
                           "/foxglove/membranes)", {
        "time": _array(TIME), "count": _array(_integer("rows of this step")),
        **{name: _array(schema) for name, schema in CELL["properties"].items()
           if name not in ("fate", "membrane_um")}}),
    "/flow/velocity": _object("vcyto.FlowField", "velocity and pressure at the mesh vertices, rows of constant y", {
        "time": TIME, "shape": {"type": "array", "items": {"type": "integer"}, "minItems": 2, "maxItems": 2,
                                "description": "(rows, columns) of the vertex grid"},
        "x_um": {"type": "array", "items": {"type": "number"}, "description": "grid abscissae (um)", "unit": "um"},
        "y_um": {"type": "array", "items": {"type": "number"}, "description": "grid ordinates (um)", "unit": "um"},
        "vx_f32_b64": {**B64, "description": "x velocity (m/s), little-endian float32, rows of constant y",
                       "unit": "m/s"},
        "vy_f32_b64": {**B64, "description": "y velocity (m/s), little-endian float32", "unit": "m/s"},
        "p_f32_b64": {**B64, "description": "pressure (Pa), little-endian float32", "unit": "Pa"}}),
    "/detector/events": _columnar("vcyto.DetectorEvents", "the detector events of a batch",
                                  RECORDS["/detector/event"]),
    "/controller/decisions": _columnar("vcyto.Decisions", "the controller's decisions of a batch (made or revised)",
                                       RECORDS["/controller/decision"]),
    "/outcomes": _columnar("vcyto.Outcomes", "the cells that left the channel in a batch", RECORDS["/outcome"]),
}
