"""The loop's end of the controller protocol (``controller.protocol``): ports, timing, and the decision ledger.

A **port** carries events to a controller and its answers back: ``InProcess`` calls a Python object;
``vcyto.wire`` talks to a controller in another process. Every port offers ``start(facts)``, ``post(event,
clock)``, ``replies(wait)`` (the answers that have come: ``Reply``), ``drive(clock)`` (None unless the controller
sets the drive itself) and ``close()``.

``Control`` is what the loop holds: it posts each event, waits for the answer (lock-step) or paces device time
to the wall clock and judges each answer against its deadline (``Timing.realtime``), keeps the ledger of
decisions and turns sorts into the IDT drive (``PulseSchedule``).

Lock-step (the default): the loop waits for each answer, which takes no device time: it is in place at the
event's own time. Results depend only on the seed. Paced real time: device time follows the wall clock
(``factor`` device seconds per wall second); an answer's device time is its event's time plus the measured
latency (wall, times ``factor``); an answer later than its event's deadline is a missed decision.
"""

from __future__ import annotations

import bisect
import math
import time
from collections import deque
from dataclasses import dataclass

from controller.events import Decision, DetectorEvent
from controller.protocol import (
    MISSED,
    ControllerError,
    DecisionLog,
    DeviceFacts,
    Drives,
    PulseSchedule,
    Starts,
    check_answer,
)

LATENCY_SAMPLES = 100_000          # the latest latencies kept (bounded memory over long runs)
LAG_SAMPLES = 100_000
SPIN = 0.3e-3                      # s: the end of a pace is waited for in a loop, not a sleep (which overshoots
                                   # by 0.1-2 ms on a shared host: the plant would lag the wall clock by that)
KNOWN_EVENTS = 1 << 12             # the latest events (and their decisions) a controller's answer may refer to


@dataclass(frozen=True)
class Timing:
    """How device time relates to the wall clock: lock-step (``realtime`` False) or paced at ``factor``."""

    realtime: bool = False
    factor: float = 1.0            # device seconds per wall second when paced

    def __post_init__(self):
        if not (math.isfinite(self.factor) and 1e-6 <= self.factor <= 1e6):
            raise ValueError(f"the real-time factor must be a number in [1e-6, 1e6] (got {self.factor!r})")

    def describe(self) -> str:
        return f"paced real time x{self.factor:g}" if self.realtime else "lock-step"


@dataclass(frozen=True)
class Reply:
    """A controller's answer to event ``event_id``, ``latency`` wall seconds after the event was posted."""

    event_id: int
    decisions: tuple
    latency: float


class InProcess:
    """A port to a Python object implementing ``controller.protocol.Controller``: each event is answered by a
    call, timed."""

    def __init__(self, controller):
        if not callable(getattr(controller, "on_event", None)):
            raise ControllerError(f"{type(controller).__name__} has no on_event(event, clock) method: "
                                  "see controller.protocol.Controller")
        self.controller = controller
        self.name = describe(controller)
        self._replies: list[Reply] = []

    def start(self, facts: DeviceFacts) -> None:
        if isinstance(self.controller, Starts):
            self.controller.start(facts)

    def post(self, event: DetectorEvent, clock: float) -> None:
        started = time.perf_counter()
        try:
            answer = self.controller.on_event(event, clock)
        except Exception as error:         # the user's code: the run stops and says where
            text = " ".join(str(error).split())[:300]
            raise ControllerError(f"{self.name}: on_event raised {type(error).__name__}: {text}") from error
        self._replies.append(Reply(event.event_id, answer, time.perf_counter() - started))

    def replies(self, wait: float = 0.0) -> list[Reply]:
        replies, self._replies = self._replies, []
        return replies

    def drive(self, clock: float) -> float | None:
        if not isinstance(self.controller, Drives):
            return None
        try:
            return self.controller.drive(clock)
        except Exception as error:
            text = " ".join(str(error).split())[:300]
            raise ControllerError(f"{self.name}: drive raised {type(error).__name__}: {text}") from error

    def close(self) -> None:
        close = getattr(self.controller, "close", None)
        if callable(close):
            close()


def describe(obj) -> str:
    """A name for a user's controller or plant in summaries: its ``name`` attribute, else module.class."""
    name = getattr(obj, "name", None)
    if isinstance(name, str) and name:
        return name
    kind = type(obj)
    return f"{kind.__module__}.{kind.__qualname__}"


class Ledger(DecisionLog):
    """The decisions of a run as they stand, the controller's latencies and the missed decisions."""

    def __init__(self, facts: DeviceFacts):
        super().__init__(keep=KNOWN_EVENTS)
        self.facts = facts
        self.latencies: deque = deque(maxlen=LATENCY_SAMPLES)
        self.missed = self.refused_aborts = 0
        self._changes: list[Decision] = []         # decisions made or revised since take_changes()

    def predicted_arrival(self, event: DetectorEvent) -> float:
        """The controller's predicted arrival where it gave one, else the device facts'."""
        decision = self.decision_for(event.event_id)
        if decision is not None and math.isfinite(decision.arrival):
            return decision.arrival
        return self.facts.arrival(event)

    def record(self, decision: Decision) -> None:
        super().record(decision)
        self._changes.append(decision)

    def take_changes(self) -> list[Decision]:
        """Decisions made or revised (a sort turned into an abort, a late answer) since the last call."""
        changes, self._changes = self._changes, []
        return changes


