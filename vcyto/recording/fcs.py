"""FCS 3.1 export of a stream's detector events, readable and gateable by standard flow-cytometry tools.

One event per detected cell, channels ($PnN as analysis tools expect: scatter and fluorescence as ``-A`` areas;
$PnS a short name): Time (integer ticks of $TIMESTEP = ``TIMESTEP`` s, the detection time), FL1-A (fluorescence,
a.u.), FSC-A (forward scatter: the cell's area with noise, um^2), Velocity (mm/s), Class (1 = type I, 2 = type II),
Decision (0 pass, 1 sort, 2 abort), Outlet (0 lower, 1 upper, 2 wall, 3 lost, 4 still in the channel when a partial
run stopped). The data are float64 ($DATATYPE D), so Time is an exact integer tick count over any run shorter than
~28 years and FL1-A is the detector's own value (the exported gate, ``vcyto.recording.gatingml``, applied to the file
counts exactly the detector's classifications). Every $PnR bounds its channel's values (a 1, 2 or 5 x 10^k at or above
the largest), so a logicle or biexponential display spreads the events over the axis; $PnE is 0,0 (linear). The run
is described by $CYT, $DATE, $BTIM, $ETIM and VCYTO_* keywords (model, seed, codes, device, detector and controller
settings).

flowio (the reader here, and FlowKit's) writes float32 data only, which cannot hold microsecond ticks past 16 s;
``fcs_bytes`` writes the FCS 3.1 segments (header, TEXT, DATA) for float64 itself.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import flowio
import numpy as np

from .. import outputs

CHANNELS = ("Time", "FL1-A", "FSC-A", "Velocity", "Class", "Decision", "Outlet")
SHORT_NAMES = ("Time", "Fluorescence", "Forward scatter", "Velocity mm/s", "Class", "Decision", "Outlet")
DESCRIPTIONS = ("time of detection (ticks of $TIMESTEP s)", "fluorescence (a.u.)", "forward scatter, cell area (um^2)",
                "velocity through the detection window (mm/s)", "detected class (1=I, 2=II)",
                "decision (0=pass, 1=sort, 2=abort)", "outlet (0=lower, 1=upper, 2=wall, 3=lost, 4=in channel)")
TIMESTEP = 1e-7               # s: Time's tick (0.1 us)
CLASS_CODES = {"I": 1, "II": 2}
DECISION_CODES = {"pass": 0, "sort": 1, "abort": 2, "missed": 3}
OUTLET_CODES = {"lower": 0, "upper": 1, "wall": 2, "lost": 3, "in_channel": 4}
_TEXT_START = 58              # the TEXT segment follows the header


def event_table(result: dict) -> np.ndarray:
    """Rows of detected cells in event order, columns as ``CHANNELS`` (float64; Time in ticks): from the summary's
    cells, else from its per-cell table (``vcyto.celltable``)."""
    cells = result.get("cells")
    if cells is None and result.get("cell_table"):
        return _table_events(result["cell_table"]["path"])
    rows = [event_row(cell) for cell in cells or () if cell["detected_class"] is not None]
    table = np.array(rows, dtype=float).reshape(-1, len(CHANNELS))
    return table[np.argsort(table[:, 0], kind="stable")]


def event_row(cell: dict) -> list:
    """The FCS event (``CHANNELS``) of a detected cell's per-cell record."""
    return [round(cell["detection_time_ms"] * 1e-3 / TIMESTEP), cell["fluorescence"], cell["scatter"],
            cell["velocity_mm_s"], CLASS_CODES[cell["detected_class"]], DECISION_CODES.get(cell["decision"], -1),
            OUTLET_CODES.get(cell["outlet"], 3)]


def _table_events(path) -> np.ndarray:
    """``event_table`` read column by column from a per-cell table (memory: a few arrays of the events)."""
    from ..celltable import read_table
    table = read_table(path, columns=["detection_time_ms", "fluorescence", "scatter", "velocity_mm_s",
                                      "detected_class", "decision", "outlet"])
    column = {name: table[name].to_numpy(zero_copy_only=False) for name in table.column_names}
    # the detected cells, by a numpy mask (pyarrow's filter imports pyarrow.compute: 0.08 s of a run's exit)
    detected = column["detected_class"] != None                                     # noqa: E711

    def coded(name, codes, missing):           # by the distinct values: no Python object per event
        distinct, index = np.unique(column[name][detected].astype(str), return_inverse=True)
        return np.array([codes.get(value, missing) for value in distinct.tolist()], dtype=float)[index]
    columns = [np.round(column["detection_time_ms"][detected].astype(float) * 1e-3 / TIMESTEP),
               *(column[name][detected].astype(float) for name in ("fluorescence", "scatter", "velocity_mm_s")),
               coded("detected_class", CLASS_CODES, 0), coded("decision", DECISION_CODES, -1),
               coded("outlet", OUTLET_CODES, 3)]
    events = np.column_stack(columns) if detected.any() else np.zeros((0, len(CHANNELS)))
    return events[np.argsort(events[:, 0], kind="stable")]


