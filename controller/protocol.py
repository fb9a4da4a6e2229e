"""The controller protocol: what the closed loop tells a controller, what the controller answers, and by when.

Every controller, the built-in ``SortController`` included, is reached by the loop through this protocol only:

- before the first event the loop calls ``start(facts)`` if the controller has it: ``DeviceFacts`` holds the
  calibrated device facts a controller may use (sort delay, reference velocity, calibrated lead and pulse,
  deflection envelope, timing error, control period, detection window);
- for each detector event (``controller.events.DetectorEvent``: its device time and every measured feature) the
  loop calls ``on_event(event, clock)``, ``clock`` being the device time at which the event is delivered, and
  takes the answer: a sequence of ``Decision``, the event's own (``sort`` with its pulse, ``pass`` or ``abort``)
  and any revision of an earlier one (an ``abort`` of a sort whose pulse has not started);
- the loop turns the sorts into the IDT drive (``PulseSchedule``: on while any scheduled pulse is on). A
  controller that wants to set the drive itself each control period offers ``drive(clock) -> float`` in [0, 1]
  (``Drives``); the loop then steps period by period and uses that value instead of the schedule.

When an answer is due. An event's **decision deadline** is the latest device time at which its pulse could still
start: the predicted arrival at the SAW window minus the calibrated lead, ``DeviceFacts.deadline(event)`` (with
the shipped calibration, 0.253 ms after detection for a cell at the reference velocity). In lock-step runs the
loop waits for every answer, so none is late; in paced real time an answer that arrives after its deadline is a
*missed decision*: the loop applies none of it to its event (the cell goes where the flow takes it), and counts,
records and reports the miss.

All times are device times in seconds; lengths in metres; velocities in m/s. This module needs the standard
library only (importing it loads neither numpy's numerics libraries nor scikit-fem nor numba).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from .events import Decision, DetectorEvent

ACTIONS = ("sort", "pass", "abort")     # what a controller may answer; the loop adds "missed" (a late answer)
MISSED = "missed"
LONGEST_PULSE = 1.0                     # s: a pulse longer than this is refused as absurd


class ControllerError(ValueError):
    """A controller answered something the protocol does not allow (the run stops; the message says what)."""


@dataclass(frozen=True)
class DeviceFacts:
    """The calibrated facts of the device that a controller may use (``vcyto calibrate`` measures them).

    ``sort_delay``: time from leaving the detection window to the SAW window's centre of a cell moving at
    ``reference_velocity``; ``lead`` and ``pulse``: the calibrated pulse (start before the predicted arrival,
    length); ``envelope``: arrival offsets (low, high; s, relative to a sorted cell) at which another cell is
    deflected too; ``timing_error``: the uncertainty of one predicted arrival; ``control_period``: how often the
    drive can change; ``detection_window``: (start, end) along the channel (m)."""

    sort_delay: float
    reference_velocity: float
    lead: float
    pulse: float
    envelope: tuple[float, float]
    timing_error: float
    control_period: float
    detection_window: tuple[float, float]

    def arrival(self, event: DetectorEvent) -> float:
        """The predicted arrival of ``event``'s cell at the SAW window's centre (s)."""
        return event.time + self.sort_delay * self.reference_velocity / max(event.velocity, 1e-9)

    def deadline(self, event: DetectorEvent) -> float:
        """The latest device time at which ``event``'s pulse could still start: its answer is due by then."""
        return self.arrival(event) - self.lead

    def as_dict(self) -> dict:
        return {"sort_delay": self.sort_delay, "reference_velocity": self.reference_velocity, "lead": self.lead,
                "pulse": self.pulse, "envelope": list(self.envelope), "timing_error": self.timing_error,
                "control_period": self.control_period, "detection_window": list(self.detection_window)}

    @classmethod
    def from_settings(cls, settings, control_period: float, detection_window) -> DeviceFacts:
        """The facts of a calibration (``controller.sorter.ControllerSettings``) on a plant and detector."""
        return cls(settings.delay, settings.reference_velocity, settings.lead, settings.pulse,
                   tuple(settings.envelope), settings.timing_error, control_period, tuple(detection_window))


@runtime_checkable
class Controller(Protocol):
    """What every controller offers the loop: an answer to each detector event."""

    def on_event(self, event: DetectorEvent, clock: float) -> Sequence[Decision]: ...


