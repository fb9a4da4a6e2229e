"""The sorting controller: IDT pulses for type-II events, timed from the measured velocity, aborted by the envelope.

For each detector event the controller predicts when the cell reaches the SAW window,
    arrival = event time + delay * reference_velocity / measured velocity,
with ``delay`` the calibrated time from the end of the detection window to the centre of the SAW window of a
cell moving at ``reference_velocity`` (a sorter's "sort delay"). A sorted cell gets the pulse
[arrival - lead, arrival - lead + pulse]. The pulse deflects more than its target: ``envelope`` = (low, high)
is the range of arrival offsets (s, relative to the target's arrival; > 0: after it) at which a non-target
cell alone under the same pulse would be deflected too (measured by ``vcyto calibrate``). Each predicted
arrival is uncertain by ``timing_error`` (s), so two cells' offset by twice that.

Modes (what a sorter offers; ``MODES``):
- ``purity``: abort a sort whenever a type-I cell's predicted offset lies in the envelope widened by
  2 * timing_error; a sort is aborted only before its pulse starts (a type-I cell detected later is told so).
- ``enrichment``: abort only when a type-I cell's predicted offset lies in the envelope itself (no margin):
  more yield, a little less purity.
- ``yield``: sort every type-II cell; co-deflected type-I cells are accepted.
- ``single``: ``purity``, and also abort when another type-II cell falls in the widened envelope (both are
  aborted), so that every sorted pulse carries exactly one cell.
It implements the controller protocol (``controller.protocol``): each event is answered with its decision and
the aborts it causes; the loop turns the sorts into the IDT drive (on while any pulse is; pulses may overlap).
It never sees ground truth, so the same object could drive an instrument.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .events import TYPE_II, Decision, DetectorEvent
from .protocol import DecisionLog

MODES = ("purity", "enrichment", "yield", "single")
REORDER_SLACK = 1e-3           # s: predicted arrivals may come out of detection order by up to this
RECENT_DECISIONS = 1 << 12     # decisions of the latest events kept (coincidences reach a few events back)


@dataclass(frozen=True)
class ControllerSettings:
    """Calibrated on the paper's device with the ``paper`` SAW model (``vcyto calibrate``; docs/results.md "The
    sort envelope"): a melanoma reaches the SAW window's centre 0.553 ms after leaving the detection window at
    0.0997 m/s (rom, with the flow's measured transient modes). A 0.40 ms pulse started 0.30 ms before the
    arrival sorts it on ``rom`` (its shortest reliable pulse there is 0.32 ms) and on
    ``feib`` at 6.67 and 3.33 um (leads from 0.15 and 0.2 ms up). That pulse deflects an RBC arriving from
    0.196 ms before to 0.2025 ms after the target on ``rom``, and from 0.21 ms before on ``feib`` at 6.67 um,
    whose runs agree with rom's up to +0.16 ms and end lower from +0.28 ms (between them the stretched
    membrane folds against the divider: no outcome). The envelope is their union. The look-ahead, delay - lead
    = 0.253 ms, covers its widened trailing edge (0.2025 + 2 x 0.0216 = 0.246 ms): every type-I cell that
    could be co-deflected is detected before the pulse starts, so purity mode can abort for it."""

    delay: float = 0.5530e-3
    reference_velocity: float = 0.0997
    lead: float = 0.30e-3
    pulse: float = 0.40e-3
    mode: str = "purity"
    envelope: tuple[float, float] = (-0.21e-3, 0.2025e-3)
    timing_error: float = 0.0216e-3
    enabled: bool = True

    def __post_init__(self):
        object.__setattr__(self, "envelope", tuple(float(v) for v in self.envelope))
        if self.mode not in MODES:
            raise ValueError(f"controller mode must be one of {', '.join(MODES)} (got {self.mode!r})")
        for name in ("delay", "reference_velocity", "pulse"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"controller {name} must be a finite positive number (got {value!r})")
        for name in ("lead", "timing_error"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"controller {name} must be a finite number >= 0 (got {value!r})")
        if len(self.envelope) != 2 or not all(math.isfinite(v) for v in self.envelope) \
                or self.envelope[0] > self.envelope[1]:
            raise ValueError("controller envelope must be two finite offsets (low <= high) in s "
                             f"(got {self.envelope!r})")

    def window(self, margin: bool = True) -> tuple[float, float]:
        """The offsets (s) at which another cell counts as coincident with a sort: the envelope, widened by the
        timing error of both cells' predictions when ``margin``."""
        widen = 2 * self.timing_error if margin else 0.0
        return self.envelope[0] - widen, self.envelope[1] + widen


