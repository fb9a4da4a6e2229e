"""`vcyto bench fluid`: what one fluid step costs at a scenario's resolution, piece by piece.

All figures come from one process and one run, so ratios are meaningful on a noisy machine: the
set-up (assembly, factorisation, steady start), the median step of each convection treatment, and the
median bare back-solve of the same factored matrix (PARDISO and SuperLU), with imex / back-solve.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from sim.fluid import NavierStokes, TaylorHood
from sim.linalg import SuperLU, pardiso_available
from sim.mesh import channel_mesh
from sim.scenario import UM, Scenario

STEPS = {"imex": 40, "stokes": 40, "oseen": 4, "implicit": 4}


def _median_ms(function, repeats):
    samples = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        samples.append(time.perf_counter() - started)
    return 1e3 * statistics.median(samples)


def bench_fluid(scenario: Scenario, repeats: int = 40, progress=lambda message: None) -> dict:
    """Measure set-up and per-step costs; returns a JSON-ready dict (times in ms unless named _s)."""
    result = {"mesh_h_um": scenario.numerics.mesh_h / UM}
    started = time.perf_counter()
    space = TaylorHood(channel_mesh(scenario.channel, scenario.numerics.mesh_h))
    result["assembly_s"] = time.perf_counter() - started
    result["dofs"] = space.dofs
    progress(f"{space.dofs:,} DOFs assembled in {result['assembly_s']:.2f} s; steady start")
    base = NavierStokes(scenario.with_numerics(convection="imex"), space)
    result["factorisation_s"] = base.timings.factor
    result["linear_solver"] = base.solver_name
    started = time.perf_counter()
    start = base.steady(0.0)
    result["steady_solve_s"] = time.perf_counter() - started
    rhs = np.random.default_rng(0).standard_normal(len(base.free))
    base.backsolve(rhs)
    result["backsolve_ms"] = _median_ms(lambda: base.backsolve(rhs), repeats)
    result["steps_ms"] = {}
    for treatment, count in STEPS.items():
        progress(f"timing {treatment} steps")
        solver = base if treatment == "imex" else NavierStokes(scenario.with_numerics(convection=treatment), space)
        state = solver.step(start)          # warm-up (numba compilation, first factorisation)
        count = max(2, min(count, repeats))
        result["steps_ms"][treatment] = _median_ms(lambda: solver.step(state), count)
    result["backsolve_after_steps_ms"] = _median_ms(lambda: base.backsolve(rhs), repeats)
    backsolve = statistics.median([result["backsolve_ms"], result["backsolve_after_steps_ms"]])
    result["imex_over_backsolve"] = result["steps_ms"]["imex"] / backsolve
    if pardiso_available() and base.solver_name == "pardiso":
        progress("SuperLU comparison")
        matrix = base.constant_matrix()
        started = time.perf_counter()
        superlu = SuperLU(matrix)
        result["superlu_factorisation_s"] = time.perf_counter() - started
        result["superlu_backsolve_ms"] = _median_ms(lambda: superlu.solve(rhs), max(5, repeats // 4))
    return result


def report_lines(result: dict) -> list[str]:
    lines = [
        f"fluid benchmark: h = {result['mesh_h_um']:.3g} um, {result['dofs']:,} DOFs, solver {result['linear_solver']}",
        f"  assembly          {result['assembly_s']:8.2f} s",
        f"  factorisation     {result['factorisation_s']:8.2f} s",
        f"  steady start      {result['steady_solve_s']:8.2f} s",
        f"  bare back-solve   {result['backsolve_ms']:8.2f} ms  (again after the steps: "
        f"{result['backsolve_after_steps_ms']:.2f} ms)",
    ]
    for treatment, value in result["steps_ms"].items():
        lines.append(f"  step {treatment:<12} {value:8.2f} ms")
    lines.append(f"  imex step / back-solve = {result['imex_over_backsolve']:.2f}  (target <= 1.3)")
    if "superlu_backsolve_ms" in result:
        lines.append(f"  SuperLU (MMD on A^T+A): factor {result['superlu_factorisation_s']:.2f} s, "
                     f"back-solve {result['superlu_backsolve_ms']:.2f} ms")
    return lines
