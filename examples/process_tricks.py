"""Measure what each whole-process choice of the ``vcyto`` executable buys, in alternating pairs of processes.

    python examples/process_tricks.py [--pairs N] [--only painter|exit|collections|switch]

- the quick exit (``vcyto.cli.exit_now``): seconds from ``main``'s return to the process's end, with ``os._exit``
  and with the interpreter's ordinary teardown, after ``vcyto paper 2 --no-png``;
- the frozen imports (``vcyto.__main__.load_command_line``): seconds in garbage collections during the imports and
  during the run of the README's stream with ``--tolerance 1um``, with the imports frozen and without;
- the switch interval (``vcyto.cli.SWITCH_INTERVAL_S``): whole-process wall of that stream (its recordings
  included) at 0.2 ms and at Python's default 5 ms;
- the figure's helper process (``vcyto.studies.painter``): whole-process wall of ``vcyto paper 2`` (with its PNG), the
  figure drawn by the helper and drawn by the command itself.

Each child runs with a warm set-up cache of its own (one untimed run first). Prints the medians and the median of
the per-pair ratios as JSON. Timings on a shared host vary 2-3x: compare within a pair.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

STREAM = ["stream", "--cells", "RBC,melanoma", "--tolerance", "1um", "--no-viewer", "--quiet"]
PAPER = ["paper", "2", "--quiet"]

EXIT = """
import sys, time
import vcyto.__main__ as entry
cli = entry.load_command_line()
quick = {quick}
original = cli.exit_now
def timed(status):
    sys.stderr.write(f"RETURNED {{time.time()!r}}\\n"); sys.stderr.flush()
    if quick:
        original(status)
    sys.exit(status)
cli.exit_now = timed
sys.argv = ["vcyto"] + {arguments!r}
cli.run()
"""

COLLECTIONS = """
import gc, sys, time, json
spent = {{"imports": 0.0, "run": 0.0}}
phase, started = ["imports"], [0.0]
def timer(event, info):
    if event == "start":
        started[0] = time.perf_counter()
    else:
        spent[phase[0]] += time.perf_counter() - started[0]
gc.callbacks.append(timer)
if {frozen}:
    import vcyto.__main__ as entry
    cli = entry.load_command_line()
else:
    import vcyto.cli as cli
phase[0] = "run"
status = cli.main({arguments!r})
sys.stderr.write("SPENT " + json.dumps(spent) + "\\n")
sys.exit(status)
"""

SWITCH = """
import sys
import vcyto.__main__ as entry
cli = entry.load_command_line()
cli.SWITCH_INTERVAL_S = {interval}
sys.argv = ["vcyto"] + {arguments!r}
cli.run()
"""

PAINTER = """
import os, sys
import vcyto.__main__ as entry
cli = entry.load_command_line()
import vcyto.studies.painter as painter
if {helper}:
    painter.core_idle = lambda: True          # the helper whatever the load
else:
    original = painter.Painter.__init__
    painter.Painter.__init__ = lambda self, start=True: original(self, start=False)
png = os.path.join({directory!r}, f"paper2-{{os.getpid()}}.png")       # a run never overwrites a file
sys.argv = ["vcyto"] + {arguments!r} + ["--png", png]
cli.run()
"""


def child(program: str, environment: dict) -> tuple[float, str]:
    started = time.time()
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, env=environment)
    ended = time.time()
    if done.returncode != 0:
        raise SystemExit(f"process_tricks: a child failed ({done.returncode}): {done.stderr.strip()[-500:]}")
    return started, ended, done.stderr


def pairs(count: int, first: str, second: str, measure, environment: dict) -> dict:
    """``measure(started, ended, stderr)`` -> {name: seconds} of ``count`` alternating pairs of the two programs:
    for each name the values, their medians and the median of the per-pair ratios first / second."""
    child(first, environment)                                   # warm the cache, untimed
    values = {"on": [], "off": []}
    for _ in range(count):
        for name, program in (("on", first), ("off", second)):
            values[name].append(measure(*child(program, environment)))
    result = {}
    for key in values["on"][0]:
        on, off = [v[key] for v in values["on"]], [v[key] for v in values["off"]]
        ratios = [a / b for a, b in zip(on, off) if b]
        result[key] = {"on": [round(v, 4) for v in on], "off": [round(v, 4) for v in off],
                       "median_on": round(statistics.median(on), 4), "median_off": round(statistics.median(off), 4),
                       "median_ratio_on_off": round(statistics.median(ratios), 3) if ratios else None}
    return result


def main(count: int, only: str | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="vcyto-tricks-") as directory:
        environment = {**os.environ, "VCYTO_CACHE_DIR": os.path.join(directory, "cache")}
        stream = STREAM + ["--output", os.path.join(directory, "runs")]

        def after_return(started, ended, stderr):
            return {"exit": ended - float(stderr.split("RETURNED ")[1].split()[0])}

        def wall(started, ended, stderr):
            return {"wall": ended - started}

        def collected(started, ended, stderr):
            return json.loads(stderr.split("SPENT ")[1].splitlines()[0])

        measurements = {
            "painter (helper on / drawn by the command)": (
                PAINTER.format(helper=True, arguments=PAPER, directory=directory),
                PAINTER.format(helper=False, arguments=PAPER, directory=directory), wall),
            "quick exit (os._exit / the ordinary exit)": (
                EXIT.format(quick=True, arguments=PAPER + ["--no-png"]),
                EXIT.format(quick=False, arguments=PAPER + ["--no-png"]), after_return),
            "collections (imports frozen / not)": (
                COLLECTIONS.format(frozen=True, arguments=stream),
                COLLECTIONS.format(frozen=False, arguments=stream), collected),
            "switch interval (0.2 ms / 5 ms)": (
                SWITCH.format(interval=2e-4, arguments=stream),
                SWITCH.format(interval=5e-3, arguments=stream), wall),
        }
        result = {}
        for name, (first, second, measure) in measurements.items():
            if only and not name.startswith(only.replace("exit", "quick exit").replace("switch", "switch interval")):
                continue
            result[name] = pairs(count, first, second, measure, environment)
            print(json.dumps({name: result[name]}), file=sys.stderr, flush=True)
        return result


USAGE = ("process_tricks: usage: python examples/process_tricks.py [--pairs N] [--only painter|exit|collections|"
         "switch] (N a whole number >= 1)")

if __name__ == "__main__":
    arguments, options = sys.argv[1:], {"--pairs": "4", "--only": None}
    while arguments:
        if len(arguments) < 2 or arguments[0] not in options:
            sys.exit(USAGE)
        options[arguments[0]], arguments = arguments[1], arguments[2:]
    if not options["--pairs"].isdigit() or int(options["--pairs"]) < 1 or \
            options["--only"] not in (None, "painter", "exit", "collections", "switch"):
        sys.exit(USAGE)
    print(json.dumps(main(int(options["--pairs"]), options["--only"]), indent=1))
