"""`vcyto bench coupling`: the explicit membrane coupling against the implicit one (``sim.coupling``) in Scenario II:
cost per step, the largest step of a ladder that reaches an outlet, and the path error against the explicit run at
the finest step.

Every run is Scenario II (the melanoma, IDT on) from entry to exit on the options' mesh with the options' membrane
method. The reference is the explicit run at ``--dt`` (default 2.5 us). Each coupling then runs at each step of the
ladder; a run ends at the outlet or at the health check that stops it (the step is beyond its stability). The path
error is the centroid's ordinate against the reference's at the same abscissa (max over the transit: where the cell
goes), and the distance at the same times (max: the first-order time scheme's lag along the path is most of it).
The cost per step is measured apart, in interleaved runs of ``steps`` steps of each coupling at the same dt from the
same start (median of ``repeats``)."""

from __future__ import annotations

import statistics
import time

import numpy as np

from sim.model.scenario import UM, Scenario

from .tolerance import path_distance


def lateral_distance(path, reference_path) -> np.ndarray:
    """|y - y_ref(x)| of the centroid ``path`` (n, 2) against the reference path taken at the same abscissa (within
    the reference's span of x)."""
    keep = (path[:, 0] >= reference_path[0, 0]) & (path[:, 0] <= reference_path[-1, 0])
    return np.abs(path[keep, 1] - np.interp(path[keep, 0], reference_path[:, 0], reference_path[:, 1]))


def bench_coupling(base: Scenario, steps=(5e-6, 10e-6, 25e-6, 50e-6, 100e-6), repeats: int = 3,
                   cost_steps: int = 20, progress=lambda message: None) -> dict:
    from sim.method.fluid import NumericalBlowUp
    from sim.method.health import HealthError

    from ..studies.paper import paper_scenario, run_paper
    base = base.with_numerics(tolerance=0.0, time_scheme="euler")
    reference_dt = base.numerics.dt
    progress(f"reference: explicit, dt = {reference_dt * 1e6:g} us")
    reference = run_paper(2, paper_scenario(2, base.with_numerics(membrane_coupling="explicit"), dt_given=True))
    rows = [_row("explicit", reference_dt, reference, reference)]
    for coupling in ("explicit", "implicit"):
        for dt in steps:
            progress(f"{coupling}, dt = {dt * 1e6:g} us")
            scenario = paper_scenario(2, base.with_numerics(dt=dt, membrane_coupling=coupling), dt_given=True)
            try:
                run = run_paper(2, scenario)
            except (HealthError, NumericalBlowUp) as error:
                rows.append({"coupling": coupling, "dt_us": dt * 1e6, "outlet": "failed",
                             "failure": str(error).split(";")[0]})
                continue
            rows.append(_row(coupling, dt, run, reference))
    costs = per_step_costs(base, repeats, cost_steps, progress)
    largest = {coupling: max((row["dt_us"] for row in rows if row["coupling"] == coupling
                              and row["outlet"] not in ("failed", "lost")), default=None) for coupling in costs}
    return {"mesh_h_um": base.numerics.mesh_h / UM, "membrane_method": base.membrane_method(),
            "reference_dt_us": reference_dt * 1e6, "rows": rows,
            "per_step_ms": {coupling: statistics.median(values) for coupling, values in costs.items()},
            "per_step_runs_ms": costs, "largest_reaching_outlet_us": largest}


def _row(coupling, dt, run, reference) -> dict:
    cell = run["cells"][0]
    return {"coupling": coupling, "dt_us": dt * 1e6, "outlet": cell["outlet"], "exit_y_um": cell["exit_y_um"],
            "exit_y_error_um": abs(cell["exit_y_um"] - reference["cells"][0]["exit_y_um"]),
            "lateral_error_um": float(lateral_distance(run["_path"], reference["_path"]).max() / UM),
            "distance_at_times_um": float(path_distance(run["_times"], run["_path"], reference["_times"],
                                                        reference["_path"]).max() / UM),
            "steps": run["steps"], "stepping_s": run["wall_time_s"]["stepping"]}


def per_step_costs(scenario: Scenario, repeats: int, steps: int, progress=lambda message: None) -> dict:
    """{coupling: [wall time per step (ms), one per repeat]}: interleaved runs of ``steps`` steps of Scenario II's
    melanoma from its start (after one step, which builds what the coupling needs once), one fluid solver shared."""
    from sim.method.feib import ImmersedBoundary
    from sim.method.fluid import NavierStokes
    from sim.method.openloop import with_cells
    fluid = NavierStokes(scenario)
    start = fluid.steady(1.0)
    costs = {"explicit": [], "implicit": []}
    for repeat in range(repeats):
        for coupling, runs in costs.items():
            progress(f"cost per step: {coupling}, {steps} steps of {scenario.numerics.dt * 1e6:g} us "
                     f"({repeat + 1}/{repeats})")
            plant = ImmersedBoundary(scenario.with_numerics(membrane_coupling=coupling), fluid)
            state = plant.step(with_cells(plant, start, [(scenario.cell_type("melanoma"), None)]), 1.0)
            started = time.perf_counter()
            for _ in range(steps):
                state = plant.step(state, 1.0)
            runs.append(1e3 * (time.perf_counter() - started) / steps)
    return costs


def coupling_lines(result: dict) -> list[str]:
    per_step = result["per_step_ms"]
    lines = [f"Scenario II on the {result['mesh_h_um']:.4g} um mesh ({result['membrane_method']} membrane method), "
             f"against the explicit run at {result['reference_dt_us']:g} us",
             "| coupling | dt (us) | outlet | exit y (um) | exit y error (um) | path error, same x (um) | "
             "distance at same times (um) | steps | stepping (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in result["rows"]:
        if row["outlet"] == "failed":
            lines.append(f"| {row['coupling']} | {row['dt_us']:g} | failed: {row['failure']} | | | | | | |")
            continue
        lines.append(f"| {row['coupling']} | {row['dt_us']:g} | {row['outlet']} | {row['exit_y_um']:.2f} | "
                     f"{row['exit_y_error_um']:.2f} | {row['lateral_error_um']:.2f} | "
                     f"{row['distance_at_times_um']:.2f} | {row['steps']} | {row['stepping_s']:.1f} |")
    largest = result["largest_reaching_outlet_us"]
    runs = len(result["per_step_runs_ms"]["explicit"])
    lines.append(f"cost per step at {result['reference_dt_us']:g} us (median of {runs} interleaved runs): explicit "
                 f"{per_step['explicit']:.1f} ms, implicit {per_step['implicit']:.1f} ms "
                 f"({per_step['implicit'] / per_step['explicit']:.2f}x)")
    lines.append("largest step of the ladder reaching an outlet: " + ", ".join(
        f"{coupling} {value:g} us" if value else f"{coupling} none" for coupling, value in largest.items()))
    return lines
