"""Cell arrivals at the injection inlet: an explicit ordered list, or a count with a type mix and a rate.

``schedule`` returns (time, type name) pairs in arrival order. Regular arrivals are 1/rate apart;
Poisson arrivals have exponential gaps drawn from the given generator. Every gap is at least
``min_spacing`` (s) so that membranes never start overlapped: with Poisson arrivals this is a dead time,
as in a real flow cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PROCESSES = ("regular", "poisson")


@dataclass(frozen=True)
class Arrivals:
    cells: tuple[str, ...] = ()            # explicit order; empty -> count / mix / rate
    count: int = 0
    mix: tuple[tuple[str, float], ...] = ()
    rate: float = 500.0                    # cells per second
    process: str = "regular"
    min_spacing: float = 0.5e-3
    first: float = 0.0

    def __post_init__(self):
        if not self.cells and self.count <= 0:
            raise ValueError("arrivals need an explicit list of cells or a positive count")
        if self.rate <= 0:
            raise ValueError(f"arrival rate must be positive (got {self.rate} cells/s)")
        if self.process not in PROCESSES:
            raise ValueError(f"arrival process must be one of {', '.join(PROCESSES)} (got {self.process!r})")
        if self.min_spacing < 0:
            raise ValueError("min_spacing must be >= 0")
        if not self.cells and (not self.mix or any(weight < 0 for _, weight in self.mix)
                               or sum(weight for _, weight in self.mix) <= 0):
            raise ValueError("a count of cells needs a type mix with non-negative weights, e.g. RBC:0.9,melanoma:0.1")


def schedule(arrivals: Arrivals, rng: np.random.Generator) -> list[tuple[float, str]]:
    if arrivals.cells:
        names = list(arrivals.cells)
    else:
        types = [name for name, _ in arrivals.mix]
        weights = np.array([weight for _, weight in arrivals.mix], dtype=float)
        names = list(rng.choice(types, size=arrivals.count, p=weights / weights.sum()))
    if arrivals.process == "poisson":
        gaps = rng.exponential(1 / arrivals.rate, size=len(names))
    else:
        gaps = np.full(len(names), 1 / arrivals.rate)
    gaps = np.maximum(gaps, arrivals.min_spacing)
    gaps[0] = 0.0
    times = arrivals.first + np.cumsum(gaps)
    return [(float(t), str(name)) for t, name in zip(times, names)]
