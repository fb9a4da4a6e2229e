"""`vcyto bench process` (vcyto.bench.process): whole processes timed in rounds. The arithmetic (medians, the
speed-up within each round, the warm-up left out, the verdicts) on scripted times; the runner on real,
quick processes: headless, the wall time measured, a failing command reported in one line."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from vcyto.bench import process
from vcyto.bench.floor import floor_probe
from vcyto.bench.process import Command, CommandFailed, Timed, bench_process, process_lines, run_command

COMMANDS = (Command("slow", ("a",), target_s=10.0), Command("fast", ("b",)), Command("fixed", ("c",), target_s=5.0))


def test_medians_and_the_speed_up_are_taken_per_round_and_the_warm_up_is_not_counted():
    scripted = {"slow": iter([99.0, 12.0, 8.0, 9.0]), "fast": iter([99.0, 3.0, 2.0, 4.0]),
                "fixed": iter([99.0, 4.0, 6.0, 5.0])}
    order = []

    def run(command, directory):
        order.append(command.name)
        assert directory.is_dir() and not any(directory.iterdir())      # a fresh directory per run
        return next(scripted[command.name])

    result = bench_process(rounds=3, commands=COMMANDS, pairs=(("slow", "fast"),), run=run, floor=None)
    assert order == ["slow", "fast", "fixed"] * 4                          # one warm-up round, then three
    rows = {row["name"]: row for row in result["rows"]}
    assert rows["slow"]["times_s"] == [12.0, 8.0, 9.0] and rows["slow"]["median_s"] == 9.0
    assert rows["fixed"]["median_s"] == 5.0
    (pair,) = result["speed_ups"]
    assert pair["per_round"] == [4.0, 4.0, 2.25]          # 12/3, 8/2, 9/4: within each round
    assert pair["median"] == 4.0                          # not median(slow) / median(fast) = 9 / 3
    lines = "\n".join(process_lines(result))
    assert "target <= 10 s: met" in lines and "target <= 5 s: met" in lines
    assert "median 4.00  target >= 3: met" in lines


def test_without_a_warm_up_every_round_counts_and_a_missed_target_says_so():
    result = bench_process(rounds=2, commands=COMMANDS, pairs=(("slow", "fast"),), warm_up=False, floor=None,
                           run=lambda command, directory: {"slow": 11.0, "fast": 5.0, "fixed": 1.0}[command.name])
    assert [len(row["times_s"]) for row in result["rows"]] == [2, 2, 2]
    lines = "\n".join(process_lines(result))
    assert "target <= 10 s: not met" in lines and "median 2.20  target >= 3: not met" in lines


def test_the_runner_times_a_headless_process_and_reports_a_failure_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setenv("VCYTO_CACHE_DIR", "relative/cache")
    environment = process.headless_environment()
    assert "DISPLAY" not in environment
    # the commands run in a directory of their own: the paths that name this one are absolute
    assert Path(environment["VCYTO_CACHE_DIR"]) == Path("relative/cache").resolve()
    assert Path(environment["PYTHONPATH"].split(os.pathsep)[0]) / "vcyto" == Path(process.__file__).parents[1]
    wall = run_command(Command("scenario", ("scenario",)), tmp_path)
    assert wall.steps is None and 0.0 < wall.wall_s < 120.0
    # a command that prints its result (--json) without its steps is refused in one line, not counted as none
    with pytest.raises(CommandFailed, match=r"`vcyto scenario --json` printed no result with its steps"):
        run_command(Command("scenario", ("scenario", "--json")), tmp_path)
    with pytest.raises(CommandFailed, match=r"`vcyto paper 3` exited with status 2: vcyto: error: .*invalid choice: 3"):
        run_command(Command("bad", ("paper", "3")), tmp_path)
    # a probe that prints no result (here: its usage error) is one line too, not a traceback
    with pytest.raises(CommandFailed, match=r"exited with status 1: startprobe: --steps needs a whole number"):
        run_command(Command("probe", ("--steps", "x"), probe=True), tmp_path)


def test_the_benchmark_refuses_a_cache_that_is_off():
    done = subprocess.run([sys.executable, "-m", "vcyto", "bench", "process"], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "VCYTO_CACHE": "off"})
    assert done.returncode == 2 and done.stderr.strip().splitlines() == [
        "vcyto: error: bench process times commands with a warm set-up cache, which VCYTO_CACHE=off turns off: "
        "unset VCYTO_CACHE"]


def test_the_command_line_refuses_zero_rounds_in_one_line():
    done = subprocess.run([sys.executable, "-m", "vcyto", "bench", "process", "--rounds", "0"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1 and "--rounds" in done.stderr


def test_the_report_counts_its_rounds():
    one = bench_process(rounds=1, commands=COMMANDS, pairs=(("slow", "fast"),), warm_up=False, floor=None,
                        run=lambda command, directory: 1.0)
    assert process_lines(one)[0].startswith("whole processes, warm set-up cache, headless; 1 round, ")
    one["rounds"] = 2
    assert "; 2 rounds, " in process_lines(one)[0]


def test_the_floor_is_each_rounds_steps_times_that_rounds_fastest_back_solve():
    # rounds where the machine's fastest back-solve was 10 ms and then 5 ms: 1,000 steps have floors of 10 s
    # and 5 s; a command of 12 s, then 8 s, is 1.2x and 1.6x above them (median 1.4)
    walls = {"slow": iter([12.0, 8.0]), "fast": iter([3.0, 2.0]), "fixed": iter([4.0, 4.0])}
    floors = iter([{"floor_ms": 10.0, "reproducible_ms": 12.0, "backsolves": {"a": 12.0, "b": 10.0}},
                   {"floor_ms": 5.0, "reproducible_ms": 6.0, "backsolves": {"a": 5.0, "b": 6.0}}])
    probed = []

    def floor(directory):
        probed.append(directory)
        return next(floors)

    def run(command, directory):
        wall = next(walls[command.name])
        return Timed(wall, 1000) if command.name == "slow" else Timed(wall, None) if command.name == "fast" else wall

    result = bench_process(rounds=2, commands=COMMANDS, pairs=(("slow", "fast"),), warm_up=False, run=run,
                           floor=floor)
    assert len(probed) == 2 and len(set(probed)) == 2                      # once a round, a directory each
    rows = {row["name"]: row for row in result["rows"]}
    assert rows["slow"]["floor_s"] == [10.0, 5.0] and rows["slow"]["floor_median_s"] == 7.5
    assert rows["slow"]["over_floor"] == pytest.approx(1.4)
    assert rows["slow"]["reproducible_floor_median_s"] == 9.0                # 1,000 x (12 ms, 6 ms): 12 s and 6 s
    assert "floor_s" not in rows["fast"] and "floor_s" not in rows["fixed"]    # steps unknown: no floor
    assert result["floor"]["median_ms"] == 7.5 and result["floor"]["backsolves_ms"] == {"a": 8.5, "b": 8.0}
    lines = "\n".join(process_lines(result))
    assert "floor 7.50 s (1,000 steps x the fastest back-solve; 9.00 s x the reproducible one), wall / floor 1.40\n" \
        in lines                                                           # both below the 10 s target
    assert "this machine's fastest back-solve at the paper's mesh" in lines and "7.50 ms [5.00-10.00]" in lines
    assert "the fastest reproducible one (the default's) 9.00 ms" in lines
    # the same steps on a machine twice as slow: the floor (15 s) passes the 10 s target, which no code then meets
    floors = iter([{"floor_ms": 20.0, "reproducible_ms": 20.0, "backsolves": {"a": 20.0}},
                   {"floor_ms": 10.0, "reproducible_ms": 10.0, "backsolves": {"a": 10.0}}])
    walls = {"slow": iter([24.0, 16.0]), "fast": iter([3.0, 2.0]), "fixed": iter([4.0, 4.0])}
    slow = bench_process(rounds=2, commands=COMMANDS, pairs=(("slow", "fast"),), warm_up=False, run=run,
                         floor=lambda directory: next(floors))
    assert "floor 15.00 s (1,000 steps x the fastest back-solve; 15.00 s x the reproducible one), wall / floor 1.40; " \
           "the target is beyond this machine at these steps" in "\n".join(process_lines(slow))
    # a floor below the target with a reproducible floor above it: beyond the reproducible back-solve only
    floors = iter([{"floor_ms": 8.0, "reproducible_ms": 11.0, "backsolves": {"a": 8.0}}] * 2)
    walls = {"slow": iter([12.0, 12.0]), "fast": iter([3.0, 2.0]), "fixed": iter([4.0, 4.0])}
    reproducible = bench_process(rounds=2, commands=COMMANDS, pairs=(("slow", "fast"),), warm_up=False, run=run,
                                 floor=lambda directory: next(floors))
    assert "wall / floor 1.50; the target is beyond this machine's reproducible back-solve at these steps" in \
        "\n".join(process_lines(reproducible))


def test_the_floor_probe_times_the_back_solves_of_the_papers_fluid(monkeypatch):
    import vcyto.bench.fluid as fluid
    monkeypatch.setattr(fluid, "BLOCK_S", 0.05)          # short blocks: what is tested is which solves and the min
    result = floor_probe(rounds=2)
    assert result["dofs"] == 54243 and result["dt_us"] == 2.5 and result["rounds"] == 2
    times = result["backsolves"]
    assert result["labels"]["default"].startswith("the default: ") and all(ms > 0 for ms in times.values())
    # the floor is the median of each round's fastest: never above any back-solve's median
    assert 0 < result["floor_ms"] <= min(times.values())
    assert result["reproducible_ms"] == times["default"]
    assert len(times) == (3 if fluid.pardiso_available() else 1)


def test_the_floor_probe_refuses_bad_arguments_in_one_line():
    done = subprocess.run([sys.executable, "-m", "vcyto.bench.floor", "--rounds", "0"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 1 and done.stderr.strip().splitlines() == [
        "floor: usage: python -m vcyto.bench.floor [--rounds N] (N a whole number >= 1, e.g. 3)"]
