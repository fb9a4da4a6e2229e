"""The sort report of a run: per-cell outcomes, a sorter's statistics, and the analytic yield they should meet.

Statistics (``statistics_of``), over the sample offered to the inlet:
- events: cells detected; offered: cells in the sample; rejected_at_inlet: cells the inlet's dead time turned
  away (``sim.arrivals``); sorted: sort decisions kept; aborted: sorts cancelled for coincidence;
- purity: true targets among the cells that left by the sorted outlet;
- yield: targets that left by the sorted outlet over the targets offered (rejected ones included);
- abort_rate: aborts over type-II detections; co_deflected: correctly detected type-I cells that left by the
  sorted outlet, and of those ``co_deflected_unexpected``: the ones whose predicted offset from every sort's
  target lay outside the controller's widened envelope (purity and single modes should have none);
- throughput: injected cells per second of simulated time.

``yield_estimate``: the yield the controller should reach by the arrival statistics alone. With the inlet's
dead time d, a Poisson sample of intensity r is admitted with probability A = 1 / (1 + r d), and the admitted
cells form a renewal process whose k-th neighbour on either side of a cell is k d + Gamma(k, r) away. A
target is aborted if a neighbour that the mode counts (type-I; in single mode any cell) arrives at the SAW
window at an offset inside the mode's window [L, H]; a neighbour of type j injected g after (before) the target
arrives at g + (T_j - T_t) (-g + ...) with T the transit time to the window, measured in the run. The two
sides are independent (the gaps are), and each side's probability that no counted neighbour falls in its
window is computed exactly for the renewal process by a backward recursion (``_clear_probability``); the
estimate is A times the mix-weighted mean over target types. A neighbour detected after the target's pulse has
started cannot abort it, so each window ends at the neighbour's look-ahead (its detection-to-arrival time minus
the lead) if that comes first. Regular arrivals: the neighbours sit at k / r.
"""

from __future__ import annotations

import bisect
import math
import re
import statistics

import numpy as np

from controller.events import TYPE_I, TYPE_II

from .outcomes import DEFAULT_OUTLET, SORTED_OUTLET, outcome_class

SORTED_MODES = {"purity": True, "single": True, "enrichment": False}


def true_class(cell_type) -> str:
    """The class a cell of ``cell_type`` (``sim.scenario.CellType``) should be sorted as."""
    return TYPE_II if cell_type.target else TYPE_I


def summarise(sample, truth, events, controller, scenario, settings, partial: bool = False) -> dict:
    """A JSON-ready record of a run: cells (admitted, in arrival order), statistics, the yield estimate.

    ``partial`` (a run interrupted, failed or cut short): the statistics count only the cells due by the time the
    run reached (admitted or turned away at the inlet by then); the sample's later cells never had their chance,
    and counting them (as "never injected", and in the yield's denominator) would understate every rate. Their
    number is ``not_yet_due`` (a cell injected counts, even when the plant injected it a step before its
    arrival time); the per-cell records still list every admitted cell, those not yet due with outcome
    ``not_injected``."""
    by_key = {cell.key: cell for cell in truth.cells}
    cells = [_cell_record(key, arrival, name, by_key.get(key), events.get(key), controller, scenario)
             for key, (arrival, name) in enumerate(sample.admitted)]
    _name_cells_in_reasons(cells, {event.event_id: key for key, event in events.items()})
    rejected = [name for time, name in sample.rejected if not partial or time <= truth.time]
    due = [c for c in cells if not partial or c["arrival_ms"] <= truth.time * 1e3 or c["outlet"] != "not_injected"]
    stats = statistics_of(due, truth.time, rejected=rejected, scenario=scenario,
                          controller_settings=settings.controller)
    stats["not_yet_due"] = len(cells) - len(due) + len(sample.rejected) - len(rejected)
    estimate = yield_estimate(due, scenario, settings)
    stats["coincidence_possible"] = _coincidence_possible(settings)
    return {"cells": cells, "statistics": stats, "yield_estimate": estimate,
            "simulated_time_ms": truth.time * 1e3, "model": settings.model, "seed": settings.seed,
            "mesh": mesh_record(scenario),
            "controller_mode": settings.controller.mode, "controller": _controller_record(settings.controller),
            "controller_latency_us": _latency(controller.latencies)}


def mesh_record(scenario) -> dict:
    """The mesh a run's flows are computed on: its size, squares and Taylor-Hood DOFs (``sim.mesh.MeshSize``)."""
    from sim.mesh import MeshSize
    size = MeshSize.of(scenario.channel, scenario.numerics.mesh_h)
    return {"h_um": size.largest * 1e6, "squares": list(size.squares), "dofs": size.dofs, "uniform": size.uniform,
            "description": size.describe()}


