"""`vcyto bench fluid`: what one fluid step costs at a scenario's resolution, piece by piece.

All figures come from one process and one run, so ratios are meaningful on a noisy machine: the
set-up (assembly, factorisation, steady start), the median step of each convection treatment, and the
median bare back-solve of the same factored matrix (PARDISO and SuperLU). The imex step and the bare
back-solve are timed in interleaved pairs; their ratio is the median of the per-pair ratios.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from sim import store
from sim.fluid import NavierStokes
from sim.linalg import Pardiso, SuperLU, pardiso_available
from sim.mesh import channel_mesh
from sim.scenario import UM, Scenario
from sim.taylorhood import TaylorHood

STEPS = {"imex": 40, "stokes": 40, "oseen": 4, "implicit": 4}


def _median_ms(function, repeats):
    samples = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        samples.append(time.perf_counter() - started)
    return 1e3 * statistics.median(samples)


def bench_fluid(scenario: Scenario, repeats: int = 40, progress=lambda message: None) -> dict:
    """Measure set-up and per-step costs; returns a JSON-ready dict (times in ms unless named _s).

    The set-up cache is off while it runs: it times what a cold start computes."""
    previous = store.install(None)
    try:
        return _bench_fluid(scenario, repeats, progress)
    finally:
        store.install(previous)


def _bench_fluid(scenario: Scenario, repeats: int, progress) -> dict:
    result = {"mesh_h_um": scenario.numerics.mesh_h / UM}
    started = time.perf_counter()
    space = TaylorHood(channel_mesh(scenario.channel, scenario.numerics.mesh_h))
    result["assembly_s"] = time.perf_counter() - started
    result["dofs"] = space.dofs
    progress(f"{space.dofs:,} DOFs assembled in {result['assembly_s']:.2f} s; steady start")
    base = NavierStokes(scenario.with_numerics(convection="imex"), space)
    result["factorisation_s"] = base.timings.factor
    result["linear_solver"] = base.solver_name
    result["reproducible"] = scenario.numerics.reproducible
    started = time.perf_counter()
    start = base.steady(0.0)
    result["steady_solve_s"] = time.perf_counter() - started
    rhs = np.random.default_rng(0).standard_normal(len(base.free))
    result["default_solver"] = type(base._constant.factor).__name__
    started = time.perf_counter()
    state = base.step(start)                # warm-up: numba compilation, MKL thread start, the split coupling
    result["first_step_s"] = time.perf_counter() - started
    fastest = _fastest_backsolve(base)
    for _ in range(5):
        base.backsolve(rhs)
        fastest(rhs)
    # the default back-solve, the fastest back-solve available and the default imex step, interleaved so all
    # three see the same machine load; ratios are medians of per-round ratios
    rounds = [(_median_ms(lambda: base.backsolve(rhs), 1), _median_ms(lambda: fastest(rhs), 1),
               _median_ms(lambda: base.step(state), 1)) for _ in range(repeats)]
    result["backsolve_ms"] = statistics.median(r[0] for r in rounds)
    result["fastest_backsolve_ms"] = statistics.median(r[1] for r in rounds)
    result["fastest_backsolve"] = getattr(fastest, "label", "the default")
    result["imex_over_backsolve"] = statistics.median(r[2] / r[0] for r in rounds)
    result["imex_over_fastest_backsolve"] = statistics.median(r[2] / r[1] for r in rounds)
    result["steps_ms"] = {"imex": statistics.median(r[2] for r in rounds)}
    for treatment, count in STEPS.items():
        if treatment == "imex":
            continue
        progress(f"timing {treatment} steps")
        solver = NavierStokes(scenario.with_numerics(convection=treatment), space)
        state = solver.step(start)          # warm-up (first factorisation)
        result["steps_ms"][treatment] = _median_ms(lambda: solver.step(state), max(2, min(count, repeats)))
    if pardiso_available() and base.solver_name == "pardiso":
        progress("PARDISO back-solve, one sequential substitution (reproducible, the earlier default)")
        twin = Pardiso(base.constant_matrix(), symmetric=True, reproducible=True)
        twin.solve(rhs)
        result["backsolve_sequential_ms"] = _median_ms(lambda: twin.solve(rhs), max(5, repeats // 2))
        twin.release()
        progress("SuperLU comparison")
        matrix = base.constant_matrix()
        started = time.perf_counter()
        superlu = SuperLU(matrix)
        result["superlu_factorisation_s"] = time.perf_counter() - started
        result["superlu_backsolve_ms"] = _median_ms(lambda: superlu.solve(rhs), max(5, repeats // 4))
    return result


def _fastest_backsolve(base: NavierStokes):
    """The fastest back-solve of the same matrix this machine offers (PARDISO's parallel, non-reproducible
    substitution when MKL loads; else the default's), as a function of the right-hand side with a ``label``."""
    if not pardiso_available() or base.solver_name != "pardiso":
        solve = base.backsolve
        return solve
    twin = Pardiso(base.constant_matrix(), symmetric=True, reproducible=False)

    def solve(rhs):
        return twin.solve(rhs)
    solve.label = "PARDISO, parallel substitution (not reproducible)"
    return solve


def report_lines(result: dict) -> list[str]:
    lines = [
        f"fluid benchmark: h = {result['mesh_h_um']:.3g} um, {result['dofs']:,} DOFs, solver {result['linear_solver']}"
        f" ({'reproducible' if result['reproducible'] else 'parallel, not reproducible'})",
        f"  assembly          {result['assembly_s']:8.2f} s",
        f"  factorisation     {result['factorisation_s']:8.2f} s",
        f"  steady start      {result['steady_solve_s']:8.2f} s",
        f"  first step        {result['first_step_s']:8.2f} s (split solve: its coupling; numba, MKL start-up)",
        f"  bare back-solve   {result['backsolve_ms']:8.2f} ms",
    ]
    for treatment, value in result["steps_ms"].items():
        lines.append(f"  step {treatment:<12} {value:8.2f} ms")
    lines.append(f"  default back-solve: {result['default_solver']}, {result['backsolve_ms']:.2f} ms")
    lines.append(f"  fastest back-solve: {result['fastest_backsolve']}, {result['fastest_backsolve_ms']:.2f} ms")
    lines.append(f"  imex step / default back-solve = {result['imex_over_backsolve']:.2f}; imex step / fastest "
                 f"back-solve = {result['imex_over_fastest_backsolve']:.2f}  (medians of interleaved rounds; "
                 "target <= 1.3)")
    if "backsolve_sequential_ms" in result:
        lines.append(f"  PARDISO, one sequential substitution (reproducible; the default before the split solve): "
                     f"back-solve {result['backsolve_sequential_ms']:.2f} ms")
    if "superlu_backsolve_ms" in result:
        lines.append(f"  SuperLU (MMD on A^T+A): factor {result['superlu_factorisation_s']:.2f} s, "
                     f"back-solve {result['superlu_backsolve_ms']:.2f} ms")
    return lines
