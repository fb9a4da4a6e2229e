"""`vcyto replay FILE.mcap`: re-log a recording to Rerun; damaged files replay what can be recovered."""

from __future__ import annotations

import json
import struct
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from zstandard import ZstdError

from sim.scenario import Scenario

from .config import scenario_from_toml
from .viewer import RerunLogger


class ReplayError(ValueError):
    """The file is not a vcyto recording at all."""


def read_recording(path: Path):
    """(metadata, [(topic, data)], problem) from an MCAP file, reading past nothing that is damaged."""
    metadata, channels, messages, problem = {}, {}, [], ""
    with open(path, "rb") as handle:
        try:
            for record in StreamReader(handle, skip_magic=False).records:
                if isinstance(record, Metadata) and record.name == "run":
                    metadata = dict(record.metadata)
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message) and record.channel_id in channels:
                    messages.append((channels[record.channel_id], json.loads(record.data)))
        except (McapError, ValueError, EOFError, struct.error, ZstdError) as error:   # damaged: stop there
            problem = f"{type(error).__name__}: {error}".strip()
    if not channels and not metadata:
        raise ReplayError(f"{path} is not a readable vcyto MCAP recording ({problem or 'no channels'})")
    return metadata, messages, problem


def replay(path: Path, target, progress=None) -> dict:
    metadata, messages, problem = read_recording(path)
    scenario = scenario_from_toml(metadata["scenario_toml"]) if "scenario_toml" in metadata else Scenario()
    window = None
    if "detector" in metadata and "window=(" in metadata["detector"]:
        text = metadata["detector"].split("window=(", 1)[1].split(")", 1)[0]
        window = tuple(float(v) for v in text.split(","))
    logger = RerunLogger(scenario, window, target)
    steps = 0
    last_time = 0.0
    for topic, data in messages:
        if topic == "/loop/step":
            steps += 1
            last_time = data["time"]
            logger.time(data["time"], data["step"])
            logger.idt(data["idt"])
        elif topic == "/cells":
            logger.cells(data["cells"])
        elif topic == "/detector/event":
            logger.text(f"cell {data['key']}: detected type {data['classification']} "
                        f"(fluorescence {data['fluorescence']:.2f})")
        elif topic == "/controller/decision":
            logger.text(f"event {data['event_id']}: {data['action']}", level="WARN" if data["action"] == "abort" else "INFO")
        elif topic == "/outcome":
            logger.text(f"cell {data['key']} ({data['type']}) left by: {data['outlet']}")
        elif topic == "/flow/velocity":
            logger.field(data)
    logger.close()
    return {"steps": steps, "messages": len(messages), "last_time_ms": last_time * 1e3, "damaged": bool(problem),
            "problem": problem}
