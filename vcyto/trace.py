"""The recorded steps of an event-driven plant, as columns: what the loop hands its recordings per stretch.

An event-driven plant (``rom``) steps from one moment the loop must look to the next (a detector crossing, a pulse
edge), often many control periods. Recordings want the cells every record interval; instead of stopping the plant
that often and building a record each time, the plant traces its cells in the channel at those moments itself
(``sim.plants.contract.Traces``: period indices that are multiples of the cadence, vectorised in the plant's kernel) and
the loop hands the rows over with its next record (``StepRecord.trace``), one ``Trace`` per record: a batch of
recorded steps as arrays. The steps are those the loop would have shown had it stopped at each of them: the same
period indices, the same positions (``tests/test_trace.py``).

A ``Trace``'s rows are in step order, ``counts[k]`` rows for step k (a step with no cell in the channel has none);
cells are centroids (plants that trace have no membranes).
"""

from __future__ import annotations

from dataclasses import dataclass

from .classes import CLASS_IDS

TRACE_BATCH = 32               # record intervals a stretch may span before the loop shows it (the live view's lag)


@dataclass(frozen=True)
class Trace:
    """Recorded steps as columns (lists: a record holds a few steps, too few for arrays to pay): ``times`` (s),
    ``steps`` (control periods since the start), ``drive`` (the IDT drive from each step on, as the loop set it),
    ``counts`` (rows per step); per row ``keys`` and the centroid ``x``, ``y`` (m)."""

    times: list
    steps: list
    drive: list
    counts: list
    keys: list
    x: list
    y: list

    def __len__(self) -> int:
        return len(self.steps)

    def row_times(self) -> list:
        """Each row's step time."""
        return [time for time, count in zip(self.times, self.counts) for _ in range(count)]


class Tracer:
    """The loop's side of a plant's trace: ``take`` after every stretch the plant ran at one drive, ``due`` when a
    recorded step has passed since the last ``batch``, ``batch`` the steps since then as a ``Trace``."""

    def __init__(self, plant, interval: float):
        self.plant, self.period = plant, plant.control_period
        self.every = plant.trace(interval)
        self._last = 0                      # the last recorded step handed over (a multiple of ``every``)
        self._spans: list = []              # (the stretch's last period index, its drive)
        self._steps, self._keys, self._x, self._y = [], [], [], []

    def take(self, step: int, drive: float):
        """After a stretch that ended at period ``step`` at ``drive``: the plant's rows of that stretch."""
        steps, keys, positions = self.plant.take_trace()
        self._spans.append((step, drive))
        if len(steps):
            self._steps += steps.tolist()
            self._keys += keys.tolist()
            self._x += positions[:, 0].tolist()
            self._y += positions[:, 1].tolist()

    @property
    def due(self) -> bool:
        return bool(self._spans) and self._spans[-1][0] >= self._last + self.every

    def batch(self, drive_now: float, final=None) -> Trace:
        """The recorded steps since the last batch (maybe none); ``drive_now``: the drive the loop has set for the
        stretch it starts now; ``final`` (step, observation): the loop's last state, added as a step of its own
        when it is not one already."""
        every, first, spans = self.every, self._last + self.every, self._spans
        ticks = list(range(first, (spans[-1][0] if spans else self._last) + 1, every))
        drive, span = [], 0
        for tick in ticks:                  # the drive from each recorded step on, as the loop set it there
            while spans[span][0] < tick:
                span += 1
            ends_here = spans[span][0] == tick
            drive.append(spans[span][1] if not ends_here else spans[span + 1][1] if span + 1 < len(spans)
                         else drive_now)
        counts = [0] * len(ticks)
        for step in self._steps:
            counts[(step - first) // every] += 1
        keys, x, y = self._keys, self._x, self._y
        if final is not None and (not ticks or final[0] > ticks[-1]):
            step, observation = final
            ticks.append(step)
            drive.append(drive_now)
            counts.append(len(observation.cells))
            keys += [cell.key for cell in observation.cells]
            x += [cell.x for cell in observation.cells]
            y += [cell.y for cell in observation.cells]
        if ticks:
            self._last = (ticks[-1] // every) * every
        self._spans, self._steps, self._keys, self._x, self._y = self._spans[-1:], [], [], [], []
        period = self.period
        return Trace([tick * period for tick in ticks], ticks, drive, counts, keys, x, y)


def class_snapshot(trace: Trace, classes) -> dict:
    """The class id (``vcyto.classes.CLASS_IDS``) of each key in ``trace`` by ``classes`` (a
    ``vcyto.classes.CellClasses``) as it stands."""
    return {key: CLASS_IDS[classes.provisional(key)] for key in set(trace.keys)}


def row_classes(trace: Trace, now: float, before: dict, after: dict) -> list:
    """Each row's class id: ``after`` (the classes with the record's events and decisions) at the record's own time
    ``now``, ``before`` at the earlier steps, as a loop that stopped at each recorded step would have shown."""
    if before is after:
        return [after[key] for key in trace.keys]
    late = now - 1e-12
    return [after[key] if time >= late else before[key] for key, time in zip(trace.keys, trace.row_times())]


def extend_paths(paths: dict, trace: Trace, x_um, y_um) -> dict:
    """Append each traced row (um) to its cell's path in ``paths`` (key -> points); the latest point of each key."""
    latest = {}
    for key, x, y in zip(trace.keys, x_um, y_um):
        paths.setdefault(key, []).append((x, y))
        latest[key] = (x, y)
    return latest
