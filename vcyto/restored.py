"""How much of each cell's area the area constraint's projection put back, and the one-line warning when that is
more than a safety net (docs/numerics.md, "Cells that keep their size").

The projection (``numerics.area_constraint`` with ``projection``) moves a membrane along its normal after each step
to restore the area it was born with; ``sim.method.feib.Measures.area_corrected`` sums what it restored (|dA| / A0 per
step) over the cell's transit. With the multiplier the step itself keeps the area and the projection restores
round-off; without it the projection may be re-inflating a leaking cell every step. Above ``RESTORED_LIMIT`` a run
says so.
"""

from __future__ import annotations

RESTORED_LIMIT = 0.01       # of the initial area over a transit: above it the projection, not the method, kept it


class Restored:
    """The largest area restored by the projection over the cells counted so far, and how many exceeded the limit."""

    def __init__(self):
        self.largest: float | None = None
        self.cell = None
        self.over = 0

    def add(self, cell, restored: float | None):
        """Count ``cell`` (a key or a name) that had ``restored`` of its area put back (None: no membrane)."""
        if restored is None:
            return
        if self.largest is None or restored > self.largest:
            self.largest, self.cell = restored, cell
        self.over += restored > RESTORED_LIMIT

    def summary(self) -> dict | None:
        """The figures for a run's summary (None when no cell had a membrane)."""
        if self.largest is None:
            return None
        return {"largest": self.largest, "cell": self.cell, "cells_over_limit": self.over, "limit": RESTORED_LIMIT}


def restored_warning(summary: dict | None) -> str | None:
    """One line when a cell had more than ``RESTORED_LIMIT`` of its area restored by the projection, else None."""
    if not summary or not summary["cells_over_limit"]:
        return None
    count = summary["cells_over_limit"]
    return (f"warning: the area projection restored more than {100 * summary['limit']:g} % of the initial area "
            f"over the transit of {count} cell{'s' if count > 1 else ''} (largest {100 * summary['largest']:.2f} %, "
            f"cell {summary['cell']}): the correction, not the method, kept the area; keep it in the step with "
            "--membrane multiplier (numerics.area_constraint = \"pressure+multiplier+projection\")")
