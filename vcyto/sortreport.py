"""The sort report of a run: per-cell outcomes, a sorter's statistics, and the analytic yield they should meet.

Statistics (``statistics_of``), over the sample offered to the inlet:
- events: cells detected; offered: cells in the sample; rejected_at_inlet: cells the inlet's dead time turned
  away (``sim.model.arrivals``); sorted: sort decisions kept; aborted: sorts cancelled for coincidence;
- purity: true targets among the cells that left by the sorted outlet;
- yield: targets that left by the sorted outlet over the targets offered (rejected ones included);
- abort_rate: aborts over type-II detections; co_deflected: correctly detected type-I cells that left by the
  sorted outlet, and of those ``co_deflected_unexpected``: the ones whose predicted offset from every sort's
  target lay outside the controller's widened envelope (purity and single modes should have none);
- throughput: injected cells per second of simulated time;
- rare_cell (what a rare-cell sort is judged by): the targets' fraction of the sample offered; enrichment (targets
  per other cell in the sorted outlet over the same ratio in the sample offered); recovery (targets in the sorted
  outlet over the targets that left by the sorted or the waste outlet) and the recovery a core facility estimates
  without knowing the truth, by re-analysing both tubes: each tube's count times the fraction of its cells the
  detector gates as targets, sorted / (sorted + waste); purity's 95 % Clopper-Pearson interval; events per
  target found.

The report is built as the run goes (``SortLedger``, a sink of the loop): a cell's record is made once, when it
leaves, counted (``Tally``: the figures above are sums over records, so memory does not grow with the run) and
written to the per-cell table (``vcyto.celltable``); ``statistics_of`` applies the same ``Tally`` to a list of
records (such as the table read back), so the two agree.

``yield_estimate``: the yield the controller should reach by the arrival statistics alone. With the inlet's
dead time d, a Poisson sample of intensity r is admitted with probability A = 1 / (1 + r d), and the admitted
cells form a renewal process whose k-th neighbour on either side of a cell is k d + Gamma(k, r) away. A
target is aborted if a neighbour that the mode counts (type-I; in single mode any cell) arrives at the SAW
window at an offset inside the mode's window [L, H]; a neighbour of type j injected g after (before) the target
arrives at g + (T_j - T_t) (-g + ...) with T the median transit time to the window, measured in the run (on its
first ``TRANSIT_CELLS`` cells, so that a long run's memory does not grow with it). The two
sides are independent (the gaps are), and each side's probability that no counted neighbour falls in its
window is computed exactly for the renewal process by a backward recursion (``_clear_probability``); the
estimate is A times the mix-weighted mean over target types. A neighbour detected after the target's pulse has
started cannot abort it, so each window ends at the neighbour's look-ahead (its detection-to-arrival time minus
the lead) if that comes first. Regular arrivals: the neighbours sit at k / r.
"""

from __future__ import annotations

import array
import bisect
import collections
import math
import re
import statistics

import numpy as np

from controller.events import TYPE_I, TYPE_II
from sim.model.arrivals import Cells, Drawn

from .outcomes import DEFAULT_OUTLET, SORTED_OUTLET, outcome_class
from .restored import Restored

SORTED_MODES = {"purity": True, "single": True, "enrichment": False}


def true_class(cell_type) -> str:
    """The class a cell of ``cell_type`` (``sim.model.scenario.CellType``) should be sorted as."""
    return TYPE_II if cell_type.target else TYPE_I


KEEP_CELLS = 10_000            # per-cell records a summary lists; a longer run's are in its table only
SORT_HORIZON = 0.1             # s: sorts kept for the co-deflection check after their predicted arrival
EVENT_NAMES = 1 << 12          # recent detector events whose cells a decision's reason can name: its neighbours, a
                               # few ms away, named within the cell's transit (tens of ms; >= 2 s at 2,000 events/s)
SORTS_KEPT = 1 << 12           # sorts in effect above which those past SORT_HORIZON are dropped
TRANSIT_CELLS = 1 << 16        # the yield estimate's transit times: of the sample's first cells (by key); full
                               # after 65,536 cells, so that a 10^5-event run and a longer one hold the same
STRETCH = 1 << 16              # cells never injected, recorded at the end a stretch at a time
ARRIVAL_BLOCK = 1 << 12        # admitted cells whose arrivals the report reads at a time (``ArrivalReader``)


