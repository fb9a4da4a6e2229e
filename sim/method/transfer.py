"""Eulerian-Lagrangian transfer: locating points in the channel mesh and evaluating P2 fields there.

The channel mesh is a tensor grid of squares split along their rising diagonals, so a point is located
by two binary searches and one comparison (``kernels.locate``); P2 values follow from the reference
coordinates. ``basis.probes`` of scikit-fem is the oracle these kernels are tested against.
"""

from __future__ import annotations

import numpy as np

from ..fast import kernels
from ..model.mesh import ChannelMesh


class PointLocator:
    """Locates points in a ``ChannelMesh`` and interpolates scalar-P2 fields (nc, N) at them."""

    def __init__(self, cmesh: ChannelMesh, element_dofs: np.ndarray):
        mesh = cmesh.mesh
        self.grid_x = np.ascontiguousarray(cmesh.x)
        self.grid_y = np.ascontiguousarray(cmesh.y)
        self.element_dofs = np.ascontiguousarray(element_dofs, dtype=np.int64)
        vertices = mesh.p[:, mesh.t]                       # (2, 3, ne)
        self.origins = np.ascontiguousarray(vertices[:, 0, :].T)
        edges = np.array([vertices[:, 1] - vertices[:, 0], vertices[:, 2] - vertices[:, 0]])  # (2 edges, 2, ne)
        jacobians = edges.transpose(2, 1, 0)               # (ne, 2 coords, 2 edges)
        self.inverse_jacobians = np.ascontiguousarray(np.linalg.inv(jacobians))
        self.square_elements = self._square_table(vertices.mean(axis=1))

    def _square_table(self, centroids):
        i = np.searchsorted(self.grid_x, centroids[0]) - 1
        j = np.searchsorted(self.grid_y, centroids[1]) - 1
        s = (centroids[0] - self.grid_x[i]) / np.diff(self.grid_x)[i]
        r = (centroids[1] - self.grid_y[j]) / np.diff(self.grid_y)[j]
        table = np.full((len(self.grid_x) - 1, len(self.grid_y) - 1, 2), -1, dtype=np.int64)
        table[i, j, (r < s).astype(int)] = np.arange(centroids.shape[1])
        if (table < 0).any():
            raise ValueError("the mesh is not a tensor grid of squares split along rising diagonals")
        return table

    def locate(self, points: np.ndarray):
        """Element index (-1 outside) and reference coordinates of points (n, 2)."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        elements = np.empty(len(points), dtype=np.int64)
        reference = np.empty((len(points), 2))
        kernels.locate(points, self.grid_x, self.grid_y, self.square_elements, self.origins,
                       self.inverse_jacobians, elements, reference)
        return elements, reference

    def interpolate(self, values: np.ndarray, points: np.ndarray) -> np.ndarray:
        """P2 field ``values`` (nc, N) at ``points`` (n, 2) as an (n, nc) array; NaN outside the channel."""
        return self.interpolate_located(values, *self.locate(points))

    def interpolate_located(self, values, elements, reference) -> np.ndarray:
        """As ``interpolate`` for points already located (reuse the location of one step)."""
        out = np.empty((len(elements), values.shape[0]))
        kernels.interpolate_p2(elements, reference, self.element_dofs, np.ascontiguousarray(values), out)
        return out

    def spread_located(self, forces, elements, reference, out) -> np.ndarray:
        """Add point forces (n, nc) at located points to the P2 load ``out`` (nc, N): sum_k f_k phi_i(x_k)."""
        kernels.spread_p2(elements, reference, self.element_dofs, np.ascontiguousarray(forces, dtype=float), out)
        return out

    def spread(self, forces: np.ndarray, points: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Add point forces (n, nc) at ``points`` (n, 2) to ``out`` (nc, N); points outside are dropped."""
        return self.spread_located(forces, *self.locate(points), out)
