"""Cell arrivals at the injection inlet: an explicit ordered list, or a count with a type mix and a rate.

``schedule`` returns the cells that enter the channel, (time, type name) pairs in arrival order;
``offer`` also returns the ones turned away. Processes (``Arrivals.process``):

- ``regular``: one cell every 1 / rate (the rate may not exceed 1 / min_spacing).
- ``poisson``: the sample's cells reach the inlet as a Poisson process of intensity ``rate``; a cell that comes
  less than ``min_spacing`` after the last admitted one is rejected and counted (a non-paralysable dead time, as
  a sorter's electronics reject coincident events): two membranes are never injected on top of each other.
  The admitted cells' gaps are then exactly min_spacing + Exp(rate) (memorylessness), their rate is
  rate / (1 + rate * min_spacing) and a cell is rejected with probability rate * min_spacing / (1 + rate *
  min_spacing) (``dead_time_acceptance``). Gaps are drawn, never clipped, so nothing piles up at the minimum.

Types are drawn from ``mix`` independently of the times (a thinned Poisson process per type).

The sample is drawn ``CHUNK`` offered cells at a time (``Offer``): once when it is made, keeping of each chunk only
the generator's state at its start, the time its gaps start from, the dead time carried into it and the running
counts (admitted and rejected, per type), and again whenever its cells are read, from that state, so that the
draws are the same. A sample therefore holds the cells of the last ``CHUNKS_KEPT`` chunks read and under a
kilobyte a chunk, not its cells: 2x10^7 cells offered (10^7 events at the inlet's usual dead time) are 306 chunks.
"""

from __future__ import annotations

import collections
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

PROCESSES = ("regular", "poisson")
MAX_COUNT = 100_000_000         # cells offered to one stream (drawn a chunk at a time: a few KB a chunk held)
CHUNK = 1 << 16                 # offered cells drawn at a time (``Offer``)
CHUNKS_KEPT = 4                 # drawn chunks kept for reading: those of the plant's window and the cells leaving


@dataclass(frozen=True)
class Arrivals:
    cells: tuple[str, ...] = ()            # explicit order; empty -> count / mix / rate
    count: int = 0                         # cells offered (poisson: admitted + rejected)
    mix: tuple[tuple[str, float], ...] = ()
    rate: float = 500.0                    # cells per second offered at the inlet
    process: str = "regular"
    min_spacing: float = 0.5e-3            # s, the inlet's dead time
    first: float = 0.0

    def __post_init__(self):
        if not self.cells and self.count <= 0:
            raise ValueError("arrivals need an explicit list of cells or a positive count")
        if self.count > MAX_COUNT or len(self.cells) > MAX_COUNT:
            raise ValueError(f"at most {MAX_COUNT:,} cells per stream (split longer samples into several runs)")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"arrival rate must be positive and finite, in cells/s (got {self.rate})")
        if self.process not in PROCESSES:
            raise ValueError(f"arrival process must be one of {', '.join(PROCESSES)} (got {self.process!r})")
        if not (math.isfinite(self.min_spacing) and self.min_spacing >= 0):
            raise ValueError(f"min_spacing must be a finite time >= 0 s (got {self.min_spacing})")
        if not (math.isfinite(self.first) and self.first >= 0):
            raise ValueError(f"the first arrival must be at a finite time >= 0 s (got {self.first})")
        if self.process == "regular" and self.rate * self.min_spacing > 1 + 1e-12:
            raise ValueError(f"regular arrivals at {self.rate:g} cells/s come closer than the minimum spacing "
                             f"{self.min_spacing * 1e3:g} ms: lower the rate to <= {1 / self.min_spacing:g} cells/s "
                             "or use poisson arrivals (coincident cells rejected and counted)")
        if not self.cells and (not self.mix or any(not (math.isfinite(w) and w >= 0) for _, w in self.mix)
                               or sum(weight for _, weight in self.mix) <= 0):
            raise ValueError("a count of cells needs a type mix with finite non-negative weights, "
                             "e.g. RBC:0.9,melanoma:0.1")


