"""Measure what each whole-process choice of the ``vcyto`` executable buys, in alternating pairs of processes.

    python examples/process_tricks.py [--pairs N]

- the quick exit (``vcyto.cli.exit_now``): seconds from ``main``'s return to the process's end, with ``os._exit``
  and with the interpreter's ordinary teardown, after ``vcyto paper 2 --no-png``;
- the frozen imports (``vcyto.__main__.load_command_line``): seconds in garbage collections during the imports and
  during the run of the README's stream with ``--tolerance 1um``, with the imports frozen and without;
- the switch interval (``vcyto.cli.SWITCH_INTERVAL_S``): whole-process wall of that stream (its recordings
  included) at 0.2 ms and at Python's default 5 ms;
- the figure's helper process (``vcyto.painter``): whole-process wall of ``vcyto paper 2`` (with its PNG), the
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
import sys
import vcyto.__main__ as entry
cli = entry.load_command_line()
import vcyto.painter as painter
if not {helper}:
    original = painter.Painter.__init__
    painter.Painter.__init__ = lambda self, start=True: original(self, start=False)
sys.argv = ["vcyto"] + {arguments!r}
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
    child(first, environment)                                   # warm the cache, untimed
    values = {"on": [], "off": []}
    for _ in range(count):
        for name, program in (("on", first), ("off", second)):
            values[name].append(measure(*child(program, environment)))
    ratios = [a / b for a, b in zip(values["on"], values["off"]) if b]
    return {"on": [round(v, 4) for v in values["on"]], "off": [round(v, 4) for v in values["off"]],
            "median_on": round(statistics.median(values["on"]), 4),
            "median_off": round(statistics.median(values["off"]), 4),
            "median_ratio_on_off": round(statistics.median(ratios), 3) if ratios else None}


def main(count: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="vcyto-tricks-") as directory:
        environment = {**os.environ, "VCYTO_CACHE_DIR": os.path.join(directory, "cache")}
        output = ["--output", os.path.join(directory, "runs")]

        def after_return(started, ended, stderr):
            returned = float(stderr.split("RETURNED ")[1].split()[0])
            return ended - returned

        def wall(started, ended, stderr):
            return ended - started

        def collected(phase):
            return lambda started, ended, stderr: json.loads(stderr.split("SPENT ")[1].splitlines()[0])[phase]

        paper_fast = PAPER + ["--no-png"]
        result = {"quick_exit_s": pairs(count, EXIT.format(quick=True, arguments=paper_fast),
                                        EXIT.format(quick=False, arguments=paper_fast), after_return, environment)}
        stream = STREAM + output
        for phase in ("imports", "run"):
            result[f"collections_{phase}_s"] = pairs(count, COLLECTIONS.format(frozen=True, arguments=stream),
                                                     COLLECTIONS.format(frozen=False, arguments=stream),
                                                     collected(phase), environment)
        result["switch_interval_wall_s"] = pairs(count, SWITCH.format(interval=2e-4, arguments=stream),
                                                 SWITCH.format(interval=5e-3, arguments=stream), wall, environment)
        paper = PAPER + ["--png", os.path.join(directory, "paper2.png")]
        result["painter_wall_s"] = pairs(count, PAINTER.format(helper=True, arguments=paper),
                                         PAINTER.format(helper=False, arguments=paper), wall, environment)
        return result


if __name__ == "__main__":
    arguments = sys.argv[1:]
    if arguments and (arguments[0] != "--pairs" or len(arguments) != 2 or not arguments[1].isdigit()
                      or int(arguments[1]) < 1):
        sys.exit("process_tricks: usage: python examples/process_tricks.py [--pairs N] (N a whole number >= 1)")
    print(json.dumps(main(int(arguments[1]) if arguments else 4), indent=1))
