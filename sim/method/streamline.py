"""Streamlines of a steady flow: where a massless tracer from an inlet's centre leaves the channel.

Classical Runge-Kutta 4 with a step that moves the tracer at most ``fraction`` of a mesh cell, until it
crosses x = length (an outlet, or the outlet-side wall), leaves through another side, or stalls.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.scenario import Channel
from .transfer import PointLocator


@dataclass(frozen=True)
class Streamline:
    """A traced path (n, 2) with its fate: outlet name, 'wall' or 'lost', exit ordinate and time."""

    path: np.ndarray
    times: np.ndarray
    outlet: str
    exit_y: float
    transit_time: float


def outlet_at(channel: Channel, y: float) -> str:
    """The outlet whose span holds ordinate ``y`` on x = length, else 'wall'."""
    for outlet in channel.outlets:
        if outlet.span[0] <= y <= outlet.span[1]:
            return outlet.name
    return "wall"


def trace(locator: PointLocator, velocity: np.ndarray, channel: Channel, start, h: float,
          fraction: float = 0.2, max_time: float = 0.1, min_speed: float = 1e-9) -> Streamline:
    """Follow ``velocity`` (2, N) from ``start`` until the tracer leaves the channel or stalls."""
    def speed_at(point):
        return locator.interpolate(velocity, point[None, :])[0]

    point = np.asarray(start, dtype=float)
    path, times = [point.copy()], [0.0]
    time = 0.0
    while time < max_time:
        v1 = speed_at(point)
        speed = np.hypot(*v1)
        if not np.isfinite(speed) or speed < min_speed:
            break
        dt = fraction * h / speed
        v2 = speed_at(point + 0.5 * dt * v1)
        v3 = speed_at(point + 0.5 * dt * v2)
        v4 = speed_at(point + dt * v3)
        increment = dt / 6 * (v1 + 2 * v2 + 2 * v3 + v4)
        if not np.all(np.isfinite(increment)):
            increment = dt * v1          # the stages left the channel: finish with an Euler step
        new_point = point + increment
        time += dt
        if new_point[0] >= channel.length:
            weight = (channel.length - point[0]) / (new_point[0] - point[0])
            crossing = point + weight * (new_point - point)
            exit_time = time - dt + weight * dt
            path.append(crossing)
            times.append(exit_time)
            return Streamline(np.array(path), np.array(times), outlet_at(channel, crossing[1]), float(crossing[1]),
                              float(exit_time))
        point = new_point
        path.append(point.copy())
        times.append(time)
        if not (0 <= point[0] <= channel.length and 0 <= point[1] <= channel.height):
            return Streamline(np.array(path), np.array(times), "lost", float("nan"), float("nan"))
    return Streamline(np.array(path), np.array(times), "lost", float("nan"), float("nan"))