@runtime_checkable
class Starts(Protocol):
    """Takes the device facts before the first event."""

    def start(self, facts: DeviceFacts) -> None: ...


@runtime_checkable
class Drives(Protocol):
    """Sets the IDT drive (in [0, 1]) for the control period that starts at ``clock``."""

    def drive(self, clock: float) -> float: ...


def check_answer(answer, known: set[int] | dict, event_id: int) -> list[Decision]:
    """The decisions of one answer to event ``event_id``, checked (``ControllerError`` names what is wrong):
    a sequence of ``Decision`` about known events, actions from ``ACTIONS``, a sort with a finite pulse that ends
    after it starts and lasts at most ``LONGEST_PULSE``, and a decision about ``event_id`` itself at most once."""
    if answer is None:
        return []
    if isinstance(answer, Decision):
        answer = (answer,)
    try:
        decisions = list(answer)
    except TypeError:
        raise ControllerError(f"on_event must return a sequence of Decision (got {type(answer).__name__})") from None
    own = 0
    for decision in decisions:
        if not isinstance(decision, Decision):
            raise ControllerError(f"on_event must return Decision objects (got {type(decision).__name__})")
        if decision.event_id not in known and decision.event_id != event_id:
            raise ControllerError(f"a decision about event {decision.event_id!r}, which the controller was never told")
        if decision.action not in ACTIONS:
            raise ControllerError(f"decision action must be one of {', '.join(ACTIONS)} (got {decision.action!r} "
                                  f"for event {decision.event_id})")
        if decision.action == "sort":
            on, off = decision.pulse_on, decision.pulse_off
            if not (isinstance(on, (int, float)) and isinstance(off, (int, float))
                    and math.isfinite(on) and math.isfinite(off) and on < off <= on + LONGEST_PULSE):
                raise ControllerError(f"the sort of event {decision.event_id} needs a pulse with finite "
                                      f"pulse_on < pulse_off, at most {LONGEST_PULSE:g} s long "
                                      f"(got {on!r}, {off!r})")
        own += decision.event_id == event_id
    if own > 1:
        raise ControllerError(f"the answer to event {event_id} decides it {own} times (at most once)")
    return decisions


class DecisionLog:
    """Decisions by event, the latest of each, in event order (what a controller or the loop has decided).

    ``keep``: remember the decisions of about the latest ``keep`` events only (between ``keep`` and twice that;
    None: all), so that a long run's memory does not grow with its events."""

    def __init__(self, keep: int | None = None):
        self._decisions: dict[int, Decision] = {}
        self._keep = keep

    @property
    def decisions(self) -> list[Decision]:
        return list(self._decisions.values())

    def decision_for(self, event_id: int) -> Decision | None:
        return self._decisions.get(event_id)

    def record(self, decision: Decision) -> None:
        self._decisions[decision.event_id] = decision
        if self._keep is not None and len(self._decisions) > 2 * self._keep:
            newest = max(self._decisions)
            self._decisions = {e: d for e, d in self._decisions.items() if e > newest - self._keep}


class PulseSchedule:
    """The IDT drive the sorts ask for: on while any scheduled pulse is on (pulses may overlap).

    A pulse is scheduled when its sort is accepted, cancelled when an abort comes before it starts (the loop
    checks that), and forgotten once over."""

    def __init__(self):
        self._pulses: dict[int, tuple[float, float]] = {}

    def add(self, event_id: int, on: float, off: float) -> None:
        self._pulses[event_id] = (on, off)

    def cancel(self, event_id: int) -> None:
        self._pulses.pop(event_id, None)

    def next_change(self, time: float) -> float:
        """The earliest pulse start or end after ``time`` (inf if none): until then the drive keeps its value."""
        return min((edge for pulse in self._pulses.values() for edge in pulse if edge > time), default=math.inf)

    def actuation(self, time: float) -> float:
        """The drive at ``time``: 1 while any pulse is on, else 0 (pulses over by then are forgotten)."""
        for event_id in [key for key, (_, stop) in self._pulses.items() if stop <= time]:
            del self._pulses[event_id]
        return 1.0 if any(start <= time for start, _ in self._pulses.values()) else 0.0
