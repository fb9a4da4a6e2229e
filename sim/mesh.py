"""The channel's triangulation: a tensor grid of squares, each cut into two right isosceles triangles.

Grid lines run through every inlet and outlet end so each boundary begins and ends at a vertex
(paper section 3.1: "a triangulation that aligns with the partition of Gamma"). Between these
breakpoints the spacing is the largest that does not exceed ``h``; for the paper's device and
h = 10/3 um this is the uniform 90 x 66 grid with 6,097 vertices and 54,243 Taylor-Hood DOFs.

Named boundaries (facet sets): one per inlet and outlet (by name), ``saw_window`` (lower-wall facets
whose midpoint lies in the window) and ``wall`` (the rest, SAW window included: it is a wall when
the IDT is off). The SAW data is interpolated on the lower wall, so the window need not be aligned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from skfem import MeshTri

from .scenario import Channel


def _graded(breakpoints, h):
    """Points through all ``breakpoints`` with spacing <= h, each gap split evenly."""
    points = [breakpoints[0]]
    for low, high in zip(breakpoints, breakpoints[1:]):
        count = max(1, math.ceil((high - low) / h - 1e-9))
        points.extend(np.linspace(low, high, count + 1)[1:])
    return np.array(points)


@dataclass(frozen=True)
class ChannelMesh:
    """A ``MeshTri`` of the channel with its grid lines and named boundaries."""

    mesh: MeshTri
    x: np.ndarray
    y: np.ndarray
    h: float

    @property
    def squares(self) -> tuple[int, int]:
        return len(self.x) - 1, len(self.y) - 1

    def boundary(self, name: str) -> np.ndarray:
        return self.mesh.boundaries[name]


def channel_mesh(channel: Channel, h: float) -> ChannelMesh:
    """Triangulate ``channel`` with target edge length ``h`` (metres)."""
    x = _graded([0.0, channel.length], h)
    y = _graded(channel.breakpoints_y(), h)
    mesh = MeshTri.init_tensor(x, y)
    length, height = channel.length, channel.height
    tolerance = 1e-6 * h
    window = channel.saw_window.span

    def on_left(span):
        return lambda p: (np.abs(p[0]) < tolerance) & (p[1] > span[0]) & (p[1] < span[1])

    def on_right(span):
        return lambda p: (np.abs(p[0] - length) < tolerance) & (p[1] > span[0]) & (p[1] < span[1])

    named = {inlet.name: on_left(inlet.span) for inlet in channel.inlets}
    named.update({outlet.name: on_right(outlet.span) for outlet in channel.outlets})
    named["saw_window"] = lambda p: (np.abs(p[1]) < tolerance) & (p[0] > window[0]) & (p[0] < window[1])
    open_boundaries = list(named.values())[: len(channel.inlets) + len(channel.outlets)]

    def is_wall(p):
        on_boundary = ((np.abs(p[0]) < tolerance) | (np.abs(p[0] - length) < tolerance)
                       | (np.abs(p[1]) < tolerance) | (np.abs(p[1] - height) < tolerance))
        for test in open_boundaries:
            on_boundary &= ~test(p)
        return on_boundary

    named["wall"] = is_wall
    mesh = mesh.with_boundaries(named)
    return ChannelMesh(mesh=mesh, x=x, y=y, h=h)
