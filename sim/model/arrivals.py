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
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

PROCESSES = ("regular", "poisson")
MAX_COUNT = 10_000_000          # ~1 GB of schedule and summary; beyond it a run is a sweep, not one stream


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
    """Cells (time in s, type name) in time order, kept as arrays (9 bytes a cell, not ~130 as a list of tuples):
    ``times``, ``kinds`` (indices into ``names``). Reads as a sequence of (time, name) pairs."""

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

    def __eq__(self, other) -> bool:
        return isinstance(other, Sequence) and len(self) == len(other) and all(a == b for a, b in zip(self, other))

    def __add__(self, other) -> list:
        return list(self) + list(other)

    def __repr__(self) -> str:
        return f"Cells({len(self)} cells of {', '.join(self.names) or 'no type'})"


@dataclass(frozen=True)
class Offer:
    """The sample as it reached the inlet: the admitted cells (time, type) and the rejected ones (``Cells``)."""

    admitted: Cells
    rejected: Cells


def dead_time_acceptance(rate: float, dead_time: float) -> float:
    """The fraction of a Poisson stream of intensity ``rate`` that a non-paralysable dead time admits."""
    return 1.0 / (1.0 + rate * dead_time)


def offer(arrivals: Arrivals, rng: np.random.Generator) -> Offer:
    """Draw the sample's types and times and apply the inlet's dead time."""
    kinds, names = _kinds(arrivals, rng)
    if arrivals.process == "regular":
        times = arrivals.first + np.arange(len(kinds)) / arrivals.rate
        return Offer(Cells(times, kinds, names), Cells((), (), names))
    gaps = rng.exponential(1 / arrivals.rate, size=len(kinds))
    gaps[0] = 0.0
    times = arrivals.first + np.cumsum(gaps)
    del gaps
    keep = _admitted(times, arrivals.min_spacing)
    return Offer(Cells(times[keep], kinds[keep], names), Cells(times[~keep], kinds[~keep], names))


def schedule(arrivals: Arrivals, rng: np.random.Generator) -> Cells:
    """The cells that enter the channel, in arrival order."""
    return offer(arrivals, rng).admitted


def _kinds(arrivals: Arrivals, rng: np.random.Generator) -> tuple[np.ndarray, tuple[str, ...]]:
    """The sample's types as indices into the names: the explicit list's, or drawn from the mix (the same draws
    as drawing the names themselves: ``Generator.choice`` picks indices either way)."""
    if arrivals.cells:
        names = tuple(dict.fromkeys(arrivals.cells))
        index = {name: k for k, name in enumerate(names)}
        return np.array([index[name] for name in arrivals.cells], dtype=np.int64), names
    names = tuple(name for name, _ in arrivals.mix)
    weights = np.array([weight for _, weight in arrivals.mix], dtype=float)
    return rng.choice(len(names), size=arrivals.count, p=weights / weights.sum()), names


def _admitted(times: np.ndarray, dead_time: float, chunk: int = 65536) -> np.ndarray:
    """Which of the sorted ``times`` a non-paralysable dead time after each admitted one lets through."""
    keep = np.zeros(len(times), dtype=bool)
    free = -math.inf
    for start in range(0, len(times), chunk):               # a chunk at a time: no list of every time at once
        for index, t in enumerate(times[start:start + chunk].tolist(), start):
            if t >= free:
                keep[index] = True
                free = t + dead_time
    return keep
