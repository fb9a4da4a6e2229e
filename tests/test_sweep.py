"""vcyto sweep: spec parsing, one-line errors, local pool == Dask LocalCluster, resume after a kill, failed points,
interrupts (SIGINT/SIGTERM to the main process alone), the record of the runs kept by a re-run."""

import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from vcyto import outputs, sweep
from vcyto.cli import main
from vcyto.outputs import strict_json
from vcyto.recording import runfiles
from vcyto.sweep.run import _chunks, report_lines

# the cheap plant on a coarse mesh (1.5 s to build); a few cells per point so the metrics vary
BASE = {"model": "streamline", "mesh_h": "5um"}


def vcyto(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "vcyto.cli", *args], capture_output=True, text=True, timeout=timeout)


def write_spec(path, text):
    path.write_text(text)
    return str(path)


def read_rows(path):
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


def values(spec):
    return [dict(point.values) for point in sweep.parse_sweep(spec).points]


# --- the spec -----------------------------------------------------------------------------------


def test_grid_is_every_combination_of_lists_and_ranges_in_spec_order():
    spec = {"base": BASE, "parameters": {"lead": [0.25, 0.5], "pulse": {"start": 0.4, "stop": 1.6, "num": 4},
                                         "seed": {"start": 3, "stop": 9, "step": 3}}}
    points = values(spec)
    assert len(points) == 2 * 4 * 3
    assert points[0] == {"lead": 0.25, "pulse": 0.4, "seed": 3}
    assert points[1] == {"lead": 0.25, "pulse": 0.4, "seed": 6}
    assert sorted({p["pulse"] for p in points}) == [0.4, 0.8, 1.2, 1.6]      # both ends, rounded: not 0.8000000001
    assert sorted({p["seed"] for p in points}) == [3, 6, 9] and all(isinstance(p["seed"], int) for p in points)


def test_ranges_take_units_for_scenario_fields_and_log_spacing():
    spec = {"base": BASE, "parameters": {"saw.streaming_force": {"start": 1e6, "stop": 1e8, "num": 3, "log": True},
                                         "channel": {"inlets": {"1": {"v_hat": {"start": "0.02", "stop": "0.03",
                                                                                "step": "0.005"}}}}}}
    built = sweep.parse_sweep(spec)
    assert [p.name for p in built.parameters] == ["saw.streaming_force", "channel.inlets.1.v_hat"]
    assert built.parameters[0].values == (1e6, 1e7, 1e8)
    assert built.parameters[1].values == (0.02, 0.025, 0.03)
    forces = sorted({point.scenario.saw.streaming_force for point in built.points})
    assert forces == [1e6, 1e7, 1e8]
    assert sorted({point.scenario.channel.inlets[1].v_hat for point in built.points}) == [0.02, 0.025, 0.03]


def test_stream_options_reach_the_settings_in_their_command_line_units():
    spec = {"base": {**BASE, "cells": ["melanoma", "RBC"], "mode": "yield"},
            "parameters": {"lead": [0.3], "noise": [0.4], "rate": [800], "saw_model": ["streaming"]}}
    point = sweep.parse_sweep(spec).points[0]
    assert point.settings.controller.lead == pytest.approx(0.3e-3) and point.settings.controller.mode == "yield"
    assert point.settings.detector.noise_cv == 0.4 and point.settings.arrivals.rate == 800.0
    assert point.settings.arrivals.cells == ("melanoma", "RBC") and point.settings.model == "streamline"
    assert point.scenario.saw.model == "streaming" and point.scenario.numerics.mesh_h == pytest.approx(5e-6)


def test_random_sampling_is_determined_by_its_seed_and_stays_in_bounds():
    def spec(seed):
        return {"base": {**BASE, "mix": "RBC:0.5,melanoma:0.5", "min_spacing": 0.05},
                "sweep": {"sampling": "random", "samples": 12, "sampling_seed": seed},
                "parameters": {"lead": {"uniform": [0.1, 0.9]}, "rate": {"log_uniform": [100, 10000]},
                               "count": {"integers": [2, 4]}, "mode": ["purity", "yield"]}}
    first, again, other = values(spec(7)), values(spec(7)), values(spec(8))
    assert first == again and first != other and len(first) == 12
    assert all(0.1 <= p["lead"] <= 0.9 and 100 <= p["rate"] <= 10000 for p in first)
    assert {p["count"] for p in first + other} == {2, 3, 4} and {p["mode"] for p in first} == {"purity", "yield"}


