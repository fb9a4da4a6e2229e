"""The plain data the instrument and the controller exchange (no numerics library, no ground truth).

Of ``sim`` the controller imports only the plant contract (``sim.plants.contract``: numpy and the standard library).
"""

from __future__ import annotations

from dataclasses import dataclass

from sim.plants.contract import CellView

TYPE_I = "I"      # leaves by the default (lower) outlet: IDT off
TYPE_II = "II"    # to be sorted to the upper outlet: IDT on


# What the optics see of one object in the channel at one instant: the plant contract's ``CellView`` (an opaque
# key, where it is, its area in m^2 and its label brightness in a.u.). One type for the plant and the controller.
Sighting = CellView


@dataclass(frozen=True)
class DetectorEvent:
    """One cell's passage through the detection window."""

    event_id: int
    time: float              # when the cell left the window (s)
    fluorescence: float      # measured intensity (a.u.)
    scatter: float           # forward scatter, proportional to size (a.u.)
    velocity: float          # window length / transit time (m/s)
    classification: str      # TYPE_I or TYPE_II, by the gate
    key: int                 # the sighting key (lets the application join events to outcomes)


@dataclass(frozen=True)
class Decision:
    """What the controller decided about one event."""

    event_id: int
    action: str              # "sort" (IDT pulse), "pass" (no pulse), "abort" (sort cancelled: coincidence)
    arrival: float           # predicted arrival at the SAW window (s)
    pulse_on: float = float("nan")
    pulse_off: float = float("nan")
    reason: str = ""
