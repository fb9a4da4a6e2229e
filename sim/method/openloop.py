"""Open-loop runs: a plant stepped with a drive fixed in advance (no controller) until its cells have left.

The paper's scenarios (``vcyto paper``), the extremes (``vcyto extremes``), the stability bisection
(``sim.method.stability``) and the trade-off scenes (``vcyto tradeoff``) all run this way; ``stepping`` is their one
loop. It is a generator: the caller takes what it records from each state (a path, an energy, a stretch) and
may stop early. ``with_cells`` places the cells of such a run in a start flow.
"""

from __future__ import annotations

import math
from typing import Callable, Iterator


def in_channel(state) -> bool:
    """Whether any cell of an FE-IB state (``sim.method.feib.State``) is still in the channel."""
    return any(cell.in_channel for cell in state.cells)


def stepping(step: Callable, state, drive=0.0, until: float = math.inf, running: Callable = in_channel,
             max_steps: int | None = None) -> Iterator:
    """Yield the state after each ``step(state, actuation)``.

    ``drive``: the IDT drive, a number or a function of the time (s) at the start of the step. The loop stops
    before a step once ``running(state)`` is false (default: no cell left in the channel), the time has
    reached ``until`` (s), or after ``max_steps`` steps. States need a ``time`` (s): FE-IB states and the
    observations of the plant contract have one (step a contract plant with ``lambda _, a: plant.step(a)``
    and ``running=lambda _: not plant.done``).
    """
    drive_at = drive if callable(drive) else (lambda time: drive)
    steps = 0
    while (max_steps is None or steps < max_steps) and running(state) and state.time < until:
        state = step(state, drive_at(state.time))
        steps += 1
        yield state


def with_cells(plant, flow, cells):
    """An FE-IB state of ``flow`` with a new cell per (cell type, centre or None: the injection point), ids 0,
    1, ... in order, born at the flow's time; ``plant`` is a ``sim.method.feib.ImmersedBoundary``."""
    from .feib import State
    return State(flow, tuple(plant.new_cell(kind, index, flow.time, centre)
                             for index, (kind, centre) in enumerate(cells)))