class SortLedger:
    """The sort report built as the run goes, with memory bounded by the cells in the channel.

    A sink of the loop (not paced: it sees the steps the loop shows anyway): each detector event and decision is
    kept until its cell leaves; then the cell's record is built once, counted (``Tally``), written to the table
    (``vcyto.celltable``, if a path is given) and kept for the summary while the run has at most ``keep`` cells
    (None: all; by default ``KEEP_CELLS``). ``summary`` adds the cells still in the channel and those never injected."""

    paced = False
    needs_state = False           # the time, the cells' truth, events and decisions are all it reads

    def __init__(self, sample, scenario, settings, predicted_arrival, table=None, keep: int | None | str = "default",
                 checkpoint=None):
        from .celltable import CellTable
        self.sample, self.scenario, self.settings = sample, scenario, settings
        self.checkpoint = checkpoint          # the summary and events as the run goes (vcyto.recording.checkpoint)
        self.predicted_arrival = predicted_arrival
        self.table = CellTable(table) if table is not None else None
        self.keep = KEEP_CELLS if keep == "default" else keep
        self.kept: list[dict] = []
        self.tally = Tally()
        self.samples = _TransitSamples()
        self.window_ms = tuple(edge * 1e3 for edge in settings.controller.window())
        self.unexpected = 0
        self.time = 0.0
        self._events: dict = {}            # key -> event, of the cells not yet recorded
        self._decisions: dict = {}         # event_id -> decision, of the cells not yet recorded
        self._keys = RecentKeys()          # event_id -> key, the recent events (reasons name them)
        self._sorts: dict = {}             # event_id -> predicted arrival (s) of the recent sorts in effect
        self._inside: dict = {}            # key -> the latest truth of a cell in the channel
        self._below = 0                    # every key below it recorded
        self._recorded: set = set()        # keys at or above ``_below`` recorded (cells that overtook others)
        self._due = self._not_due = 0
        self._arrivals = ArrivalReader(sample.admitted)
        self._classes: dict = {}           # type name -> its true class

    # --- what the loop shows ----------------------------------------------------------------------------
    def on_step(self, record):
        self.time = record.time
        for event in record.events:
            self.event(event)
        for decision in record.decisions:
            self.decision(decision)
        for cell in record.truth.cells:
            self.cell(cell)
        if self.checkpoint is not None and self.checkpoint.due():
            self.checkpoint.write(self)

    def earliest_open_event(self) -> float:
        """When the earliest detector event whose cell has not left yet happened (s; infinity: none)."""
        return min((event.time for event in self._events.values()), default=math.inf)

    def event(self, event):
        self._events[event.key] = event
        self._keys[event.event_id] = event.key

    def decision(self, decision):
        self._decisions[decision.event_id] = decision
        if decision.action == "sort":
            self._sorts[decision.event_id] = decision.arrival
        else:
            self._sorts.pop(decision.event_id, None)
        if len(self._sorts) > SORTS_KEPT:
            self._sorts = {e: t for e, t in self._sorts.items() if t >= self.time - SORT_HORIZON}

    def cell(self, cell):
        """A cell's truth: kept while it is in the channel, recorded once it has left."""
        if cell.fate == "in_channel":
            self._inside[cell.key] = cell
        else:
            self._inside.pop(cell.key, None)
            self._record(cell.key, cell)

    # --- records ----------------------------------------------------------------------------------------
    def _record(self, key: int, cell, partial: bool = False):
        if key < self._below or key in self._recorded:
            return
        self._recorded.add(key)
        while self._below in self._recorded:
            self._recorded.discard(self._below)
            self._below += 1
        event = self._events.pop(key, None)
        decision = self._decisions.pop(event.event_id, None) if event is not None else None
        arrival, name = self._arrivals[key]
        predicted = self.predicted_arrival(event) if event is not None else None
        record = cell_record(key, arrival, name, cell, event, decision, predicted, self.scenario, self._classes)
        if record["reason"]:
            record["reason"] = name_cells(record["reason"], self._keys)
        due = not partial or record["arrival_ms"] <= self.time * 1e3 or record["outlet"] != "not_injected"
        if due:
            self.tally.add(record)
            self.samples.add(record)
            self._due += 1
            if record["outcome"] == "co-deflected" and not self._covered(record["predicted_arrival_ms"]):
                self.unexpected += 1
        else:
            self._not_due += 1
        if self.table is not None:
            self.table.append(record)
        if self.checkpoint is not None:
            self.checkpoint.add(record)
        if self.keep is None or len(self.sample.admitted) <= self.keep:
            self.kept.append(record)

    def _record_not_due(self, keys: np.ndarray, times: np.ndarray, kinds: np.ndarray):
        """The cells of a partial run not yet due when it stopped (``keys``, their arrival ``times`` and type indices
        into the sample's names), recorded at once: their rows (``cell_record`` of a cell never injected, one per
        key) go to the table as columns; they are not counted, nor kept (a run longer than ``keep``). A run stopped
        early has most of its sample here: one row each would hold up its exit."""
        self._not_due += len(keys)
        if not len(keys):
            return
        from .celltable import flat
        names = [self.sample.admitted.names[kind] for kind in kinds.tolist()]
        classes = {name: true_class(self.scenario.cell_type(name)) for name in set(names)}
        columns = flat(cell_record(0, 0.0, names[0], None, None, None, None, self.scenario))   # the same in each
        columns.update(key=keys, type=names, true_class=[classes[name] for name in names], arrival_ms=times * 1e3)
        self.table.append_columns(columns, len(keys))

    def _covered(self, mine_ms) -> bool:
        """Whether a sort in effect had its predicted arrival within the widened window of ``mine_ms``."""
        if mine_ms is None:
            return False
        low, high = self.window_ms
        return any(mine_ms - high <= other * 1e3 <= mine_ms - low for other in self._sorts.values())

    def close(self):
        if self.table is not None:
            self.table.close()

    def summary(self, time: float, latencies, partial: bool = False) -> dict:
        """The run's summary at ``time`` (s): the cells still in the channel and those never injected recorded,
        statistics over the cells due (all of them unless ``partial``), the table closed.

        ``partial`` (a run interrupted, failed or cut short): the statistics count only the cells due by the time
        the run reached (admitted or turned away at the inlet by then); the sample's later cells never had their
        chance, and counting them (as "never injected", and in the yield's denominator) would understate every
        rate. Their number is ``not_yet_due``; the per-cell records still list every admitted cell, those not yet
        due with outcome ``not_injected``."""
        self.time = time
        for key in sorted(self._inside):
            self._record(key, self._inside[key], partial)
        self._inside = {}
        admitted = self.sample.admitted
        bulk = partial and self.table is not None and self.keep is not None and len(admitted) > self.keep
        below, done = self._below, np.array(sorted(self._recorded), dtype=np.int64)
        for start in range(below, len(admitted), STRETCH):            # the cells never injected, a stretch at a time
            keys = np.arange(start, min(start + STRETCH, len(admitted)))
            keys = keys[~np.isin(keys, done)]
            if bulk:
                times, kinds = admitted.arrays(start, start + STRETCH)
                later = times[keys - start] > time
                self._record_not_due(keys[later], times[keys[later] - start], kinds[keys[later] - start])
                keys = keys[~later]
            for key in keys.tolist():
                self._record(key, None, partial)
        self._below, self._recorded = len(admitted), set()
        self.close()
        settings, scenario = self.settings, self.scenario
        rejected = rejected_by(self.sample.rejected, time if partial else math.inf)
        stats = self.tally.statistics(time, rejected, scenario, self.unexpected if settings.controller else None)
        stats["not_yet_due"] = self._not_due + len(self.sample.rejected) - sum(rejected.values())
        stats["coincidence_possible"] = _coincidence_possible(settings)
        summary = {"statistics": stats, "yield_estimate": self.samples.estimate(scenario, settings),
                   "simulated_time_ms": time * 1e3, "model": settings.model, "seed": settings.seed,
                   "mesh": mesh_record(scenario), "controller_mode": settings.controller.mode,
                   "controller": _controller_record(settings.controller),
                   "controller_latency_us": _latency(latencies)}
        if self.keep is None or len(self.sample.admitted) <= self.keep:
            summary["cells"] = sorted(self.kept, key=lambda record: record["key"])
        if self.table is not None:
            summary["cell_table"] = {"path": str(self.table.path), "rows": self.table.written, "format": "parquet",
                                     "order": "as the cells left (sort by key for arrival order)"}
        return summary


