"""The machine's floor for fixed-step FE-IB runs: ``python -m vcyto.bench.floor`` prints one JSON line.

A fixed-step run of N FE-IB steps solves the fluid's saddle-point system at least N times (one back-solve a step,
a second correction only where the flow jumps: docs/numerics.md, "Mixed precision"), so N x the fastest
back-solve this machine offers is a time no code can beat without a faster solve. This probe restores the
fluid of the README's stream and of ``vcyto paper 1`` (the paper's mesh, dt = 2.5 us, imex; from the set-up
cache when it is warm), factors the same matrix for PARDISO's parallel substitution (the yardstick of ``vcyto
bench fluid``: not reproducible, the fastest there is) and times it and the default's back-solve in
``--rounds`` rounds of ``vcyto.bench.fluid``'s blocks, each in the same way as that benchmark. ``vcyto bench
process`` runs it once a round, beside the commands it times.
"""

from __future__ import annotations

import json
import statistics
import sys

import numpy as np

ROUNDS = 3


def floor_probe(rounds: int = ROUNDS) -> dict:
    """The back-solves of the fluid's matrix (ms, medians over ``rounds`` blocks each), the floor (the median over
    the rounds of each round's fastest of them: on a busy host any of them can be the fastest) and the default's,
    the fastest reproducible one."""
    from sim.method.fluid import NavierStokes
    from sim.model.scenario import Scenario

    from .fluid import _block_ms, _describe, _fastest_backsolves, _hot_block_ms

    scenario = Scenario().with_numerics(convection="imex")
    base = NavierStokes(scenario)
    rhs = np.random.default_rng(0).standard_normal(len(base.free))
    base.backsolve(rhs)                                   # the split solve's coupling (restored when warm)
    solves = {name: (_hot_block_ms, solve, solve.label) for name, solve in _fastest_backsolves(base).items()}
    solves["default"] = (_block_ms, base.backsolve, f"the default: {_describe(base._constant.factor)}")
    timed = [{name: block(lambda: solve(rhs)) for name, (block, solve, _) in solves.items()} for _ in range(rounds)]
    result = {"dofs": int(base.space.dofs), "dt_us": scenario.numerics.dt * 1e6, "rounds": rounds,
              "backsolves": {name: round(statistics.median(row[name] for row in timed), 3) for name in solves},
              "labels": {name: label for name, (_, _, label) in solves.items()},
              "floor_ms": round(statistics.median(min(row.values()) for row in timed), 3),
              # the default is the reproducible back-solve (bit for bit; PARDISO's parallel ones are not)
              "reproducible_ms": round(statistics.median(row["default"] for row in timed), 3)}
    for name, (_, solve, _) in solves.items():
        getattr(solve, "release", lambda: None)()
    return result


def _main(arguments: list[str]) -> None:
    rounds = ROUNDS
    if arguments:
        if arguments[0] != "--rounds" or len(arguments) != 2 or not arguments[1].isdigit() or int(arguments[1]) < 1:
            sys.exit("floor: usage: python -m vcyto.bench.floor [--rounds N] (N a whole number >= 1, e.g. 3)")
        rounds = int(arguments[1])
    from ..cache import install_default
    from ..speedsettings import install
    install()
    install_default()
    print(json.dumps(floor_probe(rounds)))


if __name__ == "__main__":
    _main(sys.argv[1:])
