"""The progress lines of a run: detections and exits in time order within a record (an event-driven plant's
record spans many periods), counted even when the per-cell lines are off."""

from types import SimpleNamespace

from vcyto.steps import ProgressSink, StepRecord


class Notes:
    def __init__(self):
        self.notes, self.updates = [], []

    def note(self, message):
        self.notes.append(message)

    def update(self, message):
        self.updates.append(message)


def record(events, cells, time=3e-3):
    observation = SimpleNamespace(time=time, cells=())
    return StepRecord(7, observation, SimpleNamespace(cells=tuple(cells)), 0.0, tuple(events), ())


def event(key, time):
    return SimpleNamespace(key=key, time=time, classification="II", fluorescence=1.2, event_id=key)


def cell(key, fate, exit_time):
    return SimpleNamespace(key=key, type="RBC", fate=fate, exit_time=exit_time)


def test_detections_and_exits_print_in_time_order():
    notes = Notes()
    sink = ProgressSink(notes, count=3)
    sink.on_step(record([event(2, 2.5e-3)], [cell(1, "lower", 2.0e-3), cell(0, "lower", 1.0e-3),
                                             cell(3, "in_channel", float("nan"))]))
    times = [float(line.split()[2]) for line in notes.notes]
    assert times == sorted(times) == [1.0, 2.0, 2.5]
    assert "cell 0 (RBC) left by: lower" in notes.notes[0] and "cell 2: detected" in notes.notes[2]
    assert "2 left, 1 detected" in notes.updates[-1]


def test_a_large_sample_counts_without_per_cell_lines():
    notes = Notes()
    sink = ProgressSink(notes, count=10_000)
    sink.on_step(record([event(5, 1e-3)], [cell(4, "upper", 0.5e-3)]))
    assert notes.notes == [] and "1 left, 1 detected" in notes.updates[-1]


def test_a_bar_reads_no_plant_state_and_the_per_cell_lines_do():
    """A long run's bar takes the events, the cells that left and the time: the loop need not look at the plant for
    it (``needs_state`` false) and reads a record's time from a ``Moment``; the per-cell lines' status counts the
    cells in the channel (true)."""
    from vcyto.steps import Moment, needs_state

    class Bar(Notes):
        def run(self, total):
            self.total = total

        def advance(self, left, events, simulated_s):
            self.updates.append((left, events, simulated_s))

    bar, lines = ProgressSink(Bar(), count=10_000), ProgressSink(Notes(), count=3)
    assert not needs_state(bar) and needs_state(lines)
    bar.on_step(StepRecord(7, Moment(3e-3), SimpleNamespace(cells=(cell(4, "upper", 0.5e-3),)), 0.0,
                           (event(5, 1e-3),), ()))
    assert bar.progress.updates == [(1, 1, 3e-3)]
