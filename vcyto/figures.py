"""Figures shared by the commands: the speed field as an image, the device's boundaries."""

from __future__ import annotations

import numpy as np

from sim.scenario import UM, Scenario
from sim.transfer import PointLocator


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(figure, path, dpi: int = 120) -> None:
    """Write ``figure`` as a PNG at ``path`` all at once: drawn into a temporary file beside it, then moved in
    place (``os.replace``), so an interrupted or failed save never leaves a truncated image under the name."""
    from .outputs import write_whole
    write_whole(path, lambda temporary: figure.savefig(temporary, format="png", dpi=dpi))


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
    speed, extent = speed_image(locator, velocity, scenario)
    return axis.imshow(speed, origin="lower", extent=extent, cmap="viridis", interpolation="bilinear")


def draw_device(axis, scenario: Scenario):
    """Inlets (cyan), outlets (orange) and the SAW window (red) on the channel's outline."""
    channel = scenario.channel
    for inlet in channel.inlets:
        axis.plot([0, 0], np.array(inlet.span) / UM, color="tab:cyan", lw=4)
    for outlet in channel.outlets:
        axis.plot([channel.length / UM] * 2, np.array(outlet.span) / UM, color="tab:orange", lw=4)
    axis.plot(np.array(channel.saw_window.span) / UM, [0, 0], color="tab:red", lw=4)
    axis.set_aspect("equal")
    axis.set_xlabel("x (um)")
    axis.set_ylabel("y (um)")
