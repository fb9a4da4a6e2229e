"""The sorting controller: IDT pulses for type-II events, timed from the measured velocity.

For each detector event the controller predicts when the cell reaches the SAW window,
    arrival = event time + delay * reference_velocity / measured velocity,
with ``delay`` the calibrated time from the detection window to the SAW window of a cell moving at
``reference_velocity`` (the "sort delay" of a cytometer, measured with a calibration cell: on the paper's
device with the default detection window (30, 60) um, a melanoma leaves the window at 0.91 ms at 0.094 m/s
and its centroid reaches x = 150 um 0.56 ms later, with the FE-IB and the streamline plants alike). A type-II cell
gets a pulse [arrival - lead, arrival - lead + pulse]. Modes: ``yield`` sorts every type-II cell;
``purity`` aborts a sort when a type-I cell is predicted within ``coincidence_window`` / 2 of it (the type-I
cell would be deflected too) and counts the abort. Several pending pulses may overlap: the IDT is on
while any is. The controller is fed events and asked for the actuation at each control period; it never
sees ground truth, so the same object could drive an instrument.
"""

from __future__ import annotations

import time as clock
from dataclasses import dataclass, field

from .events import TYPE_II, Decision, DetectorEvent

MODES = ("purity", "yield")


@dataclass(frozen=True)
class ControllerSettings:
    delay: float = 0.56e-3
    reference_velocity: float = 0.095
    lead: float = 0.5e-3
    pulse: float = 1.2e-3
    mode: str = "purity"
    coincidence_window: float = 1.2e-3
    enabled: bool = True

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"controller mode must be one of {', '.join(MODES)} (got {self.mode!r})")
        for name in ("delay", "reference_velocity", "pulse"):
            if not getattr(self, name) > 0:
                raise ValueError(f"controller {name} must be positive (got {getattr(self, name)!r})")
        if self.lead < 0 or self.coincidence_window < 0:
            raise ValueError("controller lead and coincidence_window must be >= 0")


@dataclass
class SortController:
    settings: ControllerSettings
    latencies: list = field(default_factory=list)
    _decisions: dict = field(default_factory=dict)    # event_id -> Decision, in event order
    _recent: list = field(default_factory=list)       # (classification, arrival, event_id) still able to coincide
    _pulses: dict = field(default_factory=dict)       # event_id -> (on, off), not yet over
    _changes: list = field(default_factory=list)      # decisions made or revised since take_changes()

    @property
    def decisions(self) -> list[Decision]:
        return list(self._decisions.values())

    def decision_for(self, event_id: int) -> Decision | None:
        return self._decisions.get(event_id)

    def on_event(self, event: DetectorEvent) -> None:
        started = clock.perf_counter()
        settings = self.settings
        arrival = event.time + settings.delay * settings.reference_velocity / max(event.velocity, 1e-9)
        horizon = event.time - settings.coincidence_window
        self._recent = [entry for entry in self._recent if entry[1] >= horizon]
        if not settings.enabled:
            self._decide(Decision(event.event_id, "pass", arrival, reason="controller disabled"))
        elif event.classification == TYPE_II:
            self._sort(event, arrival)
        else:
            self._pass(event, arrival)
        self._recent.append((event.classification, arrival, event.event_id))
        self.latencies.append(clock.perf_counter() - started)

    def _decide(self, decision: Decision):
        self._decisions[decision.event_id] = decision
        self._changes.append(decision)

    def take_changes(self) -> list[Decision]:
        """Decisions made or revised (a sort turned into an abort) since the last call."""
        changes, self._changes = self._changes, []
        return changes

    def _sort(self, event, arrival):
        settings = self.settings
        half = settings.coincidence_window / 2
        if settings.mode == "purity" and any(kind != TYPE_II and abs(other - arrival) < half
                                             for kind, other, _ in self._recent):
            self._decide(Decision(event.event_id, "abort", arrival, reason="type-I cell in coincidence"))
            return
        on = arrival - settings.lead
        self._pulses[event.event_id] = (on, on + settings.pulse)
        self._decide(Decision(event.event_id, "sort", arrival, on, on + settings.pulse))

    def _pass(self, event, arrival):
        self._decide(Decision(event.event_id, "pass", arrival))
        if self.settings.mode != "purity":
            return
        half = self.settings.coincidence_window / 2
        for kind, other, event_id in self._recent:       # a type-I cell next to a scheduled sort: abort it
            decision = self._decisions[event_id]
            if kind == TYPE_II and decision.action == "sort" and abs(other - arrival) < half:
                self._pulses.pop(event_id, None)
                self._decide(Decision(event_id, "abort", other, reason="type-I cell in coincidence"))

    def next_change(self, time: float) -> float:
        """The earliest pulse start or end after ``time`` (inf if none): until then, and until the next
        event, ``actuation`` keeps its value at ``time``. Lets a loop skip periods in which nothing happens."""
        return min((edge for pulse in self._pulses.values() for edge in pulse if edge > time), default=float("inf"))

    def actuation(self, time: float) -> float:
        """IDT drive at ``time``: 1 while any scheduled pulse is on, else 0."""
        started = clock.perf_counter()
        for event_id in [key for key, (_, stop) in self._pulses.items() if stop <= time]:
            del self._pulses[event_id]
        on = any(start <= time for start, _ in self._pulses.values())
        self.latencies.append(clock.perf_counter() - started)
        return 1.0 if on else 0.0
