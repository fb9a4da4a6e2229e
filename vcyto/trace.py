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

import numpy as np

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


class TracedRows:
    """The recorded steps of a run of records (each with a ``trace``) gathered as arrays, for the sinks to write at
    once rather than record by record: per step ``times`` (s), ``steps``, ``drive``, ``counts`` (rows), ``record``
    (the index of the record that carried it); per row ``keys``, ``x``, ``y`` (m); ``class_ids`` once
    ``classify`` has run."""

    def __init__(self, records):
        self.records = records
        times, steps, drive, counts, record_of, keys, x, y = [], [], [], [], [], [], [], []
        for index, record in enumerate(records):
            trace = record.trace
            times += trace.times
            steps += trace.steps
            drive += trace.drive
            counts += trace.counts
            record_of += [index] * len(trace)
            keys += trace.keys
            x += trace.x
            y += trace.y
        self.times, self.steps = np.array(times, dtype=float), np.array(steps, dtype=np.int64)
        self.drive, self.counts = np.array(drive, dtype=float), np.array(counts, dtype=np.int64)
        self.record, self.keys = np.array(record_of, dtype=np.int64), np.array(keys, dtype=np.int64)
        self.x, self.y = np.array(x, dtype=float), np.array(y, dtype=float)
        self.class_ids = None

    def __len__(self) -> int:
        return len(self.steps)

    def by_key(self, x, y) -> dict:
        """Each key's rows of ``x``, ``y`` (arrays per row, e.g. the positions in um) as an (n, 2) array, in step
        order."""
        if not len(self.keys):
            return {}
        order = np.argsort(self.keys, kind="stable")
        keys = self.keys[order]
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        points = np.column_stack([np.asarray(x)[order], np.asarray(y)[order]])
        return dict(zip(keys[starts].tolist(), np.split(points, starts[1:])))

    def classify(self, classes, each=None, before=None) -> np.ndarray:
        """Each row's class id, the cells' classes following ``classes`` (a ``vcyto.classes.CellClasses``) record by
        record: ``before(index, record)`` is called, the classes take the record's events and decisions, then
        ``each(index, record)`` is called (a sink's events, decisions and outcomes). A row at its record's own time
        has the classes as they stand after the record's events and decisions, an earlier row those before them, as
        a loop that stopped at every recorded step would have shown (``tests/test_trace.py``); the rows' classes are
        looked up at once, not row by row."""
        records, keys = self.records, self.keys
        unique, inverse = np.unique(keys, return_inverse=True)
        initial = np.array([CLASS_IDS[classes.provisional(key)] for key in unique.tolist()], dtype=np.int64)
        changes = []                      # (record index, key, class id) as the records' events and decisions come
        for index, record in enumerate(records):
            if before is not None:
                before(index, record)
            if record.events or record.decisions:
                changes += [(index, key, CLASS_IDS[classes.provisional(key)])
                            for key in classes.observe(record.events, record.decisions)]
            if each is not None:
                each(index, record)
        class_ids = initial[inverse] if len(keys) else np.zeros(0, dtype=np.int64)
        if changes and len(keys):
            # the latest change of each row's key at or before the record whose classes the row shows
            now = np.array([record.observation.time for record in records])
            row_record = np.repeat(self.record, self.counts)
            late = np.repeat(self.times, self.counts) >= now[row_record] - 1e-12
            shown = row_record - ~late                         # its own record's classes, or the one before's
            change = np.array(changes, dtype=np.int64)
            span = len(records) + 1
            change = change[np.argsort(change[:, 1] * span + change[:, 0], kind="stable")]
            at = np.searchsorted(change[:, 1] * span + change[:, 0], keys * span + shown, side="right") - 1
            hit = at >= 0
            hit[hit] = change[at[hit], 1] == keys[hit]
            class_ids = np.where(hit, change[np.maximum(at, 0), 2], class_ids)
        self.class_ids = class_ids
        return class_ids


def joined(pieces) -> np.ndarray:
    """A path kept in pieces (arrays of (x, y) rows, or (x, y) pairs) as one (n, 2) array."""
    if len(pieces) == 1 and isinstance(pieces[0], np.ndarray):
        return pieces[0]
    return np.vstack([np.asarray(piece, dtype=float).reshape(-1, 2) for piece in pieces])


def stretches(records):
    """``records`` split into their longest stretches of records with a trace and without: (traced, records)."""
    start = 0
    while start < len(records):
        traced = records[start].trace is not None
        end = start + 1
        while end < len(records) and (records[end].trace is not None) == traced:
            end += 1
        yield traced, records[start:end]
        start = end
