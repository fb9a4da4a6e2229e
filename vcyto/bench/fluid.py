"""`vcyto bench fluid`: what one fluid step costs at a scenario's resolution, piece by piece.

All figures come from one process and one run, so ratios are meaningful on a noisy machine: the
set-up (assembly, factorisation, steady start), the median step of each convection treatment, and the
median bare back-solve of the same factored matrix (PARDISO and SuperLU). The default imex step, its
back-solve and the fastest back-solves available are timed in rounds of back-to-back blocks (``_block_ms``);
each ratio is the median of the per-round ratios.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from sim.fast import store
from sim.fast.linalg import Pardiso, SuperLU, pardiso_available, spinning_openmp_threads
from sim.fast.splitsolve import SplitPardiso
from sim.fast.supernodal import SupernodalLDL
from sim.method.fluid import NavierStokes
from sim.method.taylorhood import TaylorHood
from sim.model.mesh import channel_mesh
from sim.model.scenario import UM, Scenario

STEPS = {"imex": 40, "stokes": 40, "oseen": 4, "implicit": 4}
BLOCK_S = 0.5
ROUNDS = 8


def _median_ms(function, repeats):
    samples = []
    for _ in range(repeats):
        started = time.perf_counter()
        function()
        samples.append(time.perf_counter() - started)
    return 1e3 * statistics.median(samples)


def bench_fluid(scenario: Scenario, repeats: int = 40, progress=lambda message: None, rounds: int = ROUNDS) -> dict:
    """Measure set-up and per-step costs; returns a JSON-ready dict (times in ms unless named _s).

    The set-up cache is off while it runs: it times what a cold start computes."""
    previous = store.install(None)
    try:
        return _bench_fluid(scenario, repeats, progress, rounds)
    finally:
        store.install(previous)


def _bench_fluid(scenario: Scenario, repeats: int, progress, rounds: int) -> dict:
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
    result["default_solver"] = _describe(base._constant.factor)
    result["default_factor_nonzeros"] = base._constant.factor.factor_nonzeros
    started = time.perf_counter()
    state = base.step(start)                # warm-up: MKL's threads, the split coupling
    result["first_step_s"] = time.perf_counter() - started
    progress(f"{rounds} rounds of blocks: the fastest back-solves, the default's back-solve and step")
    fastest = _fastest_backsolves(base)
    double = _double_default(scenario, space, base)
    matched = _matched_default(base)
    theirs = _pardiso_substitutions_default(base)
    factor = base._constant.factor
    counted = (getattr(factor, "solves", 0), getattr(factor, "corrections", 0))
    stepping = {"state": state}

    def step():
        stepping["state"] = base.step(stepping["state"])
    blocks = {name: (lambda f=solve: f(rhs)) for name, solve in fastest.items()}
    blocks["default"] = lambda: base.backsolve(rhs)
    if double is not None:
        blocks["double"] = lambda: double(rhs)
    if matched is not None:
        blocks["matched"] = lambda: matched(rhs)
    if theirs is not None:
        blocks["theirs"] = lambda: theirs(rhs)
    blocks["step"] = step
    timed = [{name: (_hot_block_ms if name in fastest else _block_ms)(function) for name, function in blocks.items()}
             for _ in range(rounds)]
    best = "fastest" if "fastest" in fastest else "default"

    def median(name, over=None):
        return statistics.median(r[name] / (r[over] if over else 1.0) for r in timed)
    result["rounds"] = len(timed)
    result["backsolve_ms"] = median("default")
    result["fastest_backsolve_ms"] = median(best)
    result["fastest_backsolve"] = getattr(fastest.get(best), "label", "the default")
    result["fastest_factor_nonzeros"] = getattr(fastest.get(best), "factor_nonzeros", result["default_factor_nonzeros"])
    if "fastest_single" in fastest:
        result["fastest_single_backsolve_ms"] = median("fastest_single")
        result["fastest_single_backsolve"] = fastest["fastest_single"].label
        result["imex_over_fastest_single_backsolve"] = median("step", "fastest_single")
    if double is not None:
        result["double_backsolve_ms"] = median("double")
        result["double_backsolve"] = double.label
    if matched is not None:
        result["matched_backsolve_ms"] = median("matched")
        result["matched_backsolve"] = matched.label
        result["backsolve_over_matched"] = median("default", "matched")
    if theirs is not None:
        result["pardiso_substitutions_backsolve_ms"] = median("theirs")
        result["pardiso_substitutions_backsolve"] = theirs.label
        result["backsolve_over_pardiso_substitutions"] = median("default", "theirs")
    result["imex_over_backsolve"] = median("step", "default")
    result["imex_over_fastest_backsolve"] = median("step", best)
    result["imex_over_fastest_backsolve_rounds"] = [round(r["step"] / r[best], 3) for r in timed]
    if hasattr(factor, "corrections"):          # mixed precision: refinement corrections per step
        result["corrections_per_step"] = (factor.corrections - counted[1]) / max(1, factor.solves - counted[0])
    for solve in (*fastest.values(), matched, theirs):
        getattr(solve, "release", lambda: None)()          # their factors: memory the next timings do not need
    result["steps_ms"] = {"imex": median("step")}
    result["load_ms"] = _load_ms(base, state, repeats)
    for treatment, count in STEPS.items():
        if treatment == "imex":
            continue
        progress(f"timing {treatment} steps")
        solver = NavierStokes(scenario.with_numerics(convection=treatment), space)
        state = solver.step(start)          # warm-up (first factorisation)
        # each repeat from the same state: no next step's momentum integrals computed ahead (none would be taken)
        result["steps_ms"][treatment] = _median_ms(lambda: solver.step(state, ahead=False),
                                                   max(2, min(count, repeats)))
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
        factor = base._constant.factor
        if isinstance(getattr(factor, "inner", factor), SplitPardiso):    # its halves are what a cache keeps
            progress("the factorisation kept in a set-up cache and restored from it")
            result.update(_kept_factorisation(scenario, space, base, rhs))
    return result


def _load_ms(base: NavierStokes, state, repeats: int) -> dict:
    """The momentum load of one imex step (the element kernel and its scatter): euler's (the mass and the convection
    of v^m) and bdf2's (the mass of (4 v^m - v^{m-1}) / 3 and the convection of 2 v^m - v^{m-1}, one pass)."""
    space, density = base.space, base.scenario.fluid.density
    rhs = np.zeros(len(base.free))
    now, before = state.velocity, 0.99 * state.velocity

    def euler():
        space.momentum_load(now, base.mass_coefficient, density, base.positions, rhs)

    def bdf2():
        space.momentum_load(now, base.mass_coefficient, density, base.positions, rhs,
                            back=((0.0, 1.0, 0.0), (before, before)))
    count = max(10, repeats)
    return {"euler": _median_ms(euler, count), "bdf2": _median_ms(bdf2, count)}