_EVENT = re.compile(r"\bevent (\d+)")


def _coincidence_possible(settings) -> bool:
    """Whether the controller can ever abort: not in yield mode, nor when the inlet keeps cells further apart
    (``min_spacing``, a dead time on arrival) than the abort window reaches (a 2 % margin for the cells'
    different speeds)."""
    controller = settings.controller
    if controller.mode == "yield" or not controller.enabled:
        return False
    low, high = controller.window(margin=controller.mode != "enrichment")
    return settings.arrivals.min_spacing < 1.02 * max(-low, high)


def name_cells(text: str, keys_by_event: dict) -> str:
    """``text`` with each ``event N`` followed by its cell, ``event N (cell K)`` (``?`` for an event not in
    ``keys_by_event``): the controller knows detector events, numbered in detection order, not cells (numbered
    in arrival order)."""
    return _EVENT.sub(lambda found: f"{found.group(0)} (cell {keys_by_event.get(int(found.group(1)), '?')})", text)


def _name_cells_in_reasons(cells, keys_by_event: dict) -> None:
    """Each decision's reason names its cells (``name_cells``); each record carries its own ``event_id``."""
    for cell in cells:
        if cell["reason"]:
            cell["reason"] = name_cells(cell["reason"], keys_by_event)


def _cell_record(key, arrival, name, cell, event, controller, scenario) -> dict:
    decision = controller.decision_for(event.event_id) if event else None
    if cell is None:
        outlet = "not_injected"
    else:
        outlet = cell.fate
    record = {
        "key": key, "type": name, "true_class": true_class(scenario.cell_type(name)), "arrival_ms": arrival * 1e3,
        "event_id": event.event_id if event else None,
        "detected_class": event.classification if event else None,
        "detection_time_ms": event.time * 1e3 if event else None,
        "fluorescence": event.fluorescence if event else None,
        "scatter": event.scatter if event else None,
        "velocity_mm_s": event.velocity * 1e3 if event else None,
        "predicted_arrival_ms": controller.predicted_arrival(event) * 1e3 if event else None,
        "decision": decision.action if decision else None,
        "reason": decision.reason if decision and decision.reason else None,
        "pulse_ms": [decision.pulse_on * 1e3, decision.pulse_off * 1e3] if decision and decision.action == "sort"
        else None,
        "outlet": outlet,
        "exit_time_ms": cell.exit_time * 1e3 if cell and math.isfinite(cell.exit_time) else None,
        "exit_y_um": cell.exit_y * 1e6 if cell and math.isfinite(cell.exit_y) else None,
        "area_ratio": cell.area_ratio if cell else None,
        **_shape_summary(cell.measures if cell else None),
    }
    record["outcome"] = outcome_class(record)
    return record


def _controller_record(settings) -> dict:
    return {"mode": settings.mode, "delay_ms": settings.delay * 1e3, "reference_velocity_m_s":
            settings.reference_velocity, "lead_ms": settings.lead * 1e3, "pulse_ms": settings.pulse * 1e3,
            "envelope_ms": [v * 1e3 for v in settings.envelope], "timing_error_ms": settings.timing_error * 1e3,
            "enabled": settings.enabled}


def _shape_summary(measures: dict | None) -> dict:
    """Area kept over the transit and the band of point spacings (FE-IB cells; None for point-like models)."""
    if not measures:
        return {"area_ratio_range": None, "spacing_over_h": None, "area_corrected": None}
    return {"area_ratio_range": [measures["area_ratio_min"], measures["area_ratio_max"]],
            "spacing_over_h": [measures["spacing_lowest"], measures["spacing_highest"]],
            "area_corrected": measures["area_corrected"]}


def _latency(samples):
    if not samples:
        return {}
    micro = np.array(samples) * 1e6
    return {"median": float(np.median(micro)), "p99": float(np.percentile(micro, 99)), "max": float(micro.max())}


