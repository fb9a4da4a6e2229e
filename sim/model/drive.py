"""The IDT drive seen through a first-order lag: the one definition every plant and the fluid use.

A level s follows the actuation a (0 = IDT off, 1 = on) as ds/dt = (a - s) / tau; over a step dt with a
held constant the exact solution is s' = a + (s - a) exp(-dt / tau). ``tau`` = 0 means no lag (s' = a).
The reduced plants blend their steady flows by s (``response_time``: the FE flow's measured delay), the
``streaming`` SAW force follows the drive with ``spin_up_time``.
"""

from __future__ import annotations

import math


def lag_decay(dt: float, time_constant: float) -> float:
    """exp(-dt / time_constant), the part of the gap to the drive left after ``dt``; 0 without a lag."""
    return math.exp(-dt / time_constant) if time_constant > 0 else 0.0


def lagged(level: float, actuation: float, dt: float, time_constant: float) -> float:
    """The level after ``dt`` of following ``actuation`` from ``level`` through a first-order lag."""
    return actuation + (level - actuation) * lag_decay(dt, time_constant)
