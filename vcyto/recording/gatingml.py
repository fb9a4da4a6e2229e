"""Gating-ML 2.0 export of the detector's classification gate, to reproduce vcyto's classes in any tool that reads
Gating-ML (FlowKit, FlowJo, Cytobank ...).

The detector calls a cell type II when its fluorescence is at or above the gate, else type I. Gating-ML's
rectangle gate includes its ``min`` and excludes its ``max``, so two rectangle gates on the FCS channel
``FL1-A`` (uncompensated, untransformed; the file holds the detector's float64 values) reproduce it exactly:
``typeII`` with min = gate and ``typeI`` with max = gate.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from .. import outputs

GATING = "http://www.isac-net.org/std/Gating-ML/v2.0/gating"
DATA_TYPE = "http://www.isac-net.org/std/Gating-ML/v2.0/datatypes"
TRANSFORMS = "http://www.isac-net.org/std/Gating-ML/v2.0/transformations"
GATE_IDS = {"II": "typeII", "I": "typeI"}


def _rectangle(root, gate_id: str, channel: str, bound: str, value: float, note: str):
    gate = ET.SubElement(root, f"{{{GATING}}}RectangleGate", {f"{{{GATING}}}id": gate_id})
    info = ET.SubElement(gate, f"{{{DATA_TYPE}}}custom_info")
    info.text = note
    dimension = ET.SubElement(gate, f"{{{GATING}}}dimension", {f"{{{GATING}}}compensation-ref": "uncompensated",
                                                               f"{{{GATING}}}{bound}": repr(float(value))})
    ET.SubElement(dimension, f"{{{DATA_TYPE}}}fcs-dimension", {f"{{{DATA_TYPE}}}name": channel})


def classification_gates(gate: float, channel: str = "FL1-A") -> ET.ElementTree:
    """The Gating-ML document of the classification at ``gate`` (fluorescence, a.u.)."""
    for prefix, uri in (("gating", GATING), ("data-type", DATA_TYPE), ("transforms", TRANSFORMS)):
        ET.register_namespace(prefix, uri)
    root = ET.Element(f"{{{GATING}}}Gating-ML")
    _rectangle(root, GATE_IDS["II"], channel, "min", gate, f"vcyto detector: type II (sorted), {channel} >= {gate!r}")
    _rectangle(root, GATE_IDS["I"], channel, "max", gate, f"vcyto detector: type I, {channel} < {gate!r}")
    ET.indent(root)
    return ET.ElementTree(root)


def write_gatingml(path: Path, gate: float, channel: str = "FL1-A") -> Path:
    outputs.write_whole(path, lambda temporary: classification_gates(gate, channel).write(
        temporary, encoding="UTF-8", xml_declaration=True))
    return Path(path)