def fcs_bytes(events: np.ndarray, keywords: dict) -> bytes:
    """An FCS 3.1 file of ``events`` (rows of float64, little-endian, list mode) with ``keywords`` (the channels'
    $PnN, $PnS, $PnR and any others; the segment offsets and data layout are added)."""
    head, data = fcs_segments(events, keywords)
    return head + data.tobytes()


def fcs_segments(events: np.ndarray, keywords: dict) -> tuple[bytes, np.ndarray]:
    """``fcs_bytes`` as (HEADER and TEXT, the DATA segment's array): written one after the other, without a copy
    of the events."""
    events = np.ascontiguousarray(events, dtype="<f8")
    return fcs_head(*events.shape, keywords), events


def fcs_head(count: int, channels: int, keywords: dict) -> bytes:
    """The header and TEXT segment of an FCS 3.1 file of ``count`` events of ``channels`` float64 values, whose
    DATA segment (``count * channels * 8`` bytes) follows them directly."""
    fixed = {"$BEGINANALYSIS": "0", "$ENDANALYSIS": "0", "$BEGINSTEXT": "0", "$ENDSTEXT": "0",
             "$BYTEORD": "1,2,3,4", "$DATATYPE": "D", "$MODE": "L", "$NEXTDATA": "0", "$PAR": str(channels),
             "$TOT": str(count), **{f"$P{i}{key}": value for i in range(1, channels + 1)
                                    for key, value in (("B", "64"), ("E", "0,0"))}}
    size, begin = count * channels * 8, 0
    while True:                         # the offsets are in the TEXT whose length they set: until they hold
        end = begin + size - 1 if size else 0
        text = _text({**fixed, **keywords, "$BEGINDATA": str(begin if size else 0), "$ENDDATA": str(end)})
        start = _TEXT_START + len(text)
        if begin == start or not size:
            break
        begin = start
    offsets = [_TEXT_START, _TEXT_START + len(text) - 1, begin if size else 0, end, 0, 0]
    header = "FCS3.1    " + "".join(f"{value if value <= 99_999_999 else 0:>8}" for value in offsets)
    return header.encode("ascii") + text


def _text(keywords: dict) -> bytes:
    """The TEXT segment: / delimited, a / inside a keyword or value doubled (FCS 3.1), UTF-8."""
    return ("/" + "/".join(f"{_escape(key)}/{_escape(str(value))}" for key, value in keywords.items())
            + "/").encode("utf-8")


def _escape(text: str) -> str:
    return text.replace("/", "//")


def channel_range(values: np.ndarray) -> str:
    """$PnR: 1, 2 or 5 x 10^k, the smallest at or above the largest value (at least 1)."""
    top = float(np.max(values)) if len(values) else 0.0
    if not top > 1:
        return "1"
    decade = 10.0 ** math.floor(math.log10(top))
    return f"{next(step * decade for step in (1, 2, 5, 10) if step * decade >= top):.0f}"


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
    head, data = fcs_segments(table, fcs_keywords(result, table.max(axis=0, initial=0.0), metadata, settings,
                                                  scenario))

    def write(temporary):
        with open(temporary, "wb") as handle:
            handle.write(head)
            data.tofile(handle)
    outputs.write_whole(path, write)
    return path


def fcs_keywords(result: dict, largest, metadata: dict | None = None, settings=None, scenario=None) -> dict:
    """The keywords of a run's FCS file: ``result`` gives the model, seed and wall time (the file's $BTIM is now
    less it), ``largest`` each channel's largest value (its $PnR)."""
    gate = settings.detector.gate if settings is not None else 0.5
    ended = time.time()
    began = ended - float(result.get("wall_time_s", 0.0))
    keywords = {"$CYT": f"vcyto virtual cytometer ({result['model']} model)", "$TIMESTEP": f"{TIMESTEP:g}",
                "$DATE": time.strftime("%d-%b-%Y", time.localtime(began)).upper(),
                "$BTIM": time.strftime("%H:%M:%S", time.localtime(began)),
                "$ETIM": time.strftime("%H:%M:%S", time.localtime(ended)),
                "VCYTO_MODEL": result["model"], "VCYTO_SEED": str(result["seed"]), "VCYTO_GATE_FL1_A": f"{gate!r}",
                "VCYTO_CLASS_CODES": "1=I,2=II", "VCYTO_DECISION_CODES": "0=pass,1=sort,2=abort,3=missed",
                "VCYTO_OUTLET_CODES": "0=lower,1=upper,2=wall,3=lost,4=in_channel"}
    keywords.update(_settings_keywords(settings))
    keywords.update(_device_keywords(scenario))
    for index, (name, short, description) in enumerate(zip(CHANNELS, SHORT_NAMES, DESCRIPTIONS), start=1):
        keywords.update({f"$P{index}N": name, f"$P{index}S": short,
                         f"$P{index}R": channel_range(np.array([largest[index - 1]])),
                         f"VCYTO_P{index}_DESCRIPTION": description})
    keywords.update({key: str(value) for key, value in (metadata or {}).items()})
    return keywords


def read_fcs(path: Path):
    """(channel names, events array, keywords) of an FCS file."""
    data = flowio.FlowData(str(path))
    return list(data.pnn_labels), np.asarray(data.as_array(preprocess=False), dtype=float), data.text
