"""FCS 3.1 export of a stream's detector events (flowio), readable by standard flow-cytometry tools.

One event per detected cell, channels: Time (ms), FL1 (fluorescence), FSC (scatter), Velocity (mm/s),
Class (1 = type I, 2 = type II), Decision (0 pass, 1 sort, 2 abort), Outlet (0 lower, 1 upper,
2 wall, 3 lost). Codes are also written as keywords ($P<n>S names and VCYTO_* keywords).
"""

from __future__ import annotations

from pathlib import Path

import flowio
import numpy as np

CHANNELS = ("Time", "FL1", "FSC", "Velocity", "Class", "Decision", "Outlet")
CLASS_CODES = {"I": 1, "II": 2}
DECISION_CODES = {"pass": 0, "sort": 1, "abort": 2}
OUTLET_CODES = {"lower": 0, "upper": 1, "wall": 2, "lost": 3}


def event_table(result: dict) -> np.ndarray:
    """Rows of detected cells in event order, columns as ``CHANNELS``."""
    rows = []
    for cell in result["cells"]:
        if cell["detected_class"] is None:
            continue
        rows.append([cell["detection_time_ms"], cell["fluorescence"], cell["scatter"], cell["velocity_mm_s"],
                     CLASS_CODES[cell["detected_class"]], DECISION_CODES.get(cell["decision"], -1),
                     OUTLET_CODES.get(cell["outlet"], 3)])
    table = np.array(rows, dtype=np.float32).reshape(-1, len(CHANNELS))
    return table[np.argsort(table[:, 0], kind="stable")]


def write_fcs(path: Path, result: dict, metadata: dict | None = None) -> Path:
    table = event_table(result)
    keywords = {"VCYTO_MODEL": result["model"], "VCYTO_SEED": str(result["seed"]),
                "VCYTO_CLASS_CODES": "1=I,2=II", "VCYTO_DECISION_CODES": "0=pass,1=sort,2=abort",
                "VCYTO_OUTLET_CODES": "0=lower,1=upper,2=wall,3=lost"}
    keywords.update({key: str(value) for key, value in (metadata or {}).items()})
    with open(path, "wb") as handle:
        flowio.create_fcs(handle, table.flatten(), list(CHANNELS), metadata_dict=keywords)
    return path


def read_fcs(path: Path):
    """(channel names, events array, keywords) of an FCS file."""
    data = flowio.FlowData(str(path))
    return list(data.pnn_labels), np.asarray(data.as_array(preprocess=False), dtype=float), data.text
