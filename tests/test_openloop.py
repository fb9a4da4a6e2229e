"""The one open-loop stepping helper (``sim.method.openloop``) the paper, extremes, stability and trade-off runs
share."""

from dataclasses import dataclass

from sim.method.openloop import stepping


@dataclass(frozen=True)
class Clock:
    time: float
    drives: tuple = ()
    cells: tuple = ()


def tick(state, actuation):
    return Clock(state.time + 1.0, state.drives + (actuation,))


def test_it_stops_at_the_time_limit_and_passes_the_drive_of_each_steps_start():
    states = list(stepping(tick, Clock(0.0), lambda t: 1.0 if 1 <= t < 3 else 0.0, until=4.0, running=lambda s: True))
    assert [s.time for s in states] == [1.0, 2.0, 3.0, 4.0]
    assert states[-1].drives == (0.0, 1.0, 1.0, 0.0)


def test_it_stops_after_max_steps_and_when_running_turns_false():
    assert len(list(stepping(tick, Clock(0.0), 0.5, running=lambda s: True, max_steps=3))) == 3
    states = list(stepping(tick, Clock(0.0), 0.5, running=lambda s: s.time < 2.0))
    assert [s.time for s in states] == [1.0, 2.0] and states[-1].drives == (0.5, 0.5)


def test_by_default_it_runs_while_a_cell_is_in_the_channel():
    @dataclass(frozen=True)
    class Cell:
        in_channel: bool

    def leave_at_two(state, actuation):
        return Clock(state.time + 1.0, cells=(Cell(state.time + 1.0 < 2.0),))
    states = list(stepping(leave_at_two, Clock(0.0, cells=(Cell(True),))))
    assert [s.time for s in states] == [1.0, 2.0]
    assert list(stepping(leave_at_two, Clock(0.0, cells=()))) == []          # nothing in the channel: no step
