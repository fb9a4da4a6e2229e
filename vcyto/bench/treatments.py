"""`vcyto bench treatments` and `vcyto bench paper`: how far the convection treatments (imex, oseen, stokes)
differ from the fully implicit one, on the flow alone (velocity after the IDT switches on) and on a paper
scenario (outlet, exit time, path distance), with their wall times."""

from __future__ import annotations

import time

import numpy as np

from sim.method.fluid import NavierStokes
from sim.method.taylorhood import TaylorHood
from sim.model.mesh import channel_mesh
from sim.model.scenario import UM, Scenario


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
    from ..studies.paper import paper_scenario, run_paper
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
