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
from sim.fluid import NavierStokes, TaylorHood
from sim.linalg import Pardiso, SuperLU, pardiso_available
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


def bench_treatments(scenario: Scenario, steps: int = 20, progress=lambda message: None) -> dict:
    """Switch the IDT on from the steady IDT-off flow and run ``steps`` steps with each treatment.

    Reports each treatment's wall time per step and its velocity's relative L2 (nodal) difference from
    the fully implicit solution (the paper's (26)) at the end.
    """
    space = TaylorHood(channel_mesh(scenario.channel, scenario.numerics.mesh_h))
    progress("steady start (IDT off)")
    start = NavierStokes(scenario.with_numerics(convection="stokes"), space).steady(0.0)
    finals, timings = {}, {}
    for treatment in ("implicit", "oseen", "imex", "stokes"):
        progress(f"{steps} steps with {treatment}")
        solver = NavierStokes(scenario.with_numerics(convection=treatment), space)
        state = start
        started = time.perf_counter()
        for _ in range(steps):
            state = solver.step(state, actuation=1.0)
        timings[treatment] = 1e3 * (time.perf_counter() - started) / steps
        finals[treatment] = state.velocity
    reference = finals["implicit"]
    scale = np.linalg.norm(reference)
    return {
        "mesh_h_um": scenario.numerics.mesh_h / UM, "dt_us": scenario.numerics.dt * 1e6, "steps": steps,
        "saw_model": scenario.saw.model,
        "step_ms": timings,
        "difference_from_implicit": {t: float(np.linalg.norm(v - reference) / scale) for t, v in finals.items()},
    }


def treatment_lines(result: dict) -> list[str]:
    lines = [f"convection treatments: IDT switched on ({result['saw_model']} SAW), {result['steps']} steps of "
             f"{result['dt_us']:g} us, h = {result['mesh_h_um']:.3g} um",
             "  treatment    ms/step   |v - v_implicit| / |v_implicit|"]
    for treatment, value in result["step_ms"].items():
        lines.append(f"  {treatment:<11} {value:8.2f}   {result['difference_from_implicit'][treatment]:.2e}")
    return lines


def bench_paper_treatments(number: int, scenario: Scenario, treatments=("imex", "implicit"), progress=None) -> dict:
    """Run paper scenario ``number`` with each convection treatment; outlet, exit time and path differences
    from the first listed as the reference is the last (the fully implicit one by default)."""
    from .paper import paper_scenario, run_paper
    runs = {}
    for treatment in treatments:
        if progress:
            progress.note(f"paper scenario {number} with {treatment} convection")
        chosen = paper_scenario(number, scenario, dt_given=False).with_numerics(convection=treatment)
        started = time.perf_counter()
        result = run_paper(number, chosen, progress=None)
        runs[treatment] = (result, time.perf_counter() - started)
    reference, _ = runs[treatments[-1]]
    rows = {}
    for treatment, (result, wall) in runs.items():
        steps = min(len(result["_path"]), len(reference["_path"]))
        distance = np.linalg.norm(result["_path"][:steps] - reference["_path"][:steps], axis=1)
        cell, reference_cell = result["cells"][0], reference["cells"][0]
        rows[treatment] = {
            "outlet": cell["outlet"], "exit_time_ms": cell["exit_time_ms"], "exit_y_um": cell["exit_y_um"],
            "exit_time_difference_us": 1e3 * (cell["exit_time_ms"] - reference_cell["exit_time_ms"]),
            "path_max_distance_um": float(distance.max() / UM), "path_mean_distance_um": float(distance.mean() / UM),
            "wall_time_s": wall, "steps": result["steps"],
        }
    return {"scenario": number, "reference": treatments[-1], "runs": rows}


def paper_treatment_lines(result: dict) -> list[str]:
    lines = [f"paper scenario {result['scenario']}: convection treatments against {result['reference']}",
             "  treatment  outlet  exit (ms)  exit y (um)  d exit (us)  path max / mean (um)  wall (s)"]
    for treatment, row in result["runs"].items():
        lines.append(f"  {treatment:<10} {row['outlet']:<6} {row['exit_time_ms']:9.4f} {row['exit_y_um']:12.2f} "
                     f"{row['exit_time_difference_us']:12.2f} {row['path_max_distance_um']:10.3f} / "
                     f"{row['path_mean_distance_um']:.3f} {row['wall_time_s']:9.1f}")
    return lines