def test_a_point_is_identified_by_its_effective_inputs():
    def ids(parameters, base=BASE):
        return [point.id for point in sweep.parse_sweep({"base": base, "parameters": parameters}).points]
    first = ids({"lead": [0.25, 0.5], "saw.streaming_force": [5.7e7]})
    assert first == ids({"lead": [0.25, 0.5], "saw.streaming_force": [5.7e7]})     # stable
    assert len(set(first)) == 2
    assert ids({"lead": [0.25], "saw.streaming_force": ["57000000"]})[0] == first[0]  # same value, other spelling
    assert ids({"lead": [0.25], "saw.streaming_force": [5.7e7]}, {**BASE, "seed": 1})[0] != first[0]


def test_points_sharing_a_plant_are_chunked_at_most_an_even_share_per_worker():
    built = sweep.parse_sweep({"base": BASE, "parameters": {"saw.streaming_force": [1e7, 2e7],
                                                            "lead": [0.1, 0.2, 0.3, 0.4, 0.5]}})
    chunks = _chunks(list(built.points), slots=2, chunk=8)
    assert [len(chunk) for chunk in chunks] == [3, 2, 3, 2]
    assert all(len({point.plant_key for point in chunk}) == 1 for chunk in chunks)
    assert [len(chunk) for chunk in _chunks(list(built.points), slots=1, chunk=4)] == [4, 1, 4, 1]


@pytest.mark.parametrize("text, words", [
    ("[parameters]\nleed = [1, 2]", ["parameters.leed: unknown parameter", "lead", "saw.streaming_force"]),
    ("[parameters]\nsaw.streaming_forc = [1, 2]", ["saw.streaming_forc: unknown field", "streaming_force"]),
    ("[parameters]\nlead = {start = 1, stop = 0, step = 0.1}", ["parameters.lead: empty range"]),
    ("[parameters]\nlead = {start = 0, stop = 1, num = 0}", ["parameters.lead.num: empty range"]),
    ("[parameters]\nlead = []", ["parameters.lead: empty list"]),
    ("[parameters]\nlead = [1]\n[sweep]\nmetrics = ['yeld']", ["unknown metric 'yeld'", "purity"]),
    ("[parameters]\nrate = [100, -5]", ["parameters.rate: must be positive", "-5"]),
    ("[parameters]\nlead = {uniform = [0, 1]}", ['needs sampling = "random"']),
    ("[base]\nmodel = 'nonsense'\n[parameters]\nlead = [1]", ["base.model: must be one of", "streamline"]),
    ("[parameters]\nlead = [", ["is not valid TOML"]),
    ("[base]\nlead = '3um'\n[parameters]\nseed = [1]", ["base.lead: '3um' is a length, but base.lead is a time"]),
])
def test_bad_specs_are_one_line_exit_2_no_traceback(tmp_path, text, words):
    result = vcyto("sweep", write_spec(tmp_path / "spec.toml", text), "--output", str(tmp_path / "out"))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vcyto: error: "), result.stderr
    assert all(word in lines[0] for word in words), lines[0]


