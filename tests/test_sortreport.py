"""The sort report built as cells leave: the per-cell table, aggregates equal to those recomputed from it, the
rare-cell figures, and a summary that names the table instead of listing a long run's cells."""

import math

import numpy as np
import pytest

from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario
from vcyto import celltable, sortreport
from vcyto.stream import StreamSettings, run_stream, statistics_of


@pytest.fixture(scope="module")
def rom_plant():
    from sim.plants.registry import build
    return build("rom", Scenario())


@pytest.fixture(scope="module")
def long_run(rom_plant, tmp_path_factory):
    """A dense rom sort (aborts, co-deflections) whose cells outnumber what a summary lists."""
    table = tmp_path_factory.mktemp("table") / "run.cells.parquet"
    arrivals = Arrivals(count=1500, mix=(("RBC", 0.7), ("melanoma", 0.3)), rate=4000.0, process="poisson",
                        min_spacing=20e-6)
    settings = StreamSettings(arrivals, model="rom", seed=11)
    keep = sortreport.KEEP_CELLS
    sortreport.KEEP_CELLS = 1000               # the summary lists no cells beyond this (here: 1,500 offered)
    try:
        result = run_stream(Scenario(), settings, plant=rom_plant, table=table)
    finally:
        sortreport.KEEP_CELLS = keep
    return result, table, settings


def test_every_admitted_cell_has_one_row_and_the_aggregates_are_the_tables(long_run):
    result, table, settings = long_run
    frame = celltable.read_table(table).to_pandas()
    assert result["cell_table"]["rows"] == len(frame) == result["statistics"]["cells"] > 1000
    assert sorted(frame["key"]) == list(range(len(frame)))
    records = [celltable.record_of(row) for row in frame.to_dict("records")]
    for record in records:                                  # pandas gives NaN for null numbers
        record.update({k: None for k, v in record.items() if isinstance(v, float) and math.isnan(v)})
    records.sort(key=lambda r: r["key"])
    from sim.model.arrivals import offer
    rejected = [name for _, name in offer(settings.arrivals, np.random.default_rng(settings.seed).spawn(2)[0]).rejected]
    recomputed = statistics_of(records, result["simulated_time_ms"] * 1e-3, rejected=rejected, scenario=Scenario(),
                               controller_settings=settings.controller)
    stats = dict(result["statistics"])
    assert stats["rejected_at_inlet"] == len(rejected) > 0
    assert stats.pop("event_rate_per_s") == pytest.approx(recomputed.pop("event_rate_per_s"), rel=1e-12)
    for key in ("not_yet_due", "coincidence_possible"):
        stats.pop(key)
    assert stats == recomputed
    assert stats["aborts"] > 0 and stats["co_deflected"] > 0          # the dense sort exercises them
    estimate = sortreport.yield_estimate(records, Scenario(), settings)
    assert estimate == result["yield_estimate"]


def test_a_long_runs_summary_names_its_table_and_lists_no_cells(long_run):
    result, table, _ = long_run
    assert "cells" not in result and result["cell_table"]["path"] == str(table)
    lines = sortreport.report_lines(result)
    assert str(table) in lines[0] and any(line.startswith("purity") for line in lines)


def test_a_pandas_and_pyarrow_reader_see_the_same_table(long_run):
    _, table, _ = long_run
    frame = celltable.read_table(table).to_pandas()
    assert set(frame["outcome"]) <= {"sorted", "passed", "aborted", "missed", "misclassified", "co-deflected",
                                     "lost", "not_injected", "unfinished"}
    streamed = list(celltable.records(table, batch_rows=100))
    assert [r["key"] for r in streamed] == frame["key"].tolist()


def test_rare_cell_figures_by_hand():
    """Enrichment, both recoveries, the purity interval and events per target from counts made by hand."""
    def cell(target, detected, outlet, decision="pass"):
        return {"true_class": "II" if target else "I", "detected_class": detected, "outlet": outlet,
                "decision": decision, "exit_time_ms": 1.0, "outcome": None}
    cells = ([cell(True, "II", "upper", "sort")] * 8 + [cell(False, "II", "upper", "sort")] * 2        # sorted tube
             + [cell(True, "II", "lower")] * 2 + [cell(False, "I", "lower")] * 9988)                    # waste tube
    tally = sortreport.Tally()
    for c in cells:
        tally.add(c)
    figures = tally.statistics(1.0)["rare_cell"]
    assert figures["target_fraction_offered"] == pytest.approx(10 / 10000)
    assert figures["enrichment"] == pytest.approx((8 / 2) / (10 / 9990))
    assert figures["recovery"] == pytest.approx(8 / 10)
    # re-analysis: 10 gated as targets in the sorted tube, 2 of 9990 in the waste
    assert figures["recovery_estimated"] == pytest.approx(10 / (10 + 2 / 9990 * 9990))
    from scipy.stats import binomtest
    exact = binomtest(8, 10).proportion_ci(confidence_level=0.95, method="exact")
    assert figures["purity_interval_95"] == pytest.approx([exact.low, exact.high], rel=1e-9)
    assert figures["events_per_target_found"] == pytest.approx(10000 / 8)