def _kept_factorisation(scenario: Scenario, space, base: NavierStokes, rhs) -> dict:
    """What a warm start pays for the default factorisation (``sim.fast.linalg.Pardiso(kept=True)``): the set-up's
    factorisation time in a run that keeps it (a temporary cache of its own) and in the next, which restores it,
    and whether the restored one solves to the bits of the benchmark's own."""
    import tempfile

    from ..cache import DiskCache
    with tempfile.TemporaryDirectory(prefix="vcyto-bench-") as directory:
        previous = store.install(DiskCache(directory))
        try:
            kept = NavierStokes(scenario.with_numerics(convection="imex"), space)
            restored = NavierStokes(scenario.with_numerics(convection="imex"), space)
        finally:
            store.install(previous)
        identical = bool(np.array_equal(restored.backsolve(rhs), base.backsolve(rhs)))
        return {"factorisation_kept_s": kept.timings.factor, "factorisation_restored_s": restored.timings.factor,
                "restored_factor_identical": identical}


def _block_ms(function) -> float:
    """The median time of ``function`` over the second half of a BLOCK_S block of back-to-back calls.

    Blocks rather than single interleaved calls: the parallel substitution is timed with its OpenMP threads
    spinning between calls (``_hot_block_ms``), and they go on spinning for 200 ms after its block, taking a
    core from whatever runs next (measured: the split solve's back-solve 15-20 ms right after one,
    9.5-11 ms without); and on this virtual machine a core that has idled runs slow for its first few calls.
    The first half of each block absorbs both. A real run steps back to back, as the block does."""
    started = time.perf_counter()
    samples = []
    while (now := time.perf_counter()) - started < BLOCK_S:
        function()
        if now - started >= BLOCK_S / 2:
            samples.append(time.perf_counter() - now)
    if not samples:                       # a call longer than half a block: time one more
        now = time.perf_counter()
        function()
        samples.append(time.perf_counter() - now)
    return 1e3 * statistics.median(samples)