def test_scheduler_without_dask_says_how_to_install_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)           # import distributed -> ImportError
    spec = write_spec(tmp_path / "spec.toml", "[base]\nmodel = 'streamline'\n[parameters]\nlead = [0.5]")
    assert main(["sweep", spec, "--scheduler", "local", "--output", str(tmp_path / "out")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "pip install 'vcyto[cluster]'" in lines[0]


def test_a_table_of_another_sweep_is_refused(tmp_path):
    table = tmp_path / "results.csv"
    table.write_text("point,status,rate,seed,yield,wall_time_s,error\n")
    with pytest.raises(sweep.SweepError, match="different sweep"):
        sweep.ResultTable(table, ["point", "status", "lead", "seed", "yield", "wall_time_s", "error"]).load()


# --- running ------------------------------------------------------------------------------------

COMPARED_SPEC = """
[base]
model = "streamline"
mesh_h = "5um"
count = 6
mix = {RBC = 0.5, melanoma = 0.5}
arrivals = "poisson"
rate = 2000
min_spacing = 0.2

[parameters]
lead = [0.0, 0.5]
seed = [1, 2, 3]

[sweep]
metrics = ["yield", "purity", "abort_rate", "melanoma.upper", "outlets", "simulated_time_ms"]
"""


def test_local_pool_and_dask_local_cluster_give_identical_results(tmp_path):
    spec = write_spec(tmp_path / "compared.toml", COMPARED_SPEC)
    local = vcyto("sweep", spec, "--output", str(tmp_path / "local"), "--workers", "2", "--json")
    dask = vcyto("sweep", spec, "--output", str(tmp_path / "dask"), "--scheduler", "local", "--workers", "2", "--json")
    assert local.returncode == 0 and dask.returncode == 0, local.stderr + dask.stderr
    assert "cluster" in json.loads(dask.stdout)["executor"] and "local process" in json.loads(local.stdout)["executor"]

    def table(name):
        return [{key: value for key, value in row.items() if key != "wall_time_s"}
                for row in read_rows(tmp_path / name / "results.csv")]
    rows = table("local")
    assert len(rows) == 6 and all(row["status"] == "ok" for row in rows)
    assert len({(row["outlets"], row["simulated_time_ms"]) for row in rows}) > 1      # the points do differ
    assert table("dask") == rows
    assert (tmp_path / "local" / "summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


KILLED_SPEC = """
[base]
model = "streamline"
mesh_h = "5um"
count = 40
mix = {RBC = 0.7, melanoma = 0.3}
rate = 800

[parameters]
seed = {start = 0, stop = 9, step = 1}

[sweep]
metrics = ["yield", "outlet.upper"]
"""


def _sweep_with_rows(spec, output, workers: int, rows: int, *options) -> subprocess.Popen:
    """``vcyto sweep SPEC`` started in a session of its own, returned once its table has ``rows`` rows."""
    table = output / "results.csv"
    command = [sys.executable, "-m", "vcyto.cli", "sweep", spec, "--output", str(output), "--workers", str(workers),
               "--chunk", "1", "--quiet", *options]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None and (
            not table.exists() or len(read_rows(table)) < rows):
        time.sleep(0.02)
    return process


def test_killing_a_sweep_and_rerunning_it_completes_only_the_missing_points(tmp_path):
    spec, output = write_spec(tmp_path / "killed.toml", KILLED_SPEC), tmp_path / "out"
    table = output / "results.csv"
    process = _sweep_with_rows(spec, output, workers=1, rows=3)
    os.killpg(process.pid, signal.SIGKILL)           # the sweep, its worker and their helpers: one session
    process.wait()
    before = read_rows(table)
    assert 3 <= len(before) < 10, "the sweep was not killed half-way"
    rerun = vcyto("sweep", spec, "--output", str(output), "--workers", "1", "--json")
    assert rerun.returncode == 0, rerun.stderr
    summary = json.loads(rerun.stdout)
    assert summary["ran"] == 10 - len(before) and summary["done_before"] == len(before)
    after = read_rows(table)
    assert sorted(int(row["seed"]) for row in after) == list(range(10))
    by_point = {row["point"]: row for row in after}
    assert all(by_point[row["point"]] == row for row in before)      # same wall time: not run again

    lines = table.read_text().splitlines(keepends=True)             # a row lost, the last one torn mid-write
    table.write_text("".join(lines[:3] + lines[4:-1]) + lines[-1][:12])
    again = json.loads(vcyto("sweep", spec, "--output", str(output), "--workers", "1", "--json").stdout)
    assert again["ran"] == 2 and again["repaired_rows"] == 1 and again["ok"] == 10
    assert len(read_rows(table)) == 10 and (output / "summary.png").exists()


def _descendants(pid: int) -> set[int]:
    """The processes whose parent chain leads to ``pid`` (read from /proc), and those of its session."""
    parents, sessions = {}, {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            parents[int(entry.name)], sessions[int(entry.name)] = int(fields[1]), int(fields[3])
    found, grown = {p for p, session in sessions.items() if session == pid}, True
    while grown:
        more = {p for p, parent in parents.items() if parent in found | {pid}} - found
        found |= more
        grown = bool(more)
    return found - {pid}


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
@pytest.mark.parametrize("options", [(), ("--scheduler", "local")], ids=["process pool", "dask local cluster"])
def test_a_sweep_killed_with_sigkill_leaves_no_process_behind(tmp_path, options):
    """SIGKILL to the sweep's own process alone (it can stop nothing): its workers (a process pool's and its
    resource tracker, or a Dask local cluster's nannies and workers) end within a few seconds, not holding their
    memory for ever."""
    spec = write_spec(tmp_path / "killed.toml", KILLED_SPEC)
    process = _sweep_with_rows(spec, tmp_path / "out", 2, 1, *options)
    try:
        helpers = _descendants(process.pid)
        assert len(helpers) >= 2, "the sweep's workers did not start"
        process.kill()                                # the parent alone
        process.wait()
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and _descendants(process.pid):
            time.sleep(0.1)
        left = _descendants(process.pid)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)       # whatever is left, so that the test run is not burdened
    assert not left, f"processes of the killed sweep still running: {sorted(left)}"


def fail_at_lead_0_75(scenario, settings):
    """A closed loop that raises for one point (lead 0.75 ms), the real one for the others."""
    if settings.controller.lead == pytest.approx(0.75e-3):
        raise RuntimeError("the IDT driver\nbroke")
    return sweep.simulate(scenario, settings)


def test_a_point_that_raises_is_recorded_as_failed_and_the_others_finish(tmp_path):
    built = sweep.parse_sweep({"base": {**BASE, "cells": "melanoma,RBC"},
                               "parameters": {"lead": [0.25, 0.5, 0.75, 1.0]}, "sweep": {"metrics": ["yield"]}})
    with sweep.executor(None, 2) as (pool, slots, _):
        result = sweep.run_sweep(built, tmp_path, pool, slots, chunk=1, simulator=fail_at_lead_0_75)
    rows = {float(row["lead"]): row for row in read_rows(tmp_path / "results.csv")}
    assert result["failed"] == 1 and result["ok"] == 3
    assert rows[0.75]["status"] == "failed" and rows[0.75]["error"] == "RuntimeError: the IDT driver broke"
    assert all(rows[lead]["status"] == "ok" and rows[lead]["yield"] in ("0.0", "1.0") for lead in (0.25, 0.5, 1.0))
    with sweep.executor(None, 1) as (pool, slots, _):
        kept = sweep.run_sweep(built, tmp_path, pool, slots, simulator=fail_at_lead_0_75)
        retried = sweep.run_sweep(built, tmp_path, pool, slots, simulator=fail_at_lead_0_75, retry_failed=True)
    assert kept["ran"] == 0 and kept["failed"] == 1
    assert retried["ran"] == 1 and retried["failed"] == 1 and len(read_rows(tmp_path / "results.csv")) == 4


def dies_at_rate_750(scenario, settings):
    """A worker process that dies (out of memory, killed) at the rate-750 point; the stand-in loop elsewhere."""
    if settings.arrivals.rate == 750:
        os._exit(9)
    return fixed_result(scenario, settings)


def test_a_worker_that_dies_fails_the_points_it_takes_down_and_the_sweep_finishes(tmp_path):
    """The pool is broken once a worker dies: the points it was running and those submitted after it become
    failed rows ("the worker ... died"), the others are kept, and the sweep ends with its summary."""
    rates = [250, 500, 750, 1000, 1250, 1500]
    built = sweep.parse_sweep({"base": BASE, "parameters": {"rate": rates}, "sweep": {"metrics": ["yield"]}})
    with sweep.executor(None, 1) as (pool, slots, _):
        result = sweep.run_sweep(built, tmp_path, pool, slots, chunk=1, simulator=dies_at_rate_750)
    rows = {float(row["rate"]): row for row in read_rows(tmp_path / "results.csv")}
    assert sorted(rows) == rates and result["ok"] + result["failed"] == len(rates)
    assert rows[250]["status"] == rows[500]["status"] == "ok" and rows[750]["status"] == "failed"
    assert all("died" in row["error"] for row in rows.values() if row["status"] == "failed")


class Interrupted:
    """An executor that is interrupted (Ctrl-C) as soon as work is submitted."""

    def submit(self, *call):
        raise KeyboardInterrupt


def test_a_record_whose_rows_are_gone_is_dropped_when_a_run_starts_even_if_it_is_interrupted(tmp_path):
    """Run A records itself; its results.csv is removed; run B starts from no rows and is interrupted; run C
    completes: the record holds C alone, never A's time for rows that no longer exist."""
    built = sweep.parse_sweep({"base": BASE, "parameters": {"rate": [500, 1000]}, "sweep": {"metrics": ["yield"]}})
    with sweep.executor(None, 1) as (pool, slots, _):
        first = sweep.run_sweep(built, tmp_path, pool, slots, simulator=fixed_result)
    (tmp_path / "sweep.json").write_text(strict_json(first))
    (tmp_path / "results.csv").unlink()
    with pytest.raises(KeyboardInterrupt):
        sweep.run_sweep(built, tmp_path, Interrupted(), 1, simulator=fixed_result)
    assert not (tmp_path / "sweep.json").exists()
    with sweep.executor(None, 1) as (pool, slots, _):
        third = sweep.run_sweep(built, tmp_path, pool, slots, simulator=fixed_result)
    assert len(third["runs"]) == 1 and third["wall_time_s"] == third["run_wall_time_s"]


def fixed_result(scenario, settings):
    """A closed loop stand-in: numbers that depend on the rate, an undefined purity (NaN), an outlet count."""
    rate = settings.arrivals.rate
    return {"statistics": {"yield": rate / 1000, "purity": float("nan"), "aborts": 3,
                           "outlets": {"lower": 4, "upper": 2}},
            "cells": [], "simulated_time_ms": 2.5}


def test_a_rerun_reading_the_table_reports_the_same_types_as_the_run_that_wrote_it(tmp_path):
    built = sweep.parse_sweep({"base": BASE, "parameters": {"rate": [500, 1000], "lead": [0.25]},
                               "sweep": {"metrics": ["yield", "purity", "aborts", "outlets", "simulated_time_ms"]}})
    with sweep.executor(None, 1) as (pool, slots, _):
        first = sweep.run_sweep(built, tmp_path, pool, slots, simulator=fixed_result)
        second = sweep.run_sweep(built, tmp_path, pool, slots, simulator=fixed_result)
    assert first["ran"] == 2 and second["ran"] == 0
    assert second["highest"]["rate"] == 1000 and isinstance(second["highest"]["yield"], float)
    for key in ("highest", "rows"):             # numbers as numbers, NaN as null, text as text, in both runs
        assert strict_json(second[key]) == strict_json(first[key])
    assert json.loads(strict_json(second["rows"]))[0]["purity"] is None


def test_the_progress_bar_counts_truncated_points_apart_from_failed_ones():
    from vcyto.sweep.run import _Tracker, report_lines
    notes = []

    class Recorder:
        interval = 1.0

        def note(self, message):
            notes.append(message)

        def update(self, message):
            notes.append(message)

    tracker = _Tracker(3, 0, Recorder())
    tracker.finished([{"point": 0, "status": "truncated", "error": "max_time"},
                      {"point": 1, "status": "failed", "error": "blow-up"}, {"point": 2, "status": "ok"}])
    assert "3/3 points, 1 failed, 1 truncated" in tracker.bar()
    counts = {"points": 2, "ok": 2, "failed": 0, "truncated": 0, "ran": 2, "done_before": 0, "wall_time_s": 1.0,
              "repaired_rows": 0, "stale_rows": 0, "highest": None, "files": {}, "rows": []}
    assert "raise max_time" not in report_lines(counts)[0]
    assert "raise max_time" in report_lines({**counts, "ok": 1, "truncated": 1})[0]


# --- the record of the runs: a re-run that computes nothing keeps it ---------------------------------------


def run_as_the_command_does(built, output, **options):
    """``run_sweep`` on a thread, then ``sweep.json`` written as ``vcyto sweep`` writes it."""
    with ThreadPoolExecutor(1) as pool:
        result = sweep.run_sweep(built, output, pool, 1, simulator=fixed_result, **options)
    outputs.write_into(output / sweep.SUMMARY, strict_json(result) + "\n")
    return result


def test_a_rerun_keeps_the_record_of_the_runs_that_computed_the_table(tmp_path):
    built = sweep.parse_sweep({"base": BASE, "parameters": {"rate": [500, 1000, 2000]},
                               "sweep": {"metrics": ["yield"]}})
    first = run_as_the_command_does(built, tmp_path)
    assert first["ran"] == 3 and not first["already_done"] and len(first["runs"]) == 1
    assert first["wall_time_s"] == first["run_wall_time_s"] == first["runs"][0]["wall_time_s"] > 0

    again = run_as_the_command_does(built, tmp_path)                   # nothing to do
    assert again["ran"] == 0 and again["already_done"]
    assert again["runs"] == json.loads(strict_json(first["runs"]))      # the record of the run that did the work
    assert again["wall_time_s"] == pytest.approx(first["wall_time_s"])
    assert "every point was already done: nothing ran" in report_lines(again)[0]
    assert json.loads((tmp_path / sweep.SUMMARY).read_text())["wall_time_s"] == pytest.approx(first["wall_time_s"])

    table = sweep.ResultTable(tmp_path / sweep.RESULTS, built.columns)   # a point lost: the next run completes it
    table.rewrite(list(table.load().values())[:2])
    completed = run_as_the_command_does(built, tmp_path)
    assert completed["ran"] == 1 and completed["done_before"] == 2 and len(completed["runs"]) == 2
    assert completed["wall_time_s"] == pytest.approx(first["wall_time_s"] + completed["run_wall_time_s"])
    assert "over 2 runs in all" in report_lines(completed)[0]


def test_a_sweep_json_of_an_older_vcyto_gives_its_one_run(tmp_path):
    built = sweep.parse_sweep({"base": BASE, "parameters": {"rate": [500, 1000]}, "sweep": {"metrics": ["yield"]}})
    run_as_the_command_does(built, tmp_path)
    (tmp_path / sweep.SUMMARY).write_text(json.dumps({"ran": 2, "wall_time_s": 12.5, "executor": "2 local processes"}))
    again = run_as_the_command_does(built, tmp_path)
    assert again["runs"] == [{"ran": 2, "wall_time_s": 12.5, "executor": "2 local processes"}]
    assert again["wall_time_s"] == 12.5 and "computed in 12.5 s over 1 run" in report_lines(again)[0]


def test_a_finished_sweep_run_again_keeps_its_timing_in_sweep_json(tmp_path):
    spec = write_spec(tmp_path / "done.toml", "[base]\nmodel = 'streamline'\nmesh_h = '5um'\ncells = 'RBC,melanoma'\n"
                                               "[parameters]\nseed = [1, 2]\n[sweep]\nmetrics = ['yield']\n")
    output = tmp_path / "out"
    first = vcyto("sweep", spec, "--output", str(output), "--workers", "1")
    assert first.returncode == 0, first.stderr
    recorded = json.loads((output / "sweep.json").read_text())
    assert recorded["ran"] == 2 and recorded["wall_time_s"] > 0            # a pool, a plant, two points (timed)
    again = vcyto("sweep", spec, "--output", str(output), "--workers", "1")
    assert again.returncode == 0, again.stderr
    assert "all 2 points are already in the table: nothing to run" in again.stderr
    assert "every point was already done: nothing ran (computed in" in again.stdout
    kept = json.loads((output / "sweep.json").read_text())
    assert kept["ran"] == 0 and kept["already_done"] and kept["run_wall_time_s"] < recorded["wall_time_s"]
    assert kept["wall_time_s"] == recorded["wall_time_s"] and len(kept["runs"]) == 1
    assert kept["runs"][0]["executor"] == recorded["executor"] == "1 local process"
    assert recorded["runs"][0]["executor"] == "1 local process" and kept["executor"] == "1 local process"


# --- interrupts: SIGINT/SIGTERM stop the sweep at once, rows whole ---------------------------------------------


def slow_after_the_first(release):
    """A closed loop stand-in: the seed-0 point at once, the others only once ``release`` is set (or 20 s)."""
    def simulate(scenario, settings):
        if settings.seed != 0:
            release.wait(20)
        return fixed_result(scenario, settings)
    return simulate


def test_an_interrupt_that_reaches_another_thread_stops_the_sweep_within_a_second(tmp_path):
    """A signal the operating system hands to another thread than the waiting one (the main thread then only
    runs the handler once it wakes) stopped the sweep when the next chunk finished, not at once."""
    built = sweep.parse_sweep({"base": BASE, "parameters": {"seed": [0, 1, 2, 3]}, "sweep": {"metrics": ["yield"]}})
    release, sent = threading.Event(), []
    table = tmp_path / sweep.RESULTS

    def interrupt_once_a_row_is_in():
        while not (table.exists() and len(table.read_text().splitlines()) >= 2) and not release.is_set():
            time.sleep(0.01)
        sent.append(time.monotonic())
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)       # to this thread, not the main one

    pool = ThreadPoolExecutor(2)
    try:
        threading.Thread(target=interrupt_once_a_row_is_in, daemon=True).start()
        with runfiles.signals_as_interrupt({}), pytest.raises(KeyboardInterrupt):
            sweep.run_sweep(built, tmp_path, pool, 2, chunk=1, simulator=slow_after_the_first(release))
        stopped = time.monotonic()
    finally:
        release.set()
        pool.shutdown(cancel_futures=True)
    assert sent and stopped - sent[0] < 1.0
    assert [row["seed"] for row in read_rows(table)] == ["0"]


def test_an_interrupt_while_a_chunk_is_appended_waits_until_its_rows_are_in(tmp_path, monkeypatch):
    """Rows finished are kept whole: an interrupt while a chunk's rows are written takes effect after them."""
    from vcyto.sweep import table as table_module
    built = sweep.parse_sweep({"base": BASE, "parameters": {"rate": [500, 1000, 2000]},
                               "sweep": {"metrics": ["yield", "outlets"]}})
    cell, calls = table_module._cell, []

    def interrupted_cell(value):
        calls.append(value)
        if len(calls) == 2:                         # within the first row's cells
            os.kill(os.getpid(), signal.SIGINT)
        return cell(value)
    monkeypatch.setattr(table_module, "_cell", interrupted_cell)
    with ThreadPoolExecutor(1) as pool, runfiles.signals_as_interrupt({}), pytest.raises(KeyboardInterrupt):
        sweep.run_sweep(built, tmp_path, pool, 1, chunk=3, simulator=fixed_result)
    rows = read_rows(tmp_path / sweep.RESULTS)
    assert [row["rate"] for row in rows] == ["500", "1000", "2000"]
    assert all(row["status"] == "ok" and row["outlets"] == "lower=4 upper=2" for row in rows)


def alive_in_session(session: int) -> list[str]:
    """The processes of ``session`` still running (zombies left out): the sweep's workers, if any."""
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == session and fields[0] != "Z":
            alive.append(stat.parent.name)
    return alive


INTERRUPTED_SPEC = KILLED_SPEC.replace("stop = 9", "stop = 39")


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_to_the_main_process_alone_stops_the_sweep_at_once_keeping_whole_rows(tmp_path, signum, status):
    """As a job scheduler or `timeout` sends it: to the sweep's process, not to its workers' group."""
    spec, output = write_spec(tmp_path / "interrupted.toml", INTERRUPTED_SPEC), tmp_path / "out"
    table = output / "results.csv"
    command = [sys.executable, "-m", "vcyto.cli", "sweep", spec, "--output", str(output), "--workers", "2",
               "--chunk", "1"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and (not table.exists() or len(table.read_text().splitlines()) < 2):
            time.sleep(0.01)
        sent = time.monotonic()
        process.send_signal(signum)                  # the main process only
        _, stderr = process.communicate(timeout=60)
        took = time.monotonic() - sent
        assert process.returncode == status, stderr
        assert took < 5, f"{took:.1f} s from the signal to the exit"
        gone = time.monotonic() + 3          # workers are joined before the exit, the resource tracker ends after
        while alive_in_session(process.pid) and time.monotonic() < gone:
            time.sleep(0.05)
        assert alive_in_session(process.pid) == [], "workers outlived the sweep"
    finally:
        if alive_in_session(process.pid):
            os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    text = table.read_text()
    rows = read_rows(table)
    assert text.endswith("\n") and 1 <= len(rows) < 40
    assert all(row["status"] == "ok" and None not in row.values() and row["vcyto"] for row in rows)
    assert f"holds {len(rows)} of the 40 points ({len(rows)} finished in this run)" in stderr


def test_an_interrupted_run_records_its_time_and_the_run_that_completes_counts_it(tmp_path):
    """A run interrupted after finishing points leaves a sweep.json that says so (status interrupted, its rows so
    far, its wall time); the run that completes the sweep counts both runs' time (it counted only its own)."""
    built = sweep.parse_sweep({"base": BASE, "parameters": {"rate": [500, 1000, 2000]},
                               "sweep": {"metrics": ["yield"]}})

    def interrupted_at_2000(scenario, settings):
        if settings.arrivals.rate == 2000:
            raise KeyboardInterrupt
        return fixed_result(scenario, settings)
    with ThreadPoolExecutor(1) as pool, pytest.raises(KeyboardInterrupt):
        sweep.run_sweep(built, tmp_path, pool, 1, chunk=1, simulator=interrupted_at_2000, where="threads")
    record = json.loads((tmp_path / sweep.SUMMARY).read_text())
    assert record["status"] == "interrupted" and "the same command completes" in record["reason"]
    assert record["ok"] == 2 and record["points"] == 3 and len(record["rows"]) == 2
    [run] = record["runs"]
    assert run["ran"] == 2 and run["interrupted"] is True and run["wall_time_s"] > 0 and run["executor"] == "threads"
    with sweep.executor(None, 1) as (pool, slots, _):
        final = sweep.run_sweep(built, tmp_path, pool, slots, simulator=fixed_result)
    assert final["status"] == "complete" and final["ran"] == 1 and final["ok"] == 3 and len(final["runs"]) == 2
    assert final["wall_time_s"] == pytest.approx(run["wall_time_s"] + final["run_wall_time_s"])


# --- units in ranges and distributions: the one unit rule, in the parameter's own unit ------------------------

def test_a_distribution_with_units_draws_in_the_unit_written(tmp_path):
    """``lead = { uniform = ["0.2ms", "0.3ms"] }``: every drawn lead lies between 0.2 and 0.3 ms (it was read as
    SI seconds and then as ms: 2.5e-4 ms, a lead that sorted nothing)."""
    from vcyto.sweep.spec import load_sweep
    spec = write_spec(tmp_path / "spec.toml", '[parameters]\nlead = { uniform = ["0.2ms", "300us"] }\n'
                                              '[sweep]\nsampling = "random"\nsamples = 20\n')
    leads = [point.settings.controller.lead for point in load_sweep(spec).points]
    assert len(leads) == 20 and all(0.2e-3 <= lead <= 0.3e-3 for lead in leads), leads
    assert len(set(leads)) == 20


def test_a_range_with_units_gives_values_in_the_unit_written(tmp_path):
    from vcyto.sweep.spec import load_sweep
    spec = write_spec(tmp_path / "spec.toml", '[parameters]\nlead = { start = "0.1ms", stop = "300 us", num = 3 }\n'
                                              '"saw.streaming_force" = ["4e7 N/m^3", 5e7]\n')
    points = load_sweep(spec).points
    assert sorted({point.settings.controller.lead for point in points}) == pytest.approx([1e-4, 2e-4, 3e-4])
    assert sorted({point.scenario.saw.streaming_force for point in points}) == pytest.approx([4e7, 5e7])


@pytest.mark.parametrize("parameter, words", [
    ('"fluid.viscosity" = { start = "1 kHz", stop = "2 kHz", num = 2 }', "is a frequency, but"),
    ('lead = { uniform = ["0.2 um", "0.3 um"] }', "is a length, but"),
    ('"saw.streaming_force" = { start = "1e7 N/m^3", stop = "5e7 N/m", num = 2 }', "but"),
    ('seed = { start = "1 ms", stop = 4, num = 2 }', "must be a finite number"),
    ('lead = { start = "0.1 ms^(9^9^9)", stop = 1, num = 2 }', "cannot read the unit"),
])
def test_a_range_or_distribution_in_another_dimension_is_refused(tmp_path, parameter, words):
    from vcyto.sweep.model import SweepError
    from vcyto.sweep.spec import load_sweep
    sampling = '[sweep]\nsampling = "random"\nsamples = 2\n' if "uniform" in parameter else ""
    spec = write_spec(tmp_path / "spec.toml", f"{sampling}[parameters]\n{parameter}\n")
    with pytest.raises(SweepError, match="parameters\\.") as refused:
        load_sweep(spec)
    assert words in str(refused.value)


@pytest.mark.parametrize("value", ['"/etc/passwd"', '["../outside.toml"]', '["link.toml"]'])
def test_a_controller_file_under_parameters_is_confined_to_the_specs_folder(tmp_path, value):
    from vcyto.sweep.model import SweepError
    from vcyto.sweep.spec import load_sweep
    folder = tmp_path / "spec"
    folder.mkdir()
    (tmp_path / "outside.toml").write_text("[controller]\nlead = \"0.3 ms\"\n[secret]\n")
    (folder / "link.toml").symlink_to(tmp_path / "outside.toml")
    spec = write_spec(folder / "spec.toml", f"[parameters]\ncontroller = {value}\n")
    with pytest.raises(SweepError, match="parameters.controller: must name a file in the spec's folder"):
        load_sweep(spec)


WIRE_SPEC = COMPARED_SPEC.replace("seed = [1, 2, 3]", "seed = [1]")


def test_every_point_can_talk_to_a_controller_in_another_process_given_on_the_command_line(tmp_path):
    """``vcyto sweep SPEC --controller-exec CMD``: each point starts its own controller (the built-in one served
    over the wire, its settings from the point's device facts), with the metrics of the in-process sweep; a
    spec cannot name a program to run."""
    spec = write_spec(tmp_path / "wire.toml", WIRE_SPEC)
    served = f"{sys.executable} -m vcyto.wire.serve --once"
    local = vcyto("sweep", spec, "--output", str(tmp_path / "local"), "--workers", "1", "--json")
    wired = vcyto("sweep", spec, "--output", str(tmp_path / "wired"), "--workers", "2", "--json",
                  "--controller-exec", served)
    assert local.returncode == 0 and wired.returncode == 0, local.stderr + wired.stderr

    def table(name):
        return [{key: value for key, value in row.items() if key not in ("wall_time_s", "point", "inputs")}
                for row in read_rows(tmp_path / name / "results.csv")]
    assert len(table("local")) == 2 and all(row["status"] == "ok" for row in table("wired"))
    assert table("wired") == table("local")
    ids = {name: {row["point"] for row in read_rows(tmp_path / name / "results.csv")} for name in ("local", "wired")}
    assert not ids["local"] & ids["wired"]          # a point's identity names the controller it ran with
    refused = vcyto("sweep", write_spec(tmp_path / "bad.toml", WIRE_SPEC.replace(
        "[base]", f"[base]\ncontroller_exec = {json.dumps(served)}")), "--output", str(tmp_path / "bad"))
    assert refused.returncode == 2 and "given on the command line" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