def rejected_by(rejected, time: float) -> dict:
    """The cells ``rejected`` at the inlet by ``time`` (s), as {name: count}: counted by the sample
    (``sim.model.arrivals.Drawn`` or ``Cells``: running counts, so that a checkpoint's cost does not grow with the
    sample), else from (time, name) pairs."""
    if isinstance(rejected, (Drawn, Cells)):
        return rejected.counts(time)
    return dict(collections.Counter(name for at, name in rejected if at <= time))


def mesh_record(scenario) -> dict:
    """The mesh a run's flows are computed on: its size, squares and Taylor-Hood DOFs (``sim.model.mesh.MeshSize``)."""
    from sim.model.mesh import MeshSize
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


class ArrivalReader:
    """The arrival (time in s, type name) of an admitted cell by key, read from the sample ``ARRIVAL_BLOCK`` cells at a
    time where it gives arrays (``sim.model.arrivals.Drawn`` or ``Cells``: one look-up of the sample per block, not
    per cell), else by indexing it. The cells leave nearly in key order: the two blocks read last are kept."""

    def __init__(self, admitted, block: int = ARRIVAL_BLOCK):
        self.admitted, self.block = admitted, block
        self._arrays = getattr(admitted, "arrays", None) if isinstance(admitted, (Drawn, Cells)) else None
        self._blocks: dict = {}            # block index -> (times, names) as lists

    def __getitem__(self, key: int) -> tuple:
        if self._arrays is None or key < 0:
            return self.admitted[key]
        number, offset = divmod(key, self.block)
        block = self._blocks.get(number)
        if block is None:
            times, kinds = self._arrays(number * self.block, (number + 1) * self.block)
            names = self.admitted.names
            block = (times.tolist(), [names[kind] for kind in kinds.tolist()])
            if len(self._blocks) >= 2:
                del self._blocks[next(iter(self._blocks))]
            self._blocks[number] = block
        times, names = block
        if offset >= len(times):
            raise IndexError("cell index out of range")
        return times[offset], names[offset]


