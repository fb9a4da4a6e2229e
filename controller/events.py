"""The plain data the instrument and the controller exchange (no numerics library, no ground truth)."""

from __future__ import annotations

from dataclasses import dataclass

TYPE_I = "I"      # leaves by the default (lower) outlet: IDT off
TYPE_II = "II"    # to be sorted to the upper outlet: IDT on


@dataclass(frozen=True)
class Sighting:
    """What the optics see of one object in the channel at one instant: an opaque key, where it is,
    how big it is (area, m^2) and how brightly its label fluoresces (arbitrary units)."""

    key: int
    x: float
    y: float
    area: float
    brightness: float


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
