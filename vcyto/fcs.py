"""FCS 3.1 export of a stream's detector events (flowio), readable and gateable by standard flow-cytometry tools.

One event per detected cell, channels ($PnN, with $PnS saying what and in which unit): Time (ms; $TIMESTEP 0.001 s),
FL1 (fluorescence, a.u.), FSC (forward scatter: the cell's area with noise, um^2), Velocity (mm/s), Class (1 = type
I, 2 = type II), Decision (0 pass, 1 sort, 2 abort), Outlet (0 lower, 1 upper, 2 wall, 3 lost, 4 still in the
channel when a partial run stopped). Every $PnR bounds its channel's values (a 1, 2 or 5 x 10^k at or above the
largest), so a logicle or biexponential display spreads the events over the axis; $PnE is 0,0 (linear, float data).
The run is described by $CYT, $DATE, $BTIM, $ETIM and VCYTO_* keywords (model, seed, codes, device, detector and
controller settings).

FL1 values are written as float32: where rounding to float32 would move a value across the classification gate,
it is moved by one float32 step back to its side, so that the exported gate (``vcyto.gatingml``) applied to the
file counts exactly the detector's classifications.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import flowio
import numpy as np

from . import outputs

CHANNELS = ("Time", "FL1", "FSC", "Velocity", "Class", "Decision", "Outlet")
DESCRIPTIONS = ("time of detection (ms)", "fluorescence (a.u.)", "forward scatter, cell area (um^2)",
                "velocity through the detection window (mm/s)", "detected class (1=I, 2=II)",
                "decision (0=pass, 1=sort, 2=abort)", "outlet (0=lower, 1=upper, 2=wall, 3=lost, 4=in channel)")
CLASS_CODES = {"I": 1, "II": 2}
DECISION_CODES = {"pass": 0, "sort": 1, "abort": 2, "missed": 3}
OUTLET_CODES = {"lower": 0, "upper": 1, "wall": 2, "lost": 3, "in_channel": 4}


def event_table(result: dict) -> np.ndarray:
    """Rows of detected cells in event order, columns as ``CHANNELS`` (float64)."""
    rows = []
    for cell in result["cells"]:
        if cell["detected_class"] is None:
            continue
        rows.append([cell["detection_time_ms"], cell["fluorescence"], cell["scatter"], cell["velocity_mm_s"],
                     CLASS_CODES[cell["detected_class"]], DECISION_CODES.get(cell["decision"], -1),
                     OUTLET_CODES.get(cell["outlet"], 3)])
    table = np.array(rows, dtype=float).reshape(-1, len(CHANNELS))
    return table[np.argsort(table[:, 0], kind="stable")]


def gate_consistent(fluorescence: np.ndarray, classes: np.ndarray, gate: float) -> np.ndarray:
    """float32 fluorescence on the same side of ``gate`` (as float32) as the detector's class (2: >= gate)."""
    values = fluorescence.astype(np.float32)
    threshold = np.float32(gate)
    above = classes == CLASS_CODES["II"]
    values = np.where(above & (values < threshold), threshold, values)
    return np.where(~above & (values >= threshold), np.nextafter(threshold, np.float32(-np.inf)), values)


def channel_range(values: np.ndarray) -> str:
    """$PnR: 1, 2 or 5 x 10^k, the smallest at or above the largest value (at least 1)."""
    top = float(np.max(values)) if len(values) else 0.0
    if not top > 1:
        return "1"
    decade = 10.0 ** math.floor(math.log10(top))
    return f"{next(step * decade for step in (1, 2, 5, 10) if step * decade >= top):g}"


def _settings_keywords(settings) -> dict:
    if settings is None:
        return {}
    keywords = {"VCYTO_MODEL": settings.model, "VCYTO_SEED": str(settings.seed)}
    for name in ("detector", "controller"):
        for key, value in dataclasses.asdict(getattr(settings, name)).items():
            keywords[f"VCYTO_{name.upper()}_{key.upper()}"] = ",".join(map(str, value)) \
                if isinstance(value, (tuple, list)) else str(value)
    return keywords


def _device_keywords(scenario) -> dict:
    if scenario is None:
        return {}
    channel = scenario.channel
    um = lambda span: ",".join(f"{v * 1e6:g}" for v in span)     # noqa: E731
    return {"VCYTO_CHANNEL_UM": f"{channel.length * 1e6:g}x{channel.height * 1e6:g}",
            "VCYTO_SAW_WINDOW_UM": um(channel.saw_window.span),
            "VCYTO_INLETS_UM": ";".join(f"{i.name}:{um(i.span)}" for i in channel.inlets),
            "VCYTO_OUTLETS_UM": ";".join(f"{o.name}:{um(o.span)}" for o in channel.outlets)}


def write_fcs(path: Path, result: dict, metadata: dict | None = None, settings=None, scenario=None) -> Path:
    """The detected events of ``run_stream``'s ``result``; ``settings`` (``StreamSettings``) and ``scenario``
    add the detector, controller and device keywords; ``metadata``: extra keywords."""
    table = event_table(result)
    gate = settings.detector.gate if settings is not None else 0.5
    table32 = table.astype(np.float32)
    table32[:, 1] = gate_consistent(table[:, 1], table[:, 4], gate)
    ended = time.time()
    began = ended - float(result.get("wall_time_s", 0.0))
    keywords = {"$CYT": f"vcyto virtual cytometer ({result['model']} model)", "$TIMESTEP": "0.001",
                "$DATE": time.strftime("%d-%b-%Y", time.localtime(began)).upper(),
                "$BTIM": time.strftime("%H:%M:%S", time.localtime(began)),
                "$ETIM": time.strftime("%H:%M:%S", time.localtime(ended)),
                "VCYTO_MODEL": result["model"], "VCYTO_SEED": str(result["seed"]), "VCYTO_GATE_FL1": f"{gate!r}",
                "VCYTO_CLASS_CODES": "1=I,2=II", "VCYTO_DECISION_CODES": "0=pass,1=sort,2=abort,3=missed",
                "VCYTO_OUTLET_CODES": "0=lower,1=upper,2=wall,3=lost,4=in_channel"}
    keywords.update(_settings_keywords(settings))
    keywords.update(_device_keywords(scenario))
    for index in range(len(CHANNELS)):
        keywords[f"$P{index + 1}R"] = channel_range(table32[:, index])
    keywords.update({key: str(value) for key, value in (metadata or {}).items()})
    def write(temporary):
        with open(temporary, "wb") as handle:
            flowio.create_fcs(handle, table32.flatten(), list(CHANNELS), opt_channel_names=list(DESCRIPTIONS),
                              metadata_dict=keywords)
    outputs.write_whole(path, write)
    return path


def read_fcs(path: Path):
    """(channel names, events array, keywords) of an FCS file."""
    data = flowio.FlowData(str(path))
    return list(data.pnn_labels), np.asarray(data.as_array(preprocess=False), dtype=float), data.text
