"""`vcyto bench membrane`: the paper's literal membrane method against the conserving one and the conserving one
with the area kept by the step (``multiplier``): area kept, what the projection restored, point spacing, outlets
and cost per step, on a melanoma at rest and on the paper's scenarios."""

from __future__ import annotations

import statistics

from sim.model.scenario import UM, Scenario


def bench_membrane(scenario: Scenario, repeats: int = 2, progress=None) -> dict:
    """The paper's literal membrane method against the conserving ones (docs/numerics.md, "Cells that keep their
    size"): a melanoma at rest in the shut device for 5 ms, and the paper's scenarios I and II, in interleaved runs;
    area kept, point spacing, outlets and the cost per step (median of ``repeats``)."""
    from sim.method.feib import ImmersedBoundary, State

    from ..studies.paper import paper_scenario, run_paper

    note = progress.note if progress else (lambda message: None)
    methods = ("paper", "conserving", "multiplier")
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
        paper = rows[-len(methods)]
        for kept in rows[-len(methods) + 1:]:
            kept["cost_ratio"] = [c / p for c, p in zip(kept["per_step_ms"], paper["per_step_ms"])]
            extra_ms = statistics.median(kept["membrane_ms"]) - statistics.median(paper["membrane_ms"])
            kept["membrane_extra"] = extra_ms / statistics.median(paper["per_step_ms"])
    return {"rows": rows, "repeats": repeats}


def membrane_lines(result: dict) -> list[str]:
    lines = ["| case | method | outlet | area / initial (min-max) | restored by projection | spacing / h | "
             "ms per step (median) | membrane + checks ms/step | method / paper cost per step (runs) | "
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