def bench_controller(events: int = 20_000, rate: float = 1000.0, control_period: float = 10e-6, seed: int = 0) -> dict:
    """Decision latency of the sorting controller on a synthetic Poisson stream of detector events.

    Each control period the controller gets the events completed in it, then is asked for the IDT drive;
    the wall time of each call is one sample (the decision for an event, the drive for a period).
    """
    from controller.events import TYPE_I, TYPE_II, DetectorEvent
    from controller.sorter import ControllerSettings, SortController

    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.exponential(1 / rate, size=events))
    controller = SortController(ControllerSettings())
    event_samples, drive_samples = [], []
    index, now = 0, 0.0
    while index < events:
        now += control_period
        while index < events and times[index] <= now:
            event = DetectorEvent(index, float(times[index]), float(rng.lognormal()), 50.0, 0.095 * rng.uniform(0.9,
                                                                                                                1.1),
                                  TYPE_II if rng.random() < 0.3 else TYPE_I, index)
            started = time.perf_counter()
            controller.on_event(event)
            event_samples.append(time.perf_counter() - started)
            index += 1
        started = time.perf_counter()
        controller.actuation(now)
        drive_samples.append(time.perf_counter() - started)

    def summary(samples):
        micro = np.array(samples) * 1e6
        return {"median_us": float(np.median(micro)), "p99_us": float(np.percentile(micro, 99)),
                "max_us": float(micro.max()), "samples": len(micro)}

    return {"events": events, "rate_per_s": rate, "control_period_us": control_period * 1e6,
            "decision": summary(event_samples), "actuation": summary(drive_samples)}


def controller_lines(result: dict) -> list[str]:
    lines = [f"controller latency: {result['events']:,} Poisson events at {result['rate_per_s']:g}/s, control period "
             f"{result['control_period_us']:g} us"]
    for key in ("decision", "actuation"):
        row = result[key]
        lines.append(f"  {key:<10} median {row['median_us']:6.2f} us, p99 {row['p99_us']:6.2f} us, "
                     f"max {row['max_us']:7.1f} us ({row['samples']:,} calls; target p99 <= 50 us)")
    return lines


def bench_recording(scenario: Scenario, cells=("RBC", "melanoma"), repeats: int = 3, progress=None) -> dict:
    """The same FE-IB stream without and with the default recording (MCAP + Rerun .rrd, written on the
    background thread of ``vcyto.sinks``), in ``repeats`` interleaved pairs: the median overhead."""
    import tempfile
    from pathlib import Path

    from controller.detector import DetectorSettings
    from sim.arrivals import Arrivals
    from sim.plant import FeibPlant

    from .recording import McapRecorder
    from .rerunlog import RerunSink
    from .sinks import BackgroundSinks
    from .stream import StreamSettings, run_stream

    settings = StreamSettings(Arrivals(cells=tuple(cells)))
    plant = FeibPlant(scenario)
    run_stream(scenario, settings.__class__(Arrivals(cells=tuple(cells[:1])), max_time=50e-6), plant=plant)  # warm-up
    pairs = []
    with tempfile.TemporaryDirectory() as directory:
        for repeat in range(repeats):
            walls = {}
            for mode in ("without", "with"):
                if progress:
                    progress.note(f"pair {repeat + 1}/{repeats}: stream {mode} recording")
                sinks = []
                if mode == "with":
                    sinks = [BackgroundSinks([McapRecorder(Path(directory) / "run.mcap", {"benchmark": "recording"},
                                                           scenario=scenario,
                                                           detection_window=DetectorSettings().window),
                                              RerunSink(scenario, DetectorSettings().window,
                                                        ("save", Path(directory) / "run.rrd"))])]
                started = time.perf_counter()
                result = run_stream(scenario, settings, plant=plant, sinks=sinks)
                for sink in sinks:
                    sink.close()
                walls[mode] = time.perf_counter() - started
            pairs.append(walls)
        sizes = {name: (Path(directory) / name).stat().st_size for name in ("run.mcap", "run.rrd")}
    steps = round(result["simulated_time_ms"] * 1e-3 / scenario.numerics.dt)
    overheads = [pair["with"] / pair["without"] - 1 for pair in pairs]
    return {"cells": list(cells), "steps": steps, "pairs_s": pairs, "overheads": overheads,
            "overhead": float(np.median(overheads)), "file_bytes": sizes}


