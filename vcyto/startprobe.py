"""How long a ``vcyto`` command takes to reach its first FE-IB step: ``python -m vcyto.startprobe [--steps N] ARGS...``.

Runs ``vcyto ARGS`` in this process with ``sim.method.feib.ImmersedBoundary.step`` replaced by a stop, so what is
timed is the start: Python's imports, the set-up (mesh, matrices, factorisation, from the cache or not), the
steady start flow and the first cell. ``--steps N`` lets N steps run before the stop: with 1, the start through
the first step. Prints one JSON line: the wall time since this module started and the process's CPU time
(user + system, all threads), the steps taken and whether pint was imported. For comparing starts in pairs on
a busy machine, where the CPU time is steadier than the wall time.
"""

from __future__ import annotations

import json
import os
import sys
import time

_STARTED = time.perf_counter()


class _FirstStep(BaseException):
    """Raised by the stand-in step: the start is over."""


def probe(arguments: list[str], steps: int = 0) -> dict:
    """Run ``vcyto arguments`` up to its plant step ``steps`` + 1 (0: the first); its start-up times (seconds)."""
    from vcyto.__main__ import load_command_line
    main = load_command_line().main          # imported as the executable imports it (the collector off)
    import sim.method.feib as feib
    step, taken = feib.ImmersedBoundary.step, []

    def stop(self, *args, **kwargs):
        if len(taken) >= steps:
            raise _FirstStep()
        taken.append(None)
        return step(self, *args, **kwargs)

    feib.ImmersedBoundary.step = stop
    reached = False
    try:
        main(arguments)
    except _FirstStep:
        reached = True
    except SystemExit:
        pass
    times = os.times()
    return {"command": ["vcyto", *arguments], "reached_first_step": reached, "steps": len(taken),
            "wall_s": round(time.perf_counter() - _STARTED, 3), "cpu_s": round(times.user + times.system, 3),
            "pint_imported": "pint" in sys.modules}


def _main(arguments: list[str]) -> None:
    steps = 0
    if arguments[:1] == ["--steps"]:
        if len(arguments) < 2 or not arguments[1].isdigit():
            sys.exit("startprobe: --steps needs a whole number of steps, e.g. --steps 1")
        steps, arguments = int(arguments[1]), arguments[2:]
    print(json.dumps(probe(arguments, steps)))


if __name__ == "__main__":
    _main(sys.argv[1:])
