"""The sorting controller on hand-made events: pulse timing, the envelope and each sort mode's aborts."""

import pytest

from controller.events import TYPE_I, TYPE_II, DetectorEvent
from controller.protocol import Controller, PulseSchedule
from controller.sorter import ControllerSettings, SortController

SETTINGS = ControllerSettings(delay=0.5e-3, reference_velocity=0.1, lead=0.3e-3, pulse=0.4e-3,
                              envelope=(-0.2e-3, 0.1e-3), timing_error=0.02e-3)
# the widened window: -0.24 to +0.14 ms; predicted arrival = detection time + 0.5 ms at 0.1 m/s


def event(n, time, label, velocity=0.1):
    return DetectorEvent(n, time, 1.0 if label == TYPE_II else 0.0, 40.0, velocity, label, n)


def drive(controller, time):
    """The IDT drive the controller's kept sorts ask for at ``time`` (as the loop's pulse schedule makes it)."""
    schedule = PulseSchedule()
    for decision in controller.decisions:
        if decision.action == "sort":
            schedule.add(decision.event_id, decision.pulse_on, decision.pulse_off)
    return schedule.actuation(time)


def test_the_built_in_controller_implements_the_protocol_and_answers_with_what_it_decided():
    controller = SortController(SETTINGS)
    assert isinstance(controller, Controller)
    first = controller.on_event(event(0, 1e-3, TYPE_II), 1e-3)
    assert [(d.event_id, d.action) for d in first] == [(0, "sort")]
    second = controller.on_event(event(1, 1e-3 + 0.05e-3, TYPE_I), 1.05e-3)      # inside the envelope: aborts 0
    assert [(d.event_id, d.action) for d in second] == [(0, "abort"), (1, "pass")]


def run(mode, events):
    controller = SortController(ControllerSettings(**{**SETTINGS.__dict__, "mode": mode}))
    for item in events:
        controller.on_event(item)
    return controller, [controller.decision_for(item.event_id).action for item in events]


def test_the_pulse_starts_lead_before_the_arrival_predicted_from_the_measured_velocity():
    controller, actions = run("purity", [event(0, 1e-3, TYPE_II, velocity=0.05)])
    decision = controller.decision_for(0)
    assert actions == ["sort"]
    assert decision.arrival == pytest.approx(1e-3 + 0.5e-3 * 0.1 / 0.05)
    assert (decision.pulse_on, decision.pulse_off) == pytest.approx((decision.arrival - 0.3e-3,
                                                                     decision.arrival + 0.1e-3))
    assert drive(controller, decision.pulse_on + 1e-9) == 1.0 and drive(controller, decision.pulse_off) == 0.0


@pytest.mark.parametrize("offset, aborted", [(-0.25e-3, False), (-0.23e-3, True), (0.13e-3, True), (0.15e-3, False)])
def test_purity_aborts_exactly_when_a_type_i_cell_is_in_the_widened_envelope(offset, aborted):
    # the type-I cell detected first, before the target (negative offsets) or after it (positive)
    events = sorted([event(0, 1e-3, TYPE_II), event(1, 1e-3 + offset, TYPE_I)], key=lambda e: e.time)
    controller, _ = run("purity", events)
    assert (controller.decision_for(0).action == "abort") == aborted


def test_a_type_i_cell_detected_after_the_pulse_started_cannot_abort_it():
    controller = SortController(SETTINGS)
    controller.on_event(event(0, 1e-3, TYPE_II))                       # pulse on at 1.2 ms
    controller.on_event(event(1, 1.25e-3, TYPE_I))                     # offset +0.25 ms: outside anyway
    assert controller.decision_for(0).action == "sort"
    controller.on_event(event(2, 1.21e-3, TYPE_I, velocity=0.2))       # predicted at 1.46 ms: -0.04 ms, inside
    assert controller.decision_for(0).action == "sort"                 # too late: the pulse is on since 1.2 ms
    assert "had started" in controller.decision_for(2).reason


def test_modes_differ_as_documented():
    near_margin = [event(0, 1e-3, TYPE_II), event(1, 1e-3 + 0.12e-3, TYPE_I)]   # inside the margin only
    inside = [event(0, 1e-3, TYPE_II), event(1, 1e-3 + 0.05e-3, TYPE_I)]        # inside the envelope itself
    two_targets = [event(0, 1e-3, TYPE_II), event(1, 1e-3 + 0.05e-3, TYPE_II)]
    assert run("purity", near_margin)[1][0] == "abort" and run("enrichment", near_margin)[1][0] == "sort"
    assert run("enrichment", inside)[1][0] == "abort" and run("yield", inside)[1][0] == "sort"
    assert run("purity", two_targets)[1] == ["sort", "sort"]
    assert run("single", two_targets)[1] == ["abort", "abort"]


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="envelope"):
        ControllerSettings(envelope=(0.1e-3, -0.1e-3))
    with pytest.raises(ValueError, match="finite positive"):
        ControllerSettings(pulse=float("inf"))
    with pytest.raises(ValueError, match="mode must be one of"):
        ControllerSettings(mode="greedy")


@pytest.mark.parametrize("lead, action, late", [(0.45e-3, "sort", ""), (0.6e-3, "sort", "0.100 ms late"),
                                                (0.95e-3, "abort", "too late")])
def test_a_lead_longer_than_the_delay_starts_the_pulse_late_or_aborts_it(lead, action, late):
    """No pulse can start before its cell is detected: a lead beyond the delay (0.5 ms) starts it at the decision,
    and beyond the delay plus the pulse (0.9 ms) the sort is aborted as too late, never a phantom sort."""
    controller = SortController(ControllerSettings(**{**SETTINGS.__dict__, "lead": lead}))
    controller.on_event(event(0, 1e-3, TYPE_II))
    decision = controller.decision_for(0)
    assert decision.action == action and late in decision.reason and bool(late) == bool(decision.reason)
    if action == "sort":
        assert drive(controller, 1e-3 + 1e-9) == (1.0 if late else 0.0)      # on from the decision when late