class RecentKeys:
    """The cells (keys) of the latest ``EVENT_NAMES`` detector events, by event id: a ring of two lists, set up
    whole at the start, so that what it holds does not depend on the run's length. Reads as a dict's ``get``; an
    event older than the latest ``EVENT_NAMES`` ids is not known."""

    def __init__(self, size: int | None = None):
        size = size or EVENT_NAMES
        self._events = [-1] * size
        self._keys = [0] * size
        self._filled = 0

    def __setitem__(self, event_id: int, key: int):
        slot = event_id % len(self._events)
        self._filled += self._events[slot] < 0
        self._events[slot], self._keys[slot] = int(event_id), int(key)

    def get(self, event_id: int, default=None):
        slot = event_id % len(self._events)
        return self._keys[slot] if self._events[slot] == event_id else default

    def __len__(self) -> int:
        return self._filled


def name_cells(text: str, keys_by_event) -> str:
    """``text`` with each ``event N`` followed by its cell, ``event N (cell K)`` (``?`` for an event not in
    ``keys_by_event``, a dict or ``RecentKeys``): the controller knows detector events, numbered in detection
    order, not cells (numbered in arrival order)."""
    return _EVENT.sub(lambda found: f"{found.group(0)} (cell {keys_by_event.get(int(found.group(1)), '?')})", text)