class Cells(Sequence):
    """Cells (time in s, type name) held as arrays (9 bytes a cell, not ~130 as a list of tuples): ``times``,
    ``kinds`` (indices into ``names``). Reads as a sequence of (time, name) pairs; a given list of cells, where a
    drawn sample is ``Drawn``."""

    __hash__ = None

    def __init__(self, times, kinds, names):
        self.times = np.asarray(times, dtype=float)
        self.kinds = np.asarray(kinds, dtype=np.uint8 if len(names) <= 256 else np.int64)
        self.names = tuple(str(name) for name in names)

    def __len__(self) -> int:
        return len(self.times)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return list(zip(self.times[index].tolist(), [self.names[k] for k in self.kinds[index].tolist()]))
        return float(self.times[index]), self.names[self.kinds[index]]

    def __iter__(self):
        for start in range(0, len(self), 65536):            # a chunk at a time: no list of every cell at once
            yield from self[start:start + 65536]

    def arrays(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """Cells ``start`` to ``stop`` (excluded) as (times, type indices)."""
        start = max(0, start)
        return self.times[start:stop], self.kinds[start:stop]

    def counts(self, time: float = math.inf) -> dict:
        """{type name: cells that came at or before ``time``} (types with none left out; the cells in time order)."""
        due = int(np.searchsorted(self.times, time, side="right"))
        counts = np.bincount(self.kinds[:due], minlength=len(self.names)).tolist()
        return {name: count for name, count in zip(self.names, counts) if count}

    def __eq__(self, other) -> bool:
        return isinstance(other, Sequence) and len(self) == len(other) and all(a == b for a, b in zip(self, other))

    def __add__(self, other) -> list:
        return list(self) + list(other)

    def __repr__(self) -> str:
        return f"Cells({len(self)} cells of {', '.join(self.names) or 'no type'})"


def dead_time_acceptance(rate: float, dead_time: float) -> float:
    """The fraction of a Poisson stream of intensity ``rate`` that a non-paralysable dead time admits."""
    return 1.0 / (1.0 + rate * dead_time)


class Offer:
    """The sample as it reached the inlet, drawn ``chunk`` offered cells at a time (the module's docstring):
    ``admitted`` (the cells that enter the channel) and ``rejected`` (those the dead time turned away), each a
    sequence of (time, name) pairs in time order that draws its cells again when they are read (``Drawn``);
    ``offered``: the sample's cells per type name.

    Held: per chunk, the generator's state at its start, the time its gaps start from, the dead time's end
    carried into it and the running counts; and the cells of the ``CHUNKS_KEPT`` chunks read last."""

    def __init__(self, arrivals: Arrivals, rng: np.random.Generator, chunk: int | None = None):
        self.arrivals, self.chunk = arrivals, int(chunk or CHUNK)
        self.names = _names(arrivals)
        self._index = {name: k for k, name in enumerate(self.names)} if arrivals.cells else None
        self._weights = None if arrivals.cells else _weights(arrivals)
        self._generator = type(rng.bit_generator)
        total = len(arrivals.cells) or arrivals.count
        chunks = -(-total // self.chunk)
        self._states: list = []                            # the generator's state as each chunk starts
        self._origin = np.empty(chunks)                    # the time each chunk's gaps start from
        self._free = np.empty(chunks)                      # when the dead time before each chunk ends
        self._first = np.empty(chunks)                     # each chunk's first offered time
        self._before = np.zeros((2, chunks + 1), dtype=np.int64)      # admitted, rejected before each chunk
        self._types = np.zeros((2, chunks + 1, len(self.names)), dtype=np.int64)  # the same per type
        self._drawn: collections.OrderedDict = collections.OrderedDict()          # chunk -> its cells
        self._lock = threading.Lock()                      # readers on several threads share the chunks drawn
        origin, free = arrivals.first, -math.inf
        for k in range(chunks):
            self._states.append(rng.bit_generator.state)
            self._origin[k], self._free[k] = origin, free
            times, kinds, keep, free = self._draw(k, rng)
            self._first[k] = times[0]
            origin = float(times[-1])
            admitted = int(np.count_nonzero(keep))
            self._before[:, k + 1] = self._before[:, k] + (admitted, len(keep) - admitted)
            every, kept = (np.bincount(part, minlength=len(self.names)) for part in (kinds, kinds[keep]))
            self._types[:, k + 1] = self._types[:, k] + (kept, every - kept)
        self.offered = dict(zip(self.names, self._types[:, -1].sum(axis=0).tolist()))
        self.admitted, self.rejected = Drawn(self, 0), Drawn(self, 1)

    def _draw(self, k: int, rng: np.random.Generator):
        """Chunk ``k``'s offered cells from ``rng`` (at the chunk's state): times, type indices, which the dead time
        admits, and when the dead time after the chunk's last admitted cell ends."""
        arrivals = self.arrivals
        start, stop = k * self.chunk, min((k + 1) * self.chunk, len(arrivals.cells) or arrivals.count)
        dtype = np.uint8 if len(self.names) <= 256 else np.int64
        if arrivals.cells:
            kinds = np.array([self._index[name] for name in arrivals.cells[start:stop]], dtype=dtype)
        else:
            kinds = rng.choice(len(self.names), size=stop - start, p=self._weights).astype(dtype)
        if arrivals.process == "regular":
            times = arrivals.first + np.arange(start, stop) / arrivals.rate
            return times, kinds, np.ones(len(times), dtype=bool), -math.inf
        gaps = rng.exponential(1 / arrivals.rate, size=stop - start)
        if k == 0:
            gaps[0] = 0.0
        times = self._origin[k] + np.cumsum(gaps)
        keep, free = _admitted(times, arrivals.min_spacing, float(self._free[k]))
        return times, kinds, keep, free

    def cells(self, k: int) -> tuple:
        """Chunk ``k``'s cells: (times, type indices) admitted, (times, type indices) rejected; drawn again from the
        chunk's state unless among the chunks read last."""
        with self._lock:
            if k in self._drawn:
                self._drawn.move_to_end(k)
                return self._drawn[k]
            rng = np.random.Generator(self._generator(0))         # its state set next
            rng.bit_generator.state = self._states[k]
            times, kinds, keep, _ = self._draw(k, rng)
            self._drawn[k] = cells = ((times[keep], kinds[keep]), (times[~keep], kinds[~keep]))
            if len(self._drawn) > CHUNKS_KEPT:
                self._drawn.popitem(last=False)
            return cells

    def __getstate__(self) -> dict:                    # copied or pickled without its lock
        return {name: value for name, value in vars(self).items() if name != "_lock"}

    def __setstate__(self, state: dict):
        vars(self).update(state, _lock=threading.Lock())

    def __repr__(self) -> str:
        return f"Offer({len(self.admitted)} admitted, {len(self.rejected)} rejected, in chunks of {self.chunk})"


class Drawn(Sequence):
    """The admitted (``side`` 0) or the rejected (1) cells of an ``Offer``, read from its chunks: a sequence of
    (time, name) pairs in time order; ``arrays(start, stop)`` gives a stretch as arrays (times, indices into
    ``names``), ``counts(time)`` the cells per type up to a time."""

    __hash__ = None

    def __init__(self, offer: Offer, side: int):
        self.offer, self.side, self.names = offer, side, offer.names
        self._before = offer._before[side]

    def __len__(self) -> int:
        return int(self._before[-1])

    def arrays(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """Cells ``start`` to ``stop`` (excluded; clipped to the sample) as (times, type indices)."""
        start, stop = max(0, start), min(stop, len(self))
        if start >= stop:
            return np.zeros(0), np.zeros(0, dtype=np.uint8 if len(self.names) <= 256 else np.int64)
        first = int(np.searchsorted(self._before, start, side="right")) - 1
        last = int(np.searchsorted(self._before, stop - 1, side="right")) - 1
        parts = []
        for k in range(first, last + 1):
            times, kinds = self.offer.cells(k)[self.side]
            lo, hi = max(start, self._before[k]) - self._before[k], min(stop, self._before[k + 1]) - self._before[k]
            parts.append((times[lo:hi], kinds[lo:hi]))
        if len(parts) == 1:
            return parts[0][0].copy(), parts[0][1].copy()
        return np.concatenate([t for t, _ in parts]), np.concatenate([k for _, k in parts])

    def counts(self, time: float = math.inf) -> dict:
        """{type name: cells that came at or before ``time``} (types with none left out)."""
        offer = self.offer
        k = int(np.searchsorted(offer._first, time, side="right")) - 1
        if k < 0:
            return {}
        before = offer._types[self.side, k]
        times, kinds = offer.cells(k)[self.side]
        due = int(np.searchsorted(times, time, side="right"))
        counts = (before + np.bincount(kinds[:due], minlength=len(self.names))).tolist()
        return {name: count for name, count in zip(self.names, counts) if count}

    def __getitem__(self, index):
        if isinstance(index, slice):
            start, stop, step = index.indices(len(self))
            if step != 1:
                return [self[i] for i in range(start, stop, step)]
            times, kinds = self.arrays(start, stop)
            return list(zip(times.tolist(), [self.names[k] for k in kinds.tolist()]))
        index = int(index)
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError("cell index out of range")
        times, kinds = self.arrays(index, index + 1)
        return float(times[0]), self.names[int(kinds[0])]

    def __iter__(self):
        for start in range(0, len(self), 65536):            # a stretch at a time: no list of every cell at once
            yield from self[start:start + 65536]

    def __eq__(self, other) -> bool:
        return isinstance(other, Sequence) and len(self) == len(other) and all(a == b for a, b in zip(self, other))

    def __add__(self, other) -> list:
        return list(self) + list(other)

    def __repr__(self) -> str:
        return f"Drawn({len(self)} {('admitted', 'rejected')[self.side]} cells of {', '.join(self.names)})"


def offer(arrivals: Arrivals, rng: np.random.Generator, chunk: int | None = None) -> Offer:
    """Draw the sample's types and times and apply the inlet's dead time (a chunk at a time: ``Offer``)."""
    return Offer(arrivals, rng, chunk)


def schedule(arrivals: Arrivals, rng: np.random.Generator) -> Drawn:
    """The cells that enter the channel, in arrival order."""
    return offer(arrivals, rng).admitted


def _names(arrivals: Arrivals) -> tuple[str, ...]:
    if arrivals.cells:
        return tuple(dict.fromkeys(arrivals.cells))
    return tuple(name for name, _ in arrivals.mix)


def _weights(arrivals: Arrivals) -> np.ndarray:
    weights = np.array([weight for _, weight in arrivals.mix], dtype=float)
    return weights / weights.sum()


def _admitted(times: np.ndarray, dead_time: float, free: float = -math.inf) -> tuple[np.ndarray, float]:
    """Which of the sorted ``times`` a non-paralysable dead time after each admitted one lets through, the dead time
    of an earlier admitted cell ending at ``free``; and when the last one's ends."""
    keep = np.zeros(len(times), dtype=bool)
    for index, t in enumerate(times.tolist()):
        if t >= free:
            keep[index] = True
            free = t + dead_time
    return keep, free