def _hot_block_ms(function) -> float:
    """``_block_ms`` with Intel OpenMP's threads spinning between calls (200 ms), the parallel substitution's
    best setting; vcyto otherwise runs with KMP_BLOCKTIME=0 (``sim.fast.linalg._mkl_runtime``)."""
    with spinning_openmp_threads(200):
        return _block_ms(function)


def _fastest_backsolves(base: NavierStokes) -> dict:
    """The fastest back-solves of the same matrix this machine offers, as functions of the right-hand side
    with a ``label``: PARDISO's parallel, non-reproducible substitution in double precision ("fastest", the
    target's yardstick: the double factor's memory traffic) and in single precision ("fastest_single": half
    the bytes, but a solution to ~1e-6 only). None without PARDISO: the default is then the only one."""
    if not pardiso_available() or base.solver_name != "pardiso":
        return {}
    solves = {}
    for name, single, label in (("fastest", False, "PARDISO, parallel substitution (not reproducible)"),
                                ("fastest_single", True, "PARDISO, parallel substitution in single precision "
                                                         "(not reproducible; ~1e-6 relative)")):
        factor = Pardiso(base.constant_matrix(), symmetric=True, reproducible=False, single=single)
        solves[name] = _labelled(factor.solve, label[:-1] + "; " + _factor_size(factor).strip(" ()") + ")")
        solves[name].factor_nonzeros = factor.factor_nonzeros
        solves[name].release = factor.release
    return solves


def _double_default(scenario: Scenario, space: TaylorHood, base: NavierStokes):
    """The default back-solve in double precision (what the default was before mixed precision), or None
    when the default already is double precision."""
    if scenario.numerics.precision == "double" or base.solver_name != "pardiso":
        return None
    twin = NavierStokes(scenario.with_numerics(convection="imex", precision="double"), space)
    twin.backsolve(np.zeros(len(twin.free)))      # the split solve's coupling
    return _labelled(twin.backsolve, f"{_describe(twin._constant.factor)}, double precision")


def _split_variant(base: NavierStokes, wanted, **options):
    """The default split solve built again with ``options`` (``SplitPardiso``'s), its coupling computed, as a
    labelled back-solve with a ``release``; None unless the default is the split solve and ``wanted(split)``."""
    factor = base._constant.factor
    inner = getattr(factor, "inner", factor)
    if not isinstance(inner, SplitPardiso) or not wanted(inner):
        return None
    twin = SplitPardiso(base.constant_matrix(), base.free_x, single=inner.single, **options)
    twin.solve(np.zeros(twin.shape[0]))         # its coupling
    solve = _labelled(twin.solve, f"{_describe(twin)}{' in single precision' if inner.single else ''}")
    solve.release = twin.release
    return solve


def _matched_default(base: NavierStokes):
    """The default's back-solve with its halves factored with weighted matching (no unknown moved), or
    None when the default is not the split solve."""
    return _split_variant(base, lambda split: True, matching=True)


def _pardiso_substitutions_default(base: NavierStokes):
    """The default's back-solve with PARDISO's substitutions in its halves instead of our own, or
    None when the default does not use our own (``sim.fast.supernodal``)."""
    return _split_variant(base, lambda split: split.own, own=False)


def _labelled(function, label):
    def solve(rhs):
        return function(rhs)
    solve.label = label
    return solve


def _describe(factor) -> str:
    inner = getattr(factor, "inner", None)
    text = type(factor if inner is None else inner).__name__ + _factor_size(factor if inner is None else inner)
    if inner is not None:
        return f"{text} in single precision, refined in double ({type(factor).__name__})"
    return text


def _factor_size(factor) -> str:
    """' (N M factor entries...)': the bytes a back-solve streams (the split solve: its halves' factors, without
    the coupling H); for the split solve how its halves were factored."""
    size = getattr(factor, "factor_nonzeros", None)
    if size is None:
        return ""
    halves = getattr(factor, "halves", ())
    detail = ""
    if halves:
        size = sum(half.factor.factor_nonzeros for half in halves)
        matched = sum(half.matched for half in halves)
        moved = sum(len(half.moved) for half in halves)
        detail = "; halves with weighted matching" if matched == len(halves) else (
            f"; halves {'partly ' if matched else ''}without weighted matching, {moved} unknown{'s' * (moved != 1)}"
            " with perturbed pivots moved to the separator")
        if all(isinstance(half.factor, SupernodalLDL) for half in halves):
            detail += "; our own compiled substitutions"
    return f" ({size / 1e6:.2f} M factor entries{detail})"