def cell_record(key, arrival, name, cell, event, decision, predicted_arrival, scenario, classes=None) -> dict:
    """A cell's record: its arrival (s) and type, its truth (None: never injected), its detector event and the
    controller's decision on it (or None), the predicted arrival at the SAW window (s). ``classes``: a dict the
    caller keeps of each type's true class, filled as types are met (None: looked up each time)."""
    if cell is None:
        outlet = "not_injected"
    else:
        outlet = cell.fate
    if classes is None:
        cell_class = true_class(scenario.cell_type(name))
    else:
        cell_class = classes.get(name)
        if cell_class is None:
            cell_class = classes[name] = true_class(scenario.cell_type(name))
    record = {
        "key": key, "type": name, "true_class": cell_class, "arrival_ms": arrival * 1e3,
        "event_id": event.event_id if event else None,
        "detected_class": event.classification if event else None,
        "detection_time_ms": event.time * 1e3 if event else None,
        "fluorescence": event.fluorescence if event else None,
        "scatter": event.scatter if event else None,
        "velocity_mm_s": event.velocity * 1e3 if event else None,
        "predicted_arrival_ms": predicted_arrival * 1e3 if event else None,
        "decision": decision.action if decision else None,
        "reason": decision.reason if decision and decision.reason else None,
        "pulse_ms": [decision.pulse_on * 1e3, decision.pulse_off * 1e3] if decision and decision.action == "sort"
        else None,
        "outlet": outlet,
        "exit_time_ms": cell.exit_time * 1e3 if cell and math.isfinite(cell.exit_time) else None,
        "exit_y_um": cell.exit_y * 1e6 if cell and math.isfinite(cell.exit_y) else None,
        "area_ratio": cell.area_ratio if cell else None,
        **(_shape_summary(cell.measures) if cell and cell.measures else _NO_SHAPE),
    }
    record["outcome"] = outcome_class(record)
    return record


def _controller_record(settings) -> dict:
    return {"mode": settings.mode, "delay_ms": settings.delay * 1e3, "reference_velocity_m_s":
            settings.reference_velocity, "lead_ms": settings.lead * 1e3, "pulse_ms": settings.pulse * 1e3,
            "envelope_ms": [v * 1e3 for v in settings.envelope], "timing_error_ms": settings.timing_error * 1e3,
            "enabled": settings.enabled}


_NO_SHAPE = {"area_ratio_range": None, "spacing_over_h": None, "area_corrected": None}


def _shape_summary(measures: dict | None) -> dict:
    """Area kept over the transit and the band of point spacings (FE-IB cells; None for point-like models)."""
    if not measures:
        return dict(_NO_SHAPE)
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
    tally = Tally()
    for cell in cells:
        tally.add(cell)
    has_outcomes = bool(cells) and "outcome" in cells[0]
    co_deflected = [c for c in cells if c["outcome"] == "co-deflected"] if has_outcomes else []
    return tally.statistics(simulated_time, rejected, scenario, _unexpected(co_deflected, cells, controller_settings))