def recording_lines(result: dict) -> list[str]:
    pairs = "; ".join(f"{p['without']:.1f} s / {p['with']:.1f} s" for p in result["pairs_s"])
    return [f"recording overhead: stream {','.join(result['cells'])}, {result['steps']} steps (FE-IB)",
            f"  without / with MCAP + Rerun, interleaved pairs: {pairs}",
            f"  overhead per pair {', '.join(f'{100 * o:.1f} %' for o in result['overheads'])}: "
            f"median {100 * result['overhead']:.1f} % (target <= 10 %)",
            f"  files: MCAP {result['file_bytes']['run.mcap'] / 1e6:.2f} MB, "
            f"Rerun {result['file_bytes']['run.rrd'] / 1e6:.2f} MB"]

def bench_membrane(scenario: Scenario, repeats: int = 2, progress=None) -> dict:
    """The paper's literal membrane method against the conserving one (README, "Cells that keep their size"):
    a melanoma at rest in the shut device for 5 ms, and the paper's scenarios I and II, in interleaved runs;
    area kept, point spacing, outlets and the cost per step (median of ``repeats``)."""
    from sim.feib import ImmersedBoundary, State

    from .paper import paper_scenario, run_paper

    note = progress.note if progress else (lambda message: None)
    methods = ("paper", "conserving")
    rows = []
    for method in ("paper",) + methods:             # the first run warms the kernels up and is not kept
        note(f"melanoma at rest, 5 ms, {method}")
        shut = scenario.with_membrane(method).with_inlets_shut().with_numerics(dt=25e-6, convection="stokes")
        plant = ImmersedBoundary(shut)
        state = State(plant.fluid.rest(), (plant.new_cell(shut.cell_type("melanoma"), 0, 0.0, (150 * UM, 110 * UM)),))
        while state.time < 5e-3 - 1e-9:
            state = plant.step(state)
        measures = state.cells[0].measures
        rows.append({"case": "melanoma at rest, 5 ms", "method": method, "outlet": "-",
                     "area_ratio": [measures.area_ratio_min, measures.area_ratio_max],
                     "area_corrected": measures.area_corrected,
                     "spacing_over_h": [measures.spacing_lowest, measures.spacing_highest],
                     "per_step_ms": [1e3 * (plant.timings.fluid + plant.timings.membrane + plant.timings.health)
                                         / plant.timings.steps],
                     "membrane_ms": [1e3 * (plant.timings.membrane + plant.timings.health) / plant.timings.steps]})
    del rows[0]
    for number in (2, 1):
        runs = {method: [] for method in methods}
        for repeat in range(repeats):
            for method in methods:
                note(f"scenario {number}, {method} ({repeat + 1}/{repeats})")
                runs[method].append(run_paper(number, paper_scenario(number, scenario.with_membrane(method), False)))
        for method in methods:
            cell = runs[method][-1]["cells"][0]
            final = runs[method][-1]["_final"].measures
            walls = [run["wall_time_s"] for run in runs[method]]
            rows.append({"case": f"scenario {number}", "method": method, "outlet": cell["outlet"],
                         "exit_time_ms": cell["exit_time_ms"], "exit_y_um": cell["exit_y_um"],
                         "area_ratio": [cell["area_ratio_min"], cell["area_ratio_max"]],
                         "area_corrected": final.area_corrected, "spacing_over_h": cell["spacing_over_h"],
                         "membrane_points": cell["membrane_points"], "redistributions": cell["redistributions"],
                         "per_step_ms": [w["per_step_ms"] for w in walls],
                         "membrane_ms": [1e3 * (w["membrane"] + w["health_checks"]) / run["steps"]
                                         for w, run in zip(walls, runs[method])]})
        paper, conserving = rows[-2], rows[-1]
        conserving["cost_ratio"] = [c / p for c, p in zip(conserving["per_step_ms"], paper["per_step_ms"])]
        extra_ms = statistics.median(conserving["membrane_ms"]) - statistics.median(paper["membrane_ms"])
        conserving["membrane_extra"] = extra_ms / statistics.median(paper["per_step_ms"])
    return {"rows": rows, "repeats": repeats}