def report_lines(result: dict) -> list[str]:
    lines = [
        f"fluid benchmark: h = {result['mesh_h_um']:.3g} um, {result['dofs']:,} DOFs, solver {result['linear_solver']}"
        f" ({'reproducible' if result['reproducible'] else 'parallel, not reproducible'})",
        f"  assembly          {result['assembly_s']:8.2f} s",
        f"  factorisation     {result['factorisation_s']:8.2f} s"
        + (f" (kept in the set-up cache: {result['factorisation_kept_s']:.2f} s; restored from it: "
           f"{result['factorisation_restored_s']:.3f} s, "
           f"{'the same bits' if result['restored_factor_identical'] else 'OTHER BITS'})"
           if "factorisation_restored_s" in result else ""),
        f"  steady start      {result['steady_solve_s']:8.2f} s",
        f"  first step        {result['first_step_s']:8.2f} s (split solve: its coupling; MKL start-up)",
        f"  bare back-solve   {result['backsolve_ms']:8.2f} ms",
    ]
    for treatment, value in result["steps_ms"].items():
        lines.append(f"  step {treatment:<12} {value:8.2f} ms")
    if "load_ms" in result:
        lines.append(f"  momentum load: euler {result['load_ms']['euler']:.2f} ms, bdf2 (one pass) "
                     f"{result['load_ms']['bdf2']:.2f} ms")
    lines.append(f"  default back-solve: {result['default_solver']}, {result['backsolve_ms']:.2f} ms")
    slower = result["fastest_backsolve_ms"] > result["backsolve_ms"]
    lines.append(f"  fastest back-solve (the target's yardstick): {result['fastest_backsolve']}, "
                 f"{result['fastest_backsolve_ms']:.2f} ms"
                 + ((" (slower than the default in this run: the default's own compiled substitutions outrun it)"
                     if "our own" in result["default_solver"] else
                     " (slower than the default in this run: the machine was busy, and a parallel substitution "
                     "suffers most when another process holds a core; rerun on a quiet machine)") if slower else ""))
    if "fastest_single_backsolve_ms" in result:
        lines.append(f"  fastest single-precision back-solve: {result['fastest_single_backsolve']}, "
                     f"{result['fastest_single_backsolve_ms']:.2f} ms (imex step / it = "
                     f"{result['imex_over_fastest_single_backsolve']:.2f})")
    if "matched_backsolve_ms" in result:
        lines.append(f"  the default with matched halves: {result['matched_backsolve']}, back-solve "
                     f"{result['matched_backsolve_ms']:.2f} ms (default / it = {result['backsolve_over_matched']:.2f})")
    if "pardiso_substitutions_backsolve_ms" in result:
        lines.append(f"  the default with PARDISO's substitutions: "
                     f"{result['pardiso_substitutions_backsolve']}, back-solve "
                     f"{result['pardiso_substitutions_backsolve_ms']:.2f} ms (default / it = "
                     f"{result['backsolve_over_pardiso_substitutions']:.2f})")
    if "double_backsolve_ms" in result:
        lines.append(f"  the default in double precision: {result['double_backsolve']}, back-solve "
                     f"{result['double_backsolve_ms']:.2f} ms")
    if "corrections_per_step" in result:
        lines.append(f"  mixed precision: {result['corrections_per_step']:.2f} corrections per timed step")
    lines.append(f"  imex step / default back-solve = {result['imex_over_backsolve']:.2f}; imex step / fastest "
                 f"back-solve = {result['imex_over_fastest_backsolve']:.2f}  (medians of per-round ratios, "
                 f"{result['rounds']} rounds of blocks; target <= 1.3)")
    if "backsolve_sequential_ms" in result:
        lines.append(f"  PARDISO, one sequential substitution (reproducible; the default before the split solve): "
                     f"back-solve {result['backsolve_sequential_ms']:.2f} ms")
    if "superlu_backsolve_ms" in result:
        lines.append(f"  SuperLU (MMD on A^T+A): factor {result['superlu_factorisation_s']:.2f} s, "
                     f"back-solve {result['superlu_backsolve_ms']:.2f} ms")
    return lines