class Tally:
    """The counts a sort report is made of, added one per-cell record at a time (memory: a few counters)."""

    COUNTS = ("cells", "events", "sorted", "sorted_out", "sorted_out_targets", "sorted_out_correct",
              "sorted_out_correct_targets", "sorted_out_detected_targets", "waste", "waste_detected",
              "waste_detected_targets", "waste_targets", "targets", "targets_sorted", "detected_targets", "aborts",
              "co_deflected", "misclassified", "undetected", "injected", "missed_decisions")

    def __init__(self):
        self.counts = dict.fromkeys(self.COUNTS, 0)
        self.outlets: dict[str, int] = {}
        self.outcomes: dict[str, int] = {}
        self.last_exit_ms: float | None = None
        self.restored = Restored()

    def add(self, cell: dict):
        count = self.counts
        target, detected, outlet = cell["true_class"] == TYPE_II, cell["detected_class"], cell["outlet"]
        count["cells"] += 1
        count["events"] += detected is not None
        count["sorted"] += cell["decision"] == "sort"
        count["aborts"] += cell["decision"] == "abort"
        count["missed_decisions"] += cell["decision"] == "missed"
        count["targets"] += target
        count["detected_targets"] += detected == TYPE_II
        count["misclassified"] += detected is not None and detected != cell["true_class"]
        # a cell still in the channel (an unfinished run) may not have reached the detector yet: not undetected
        count["undetected"] += detected is None and outlet not in ("not_injected", "in_channel")
        count["injected"] += outlet != "not_injected"
        if outlet == SORTED_OUTLET:
            count["sorted_out"] += 1
            count["sorted_out_targets"] += target
            count["targets_sorted"] += target
            count["sorted_out_detected_targets"] += detected == TYPE_II
            if detected == cell["true_class"]:
                count["sorted_out_correct"] += 1
                count["sorted_out_correct_targets"] += target
        elif outlet == DEFAULT_OUTLET:
            count["waste"] += 1
            count["waste_targets"] += target
            count["waste_detected"] += detected is not None
            count["waste_detected_targets"] += detected == TYPE_II
        self.outlets[outlet] = self.outlets.get(outlet, 0) + 1
        outcome = cell.get("outcome")
        if outcome is not None:
            self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1
            count["co_deflected"] += outcome == "co-deflected"
        self.restored.add(cell.get("key"), cell.get("area_corrected"))
        if cell["exit_time_ms"] is not None:
            self.last_exit_ms = max(self.last_exit_ms or cell["exit_time_ms"], cell["exit_time_ms"])

    def statistics(self, simulated_time: float, rejected=(), scenario=None, unexpected=None) -> dict:
        """The sort's figures; ``rejected``: the names of the cells turned away at the inlet, or {name: count}."""
        count = self.counts
        rejected = rejected if isinstance(rejected, dict) else collections.Counter(rejected)
        targets_rejected = sum(number for name, number in rejected.items()
                               if scenario is not None and scenario.cell_type(name).target)
        turned_away = sum(rejected.values())
        offered_targets = count["targets"] + targets_rejected
        last_exit = self.last_exit_ms
        stats = {
            "offered": count["cells"] + turned_away,
            "rejected_at_inlet": turned_away,
            "cells": count["cells"],
            "events": count["events"],
            "sorted": count["sorted"],
            "missed_decisions": count["missed_decisions"],
            "purity": _ratio(count["sorted_out_targets"], count["sorted_out"]),
            "purity_of_sorting": _ratio(count["sorted_out_correct_targets"], count["sorted_out_correct"]),
            "yield": _ratio(count["targets_sorted"], offered_targets),
            "abort_rate": _ratio(count["aborts"], count["detected_targets"]),
            "aborts": count["aborts"],
            "co_deflected": count["co_deflected"],
            "co_deflected_unexpected": unexpected,
            "misclassified": count["misclassified"],
            "undetected": count["undetected"],
            "not_injected": count["cells"] - count["injected"],
            "throughput_cells_per_s": count["injected"] / (last_exit * 1e-3) if last_exit else None,
            "event_rate_per_s": count["events"] / simulated_time if simulated_time > 0 else None,
            "outlets": dict(sorted(self.outlets.items())),
            "outcomes": dict(sorted(self.outcomes.items())),
        }
        stats["rare_cell"] = self.rare_cell(offered_targets, stats["offered"])
        stats["area_restored"] = self.restored.summary()
        return stats

    def rare_cell(self, offered_targets: int, offered: int) -> dict:
        """What a rare-cell sort's user reads (module docstring): enrichment, recovery (exact and estimated from
        the waste as a core facility does), purity with its 95 % Clopper-Pearson interval, events per target
        found."""
        count = self.counts
        found, sorted_out = count["sorted_out_targets"], count["sorted_out"]
        others_sorted = sorted_out - found
        input_ratio = _ratio(offered_targets, offered - offered_targets)
        enrichment = (found / others_sorted / input_ratio) if others_sorted and input_ratio else None
        # a facility re-analyses both tubes: the fraction gated as target in each, times the tube's count
        sorted_estimate = count["sorted_out_detected_targets"]
        waste_fraction = _ratio(count["waste_detected_targets"], count["waste_detected"])
        waste_estimate = waste_fraction * count["waste"] if waste_fraction is not None else None
        estimated = (_ratio(sorted_estimate, sorted_estimate + waste_estimate)
                     if waste_estimate is not None and sorted_estimate + waste_estimate > 0 else None)
        return {"target_fraction_offered": _ratio(offered_targets, offered), "enrichment": enrichment,
                "recovery": _ratio(found, found + count["waste_targets"]), "recovery_estimated": estimated,
                "purity_interval_95": purity_interval(found, sorted_out), "targets_found": found,
                "events_per_target_found": _ratio(count["events"], found)}


def _ratio(numerator, denominator):
    return numerator / denominator if denominator else None


