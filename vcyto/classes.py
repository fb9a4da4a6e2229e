"""Each cell's class while a run is recorded: provisional while it is in the channel, its outcome once it left.

The recordings (MCAP, Rerun) colour a cell by a class id: ids ``0 .. len(OUTCOME_CLASSES) - 1`` are the outcome
classes of ``vcyto.outcomes`` (known once a cell has left the channel); the ids after them are the provisional
classes of a cell still in the channel (what the detector and the controller said of it so far).

``CellClasses`` follows the detector events and decisions a sink is handed and keeps only the cells in the
channel (a cell is forgotten when it leaves), so its state is bounded by the number of cells in the channel.
"""

from __future__ import annotations

import math

from controller.events import TYPE_I, TYPE_II

from .outcomes import OUTCOME_CLASSES, outcome_class

PROVISIONAL_CLASSES = ("in channel", "detected type I", "type II: sort scheduled", "type II: sort aborted")
CLASS_NAMES = OUTCOME_CLASSES + PROVISIONAL_CLASSES
CLASS_IDS = {name: index for index, name in enumerate(CLASS_NAMES)}
CLASS_COLOURS = {                     # RGB, one per class name
    "sorted": (40, 200, 80), "passed": (80, 140, 255), "aborted": (255, 150, 0), "missed": (200, 60, 220),
    "misclassified": (255, 40, 40), "co-deflected": (255, 230, 0), "lost": (140, 140, 140),
    "not_injected": (90, 90, 90), "unfinished": (60, 60, 60), "in channel": (235, 235, 235), "detected type I": (150,
                                                                                                                 190,
                                                                                                                 255),
    "type II: sort scheduled": (150, 240, 170), "type II: sort aborted": (255, 200, 120),
}


def provisional_class(detected: str | None, action: str | None) -> str:
    """The class of a cell still in the channel from its detected class and the latest decision about it."""
    if detected is None:
        return "in channel"
    if detected != "II":
        return "detected type I"
    return "type II: sort aborted" if action == "abort" else "type II: sort scheduled"


def class_of_type(scenario):
    """A function from a cell type's name to its true class ("II" for the scenario's target types)."""
    targets = {cell.name for cell in scenario.cell_types if cell.target}
    return lambda name: TYPE_II if name in targets else TYPE_I


class CellClasses:
    """Detected class and latest decision of the cells in the channel; their class ids."""

    def __init__(self, scenario):
        self.true_class = class_of_type(scenario)
        self._detected: dict[int, str] = {}        # key -> "I" / "II"
        self._event_keys: dict[int, int] = {}      # event_id -> key, for the cells in the channel
        self._action: dict[int, str] = {}          # key -> "sort" / "pass" / "abort"
        self.pulses: dict[int, tuple[float, float]] = {}   # event_id -> (on, off) of a sort, until it is over

    def observe(self, events, decisions) -> list[int]:
        """Take a control period's new detector events and decisions (made or revised); the keys of the cells whose
        class they may have changed."""
        touched = []
        for event in events:
            self._detected[event.key] = event.classification
            self._event_keys[event.event_id] = event.key
            touched.append(event.key)
        for decision in decisions:
            key = self._event_keys.get(decision.event_id)
            if key is not None:
                self._action[key] = decision.action
                touched.append(key)
            if decision.action == "sort" and math.isfinite(decision.pulse_on):
                self.pulses[decision.event_id] = (decision.pulse_on, decision.pulse_off)
        return touched

    def provisional(self, key: int) -> str:
        """The class name of a cell still in the channel."""
        return provisional_class(self._detected.get(key), self._action.get(key))

    def settle(self, cell) -> str:
        """The outcome class of a cell (``sim.plants.feib.CellTruth``) that has left; the cell is forgotten."""
        summary = {"outlet": cell.fate if cell.fate != "in_channel" else "lost",
                   "true_class": self.true_class(cell.type),
                   "detected_class": self._detected.pop(cell.key, None), "decision": self._action.pop(cell.key, None)}
        for event_id in [e for e, key in self._event_keys.items() if key == cell.key]:
            del self._event_keys[event_id]
        return outcome_class(summary)

    def keep_only(self, keys):
        """Forget every cell but ``keys`` (those in the channel): cells whose leaving a sink was not shown."""
        self._detected = {key: name for key, name in self._detected.items() if key in keys}
        self._action = {key: action for key, action in self._action.items() if key in keys}
        self._event_keys = {event: key for event, key in self._event_keys.items() if key in keys}

    def forget_pulses(self, now: float):
        """Drop the pulses that are over (bounded state)."""
        for event_id in [e for e, (_, off) in self.pulses.items() if off < now]:
            del self.pulses[event_id]

    def name(self, cell) -> str:
        return self.provisional(cell.key) if cell.fate == "in_channel" else self.settle(cell)