def statistics_of(cells, simulated_time, rejected=(), scenario=None, controller_settings=None) -> dict:
    """Purity, yield, aborts, co-deflections, throughput and misclassifications from per-cell outcomes."""
    sorted_cells = [c for c in cells if c["outlet"] == SORTED_OUTLET]
    targets = [c for c in cells if c["true_class"] == TYPE_II]
    targets_rejected = sum(1 for name in rejected if scenario is not None and scenario.cell_type(name).target)
    detected_ii = [c for c in cells if c["detected_class"] == TYPE_II]
    aborts = [c for c in cells if c["decision"] == "abort"]
    exits = [c["exit_time_ms"] for c in cells if c["exit_time_ms"] is not None]
    injected = [c for c in cells if c["outlet"] != "not_injected"]
    co_deflected = [c for c in cells if c["outcome"] == "co-deflected"] if cells and "outcome" in cells[0] else []
    offered_targets = len(targets) + targets_rejected
    return {
        "offered": len(cells) + len(rejected),
        "rejected_at_inlet": len(rejected),
        "cells": len(cells),
        "events": sum(c["detected_class"] is not None for c in cells),
        "sorted": sum(c["decision"] == "sort" for c in cells),
        "purity": (sum(c["true_class"] == TYPE_II for c in sorted_cells) / len(sorted_cells)) if sorted_cells else None,
        "purity_of_sorting": _purity_of_sorting(sorted_cells),
        "yield": (sum(c["outlet"] == SORTED_OUTLET for c in targets) / offered_targets) if offered_targets else None,
        "abort_rate": (len(aborts) / len(detected_ii)) if detected_ii else None,
        "aborts": len(aborts),
        "co_deflected": len(co_deflected),
        "co_deflected_unexpected": _unexpected(co_deflected, cells, controller_settings),
        "misclassified": sum(c["detected_class"] is not None and c["detected_class"] != c["true_class"] for c in cells),
        # a cell still in the channel (an unfinished run) may not have reached the detector yet: not undetected
        "undetected": sum(c["detected_class"] is None and c["outlet"] not in ("not_injected", "in_channel")
                          for c in cells),
        "not_injected": len(cells) - len(injected),
        "throughput_cells_per_s": (len(injected) / (max(exits) * 1e-3)) if exits and max(exits) > 0 else None,
        "event_rate_per_s": (sum(c["detected_class"] is not None for c in cells) / simulated_time)
        if simulated_time > 0 else None,
        "outlets": {outlet: sum(c["outlet"] == outlet for c in cells)
                    for outlet in sorted({c["outlet"] for c in cells})},
        "outcomes": {name: sum(c.get("outcome") == name for c in cells)
                     for name in sorted({c.get("outcome") for c in cells} - {None})},
    }


def _purity_of_sorting(sorted_cells):
    """Purity of the sorted outlet among the cells the detector classified correctly (what the sort itself
    achieves; misclassified cells are counted apart)."""
    correct = [c for c in sorted_cells if c["detected_class"] == c["true_class"]]
    return sum(c["true_class"] == TYPE_II for c in correct) / len(correct) if correct else None


def _unexpected(co_deflected, cells, settings) -> int | None:
    """Co-deflected cells whose predicted offset from every kept sort's target lay outside the widened window."""
    if settings is None:
        return None
    low, high = (edge * 1e3 for edge in settings.window())            # ms, as the arrivals
    sorts = sorted(c["predicted_arrival_ms"] for c in cells if c["decision"] == "sort")
    count = 0
    for cell in co_deflected:            # a sort at ``other`` covers ``mine`` if other in [mine - high, mine - low]
        mine = cell["predicted_arrival_ms"]
        first = bisect.bisect_left(sorts, mine - high) if mine is not None else len(sorts)
        if first == len(sorts) or sorts[first] > mine - low:
            count += 1
    return count


def yield_estimate(cells, scenario, settings) -> dict | None:
    """The analytic yield (module docstring) for the run's mix, rate, dead time and controller window."""
    arrivals, controller = settings.arrivals, settings.controller
    transit = _transit_times(cells)
    types = [c for c in scenario.cell_types if c.name in transit]
    mix = _mix_fractions(arrivals, cells)
    targets = [c for c in types if c.target and mix.get(c.name)]
    if not targets or not controller.enabled:
        return None
    low, high = controller.window(margin=SORTED_MODES.get(controller.mode, True))
    poisson = arrivals.process == "poisson"
    acceptance = 1.0 / (1.0 + arrivals.rate * arrivals.min_spacing) if poisson else 1.0
    lookahead = _lookahead(cells)
    total, weight = 0.0, 0.0
    for target in targets:
        # a neighbour detected after the target's pulse started cannot abort it: offsets beyond its look-ahead
        # (its detection-to-arrival time minus the lead) do not count
        counted = [(mix[other.name], transit[other.name] - transit[target.name],
                    min(high, lookahead[other.name] - controller.lead)) for other in types
                   if _counts(controller.mode, other)]
        keep = 1.0
        for side in (1, -1):       # neighbours injected after (+) and before (-) the target
            windows = [(share, *sorted((side * (low - shift), side * (top - shift)))) for share, shift, top in counted
                       if top > low]
            keep *= _clear_probability(windows, arrivals)
        total += mix[target.name] * keep
        weight += mix[target.name]
    value = acceptance * total / weight
    n = sum(c["true_class"] == TYPE_II for c in cells) / max(acceptance, 1e-12)
    return {"yield": value, "acceptance": acceptance, "window_ms": [low * 1e3, high * 1e3],
            "standard_error": math.sqrt(value * (1 - value) / n) if n else None,
            "transit_ms": {name: t * 1e3 for name, t in transit.items()}}


