"""`vcyto bench process`: the wall time of whole ``vcyto`` processes, as a user who types the commands waits for
them, with a warm set-up cache.

Each command runs as its own process (``python -m vcyto ...``) with its files in a temporary directory, headless
(``DISPLAY`` and ``WAYLAND_DISPLAY`` removed: the Rerun view is saved as an ``.rrd``, as on a machine without a
display). One untimed run of every command first fills the set-up cache. Then each round runs every command
once, in the same order, so that the README's stream at fixed 2.5 us steps and at ``--tolerance 1um`` run next
to each other: their speed-up is taken within a round (the machine's load changes slowly against a round), and
the median over the rounds is reported. The start is ``python -m vcyto.startprobe``'s time to the first FE-IB
step of ``vcyto paper 2``.

The targets (the README's first screen; docs/numerics.md, "Time steps chosen by a tolerance"): the start well
under a second, ``vcyto paper 2`` <= 2 s, ``vcyto paper 1`` <= 10 s, the README's stream <= 15 s, and with
``--tolerance 1um`` the stream >= 3x faster.

The floor: once a round, after the commands, ``python -m vcyto.bench.floor`` times the back-solves this machine
offers for the fluid at the paper's mesh (PARDISO's parallel substitution in double and single precision, the
default's); the fastest of them is the round's floor of one FE-IB step, and the default's the fastest that gives
the same bits on every run. A fixed-step command that prints its result (``--json``, which the timed commands
pass) is reported with its steps x that floor (the time no code could beat without a faster solve: every step
solves the fluid at least once), its steps x the reproducible back-solve, and its wall time over the floor; a
target below its floor is beyond this machine at those steps, whatever the code does, and a target below the
reproducible floor is beyond it for a reproducible run with the solvers this machine offers. ``vcyto paper 2`` steps
at 25 us, whose matrix has the same pattern and so the same factor sizes as the probe's (2.5 us).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

STREAM = ("stream", "--cells", "RBC,melanoma")
TOLERANCE = ("--tolerance", "1um")
UNRECORDED = ("--no-viewer", "--output", "")


class Command(NamedTuple):
    """One timed command: its name in the report, its ``vcyto`` arguments (``{dir}`` is the round's directory),
    its target in seconds (None: none of its own), whether the time is the start probe's, and a note."""
    name: str
    arguments: tuple
    target_s: float | None = None
    probe: bool = False
    note: str = ""


COMMANDS = (
    Command("start to the first step (paper 2)", ("paper", "2", "--no-png", "--quiet"), probe=True,
            note="target: well under a second"),
    Command("vcyto paper 2", ("paper", "2", "--png", "{dir}/paper2.png", "--quiet", "--json"), 2.0),
    Command("vcyto paper 1", ("paper", "1", "--png", "{dir}/paper1.png", "--quiet", "--json"), 10.0),
    Command("stream", (*STREAM, "--output", "{dir}", "--quiet", "--json"), 15.0),
    Command("stream --tolerance 1um", (*STREAM, *TOLERANCE, "--output", "{dir}", "--quiet")),
    Command("stream, no recordings", (*STREAM, *UNRECORDED, "--quiet")),
    Command("stream --tolerance 1um, no recordings", (*STREAM, *TOLERANCE, *UNRECORDED, "--quiet")),
)
# (fixed steps, --tolerance 1um): the speed-up pairs, run next to each other in a round
PAIRS = (("stream", "stream --tolerance 1um"),
         ("stream, no recordings", "stream --tolerance 1um, no recordings"))
SPEED_UP_TARGET = 3.0


TIMEOUT_S = 1800.0          # a command that takes longer has hung (the slowest, paper 1, takes ~10-20 s)


class Timed(NamedTuple):
    """One run of a command: its wall time and, for a command with ``--json``, the FE-IB steps it took."""
    wall_s: float
    steps: int | None = None


class CommandFailed(RuntimeError):
    """A timed command failed, hung or said nothing usable (the benchmark reports it in one line and stops)."""


def headless_environment() -> dict:
    """This process's environment without a display, its paths made absolute (the commands run in a directory
    of their own: a relative cache directory or import path would name another one there)."""
    environment = {key: value for key, value in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    environment.pop("PYTHONDONTWRITEBYTECODE", None)        # a user's environment keeps the compiled modules
    if environment.get("VCYTO_CACHE_DIR"):
        environment["VCYTO_CACHE_DIR"] = str(Path(environment["VCYTO_CACHE_DIR"]).resolve())
    # this vcyto first (importable as here, from an uninstalled checkout too), then the given path, made absolute
    paths = [str(Path(__file__).resolve().parents[2])]
    paths += [str(Path(entry).resolve()) for entry in environment.get("PYTHONPATH", "").split(os.pathsep) if entry]
    environment["PYTHONPATH"] = os.pathsep.join(paths)
    return environment


def _run(module: str, arguments: list[str], directory: Path, shown: str) -> tuple[subprocess.CompletedProcess, str]:
    """``python -m module arguments`` in ``directory``, headless: the finished process and its last stderr line; a
    timeout, a signal or a non-zero status is a ``CommandFailed`` naming ``shown``."""
    try:
        done = subprocess.run([sys.executable, "-m", module, *arguments], capture_output=True, text=True,
                              env=headless_environment(), cwd=directory, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise CommandFailed(f"{shown} took more than {TIMEOUT_S:.0f} s: stopped") from None
    last = (done.stderr.strip().splitlines() or ["(nothing on stderr)"])[-1]
    if done.returncode < 0:
        raise CommandFailed(f"{shown} was killed by signal {-done.returncode}: {last}")
    if done.returncode != 0:
        raise CommandFailed(f"{shown} exited with status {done.returncode}: {last}")
    return done, last


def run_command(command: Command, directory: Path) -> Timed:
    """Run ``command`` in a new process: its wall time in seconds (the probe's: to the first step) and, when it
    prints its result (``--json``), its FE-IB steps."""
    arguments = [part.replace("{dir}", str(directory)) for part in command.arguments]
    shown = f"`vcyto {' '.join(arguments)}`"
    started = time.perf_counter()
    done, last = _run("vcyto.startprobe" if command.probe else "vcyto", arguments, directory, shown)
    wall = time.perf_counter() - started
    if command.probe:
        try:
            probed = json.loads(done.stdout.strip().splitlines()[-1])
            reached, wall = bool(probed["reached_first_step"]), float(probed["wall_s"])
        except (IndexError, ValueError, KeyError, TypeError):
            raise CommandFailed(f"{shown}: the start-up probe printed no result ({last})") from None
        if not reached:
            raise CommandFailed(f"{shown} ended before its first FE-IB step: {last}")
    steps = None
    if "--json" in arguments:
        try:
            printed = json.loads(done.stdout)
            # a stream's "steps" are its control periods; its FE-IB steps are in "time_steps" (equal at fixed dt)
            steps = int((printed.get("time_steps") or printed)["steps"])
        except (ValueError, KeyError, TypeError):
            raise CommandFailed(f"{shown} printed no result with its steps ({last})") from None
    return Timed(wall, steps)


def run_floor(directory: Path) -> dict:
    """``vcyto.bench.floor`` in a new process (this machine's back-solves at the paper's mesh, now): its result."""
    shown = "the floor probe (`python -m vcyto.bench.floor`)"
    done, last = _run("vcyto.bench.floor", [], directory, shown)
    try:
        return json.loads(done.stdout.strip().splitlines()[-1])
    except (IndexError, ValueError):
        raise CommandFailed(f"{shown} printed no result ({last})") from None


def bench_process(rounds: int = 3, commands=COMMANDS, pairs=PAIRS, warm_up: bool = True,
                  run: Callable[[Command, Path], Timed | float] = run_command,
                  floor: Callable[[Path], dict] | None = run_floor, progress=lambda message: None) -> dict:
    """Time ``commands`` in ``rounds`` rounds (after one untimed run of each if ``warm_up``); with ``floor``, probe
    the machine's fastest back-solve once a round, after the commands (``vcyto.bench.floor``)."""
    times: dict[str, list[float]] = {command.name: [] for command in commands}
    steps: dict[str, list[int | None]] = {command.name: [] for command in commands}
    floors: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="vcyto-bench-process-") as scratch:
        for number in range(rounds + (1 if warm_up else 0)):
            timed = number >= (1 if warm_up else 0)
            label = f"round {number + (0 if warm_up else 1)}/{rounds}" if timed else "warm-up (untimed)"
            for index, command in enumerate(commands):
                progress(f"{label}: {command.name}")
                directory = Path(scratch) / f"{number}-{index}"
                directory.mkdir()
                done = run(command, directory)
                done = done if isinstance(done, Timed) else Timed(float(done))
                if timed:
                    times[command.name].append(done.wall_s)
                    steps[command.name].append(done.steps)
            if timed and floor is not None:
                progress(f"{label}: this machine's fastest back-solve (the floor of fixed steps)")
                directory = Path(scratch) / f"{number}-floor"
                directory.mkdir()
                floors.append(floor(directory))
    rows = [{"name": command.name, "arguments": list(command.arguments), "times_s": times[command.name],
             "median_s": float(np.median(times[command.name])), "target_s": command.target_s, "note": command.note,
             **_floor_of(times[command.name], steps[command.name], floors)}
            for command in commands]
    speed_ups = []
    for fixed, tolerance in pairs:
        ratios = [a / b for a, b in zip(times[fixed], times[tolerance])]
        speed_ups.append({"fixed": fixed, "tolerance": tolerance, "per_round": ratios,
                          "median": float(np.median(ratios)), "target": SPEED_UP_TARGET})
    result = {"rounds": rounds, "python": sys.executable, "rows": rows, "speed_ups": speed_ups}
    if floors:
        result["floor"] = {"per_round_ms": [probe["floor_ms"] for probe in floors],
                           "median_ms": float(np.median([probe["floor_ms"] for probe in floors])),
                           "reproducible_ms": float(np.median([probe["reproducible_ms"] for probe in floors])),
                           "backsolves_ms": {name: float(np.median([probe["backsolves"][name] for probe in floors]))
                                             for name in floors[0]["backsolves"]},
                           "labels": floors[-1].get("labels", {})}
    return result


def _floor_of(times: list[float], steps: list[int | None], floors: list[dict]) -> dict:
    """A fixed-step command's floor in each round (its steps x that round's fastest back-solve) and the medians of
    the floor and of wall / floor; nothing for a command whose steps are unknown or without floor probes."""
    if not floors or not steps or any(count is None or count <= 0 for count in steps):
        return {}
    floor_s = [count * probe["floor_ms"] / 1e3 for count, probe in zip(steps, floors)]
    reproducible_s = [count * probe["reproducible_ms"] / 1e3 for count, probe in zip(steps, floors)]
    return {"steps": steps, "floor_s": floor_s, "floor_median_s": float(np.median(floor_s)),
            "reproducible_floor_median_s": float(np.median(reproducible_s)),
            "over_floor": float(np.median([wall / low for wall, low in zip(times, floor_s)]))}


def process_lines(result: dict) -> list[str]:
    rounds = f"{result['rounds']} round" + ("" if result["rounds"] == 1 else "s")
    lines = [f"whole processes, warm set-up cache, headless; {rounds}, median [lowest-highest]:"]
    for row in result["rows"]:
        verdict = f"  {row['note']}" if row["target_s"] is None else f"  target <= {row['target_s']:g} s: " + (
            "met" if row["median_s"] <= row["target_s"] else "not met")
        times = row["times_s"]
        lines.append(f"  {row['name']:<40} {row['median_s']:6.2f} s [{min(times):.2f}-{max(times):.2f}]{verdict}")
        if "floor_median_s" in row:
            steps = sorted(set(row["steps"]))
            counted = f"{steps[0]:,}" if len(steps) == 1 else f"{steps[0]:,}-{steps[-1]:,}"
            target = row["target_s"] if row["target_s"] is not None else math.inf
            beyond = ("; the target is beyond this machine at these steps" if row["floor_median_s"] > target else
                      "; the target is beyond this machine's reproducible back-solve at these steps"
                      if row["reproducible_floor_median_s"] > target else "")
            lines.append(f"  {'':<40} floor {row['floor_median_s']:.2f} s ({counted} steps x the fastest back-solve; "
                         f"{row['reproducible_floor_median_s']:.2f} s x the reproducible one), wall / floor "
                         f"{row['over_floor']:.2f}{beyond}")
    for pair in result["speed_ups"]:
        ratios = ", ".join(f"{ratio:.2f}" for ratio in pair["per_round"])
        verdict = "met" if pair["median"] >= pair["target"] else "not met"
        lines.append(f"  speed-up '{pair['fixed']}' / '{pair['tolerance']}': per round {ratios}; "
                     f"median {pair['median']:.2f}  target >= {pair['target']:g}: {verdict}")
    if "floor" in result:
        floor = result["floor"]
        per_round = floor["per_round_ms"]
        lines.append(f"this machine's fastest back-solve at the paper's mesh (python -m vcyto.bench.floor, once a "
                     f"round): {floor['median_ms']:.2f} ms [{min(per_round):.2f}-{max(per_round):.2f}], the fastest "
                     f"reproducible one (the default's) {floor['reproducible_ms']:.2f} ms; medians:")
        lines += [f"  {ms:6.2f} ms  {floor['labels'].get(name, name)}" for name, ms in floor["backsolves_ms"].items()]
    return lines