def test_a_rare_cell_sort_reports_its_figures(rom_plant):
    """A sample with targets at 2e-3 (forced to hold some): the report's rare-cell line with the interval."""
    settings = StreamSettings(Arrivals(count=3000, mix=(("RBC", 0.998), ("melanoma", 0.002)), rate=1000.0,
                                       process="poisson"), model="rom", seed=5)
    result = run_stream(Scenario(), settings, plant=rom_plant)
    stats = result["statistics"]
    figures = stats["rare_cell"]
    assert figures["targets_found"] >= 1 and figures["target_fraction_offered"] < 0.01
    assert figures["enrichment"] is None or figures["enrichment"] > 50
    assert figures["recovery"] >= stats["yield"]                # the yield also counts targets turned away
    low, high = figures["purity_interval_95"]
    assert low <= stats["purity"] <= high
    assert figures["events_per_target_found"] == stats["events"] / figures["targets_found"]
    line = next(line for line in sortreport.report_lines(result) if line.startswith("rare cells"))
    assert "events per target found" in line and "interval" in line


def test_the_fcs_of_a_long_run_is_read_from_its_table(long_run):
    """A summary without cells: the FCS events come from the table, the same as from the records."""
    from vcyto.recording.fcs import event_table
    result, table, _ = long_run
    records = sorted(celltable.records(table), key=lambda r: r["key"])
    assert np.array_equal(event_table(result), event_table({"cells": records}))
    assert len(event_table(result)) == result["statistics"]["events"]


def test_the_cells_not_yet_due_when_a_long_run_stops_have_the_rows_one_by_one_would_give(rom_plant, tmp_path):
    """A run stopped early has most of its sample not yet due: their rows are written together (a long run's
    exit would wait on a row each), and are the rows the per-record path writes."""
    arrivals = Arrivals(count=1500, mix=(("RBC", 0.7), ("melanoma", 0.3)), rate=2000.0)
    settings = StreamSettings(arrivals, model="rom", seed=3, max_time=40e-3)
    keep, tables = sortreport.KEEP_CELLS, {}
    try:
        for kept in (1000, None):              # 1000: fewer than the sample (rows together); None: one by one
            sortreport.KEEP_CELLS = kept
            tables[kept] = tmp_path / f"{kept}.cells.parquet"
            result = run_stream(Scenario(), settings, plant=rom_plant, table=tables[kept])
            assert result["status"] == "truncated" and result["statistics"]["not_yet_due"] > 1000
    finally:
        sortreport.KEEP_CELLS = keep
    together, one_by_one = (sorted(celltable.read_table(tables[k]).to_pylist(), key=lambda row: row["key"])
                            for k in (1000, None))
    assert len(together) == 1500 and together == one_by_one


def test_the_fcs_events_of_a_long_run_read_from_its_table_are_those_of_its_cells(long_run):
    from vcyto.recording import fcs
    result, table, _ = long_run
    cells = list(celltable.records(table))
    from_table = fcs.event_table(result)
    assert "cells" not in result and len(from_table) == result["statistics"]["events"] > 1000
    np.testing.assert_array_equal(from_table, fcs.event_table({"cells": cells}))


@pytest.mark.parametrize("kind", ["drawn", "cells", "list"])
def test_the_arrival_reader_reads_what_indexing_the_sample_gives(kind):
    """``ArrivalReader`` (blocks of arrays) gives each key the (time, name) that indexing the sample gives, in the
    nearly sorted order cells leave in and in any other, across blocks and the sample's chunks; a key past the end
    is refused."""
    from sim.model.arrivals import Cells, offer
    sample = offer(Arrivals(count=3000, mix=(("RBC", 0.8), ("melanoma", 0.2)), rate=2000.0, process="poisson"),
                   np.random.default_rng(5), chunk=700).admitted
    if kind == "cells":
        sample = Cells(*sample.arrays(0, len(sample)), sample.names)
    elif kind == "list":
        sample = list(sample)
    reader = sortreport.ArrivalReader(sample, block=256)
    rng = np.random.default_rng(1)
    leaving = np.argsort(np.arange(len(sample)) + rng.normal(0, 40, len(sample)))     # a few overtake others
    for key in [*leaving.tolist(), *rng.permutation(len(sample)).tolist()]:
        assert reader[key] == sample[key]
    assert len({reader[key][1] for key in range(len(sample))}) == 2
    with pytest.raises(IndexError):
        reader[len(sample)]


def test_the_cell_table_keeps_columns_that_make_the_rows_of_flat_records(tmp_path):
    """The table's rows (kept as columns, written a row group at a time) are ``flat`` of each record: pairs split,
    a name missing or None null, across row groups and a write of columns between rows."""
    import pyarrow as pa
    records = [{"key": k, "type": "RBC", "true_class": "I", "arrival_ms": 0.5 * k,
                "decision": "sort" if k % 3 else None, "pulse_ms": [k, k + 0.4] if k % 3 else None,
                "area_ratio_range": [0.99, 1.0] if k % 2 else None, "outlet": "upper",
                "exit_time_ms": None if k % 5 else 2.0 * k, "outcome": "sorted"}
               for k in range(23)]
    records[4] = {"key": 4}                                   # a record with most names missing
    table = celltable.CellTable(tmp_path / "t.parquet", rows_per_group=5)
    for record in records[:12]:
        table.append(record)
    table.append_columns({"key": np.array([100, 101]), "type": "RBC", "outlet": "not_injected"}, 2)
    for record in records[12:]:
        table.append(record)
    table.close()
    written = celltable.read_table(tmp_path / "t.parquet")
    expected = pa.Table.from_pylist([celltable.flat(r) for r in records[:12]]
                                    + [{"key": k, "type": "RBC", "outlet": "not_injected"} for k in (100, 101)]
                                    + [celltable.flat(r) for r in records[12:]], schema=celltable.SCHEMA)
    assert table.written == 25 and written.equals(expected)
    assert written["pulse_on_ms"].to_pylist()[:3] == [None, 1.0, 2.0]