def membrane_lines(result: dict) -> list[str]:
    lines = ["| case | method | outlet | area / initial (min-max) | restored by projection | spacing / h | "
             "ms per step (median) | membrane + checks ms/step | conserving / paper cost per step (runs) | "
             "extra membrane work / paper step |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in result["rows"]:
        ratio = row.get("cost_ratio")
        lines.append(
            f"| {row['case']} | {row['method']} | {row['outlet']} | {100 * row['area_ratio'][0]:.2f}-"
            f"{100 * row['area_ratio'][1]:.2f} % | {100 * row['area_corrected']:.2f} % | "
            f"{row['spacing_over_h'][0]:.2f}-{row['spacing_over_h'][1]:.2f} | "
            f"{statistics.median(row['per_step_ms']):.2f} | "
            f"{statistics.median(row['membrane_ms']):.3f} | "
            + (f"{', '.join(f'{r:.3f}' for r in ratio)} (median {statistics.median(ratio):.3f})" if ratio else "")
            + (f" | {100 * row['membrane_extra']:+.1f} %" if "membrane_extra" in row else " |") + " |")
    return lines


def bench_sweep(spec_path, worker_counts=(1, 2), repeats: int = 1, progress=None) -> dict:
    """The same sweep on a local pool of each size in ``worker_counts``, ``repeats`` times (sizes interleaved, so
    machine load falls on all alike); whole-sweep wall times (pool start, imports and plant builds included) and
    the speed-up over the first size. Each run starts from an empty table in a temporary directory."""
    import os
    import tempfile
    from pathlib import Path

    from . import sweep
    plan = sweep.load_sweep(spec_path)
    walls = {workers: [] for workers in worker_counts}
    point_seconds = {workers: [] for workers in worker_counts}
    for repeat in range(repeats):
        for workers in worker_counts:
            if progress:
                progress.note(f"{len(plan.points)} points on {workers} worker(s) ({repeat + 1}/{repeats})")
            with tempfile.TemporaryDirectory() as directory:
                started = time.perf_counter()
                with sweep.executor(None, workers) as (pool, slots, _):
                    result = sweep.run_sweep(plan, Path(directory), pool, slots)
                walls[workers].append(time.perf_counter() - started)
            if result["failed"]:
                raise RuntimeError(f"{result['failed']} point(s) of the benchmark sweep failed")
            point_seconds[workers].append(sum(row["wall_time_s"] for row in result["rows"]))
    medians = {workers: statistics.median(times) for workers, times in walls.items()}
    first = worker_counts[0]
    return {"spec": str(spec_path), "points": len(plan.points),
            "models": sorted({p.settings.model for p in plan.points}),
            "repeats": repeats, "wall_s": walls, "median_wall_s": medians, "point_work_s": point_seconds,
            "speed_up": {workers: medians[first] / medians[workers] for workers in worker_counts},
            "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()}


def sweep_lines(result: dict) -> list[str]:
    first = next(iter(result["median_wall_s"]))
    lines = [f"{result['points']} points of {result['spec']} (model {', '.join(result['models'])}), "
             f"{result['repeats']} run(s) per pool size, {result['cpus']} CPUs; whole sweep, pool start included:"]
    for workers, median in result["median_wall_s"].items():
        runs = ", ".join(f"{t:.1f}" for t in result["wall_s"][workers])
        work = statistics.median(result["point_work_s"][workers])
        lines.append(f"  {workers} worker(s): median {median:.1f} s (runs {runs} s; points' own time {work:.1f} s), "
                     f"speed-up {result['speed_up'][workers]:.2f}x over {first}")
    return lines


def bench_realtime(scenario: Scenario, rate: float = 1000.0, duration: float = 1.0,
                   mix=(("RBC", 0.9), ("melanoma", 0.1)), repeats: int = 3, control_period: float | None = None,
                   seed: int = 0, progress=lambda message: None) -> dict:
    """Real-time factor of the closed loop with the ``rom`` plant: a Poisson stream of ``rate`` x ``duration``
    cells (no dead time), detector and controller in the loop, no recording.

    Set-up (the two steady FE solves, sampling the grid, loading the kernels) is timed once; then the same
    stream runs ``repeats`` times on that plant. Loop wall = the run's wall time minus its own set-up
    (schedule, reset); real-time factor = device time simulated / loop wall; the median over repeats.
    """
    from sim.arrivals import Arrivals

    from .stream import StreamSettings, make_plant, run_stream

    arrivals = Arrivals(count=max(1, round(rate * duration)), mix=tuple(mix), rate=rate, process="poisson",
                        min_spacing=0.0)
    settings = StreamSettings(arrivals, model="rom", seed=seed, control_period=control_period,
                              max_time=2 * duration + 20e-3)
    progress("set-up: steady flows with the IDT off and on, sampled on the grid")
    started = time.perf_counter()
    plant = make_plant(scenario, settings)
    setup = time.perf_counter() - started
    runs = []
    for repeat in range(repeats):
        progress(f"run {repeat + 1} of {repeats}")
        result = run_stream(scenario, settings, plant=plant)
        loop = result["wall_time_s"] - result["setup_time_s"]
        runs.append({"loop_wall_s": loop, "device_time_s": result["simulated_time_ms"] * 1e-3,
                     "real_time_factor": result["simulated_time_ms"] * 1e-3 / loop})
    stats = result["statistics"]
    return {
        "model": "rom", "rate_per_s": rate, "duration_s": duration, "cells": arrivals.count,
        "mix": [list(pair) for pair in mix], "seed": seed, "control_period_us": plant.control_period * 1e6,
        "substep_us": plant.control_period / plant.substeps * 1e6, "response_time_us": plant.response_time * 1e6,
        "grid_spacing_um": [s / UM for s in plant.flows.spacing],
        "setup_s": setup, "setup_parts_s": dict(plant.timings),
        "runs": runs, "loop_wall_s": statistics.median(r["loop_wall_s"] for r in runs),
        "device_time_s": runs[-1]["device_time_s"],
        "real_time_factor": statistics.median(r["real_time_factor"] for r in runs),
        "purity": stats["purity"], "yield": stats["yield"], "abort_rate": stats["abort_rate"],
        "outlets": stats["outlets"], "misclassified": stats["misclassified"],
    }


def realtime_lines(result: dict) -> list[str]:
    def percent(value):
        return "n/a" if value is None else f"{100 * value:.1f} %"

    parts = ", ".join(f"{name.removesuffix('_s').replace('_', ' ')} {value:.2f} s"
                      for name, value in result["setup_parts_s"].items())
    factors = ", ".join(f"{run['real_time_factor']:.1f}" for run in result["runs"])
    return [
        f"real time: rom plant, {result['cells']:,} cells at {result['rate_per_s']:g}/s (Poisson, "
        f"{', '.join(f'{name}:{weight:g}' for name, weight in result['mix'])}), control period "
        f"{result['control_period_us']:g} us, detector and controller in the loop, no recording",
        f"  set-up {result['setup_s']:.2f} s ({parts})",
        f"  loop: {result['device_time_s'] * 1e3:.1f} ms of device time in {result['loop_wall_s'] * 1e3:.1f} ms wall "
        f"(median of {len(result['runs'])})",
        f"  real-time factor {result['real_time_factor']:.1f} (runs: {factors}; target >= 10)",
        f"  purity {percent(result['purity'])}, yield {percent(result['yield'])}, abort rate "
        f"{percent(result['abort_rate'])}, outlets {result['outlets']}",
    ]


def bench_auto(scenario: Scenario, count: int = 100, rate: float = 500.0, mix=(("RBC", 0.8), ("melanoma", 0.2)),
               seed: int = 0, progress=None) -> dict:
    """The same mixed Poisson stream with ``--model auto`` and ``--model feib``: outcomes cell by cell, and
    the wall time of each (set-up apart)."""
    from sim.arrivals import Arrivals

    from .stream import StreamSettings, StreamStopped, run_stream

    arrivals = Arrivals(count=count, mix=tuple(mix), rate=rate, process="poisson")
    results = {}
    for model in ("auto", "feib"):
        if progress:
            progress.note(f"{count}-cell stream with the {model} model")
        try:
            results[model] = run_stream(scenario, StreamSettings(arrivals, model=model, seed=seed))
        except StreamStopped as error:           # reported, not hidden: the comparison cannot be made
            if error.status != "failed":
                raise
            return {"cells": count, "rate": rate, "failed": model, "error": str(error)}
    auto, feib = results["auto"], results["feib"]
    pairs = list(zip(auto["cells"], feib["cells"]))
    differ = [{"key": a["key"], "type": a["type"], "arrival_ms": f["arrival_ms"], "auto": a["outlet"],
               "feib": f["outlet"], "auto_exit_y_um": a["exit_y_um"], "feib_exit_y_um": f["exit_y_um"]}
              for a, f in pairs if a["outlet"] != f["outlet"]]
    exit_errors = [abs(a["exit_time_ms"] - f["exit_time_ms"]) for a, f in pairs
                   if a["exit_time_ms"] is not None and f["exit_time_ms"] is not None]
    run = {model: r["wall_time_s"] - r["setup_time_s"] for model, r in results.items()}
    return {"cells": count, "rate": rate, "mix": [list(m) for m in mix], "seed": seed,
            "simulated_ms": feib["simulated_time_ms"], "outlets_differ": differ,
            "exit_time_error_ms": {"max": max(exit_errors), "median": float(np.median(exit_errors))},
            "statistics": {model: r["statistics"] for model, r in results.items()},
            "wall_s": {model: r["wall_time_s"] for model, r in results.items()},
            "setup_s": {model: r["setup_time_s"] for model, r in results.items()},
            "run_s": run, "speedup_run": run["feib"] / run["auto"],
            "speedup_total": results["feib"]["wall_time_s"] / results["auto"]["wall_time_s"],
            "feib_fraction": auto.get("auto", {}).get("feib_fraction"),
            "switches": len(auto.get("auto", {}).get("switches", [])) - 1,
            "outcomes": [{"key": a["key"], "type": a["type"], "auto": a["outlet"], "feib": f["outlet"],
                          "auto_exit_ms": a["exit_time_ms"], "feib_exit_ms": f["exit_time_ms"]} for a, f in pairs]}


def _fraction(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def _exit_at(y_um) -> str:
    return f" (exit at y = {y_um:.1f} um)" if y_um is not None else ""


def auto_lines(result: dict) -> list[str]:
    if "failed" in result:
        return [f"{result['cells']}-cell stream: the {result['failed']} run stopped: {result['error']}"]
    stats = result["statistics"]
    differ = "".join(f"; cell {d['key']} ({d['type']}, arrived {d['arrival_ms']:.3f} ms): auto {d['auto']}"
                     f"{_exit_at(d['auto_exit_y_um'])}, feib {d['feib']}{_exit_at(d['feib_exit_y_um'])}"
                     for d in result["outlets_differ"])
    return [f"{result['cells']}-cell Poisson stream at {result['rate']:g}/s ({result['simulated_ms']:.1f} ms of device "
            f"time), seed {result['seed']}: auto against feib",
            f"  outlets that differ: {len(result['outlets_differ'])} of {result['cells']}{differ}",
            f"  exit time difference: median {result['exit_time_error_ms']['median'] * 1e3:.1f} us, "
            f"max {result['exit_time_error_ms']['max'] * 1e3:.1f} us",
            f"  purity / yield: auto {_fraction(stats['auto']['purity'])} / {_fraction(stats['auto']['yield'])}, "
            f"feib {_fraction(stats['feib']['purity'])} / {_fraction(stats['feib']['yield'])}",
            f"  wall: auto {result['wall_s']['auto']:.1f} s (set-up {result['setup_s']['auto']:.1f} s), feib "
            f"{result['wall_s']['feib']:.1f} s (set-up {result['setup_s']['feib']:.1f} s): "
            f"{result['speedup_run']:.1f}x "
            f"faster without set-up, {result['speedup_total']:.1f}x with",
            f"  auto ran feib for {100 * result['feib_fraction']:.1f} % of the periods ({result['switches']} switches)"]