def purity_interval(successes: int, trials: int, confidence: float = 0.95):
    """The Clopper-Pearson ("exact") interval of a binomial proportion, [low, high] (never narrower than its
    confidence promises, also for the few targets of a rare-cell sort); None without trials. The beta quantiles
    are scipy.special's (scipy.stats gives the same interval, ``binomtest(...).proportion_ci()``, but its import
    costs a run 1-2 s)."""
    if not trials:
        return None
    from scipy.special import betaincinv
    tail = (1.0 - confidence) / 2
    low = float(betaincinv(successes, trials - successes + 1, tail)) if successes else 0.0
    high = float(betaincinv(successes + 1, trials - successes, 1.0 - tail)) if successes < trials else 1.0
    return [low, high]


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
    samples = _TransitSamples()
    for cell in cells:
        samples.add(cell)
    return samples.estimate(scenario, settings)


class _TransitSamples:
    """Per cell type, the times from injection and from detection to the predicted arrival at the SAW window
    (s, of the detected cells among the sample's first ``TRANSIT_CELLS`` by key: their medians have long settled
    by then, and a longer run keeps no more), the cells of each type and the targets: what ``yield_estimate``
    needs, gathered a record at a time in any order (8 bytes a sampled cell per series)."""

    def __init__(self):
        self.transit: dict[str, array.array] = {}
        self.lookahead: dict[str, array.array] = {}
        self.types: dict[str, int] = {}
        self.targets = 0

    def add(self, cell: dict):
        name = cell["type"]
        self.types[name] = self.types.get(name, 0) + 1
        self.targets += cell["true_class"] == TYPE_II
        if cell["predicted_arrival_ms"] is not None and (cell.get("key") or 0) < TRANSIT_CELLS:
            for series, since in ((self.transit, "arrival_ms"), (self.lookahead, "detection_time_ms")):
                series.setdefault(name, array.array("d")).append((cell["predicted_arrival_ms"] - cell[since]) * 1e-3)

    def estimate(self, scenario, settings) -> dict | None:
        arrivals, controller = settings.arrivals, settings.controller
        transit = {name: statistics.median(values) for name, values in self.transit.items()}
        lookahead = {name: statistics.median(values) for name, values in self.lookahead.items()}
        types = [c for c in scenario.cell_types if c.name in transit]
        mix = _mix_fractions(arrivals, self.types)
        targets = [c for c in types if c.target and mix.get(c.name)]
        if not targets or not controller.enabled:
            return None
        low, high = controller.window(margin=SORTED_MODES.get(controller.mode, True))
        poisson = arrivals.process == "poisson"
        acceptance = 1.0 / (1.0 + arrivals.rate * arrivals.min_spacing) if poisson else 1.0
        total, weight = 0.0, 0.0
        for target in targets:
            # a neighbour detected after the target's pulse started cannot abort it: offsets beyond its look-ahead
            # (its detection-to-arrival time minus the lead) do not count
            counted = [(mix[other.name], transit[other.name] - transit[target.name],
                        min(high, lookahead[other.name] - controller.lead)) for other in types
                       if _counts(controller.mode, other)]
            keep = 1.0
            for side in (1, -1):       # neighbours injected after (+) and before (-) the target
                windows = [(share, *sorted((side * (low - shift), side * (top - shift))))
                           for share, shift, top in counted if top > low]
                keep *= _clear_probability(windows, arrivals)
            total += mix[target.name] * keep
            weight += mix[target.name]
        value = acceptance * total / weight
        n = self.targets / max(acceptance, 1e-12)
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


def _mix_fractions(arrivals, type_counts: dict) -> dict:
    """Each type's share: the sample's mix, else the shares counted in the run."""
    if arrivals.mix:
        total = sum(weight for _, weight in arrivals.mix)
        return {name: weight / total for name, weight in arrivals.mix}
    total = sum(type_counts.values())
    return {name: count / total for name, count in type_counts.items()}


def report_lines(result: dict, table_limit: int = 200) -> list[str]:
    """The summary as text: a table of cells (up to ``table_limit``), then the sort report."""
    lines = []
    cells = result.get("cells")
    if cells is None:
        table = (result.get("cell_table") or {}).get("path", "the per-cell table")
        lines.append(f"({result['statistics']['cells']} cells counted: one row per cell in {table} (Parquet), the "
                     "detector events in the FCS file)")
    elif len(cells) <= table_limit:
        lines.append(f"{'cell':>4}  {'type':<9} {'detected':>8}  {'decision':<8} {'outlet':<12} {'outcome':<13} "
                     f"{'exit (ms)':>9}  {'area kept (min-max)':<20} {'spacing / h':<11} restored")
        lines += [_cell_line(cell) for cell in cells]
    else:
        due = result["statistics"].get("cells", len(cells))
        counted = f", {due} of them due by the end and counted" if due != len(cells) else ""
        lines.append(f"({len(cells)} cells admitted{counted}: the table is in the JSON summary, --json, the per-cell "
                     "table and the FCS file)")
    lines += sort_report_lines(result)
    return lines


