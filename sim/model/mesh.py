"""The channel's triangulation: a tensor grid of squares, each cut into two right isosceles triangles.

Grid lines run through every inlet and outlet end so each boundary begins and ends at a vertex
(paper section 3.1: "a triangulation that aligns with the partition of Gamma"). Between these
breakpoints the spacing is the largest that does not exceed ``h`` by more than ``MESH_H_SLACK``
(0.2 %: a size written to three digits, 3.33 um, names the mesh of 10/3 um, not one with an extra column);
for the paper's device and h = 10/3 um this is the uniform 90 x 66 grid with 6,097 vertices and 54,243
Taylor-Hood DOFs. ``MeshSize`` says which mesh a size builds (its squares, spacings, DOFs, whether it is
uniform) without building it; the meshes of a channel are uniform exactly for h = G / k, G the largest length
that divides every gap between its breakpoints (10 um for the paper's device: 10, 5, 3.33, 2.5, 2 um, ...).

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

MESH_H_SLACK = 0.002     # a spacing may exceed the asked h by this share: h written to three or four digits


def _divisions(low: float, high: float, h: float) -> int:
    """The fewest equal divisions of (low, high) whose spacing is at most h (1 + MESH_H_SLACK)."""
    return max(1, math.ceil((high - low) / (h * (1 + MESH_H_SLACK)) - 1e-9))


def _graded(breakpoints, h):
    """Points through all ``breakpoints``, each gap split evenly into ``_divisions``."""
    points = [breakpoints[0]]
    for low, high in zip(breakpoints, breakpoints[1:]):
        points.extend(np.linspace(low, high, _divisions(low, high, h) + 1)[1:])
    return np.array(points)


def _gaps(channel: Channel) -> list[float]:
    ys = channel.breakpoints_y()
    return [channel.length] + [high - low for low, high in zip(ys, ys[1:])]


def uniform_unit(channel: Channel, resolution: float = 1e-9) -> float:
    """G: the largest length (a whole number of ``resolution``) dividing every gap between the channel's
    breakpoints; its uniform meshes have h = G / k."""
    return math.gcd(*(round(gap / resolution) for gap in _gaps(channel))) * resolution


@dataclass(frozen=True)
class MeshSize:
    """Which mesh the size ``asked`` builds: its squares, largest and smallest spacing and Taylor-Hood DOFs."""

    asked: float
    squares: tuple[int, int]
    largest: float
    smallest: float
    uniform_unit: float

    @classmethod
    def of(cls, channel: Channel, h: float) -> "MeshSize":
        ys = channel.breakpoints_y()
        gaps = [(0.0, channel.length)] + list(zip(ys, ys[1:]))
        counts = [_divisions(low, high, h) for low, high in gaps]
        spacings = [(high - low) / count for (low, high), count in zip(gaps, counts)]
        return cls(h, (counts[0], sum(counts[1:])), max(spacings), min(spacings), uniform_unit(channel))

    @property
    def uniform(self) -> bool:
        return self.smallest >= self.largest * (1 - 1e-9)

    @property
    def dofs(self) -> int:
        """Taylor-Hood P2/P1 unknowns: 2 velocities at (2 nx + 1)(2 ny + 1) nodes, (nx + 1)(ny + 1) pressures."""
        nx, ny = self.squares
        return 2 * (2 * nx + 1) * (2 * ny + 1) + (nx + 1) * (ny + 1)

    @property
    def snapped(self) -> bool:
        """Whether the mesh's largest spacing differs from the size asked (beyond round-off)."""
        return not math.isclose(self.largest, self.asked, rel_tol=1e-9)

    def nearest_uniform(self) -> tuple[float, float]:
        """The uniform meshes' sizes G / k just above and below the asked one."""
        k = self.uniform_unit / self.asked
        return self.uniform_unit / max(1, math.floor(k)), self.uniform_unit / (math.floor(k) + 1)

    def describe(self) -> str:
        """E.g. "90 x 66 squares, uniform, h = 3.333 um, 54,243 DOFs"."""
        um = 1e-6
        if self.uniform:
            shape = f"uniform, h = {self.largest / um:.4g} um"
        else:
            shape = f"graded, spacing {self.smallest / um:.4g}-{self.largest / um:.4g} um"
        return f"{self.squares[0]} x {self.squares[1]} squares, {shape}, {self.dofs:,} DOFs"

    def note(self) -> str | None:
        """What to tell a user who asked for ``asked``: None when the mesh is uniform with that h."""
        if self.uniform and not self.snapped:
            return None
        um = 1e-6
        text = f"mesh h = {self.asked / um:.6g} um builds {self.describe()}"
        if self.snapped:
            text += f"; the run uses h = {self.largest / um:.6g} um, its largest spacing"
        if not self.uniform and self.uniform_unit >= 1e-7:
            coarser, finer = self.nearest_uniform()
            text += (f" (not uniform: grid lines run through the inlets' and outlets' ends; the nearest uniform meshes "
                     f"have h = {coarser / um:.4g} um or {finer / um:.4g} um)")
        return text


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
