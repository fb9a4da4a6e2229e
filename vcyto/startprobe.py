"""How long a ``vcyto`` command takes to reach its first FE-IB step: ``python -m vcyto.startprobe ARGS...``.

Runs ``vcyto ARGS`` in this process with ``sim.feib.ImmersedBoundary.step`` replaced by a stop, so what is
timed is the start: Python's imports, the set-up (mesh, matrices, factorisation, from the cache or not), the
steady start flow and the first cell. Prints one JSON line: the wall time since this module started and the
process's CPU time (user + system, all threads) and whether pint was imported. For comparing starts in pairs
on a busy machine, where the CPU time is steadier than the wall time.
"""

from __future__ import annotations

import json
import os
import sys
import time

_STARTED = time.perf_counter()


class _FirstStep(BaseException):
    """Raised by the stand-in step: the start is over."""


def probe(arguments: list[str]) -> dict:
    """Run ``vcyto arguments`` up to the first plant step; its start-up times (seconds)."""
    import sim.feib as feib

    def stop(self, *args, **kwargs):
        raise _FirstStep()

    feib.ImmersedBoundary.step = stop
    from vcyto.cli import main
    reached = False
    try:
        main(arguments)
    except _FirstStep:
        reached = True
    except SystemExit:
        pass
    times = os.times()
    return {"command": ["vcyto", *arguments], "reached_first_step": reached,
            "wall_s": round(time.perf_counter() - _STARTED, 3), "cpu_s": round(times.user + times.system, 3),
            "pint_imported": "pint" in sys.modules}


if __name__ == "__main__":
    print(json.dumps(probe(sys.argv[1:])))
