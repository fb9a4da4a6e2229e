"""What happened to each cell, in a sorter's terms: one outcome class per cell of a run's summary.

The classes (in this order, which recordings and viewers use as class ids 0..N-1):
- ``sorted``: a target (true class II) that left by the sorted (upper) outlet;
- ``passed``: a non-target (true class I) that left by the default (lower) outlet;
- ``aborted``: a target whose sort the controller aborted (coincidence) and that did not leave upper;
- ``missed``: a target that was detected and sorted but did not leave upper (the pulse failed);
- ``misclassified``: a cell whose detected class differs from its true class (whatever its outlet);
- ``co-deflected``: a non-target, detected as such, that left by the sorted outlet anyway;
- ``lost``: a cell that hit a wall, never left, or was never detected;
- ``not_injected``: a scheduled cell that never entered the channel (a run cut short);
- ``unfinished``: a cell still in the channel when a run was cut short (its outcome is unknown).
"""

from __future__ import annotations

OUTCOME_CLASSES = ("sorted", "passed", "aborted", "missed", "misclassified", "co-deflected", "lost",
                   "not_injected", "unfinished")
SORTED_OUTLET = "upper"
DEFAULT_OUTLET = "lower"


def outcome_class(cell: dict) -> str:
    """The outcome class of one cell of ``run_stream``'s summary (keys true_class, detected_class,
    decision, outlet)."""
    outlet, detected, true = cell["outlet"], cell["detected_class"], cell["true_class"]
    if outlet in ("not_injected", "in_channel"):
        return "not_injected" if outlet == "not_injected" else "unfinished"
    if detected is not None and detected != true:
        return "misclassified"
    if outlet not in (SORTED_OUTLET, DEFAULT_OUTLET) or detected is None:
        return "lost"
    if true == "II":
        if outlet == SORTED_OUTLET:
            return "sorted"
        return "aborted" if cell["decision"] == "abort" else "missed"
    return "co-deflected" if outlet == SORTED_OUTLET else "passed"


def outcome_text(key, cell_type: str, outlet: str, class_name: str, restored: float | None = None) -> str:
    """A cell's line in the log as it leaves; with how much of its area the projection restored over its transit
    (``vcyto.restored``), where it restored any."""
    text = f"cell {key} ({cell_type}) left by: {outlet} ({class_name})"
    if restored:
        text += f"; the area projection restored {restored * 100:.2f} % of its area"
    return text