@dataclass
class _Pending:
    """A recent event that may still coincide with another: its class, predicted arrival and event id."""

    classification: str
    arrival: float
    event_id: int


class SortController(DecisionLog):
    """The built-in controller (``controller.protocol.Controller``): answers each event with its decision and the
    aborts it causes. It keeps its own log of what it decided (``DecisionLog``), to judge coincidences."""

    name = "built-in"

    def __init__(self, settings: ControllerSettings):
        super().__init__(keep=RECENT_DECISIONS)
        self.settings = settings
        self._recent: list = []        # _Pending entries still able to coincide
        self._answer: list = []        # the decisions of the event being answered

    def predicted_arrival(self, event: DetectorEvent) -> float:
        settings = self.settings
        return event.time + settings.delay * settings.reference_velocity / max(event.velocity, 1e-9)

    def on_event(self, event: DetectorEvent, clock: float | None = None) -> list[Decision]:
        """The decision about ``event`` and the aborts it causes (decided at the event's time)."""
        self._answer = []
        arrival = self.predicted_arrival(event)
        low, high = self.settings.window()
        reach = max(high, -low, 0.0)
        self._recent = [entry for entry in self._recent if entry.arrival >= arrival - reach - REORDER_SLACK]
        if not self.settings.enabled:
            self._decide(Decision(event.event_id, "pass", arrival, reason="controller disabled"))
        elif event.classification == TYPE_II:
            self._sort(event, arrival)
        else:
            self._pass(event, arrival)
        self._recent.append(_Pending(event.classification, arrival, event.event_id))
        return self._answer

    def _decide(self, decision: Decision):
        self.record(decision)
        self._answer.append(decision)

    def _coincident(self, offset: float, other_class: str) -> bool:
        """Whether a cell of ``other_class`` at ``offset`` (s, after the target) forbids the target's sort."""
        mode = self.settings.mode
        if mode == "yield" or (other_class == TYPE_II and mode != "single"):
            return False
        low, high = self.settings.window(margin=mode != "enrichment")
        return low <= offset <= high

    def _sort(self, event, arrival):
        for other in self._recent:
            if self._coincident(other.arrival - arrival, other.classification):
                self._decide(Decision(event.event_id, "abort", arrival,
                                      reason=f"{_describe(other, arrival)} inside the sort envelope"))
                if other.classification == TYPE_II:          # single-cell mode: the other one goes too
                    self._abort(other.event_id, event.time, f"type-II event {event.event_id} inside its envelope")
                return
        on = arrival - self.settings.lead
        off = on + self.settings.pulse
        if off <= event.time:                    # a lead longer than the delay and the pulse: nothing can be done
            self._decide(Decision(event.event_id, "abort", arrival, reason="too late: its pulse would be over "
                                                                           "before the decision (lead > delay)"))
            return
        late = f"pulse from the decision, {(event.time - on) * 1e3:.3f} ms late (lead > delay)" if on < event.time \
            else ""
        self._decide(Decision(event.event_id, "sort", arrival, on, off, reason=late))

    def _pass(self, event, arrival):
        reason = ""
        for other in self._recent:
            decision = self.decision_for(other.event_id)
            if decision.action == "sort" and self._coincident(arrival - other.arrival, event.classification):
                if not self._abort(other.event_id, event.time, f"type-I event {event.event_id} inside its envelope"):
                    reason = f"inside the envelope of event {other.event_id}'s pulse, which had started"
        self._decide(Decision(event.event_id, "pass", arrival, reason=reason))

    def _abort(self, event_id: int, now: float, reason: str) -> bool:
        """Abort the sort of ``event_id`` if its pulse has not started by ``now``; whether it was aborted."""
        decision = self.decision_for(event_id)
        if decision.action != "sort" or decision.pulse_on <= now:
            return decision.action == "abort"
        self._decide(Decision(event_id, "abort", decision.arrival, reason=reason))
        return True


def _describe(other: _Pending, arrival: float) -> str:
    offset = (other.arrival - arrival) * 1e3
    return f"type-{other.classification} event {other.event_id} ({offset:+.3f} ms)"
