"""The time schemes' arithmetic on a step history: a value one step back, and polynomial interpolation.

The second-order scheme (``bdf2``) needs v^{m-1} and X^{m-1} at t - dt, also after a change of step size
(``sim.method.adaptive``): an earlier value where its time is t - dt, else the parabola through the last three.
"""

from __future__ import annotations

import numpy as np


def value_back(time: float, value: np.ndarray, times, values, target: float) -> np.ndarray | None:
    """bdf2's history: the value at ``target`` (one step back) from the value at ``time`` and the earlier
    ``values`` at ``times`` (the latest first): an earlier value where its time is the target (equal steps, or
    one level up after two equal steps), else the parabola through the three (the line through two) there;
    None without history."""
    if not len(values):
        return None
    index = earlier_at(time, times, target)
    if index is not None:
        return values[index]
    return lagrange([time, *times], [value, *values], target)


def earlier_at(time: float, times, target: float) -> int | None:
    """The index in ``times`` (earlier than ``time``, the latest first) of the one that is ``target``, else None."""
    for index, known in enumerate(times):
        if abs(known - target) <= 1e-9 * abs(time - target):
            return index
    return None


def lagrange_weights(nodes, target: float) -> list[float]:
    """The weights of the values at ``nodes`` in the polynomial through them, evaluated at ``target``."""
    weights = []
    for i, node in enumerate(nodes):
        weight = 1.0
        for j, other in enumerate(nodes):
            if j != i:
                weight *= (target - other) / (node - other)
        weights.append(weight)
    return weights


def lagrange(nodes, values, target: float):
    """The polynomial through ``values`` at ``nodes`` (numbers or arrays), evaluated at ``target``."""
    result = 0.0
    for weight, point in zip(lagrange_weights(nodes, target), values):
        result = result + weight * point
    return result