class Control:
    """The controller as the loop sees it: events in, the IDT drive out, every decision in the ledger."""

    def __init__(self, port, facts: DeviceFacts, timing: Timing = Timing()):
        self.port, self.facts, self.timing = port, facts, timing
        self.ledger = Ledger(facts)
        self.schedule = PulseSchedule()
        self.outstanding: dict[int, tuple[DetectorEvent, float]] = {}     # event_id -> (event, wall when posted)
        self.events: dict[int, DetectorEvent] = {}
        self.lags: deque = deque(maxlen=LAG_SAMPLES)                      # s the plant was behind the wall clock
        self.max_lag = 0.0
        self._wall0 = None
        self._driven = None
        port.start(facts)

    # --- device time and the wall clock
    def pace(self, device_time: float) -> None:
        """Paced real time: wait until the wall clock reaches ``device_time``; record how late the plant was."""
        if not self.timing.realtime:
            return
        now = time.perf_counter()
        if self._wall0 is None:
            self._wall0 = now - device_time / self.timing.factor
        target = self._wall0 + device_time / self.timing.factor
        lag = max(0.0, now - target)
        self.lags.append(lag)
        self.max_lag = max(self.max_lag, lag)
        if target - now > SPIN:
            time.sleep(target - now - SPIN)
        while time.perf_counter() < target:       # the last SPIN s in a loop: a sleep can overshoot by more
            pass

    def next_deadline(self) -> float:
        """The earliest deadline of an event still unanswered (inf if none): the loop steps no further before
        knowing whether its answer came in time."""
        return min((self.facts.deadline(event) for event, _ in self.outstanding.values()), default=math.inf)

    def next_change(self, clock: float) -> float:
        if self.driven:
            return clock + self.facts.control_period
        return min(self.schedule.next_change(clock), self.next_deadline())

    @property
    def driven(self) -> bool:
        """Whether the controller sets the drive itself each control period (``controller.protocol.Drives``)."""
        if self._driven is None:
            self._driven = getattr(self.port, "drives", None) or isinstance(getattr(self.port, "controller", None),
                                                                             Drives)
        return bool(self._driven)

    # --- events and answers
    def deliver(self, events, clock: float) -> None:
        """Tell the controller of ``events`` (detected by ``clock``); lock-step: take every answer before going on."""
        self.post(events)
        self.collect()

    def post(self, events) -> None:
        """Tell the controller of ``events`` without waiting for its answers (``collect`` takes them in lock-step).

        The controller sees the events in order and answers each in turn whether or not the loop waits between
        them: the loop's state (schedule, ledger) is not part of what it is told. So a loop may post, do work that
        does not depend on the answers (looking at the plant for its sinks), then collect, with the same results as
        taking each answer at once; over the wire that work overlaps the controller's."""
        for event in events:
            self.events[event.event_id] = event
            if len(self.events) > 2 * KNOWN_EVENTS:         # bounded memory: the latest events
                self.events = {e: v for e, v in self.events.items()
                               if e > event.event_id - KNOWN_EVENTS or e in self.outstanding}
            self.outstanding[event.event_id] = (event, time.perf_counter())
            self.port.post(event, event.time)

    def collect(self) -> None:
        """Lock-step: wait for the answer to every event posted (paced real time: ``settle`` judges them)."""
        if self.timing.realtime:
            return
        while self.outstanding:
            for reply in self.port.replies(wait=math.inf):
                self._apply(reply)

    def settle(self, now: float) -> None:
        """Paced real time, at device time ``now``: apply the answers that came; an event whose deadline has
        passed with no answer is missed (its answer's budget is waited for to the end first)."""
        if not self.timing.realtime:
            return
        for reply in self.port.replies(wait=0.0):
            self._apply(reply)
        for event_id, (event, posted) in sorted(self.outstanding.items()):
            deadline = self.facts.deadline(event)
            if deadline > now:
                continue
            budget = max(deadline - event.time, 0.0) / self.timing.factor
            while event_id in self.outstanding:
                remaining = posted + budget - time.perf_counter()
                if remaining <= 0:
                    self._miss(event, deadline)
                    break
                for reply in self.port.replies(wait=remaining):
                    self._apply(reply)

    def _apply(self, reply: Reply) -> None:
        pending = self.outstanding.pop(reply.event_id, None)
        if pending is None:
            if reply.event_id in self.events:     # the late answer of a missed decision: its latency counts
                self.ledger.latencies.append(reply.latency)
                return
            raise ControllerError(f"an answer to event {reply.event_id!r}, which the controller was never told")
        event, _ = pending
        self.ledger.latencies.append(reply.latency)
        decisions = check_answer(reply.decisions, self.events, event.event_id)
        answered = event.time + (reply.latency * self.timing.factor if self.timing.realtime else 0.0)
        if self.timing.realtime and answered > self.facts.deadline(event):     # lock-step answers are never late
            self._miss(event, self.facts.deadline(event), reply.latency)
            decisions = [d for d in decisions if d.event_id != event.event_id]
        elif not any(d.event_id == event.event_id for d in decisions):
            raise ControllerError(f"the answer to event {event.event_id} has no decision about it "
                                  "(answer sort, pass or abort)")
        for decision in decisions:
            self._take(decision, answered)

    def _take(self, decision: Decision, answered: float) -> None:
        earlier = self.ledger.decision_for(decision.event_id)
        if earlier is not None and earlier.action == MISSED:     # a missed decision stays missed
            return
        if decision.action == "sort":
            if earlier is not None and earlier.action != "sort":
                raise ControllerError(f"event {decision.event_id} was decided {earlier.action!r}: a sort cannot "
                                      "follow it")
            self.schedule.add(decision.event_id, decision.pulse_on, decision.pulse_off)
        elif earlier is not None and earlier.action == "sort":
            if earlier.pulse_on <= answered:           # its pulse has started: too late to take it back
                self.ledger.refused_aborts += 1
                return
            self.schedule.cancel(decision.event_id)
        self.ledger.record(decision)

    def _miss(self, event: DetectorEvent, deadline: float, latency: float | None = None) -> None:
        self.outstanding.pop(event.event_id, None)
        self.ledger.missed += 1
        if latency is not None:
            told = f"answered {latency * 1e3:.3f} ms after the event"
        else:
            told = "no answer"
        budget = (deadline - event.time) * 1e3
        self.ledger.record(Decision(event.event_id, MISSED, self.facts.arrival(event),
                                    reason=f"missed decision: {told}, its deadline {budget:.3f} ms after it"))

    def actuation(self, clock: float) -> float:
        """The IDT drive from ``clock`` on: the controller's own drive, else the pulse schedule's."""
        if self.driven:
            level = self.port.drive(clock)
            if not (isinstance(level, (int, float)) and 0.0 <= level <= 1.0):
                raise ControllerError(f"drive({clock!r}) must return a number in [0, 1] (got {level!r})")
            return float(level)
        return self.schedule.actuation(clock)

    def finish(self) -> None:
        """At the end of a run: answers still outstanding are collected (lock-step has none)."""
        if self.timing.realtime:
            for reply in self.port.replies(wait=0.0):
                if reply.event_id in self.outstanding:
                    self._apply(reply)

    def report(self) -> dict:
        """The timing figures of the run: mode, deadline budget, missed decisions, latency and lag percentiles."""
        budget = self.facts.sort_delay - self.facts.lead
        report = {"timing": self.timing.describe(), "controller": getattr(self.port, "name", "?"),
                  "deadline_budget_ms": budget * 1e3, "missed_decisions": self.ledger.missed,
                  "refused_aborts": self.ledger.refused_aborts,
                  "latency_ms": _percentiles(self.ledger.latencies),
                  "latency_histogram": histogram(self.ledger.latencies)}
        if self.timing.realtime:
            report["lag_ms"] = {**_percentiles(self.lags), "max": self.max_lag * 1e3}
            report["factor"] = self.timing.factor
        return report


