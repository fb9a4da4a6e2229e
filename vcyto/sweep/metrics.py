"""The metrics a sweep can tabulate (sort statistics, run figures, outlet counts and fractions per cell type),
checked against the scenario, and their values in one run's result."""

from __future__ import annotations

from .model import SweepError

STATISTICS = ("yield", "purity", "abort_rate", "aborts", "misclassified", "undetected", "throughput_cells_per_s",
              "cells", "purity_of_sorting", "offered", "events", "event_rate_per_s", "rejected_at_inlet", "sorted",
              "co_deflected",
              "co_deflected_unexpected", "not_injected", "yield_estimate")
RARE_CELL = ("enrichment", "recovery", "recovery_estimated", "targets_found", "events_per_target_found")
RUN_FIGURES = ("simulated_time_ms", "idt_on_time_ms", "wall_time_s")
DEFAULT_METRICS = ("yield", "purity", "abort_rate", "outlets")


def check_metrics(names, scenario) -> tuple[str, ...]:
    if isinstance(names, str) or not isinstance(names, list) or not names:
        raise SweepError('sweep.metrics: must be a non-empty list, e.g. ["yield", "purity", "melanoma.upper"]')
    outlets = [outlet.name for outlet in scenario.channel.outlets] + ["wall", "lost"]
    types = [cell.name for cell in scenario.cell_types]
    for name in names:
        group, _, outlet = str(name).partition(".")
        known = (name in STATISTICS + RARE_CELL + RUN_FIGURES + ("outlets",)
                 or (group in ["outlet", *types] and outlet in outlets))
        if not known:
            raise SweepError(f"sweep.metrics: unknown metric {name!r}; known: "
                             f"{', '.join(STATISTICS + RARE_CELL + RUN_FIGURES)}, "
                             f"outlets, outlet.NAME (cells leaving by outlet NAME: {', '.join(outlets)}) and "
                             f"TYPE.NAME (the fraction of TYPE cells leaving by NAME, TYPE one of {', '.join(types)})")
    return tuple(dict.fromkeys(names))


def metric_value(result: dict, name: str):
    """The metric ``name`` of one ``run_stream`` result (None where it is undefined, e.g. purity of no sort)."""
    if name == "yield_estimate":
        return (result.get("yield_estimate") or {}).get("yield")
    if name in STATISTICS:
        return result["statistics"].get(name)
    if name in RARE_CELL:                           # a rare-cell sort's figures (vcyto.sortreport.Tally.rare_cell)
        return (result["statistics"].get("rare_cell") or {}).get(name)
    if name in RUN_FIGURES:
        return result[name]
    outlets = result["statistics"]["outlets"]
    if name == "outlets":
        return " ".join(f"{outlet}={count}" for outlet, count in outlets.items())
    group, _, outlet = name.partition(".")
    if group == "outlet":
        return outlets.get(outlet, 0)
    # a run of more than sortreport.KEEP_CELLS cells lists none in its summary: the metric is then undefined
    cells = [cell for cell in result.get("cells") or () if cell["type"] == group]
    return sum(cell["outlet"] == outlet for cell in cells) / len(cells) if cells else None