def _counts(mode: str, other) -> bool:
    """Whether a neighbour of type ``other`` aborts a sort in ``mode``."""
    return mode == "single" or (mode in ("purity", "enrichment") and not other.target)


def _clear_probability(windows, arrivals, step: float = 1e-6) -> float:
    """P(no neighbour on one side at an injection gap inside its type's window), windows = [(share, a, b)]:
    exact for the admitted renewal process (gaps d + Exp(r)) by a backward recursion on a time grid,
    F(t) = P(gap > B - t) + int g(s) w(t + s) F(t + s) ds, w(x) = 1 - sum of shares whose window holds x."""
    windows = [(share, max(a, 0.0), b) for share, a, b in windows if b > 0 and share > 0]
    if not windows:
        return 1.0
    end = max(b for _, _, b in windows)
    grid = np.arange(0.0, end + step, step)
    w = 1.0 - sum(share * ((grid >= a) & (grid <= b)) for share, a, b in windows)
    if arrivals.process != "poisson":
        spacing = 1 / arrivals.rate
        return float(np.prod([np.interp(k * spacing, grid, w) for k in range(1, int(end / spacing) + 1)]))
    rate, dead = arrivals.rate, arrivals.min_spacing
    lag = np.arange(len(grid)) * step
    density = np.where(lag >= dead, rate * np.exp(-rate * np.maximum(lag - dead, 0.0)), 0.0) * step
    survival = np.where(lag >= dead, np.exp(-rate * np.maximum(lag - dead, 0.0)), 1.0)
    clear = np.zeros(len(grid))
    for i in range(len(grid) - 1, -1, -1):
        ahead = len(grid) - 1 - i
        clear[i] = survival[ahead] + float(np.dot(density[1:ahead + 1], (w * clear)[i + 1:]))
    return float(clear[0])


def _transit_times(cells) -> dict:
    """Median time (s) from injection to the predicted arrival at the SAW window, per type, in this run."""
    return _median_to_arrival(cells, "arrival_ms")


def _lookahead(cells) -> dict:
    """Median time (s) from detection to the predicted arrival at the SAW window, per type, in this run."""
    return _median_to_arrival(cells, "detection_time_ms")


def _median_to_arrival(cells, since: str) -> dict:
    """Per type, the median of (predicted arrival - ``since``) over the detected cells (s)."""
    times = {}
    for cell in cells:
        if cell["predicted_arrival_ms"] is not None:
            times.setdefault(cell["type"], []).append((cell["predicted_arrival_ms"] - cell[since]) * 1e-3)
    return {name: statistics.median(values) for name, values in times.items()}


def _mix_fractions(arrivals, cells) -> dict:
    if arrivals.mix:
        total = sum(weight for _, weight in arrivals.mix)
        return {name: weight / total for name, weight in arrivals.mix}
    names = [c["type"] for c in cells]
    return {name: names.count(name) / len(names) for name in set(names)}


def report_lines(result: dict, table_limit: int = 200) -> list[str]:
    """The summary as text: a table of cells (up to ``table_limit``), then the sort report."""
    lines = []
    cells = result["cells"]
    if len(cells) <= table_limit:
        lines.append(f"{'cell':>4}  {'type':<9} {'detected':>8}  {'decision':<8} {'outlet':<12} {'outcome':<13} "
                     f"{'exit (ms)':>9}  {'area kept (min-max)':<20} spacing / h")
        lines += [_cell_line(cell) for cell in cells]
    else:
        due = result["statistics"].get("cells", len(cells))
        counted = f", {due} of them due by the end and counted" if due != len(cells) else ""
        lines.append(f"({len(cells)} cells admitted{counted}: the table is in the JSON summary, --json, and the FCS "
                     "file)")
    lines += sort_report_lines(result)
    return lines