def _cell_line(cell) -> str:
    exit_ms = f"{cell['exit_time_ms']:9.3f}" if cell["exit_time_ms"] is not None else "        -"
    low_high = cell.get("area_ratio_range")
    area = f"{100 * low_high[0]:6.2f}-{100 * low_high[1]:6.2f} %" if low_high else "-"
    spacing = cell.get("spacing_over_h")
    band = f"{spacing[0]:.2f}-{spacing[1]:.2f}" if spacing else "-"
    restored = cell.get("area_corrected")
    restored = f"{100 * restored:.3f} %" if restored is not None else "-"
    return (f"{cell['key']:>4}  {cell['type']:<9} {cell['detected_class'] or '-':>8}  {cell['decision'] or '-':<8} "
            f"{cell['outlet']:<12} {cell.get('outcome', '-'):<13} {exit_ms}  {area:<20} {band:<11} {restored}")


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
        f"sort report ({_controller_words(result)}): {stats['offered']} offered, "
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
        *_rare_cell_lines(stats.get("rare_cell")),
        *_restored_lines(stats.get("area_restored")),
        f"simulated {result['simulated_time_ms']:.3f} ms (IDT on {result['idt_on_time_ms']:.3f} ms) in "
        f"{result['wall_time_s']:.1f} s wall ({result['model']} model: set-up {result['setup_time_s']:.1f} s, loop "
        f"{result['wall_time_s'] - result['setup_time_s']:.3g} s); "
        + _latency_line(result['controller_latency_us']),
    ]
    if "control" in result:
        from .control import timing_line
        lines.append(timing_line(result["control"]))
    if result.get("mesh"):
        lines.append(f"mesh: {result['mesh']['description']}")
    if (result.get("time_steps") or {}).get("levels_us"):
        from .studies.paper import time_step_line
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


__all__ = ["SortLedger", "statistics_of", "yield_estimate", "report_lines", "true_class", "DEFAULT_OUTLET"]


def _controller_words(result: dict) -> str:
    """The controller that ran: the built-in one with its mode, or a user's by its name."""
    name = result.get("controller_name", "built-in")
    mode = f"{result.get('controller_mode', '?')} mode"
    return mode if name == "built-in" else f"controller {name}"


def _rare_cell_lines(figures: dict | None) -> list[str]:
    """The figures a rare-cell sort is judged by (``Tally.rare_cell``), for a sample whose targets are rare."""
    if not figures or figures["target_fraction_offered"] is None or figures["target_fraction_offered"] > 0.05:
        return []
    interval = figures["purity_interval_95"]
    enrichment, per_target = figures["enrichment"], figures["events_per_target_found"]
    return [f"rare cells: targets {figures['target_fraction_offered']:.2g} of the sample, "
            f"{figures['targets_found']} found in the sorted outlet; enrichment "
            + (f"{enrichment:.3g}x" if enrichment is not None else "n/a (no other cell sorted)")
            + f"; recovery {_percent(figures['recovery'])} (estimated from the waste as a core facility does: "
            f"{_percent(figures['recovery_estimated'])}); purity 95 % interval "
            + (f"{100 * interval[0]:.1f}-{100 * interval[1]:.1f} %" if interval else "n/a")
            + (f"; {per_target:,.0f} events per target found" if per_target is not None else "")]


def _restored_lines(figures: dict | None) -> list[str]:
    """What the area projection restored (``vcyto.restored``), for runs whose cells have membranes."""
    if not figures:
        return []
    return [f"area restored by the projection over a transit: largest {100 * figures['largest']:.3f} % of the initial "
            f"area (cell {figures['cell']}); {figures['cells_over_limit']} cells over {100 * figures['limit']:g} %"]


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
