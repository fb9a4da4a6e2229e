"""Figures shared by the commands: the speed field as an image, the device's boundaries."""

from __future__ import annotations

import numpy as np

from sim.method.transfer import PointLocator
from sim.model.scenario import UM, Scenario

from . import painter
from .painter import pyplot, save_figure  # noqa: F401 - the figures' commands take them from here


def speed_image(locator: PointLocator, velocity: np.ndarray, scenario: Scenario, pixel: float = 1 * UM):
    """|v| sampled on a pixel grid (rows = y upward) and the image's extent in um."""
    channel = scenario.channel
    xs = np.arange(pixel / 2, channel.length, pixel)
    ys = np.arange(pixel / 2, channel.height, pixel)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    values = locator.interpolate(velocity, grid)
    speed = np.hypot(values[:, 0], values[:, 1]).reshape(len(ys), len(xs))
    return speed, (0, channel.length / UM, 0, channel.height / UM)


def show_speed(axis, locator, velocity, scenario):
    return painter.show_speed(axis, *speed_image(locator, velocity, scenario))


def device_lines(scenario: Scenario) -> list[tuple]:
    """Inlets (cyan), outlets (orange) and the SAW window (red) on the channel's outline, as (x, y, colour,
    width) in um."""
    channel = scenario.channel
    lines = [([0.0, 0.0], list(np.array(inlet.span) / UM), "tab:cyan", 4) for inlet in channel.inlets]
    lines += [([channel.length / UM] * 2, list(np.array(outlet.span) / UM), "tab:orange", 4)
              for outlet in channel.outlets]
    return lines + [(list(np.array(channel.saw_window.span) / UM), [0.0, 0.0], "tab:red", 4)]


def draw_device(axis, scenario: Scenario):
    """``device_lines`` drawn on ``axis``, at equal scales, with the axes' labels."""
    painter.draw_lines(axis, device_lines(scenario))