def _cell_line(cell) -> str:
    exit_ms = f"{cell['exit_time_ms']:9.3f}" if cell["exit_time_ms"] is not None else "        -"
    low_high = cell.get("area_ratio_range")
    area = f"{100 * low_high[0]:6.2f}-{100 * low_high[1]:6.2f} %" if low_high else "-"
    spacing = cell.get("spacing_over_h")
    band = f"{spacing[0]:.2f}-{spacing[1]:.2f}" if spacing else "-"
    return (f"{cell['key']:>4}  {cell['type']:<9} {cell['detected_class'] or '-':>8}  {cell['decision'] or '-':<8} "
            f"{cell['outlet']:<12} {cell.get('outcome', '-'):<13} {exit_ms}  {area:<20} {band}")


def _percent(value) -> str:
    return "n/a" if value is None else f"{100 * value:.1f} %"


def sort_report_lines(result: dict) -> list[str]:
    stats = result["statistics"]
    estimate = result.get("yield_estimate")
    expected = ""
    if estimate:
        error = estimate["standard_error"]
        expected = f" (analytic {_percent(estimate['yield'])}" + (f" +/- {100 * error:.1f}" if error else "") + ")"
    throughput = stats["throughput_cells_per_s"]
    lines = [
        f"sort report ({result.get('controller_mode', '?')} mode): {stats['offered']} offered, "
        f"{stats['rejected_at_inlet']} rejected at the inlet, {stats['events']} events, {stats['sorted']} sort "
        f"decisions, {stats['aborts']} aborted",
        _outcome_line(stats),
        f"purity {_percent(stats['purity'])} ({_percent(stats['purity_of_sorting'])} of the correctly detected), "
        f"yield {_percent(stats['yield'])}{expected}, abort rate "
        f"{_percent(stats['abort_rate'])}{_no_coincidence(stats, result)}, co-deflected {stats['co_deflected']} "
        f"(outside the envelope: {stats['co_deflected_unexpected']}), misclassified {stats['misclassified']}, "
        f"undetected {stats['undetected']}, never injected {stats['not_injected']}"
        + (f"; {stats['not_yet_due']} cells of the sample were not yet due when the run stopped (not counted)"
           if stats.get("not_yet_due") else ""),
        f"throughput {throughput:.0f} cells/s of simulated time" if throughput else "throughput n/a",
        f"simulated {result['simulated_time_ms']:.3f} ms (IDT on {result['idt_on_time_ms']:.3f} ms) in "
        f"{result['wall_time_s']:.1f} s wall ({result['model']} model: set-up {result['setup_time_s']:.1f} s, loop "
        f"{result['wall_time_s'] - result['setup_time_s']:.3g} s); "
        + _latency_line(result['controller_latency_us']),
    ]
    if result.get("mesh"):
        lines.append(f"mesh: {result['mesh']['description']}")
    if (result.get("time_steps") or {}).get("levels_us"):
        from .paper import time_step_line
        lines += [line.strip() for line in time_step_line(result["time_steps"])]
    if result.get("status", "complete") != "complete":
        lines.append(f"PARTIAL RESULT ({result['status']}): {result['reason']}")
    if "auto" in result:
        auto = result["auto"]
        switches = "".join(f"\n  t = {s['time_ms']:7.3f} ms -> {s['model']}: {s['reason']}"
                           for s in auto["switches"][1:9])
        lines.append(f"auto: feib for {100 * auto['feib_fraction']:.1f} % of the periods, "
                     f"{len(auto['switches']) - 1} switches" + switches
                     + ("\n  ..." if len(auto["switches"]) > 9 else ""))
    return lines


__all__ = ["summarise", "statistics_of", "yield_estimate", "report_lines", "true_class", "DEFAULT_OUTLET"]


def _no_coincidence(stats: dict, result: dict) -> str:
    """Why a purity or single-cell run cannot abort, when it cannot."""
    if stats.get("coincidence_possible", True) or result.get("controller_mode") == "yield":
        return ""
    return (" (no coincidence can occur: the inlet keeps cells further apart than the abort window reaches; "
            "lower --min-spacing to see aborts)")


def _outcome_line(stats: dict) -> str:
    """What became of the cells: every outcome class that occurred and every outlet, so cells lost to a wall or
    targets whose pulse missed stand beside the decisions."""
    outcomes = ", ".join(f"{name} {count}" for name, count in sorted(stats.get("outcomes", {}).items(),
                                                                     key=lambda item: -item[1]) if count)
    outlets = ", ".join(f"{name} {count}" for name, count in sorted(stats.get("outlets", {}).items()) if count)
    return f"outcomes: {outcomes or 'none'}; outlets: {outlets or 'none'}"


def _latency_line(latency_us: dict) -> str:
    """The controller's p99 decision latency, or n/a when it decided nothing."""
    p99 = latency_us.get("p99")
    return f"controller latency p99 {p99:.1f} us" if p99 is not None and math.isfinite(p99) else \
        "controller latency n/a (no decisions)"
