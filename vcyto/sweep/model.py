"""The data of a sweep: its parameters, its points (each a scenario and stream settings with an id), the sweep
itself, and ``SweepError``, the one-line error of a bad spec or sweep option."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


class SweepError(ValueError):
    """A bad spec or sweep option; ``str(error)`` is one line naming what is wrong."""


@dataclass(frozen=True)
class Parameter:
    name: str
    values: tuple = ()                 # a list or a range
    distribution: tuple | None = None  # ("uniform" | "log_uniform" | "integers", low, high): random sampling only
    quantity: tuple | None = None      # (dimension, unit of a bare number) of a physical quantity, else None

    def draw(self, rng: np.random.Generator):
        if self.distribution is None:
            return self.values[int(rng.integers(len(self.values)))]
        kind, low, high = self.distribution
        if kind == "integers":
            return int(rng.integers(low, high + 1))
        if kind == "log_uniform":
            return rounded(math.exp(rng.uniform(math.log(low), math.log(high))))
        return rounded(rng.uniform(low, high))


@dataclass(frozen=True)
class Point:
    values: tuple                      # ((parameter name, value as given), ...)
    scenario: object                   # sim.model.scenario.Scenario
    settings: object                   # vcyto.stream.StreamSettings
    id: str                            # digest of the inputs and of the code (version, schema)
    inputs: str = ""                   # digest of the inputs alone (scenario TOML and settings)

    @property
    def label(self) -> str:
        return ", ".join(f"{name}={value}" for name, value in self.values)

    @property
    def plant_key(self):
        return (self.settings.model, self.settings.control_period, self.scenario)


@dataclass(frozen=True)
class Sweep:
    path: str
    parameters: tuple[Parameter, ...]
    metrics: tuple[str, ...]
    plot: str
    sampling: str
    points: tuple[Point, ...]

    @property
    def columns(self) -> list[str]:
        names = [parameter.name for parameter in self.parameters]
        metrics = [metric for metric in self.metrics if metric != "wall_time_s"]
        return ["point", "status", *names, *([] if "seed" in names else ["seed"]), *metrics, "wall_time_s", "error",
                "inputs", "vcyto"]


def rounded(value) -> float:
    """``value`` to 12 significant digits: 0.3, not 0.30000000000000004, in tables and hashes."""
    return float(f"{float(value):.12g}")


def float_or_nan(value) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return float("nan")
    return number if math.isfinite(number) else float("nan")


def one_line(error) -> str:
    return " ".join(str(error).split())