def timing_line(report: dict) -> str:
    """One line of ``Control.report()``: the timing mode, missed decisions against the budget, latency and lag."""
    latency = report.get("latency_ms") or {}
    said = (f"timing: {report['timing']}: {report['missed_decisions']} missed decisions (deadline "
            f"{report['deadline_budget_ms']:.3f} ms after detection at the reference velocity)")
    if latency:
        said += (f"; controller latency p50 {latency['p50'] * 1e3:.1f} us, p99 {latency['p99'] * 1e3:.1f} us, "
                 f"max {latency['max'] * 1e3:.1f} us")
    lag = report.get("lag_ms")
    if lag:
        said += f"; the plant behind the wall clock p99 {lag['p99']:.3f} ms, max {lag['max']:.3f} ms"
    return said


HISTOGRAM_EDGES_US = (0, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1_000, 2_000, 5_000, 10_000, 100_000, 1_000_000)


def histogram(samples) -> dict:
    """Latencies (s) counted between ``HISTOGRAM_EDGES_US`` (us; the last bin open above)."""
    counts = [0] * len(HISTOGRAM_EDGES_US)
    for sample in samples:
        counts[bisect.bisect_right(HISTOGRAM_EDGES_US, sample * 1e6) - 1] += 1
    return {"edges_us": list(HISTOGRAM_EDGES_US), "counts": counts}


def _percentiles(samples) -> dict:
    if not samples:
        return {}
    ordered = sorted(samples)

    def at(q):
        return ordered[min(len(ordered) - 1, int(math.ceil(q * len(ordered))) - 1)] * 1e3
    return {"p50": at(0.5), "p99": at(0.99), "max": ordered[-1] * 1e3, "count": len(ordered)}
