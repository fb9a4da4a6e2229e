"""What the closed loop hands its sinks: one ``StepRecord`` per step shown; and the sink that prints progress.

A sink is any object with ``on_step(record)`` and, optionally, ``on_end(ending)`` (how the run ended: status,
reason, the sort report's figures, after the last step) and ``close()`` (called by whoever opened it). A sink
whose ``paced`` attribute is false (``ProgressSink``) does not make the loop stop an event-driven plant at the
record interval: it sees the steps the loop takes anyway. Recording sinks (MCAP, Rerun) are paced.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

NOTE_LIMIT = 200               # per-cell lines on screen for samples up to this size; beyond, counts only


@dataclass(frozen=True)
class StepRecord:
    """One step as the sinks see it (immutable: a background sink may read it while the loop goes on).

    ``truth`` holds the cells in the channel and those that left since the previous record (each once);
    ``events`` and ``decisions`` are the detector events and the controller's decisions (made or revised) since
    the previous record; ``fields`` computes the flow field payload of this step (plants with a flow field;
    only called where a sink asks for it); ``diagnostics`` is the plant's (``Plant.diagnostics``), if any;
    ``trace``: an event-driven plant's recorded steps since the previous record, as columns (``vcyto.trace.Trace``;
    None for plants whose every record is a recorded step)."""

    step: int
    observation: Any
    truth: Any
    actuation: float
    events: tuple = ()
    decisions: tuple = ()
    fields: Callable[[], dict] | None = None
    diagnostics: dict | None = None
    trace: Any = None

    @property
    def time(self) -> float:
        return self.observation.time


@dataclass(frozen=True)
class Moment:
    """The observation a record carries when no sink looks at the plant's state (``needs_state``): its time."""

    time: float
    cells: tuple = ()


def needs_state(sink) -> bool:
    """Whether ``sink`` reads the plant's observation and diagnostics (recordings, progress), or only the time,
    the cells' truth, events and decisions (``needs_state = False``: the sort report), so that the loop can skip
    looking at the plant for it."""
    return getattr(sink, "needs_state", True)


def is_paced(sink) -> bool:
    """Whether ``sink`` wants the state every record interval (recordings) or only the loop's own steps."""
    return getattr(sink, "paced", True)


class ProgressSink:
    """Progress of a run on a ``vcyto.progress.Progress``: a status line, and for samples of at most
    ``NOTE_LIMIT`` cells a line per detector event (with the decision) and per cell that leaves."""

    paced = False

    def __init__(self, progress, count: int):
        self.progress = progress
        self.notes = count <= NOTE_LIMIT
        self.left = self.detected = 0
        self.bar = not self.notes and hasattr(progress, "run")      # a long run: a bar with a rate and an ETA
        if self.bar:
            progress.run(count)

    @property
    def needs_state(self) -> bool:
        """A long run's bar reads the events, the cells that left and the time, not the plant's observation: the loop
        need not look at the plant for it (``needs_state``); the per-cell notes' status line counts the cells in
        the channel."""
        return not self.bar

    def on_step(self, record: StepRecord):
        """The record's detections and exits, in time order (one record of an event-driven plant spans many
        periods: a cell may leave before another is detected), then the status line."""
        progress = self.progress
        if self.bar:
            self.detected += len(record.events)
            self.left += sum(cell.fate != "in_channel" for cell in record.truth.cells)
            progress.advance(self.left, self.detected, record.time)
            return
        actions = {decision.event_id: decision.action for decision in record.decisions}
        lines = []
        for event in record.events:
            self.detected += 1
            lines.append((event.time, 0, f"t = {event.time * 1e3:7.3f} ms  cell {event.key}: detected type "
                                         f"{event.classification} (fluorescence {event.fluorescence:.2f}), "
                                         f"decision {actions.get(event.event_id, 'pending')}"))
        for cell in record.truth.cells:
            if cell.fate != "in_channel":
                self.left += 1
                lines.append((cell.exit_time, 1, f"t = {cell.exit_time * 1e3:7.3f} ms  cell {cell.key} ({cell.type}) "
                                                 f"left by: {cell.fate}"))
        if self.notes:
            for _, _, line in sorted(lines, key=lambda item: (item[0] if item[0] == item[0] else math.inf, item[1])):
                progress.note(line)
        progress.update(f"t = {record.time * 1e3:.3f} ms, {len(record.observation.cells)} cells in the channel, "
                        f"{self.left} left, {self.detected} detected, IDT {'on' if record.actuation else 'off'}")

    def close(self):
        pass
