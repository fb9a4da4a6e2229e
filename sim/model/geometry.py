"""Where cells start and how points are held in the channel: the one definition of each, for every plant.

- ``injection_y``: the centre of the injection inlet (``channel.injection_inlet``); streamlines and cells
  start on it.
- ``injection_point``: a cell's start, its centroid one semi-axis plus ``gap`` (1 um) inside the channel on
  the injection inlet's centre line (docs/physics.md, "Where a cell starts and how it ends").
- ``clip_to_channel``: points moved into the channel before the flow is evaluated at them: points that have
  passed the outlet plane x = L (a membrane leaving through an outlet) are evaluated on it, ``inset``
  (relative) inside so that a point location in the mesh finds an element; with ``walls`` every coordinate
  is clipped to the closed rectangle [0, L] x [0, H] (a sampling rule reaching past the walls).
"""

from __future__ import annotations

import numpy as np

from .scenario import CellType, Channel, Scenario

INJECTION_GAP = 1e-6     # m between the channel's entrance x = 0 and a new cell's leftmost point
MESH_INSET = 1e-12       # relative: x = L (1 - MESH_INSET) lies inside the mesh's last element


def injection_y(channel: Channel) -> float:
    """The ordinate (m) of the injection inlet's centre."""
    inlet = channel.inlet(channel.injection_inlet)
    return 0.5 * (inlet.span[0] + inlet.span[1])


def injection_point(scenario: Scenario, cell_type: CellType, gap: float = INJECTION_GAP) -> tuple[float, float]:
    """The start of a cell: just inside the channel, centred on the injection inlet (docs/physics.md)."""
    return cell_type.semi_axes[0] + gap, injection_y(scenario.channel)


def clip_to_channel(points: np.ndarray, channel: Channel, inset: float = 0.0, walls: bool = True) -> np.ndarray:
    """``points`` (n, 2) with x at most L (1 - ``inset``); with ``walls`` also x >= 0 and 0 <= y <= H.

    ``walls=False`` leaves points outside the walls as they are (the FE-IB plants: such a point is the
    health checks' business, not the interpolation's)."""
    upper_x = channel.length * (1 - inset)
    if walls:
        return np.clip(points, 0.0, np.array([upper_x, channel.height]))
    return np.column_stack([np.minimum(points[:, 0], upper_x), points[:, 1]])
