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
    result["reproducible"] = scenario.numerics.reproducible
    started = time.perf_counter()
    start = base.steady(0.0)
    result["steady_solve_s"] = time.perf_counter() - started
    rhs = np.random.default_rng(0).standard_normal(len(base.free))
    state = base.step(start)                # warm-up: numba compilation, MKL thread start
    for _ in range(5):
        base.backsolve(rhs)
    # the yardstick and the imex step, interleaved so both see the same machine load
    pairs = [(_median_ms(lambda: base.backsolve(rhs), 1), _median_ms(lambda: base.step(state), 1))
             for _ in range(repeats)]
    result["backsolve_ms"] = statistics.median(p[0] for p in pairs)
    result["imex_over_backsolve"] = statistics.median(p[1] / p[0] for p in pairs)
    result["steps_ms"] = {"imex": statistics.median(p[1] for p in pairs)}
    for treatment, count in STEPS.items():
        if treatment == "imex":
            continue
        progress(f"timing {treatment} steps")
        solver = NavierStokes(scenario.with_numerics(convection=treatment), space)
        state = solver.step(start)          # warm-up (first factorisation)
        result["steps_ms"][treatment] = _median_ms(lambda: solver.step(state), max(2, min(count, repeats)))
    if pardiso_available() and base.solver_name == "pardiso":
        other = not scenario.numerics.reproducible
        progress(f"PARDISO back-solve with reproducible={other}")
        twin = Pardiso(base.constant_matrix(), symmetric=True, reproducible=other)
        twin.solve(rhs)
        result["backsolve_reproducible_ms" if other else "backsolve_parallel_ms"] = \
            _median_ms(lambda: twin.solve(rhs), repeats)
        twin.release()
        progress("SuperLU comparison")
        matrix = base.constant_matrix()
        started = time.perf_counter()
        superlu = SuperLU(matrix)
        result["superlu_factorisation_s"] = time.perf_counter() - started
        result["superlu_backsolve_ms"] = _median_ms(lambda: superlu.solve(rhs), max(5, repeats // 4))
    return result


def report_lines(result: dict) -> list[str]:
    lines = [
        f"fluid benchmark: h = {result['mesh_h_um']:.3g} um, {result['dofs']:,} DOFs, solver {result['linear_solver']}"
        f" ({'reproducible' if result['reproducible'] else 'parallel'} substitution)",
        f"  assembly          {result['assembly_s']:8.2f} s",
        f"  factorisation     {result['factorisation_s']:8.2f} s",
        f"  steady start      {result['steady_solve_s']:8.2f} s",
        f"  bare back-solve   {result['backsolve_ms']:8.2f} ms",
    ]
    for treatment, value in result["steps_ms"].items():
        lines.append(f"  step {treatment:<12} {value:8.2f} ms")
    lines.append(f"  imex step / back-solve = {result['imex_over_backsolve']:.2f}  (median of interleaved pairs; "
                 "target <= 1.3)")
    if "backsolve_parallel_ms" in result:
        lines.append(f"  PARDISO with parallel substitution (numerics.reproducible = false): back-solve "
                     f"{result['backsolve_parallel_ms']:.2f} ms")
    if "backsolve_reproducible_ms" in result:
        lines.append(f"  PARDISO with sequential, reproducible substitution: back-solve "
                     f"{result['backsolve_reproducible_ms']:.2f} ms")
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
            event = DetectorEvent(index, float(times[index]), float(rng.lognormal()), 50.0, 0.095 * rng.uniform(0.9, 1.1),
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


def bench_recording(scenario: Scenario, cells=("RBC", "melanoma"), progress=None) -> dict:
    """The same FE-IB stream with the default recording (MCAP + Rerun .rrd) and without: the overhead."""
    import tempfile
    from pathlib import Path

    from controller.detector import DetectorSettings
    from sim.arrivals import Arrivals
    from sim.plant import FeibPlant

    from .recording import McapRecorder
    from .stream import StreamSettings, run_stream
    from .viewer import RerunSink

    settings = StreamSettings(Arrivals(cells=tuple(cells)))
    plant = FeibPlant(scenario)
    walls = {}
    with tempfile.TemporaryDirectory() as directory:
        for mode in ("without", "with", "without again"):
            if progress:
                progress.note(f"stream {mode} recording")
            sinks = []
            if mode == "with":
                sinks = [McapRecorder(Path(directory) / "run.mcap", {"benchmark": "recording"}),
                         RerunSink(scenario, DetectorSettings().window, ("save", Path(directory) / "run.rrd"))]
            started = time.perf_counter()
            result = run_stream(scenario, settings, plant=plant, sinks=sinks)
            for sink in sinks:
                sink.close()
            walls[mode] = time.perf_counter() - started
            if mode == "with":
                sizes = {name: (Path(directory) / name).stat().st_size for name in ("run.mcap", "run.rrd")}
                steps = round(result["simulated_time_ms"] * 1e-3 / scenario.numerics.dt)
    baseline = min(walls["without"], walls["without again"])
    return {"cells": list(cells), "steps": steps, "wall_s": walls, "overhead": walls["with"] / baseline - 1,
            "file_bytes": sizes}


def recording_lines(result: dict) -> list[str]:
    walls = result["wall_s"]
    return [f"recording overhead: stream {','.join(result['cells'])}, {result['steps']} steps (FE-IB)",
            f"  without recording {walls['without']:.1f} s and {walls['without again']:.1f} s, with MCAP + Rerun "
            f"{walls['with']:.1f} s: overhead {100 * result['overhead']:.1f} % of the faster run (target <= 10 %)",
            f"  files: MCAP {result['file_bytes']['run.mcap'] / 1e6:.2f} MB, Rerun {result['file_bytes']['run.rrd'] / 1e6:.2f} MB"]
