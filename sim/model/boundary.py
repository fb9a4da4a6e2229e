"""Boundary data: inflow profiles (paper section 4), the SAW window's jet, and the smooth cut-off m.

Inflow on inlet i: v = v_hat m(y) (y - b1)(b2 - y) (cos alpha, sin alpha). The ``paper`` reading
measures the lengths of this formula in units of 10 um (peak 0.0225 m/s on inlet 2); the ``peak``
reading takes v_hat as the parabola's peak speed. The Dirichlet SAW models (``paper``, ``envelope``) impose
a normal jet v_2 = 2 pi a f m_ac(x) on the window while the IDT is on: the 100 MHz carrier's amplitude,
switched by the drive, never its phase at a step time (docs/physics.md, "SAW models").
"""

from __future__ import annotations

import numpy as np

from .scenario import Channel, Inlet, Saw

PAPER_LENGTH_UNIT = 10e-6   # the paper's inflow formula measures lengths in units of 10 um


def _smooth_step(t):
    """C-infinity step: 0 for t <= 0, 1 for t >= 1."""
    t = np.clip(t, 0.0, 1.0)
    with np.errstate(divide="ignore", over="ignore"):
        rising = np.where(t > 0, np.exp(-1.0 / np.where(t > 0, t, 1.0)), 0.0)
        falling = np.where(t < 1, np.exp(-1.0 / np.where(t < 1, 1.0 - t, 1.0)), 0.0)
    return rising / (rising + falling)


def cutoff(s, low, high, width):
    """The smooth cut-off m: 1 on [low + width, high - width], 0 outside (low, high)."""
    s = np.asarray(s, dtype=float)
    if width == 0:
        return ((s > low) & (s < high)).astype(float)
    return _smooth_step((s - low) / width) * _smooth_step((high - s) / width)


def inflow_speed(inlet: Inlet, y, reading: str):
    """Speed of the inflow along its direction at ordinates ``y`` (zero outside the inlet)."""
    low, high = inlet.span
    y = np.asarray(y, dtype=float)
    parabola = np.clip((y - low) * (high - y), 0.0, None)
    if reading == "paper":
        scale = inlet.v_hat / PAPER_LENGTH_UNIT**2
    else:
        scale = 4 * inlet.v_hat / (high - low) ** 2
    return scale * cutoff(y, low, high, inlet.cutoff) * parabola


def inflow_velocity(channel: Channel, y):
    """Velocity (2, n) imposed on the left wall x = 0 at ordinates ``y``: the sum over inlets."""
    y = np.asarray(y, dtype=float)
    velocity = np.zeros((2,) + y.shape)
    for inlet in channel.inlets:
        speed = inflow_speed(inlet, y, channel.profile_reading)
        velocity[0] += speed * np.cos(inlet.tilt)
        velocity[1] += speed * np.sin(inlet.tilt)
    return velocity


def saw_window_profile(channel: Channel, x):
    """m_ac(x): the window's cut-off along the lower wall."""
    window = channel.saw_window
    return cutoff(x, window.span[0], window.span[1], window.cutoff)


def saw_jet_factor(saw: Saw) -> float:
    """The jet's factor while the IDT is on: 1 for the Dirichlet models (the carrier's amplitude 2 pi a f, the
    same at every time: no step samples the 10 ns carrier), 0 for ``streaming`` (a body force, no jet)."""
    return 0.0 if saw.model == "streaming" else 1.0


def inlet_flux(inlet: Inlet, reading: str) -> float:
    """Volume flux (m^2/s per unit depth) through one inlet, by Gauss-Legendre quadrature."""
    nodes, weights = np.polynomial.legendre.leggauss(64)
    low, high = inlet.span
    y = 0.5 * (high - low) * nodes + 0.5 * (high + low)
    return float(0.5 * (high - low) * weights @ inflow_speed(inlet, y, reading)) * float(np.cos(inlet.tilt))
