"""`vcyto bench tolerance`: the paper scenarios with time steps chosen by a tolerance against fixed steps.

For each scenario (the paper's literal membrane method, dt = 2.5 us, the mesh of the options) the fixed-step
run in the tolerance runs' time scheme is the reference (with bdf2, the paper's euler step is a row too);
each tolerance's run reports its outlet, the centroid path distance at its own times to the reference path
interpolated there (max, mean; as ``vcyto tradeoff`` measures it), its steps in all and per
level, and both runs' stepping wall times.
"""

from __future__ import annotations

import numpy as np

from sim.model.scenario import UM, Scenario

from ..studies.paper import paper_scenario, run_paper


def path_distance(times, path, reference_times, reference_path) -> np.ndarray:
    """Centroid distance at ``times`` (within the reference's span) to the reference path interpolated there."""
    keep = (times >= reference_times[0]) & (times <= reference_times[-1])
    return np.hypot(path[keep, 0] - np.interp(times[keep], reference_times, reference_path[:, 0]),
                    path[keep, 1] - np.interp(times[keep], reference_times, reference_path[:, 1]))


def bench_tolerance(base: Scenario, numbers=(1, 2), tolerances=(1e-6, 3e-6), progress=lambda message: None) -> dict:
    """The reference of each scenario is the fixed-step run in the tolerance runs' time scheme (bdf2 unless
    ``numerics.time_scheme`` says otherwise); with bdf2 the paper's euler step at the same dt is a row too."""
    rows = []
    base = base.with_numerics(dt=base.numerics.dt, tolerance=0.0).with_membrane("paper")
    scheme = base.with_numerics(tolerance=max(tolerances, default=1e-6)).numerics.scheme
    fixed = base.with_numerics(time_scheme=scheme)
    for number in numbers:
        progress(f"scenario {number}, fixed dt = {base.numerics.dt * 1e6:g} us ({scheme})")
        reference = run_paper(number, paper_scenario(number, fixed, dt_given=True))
        rows.append(_row(number, None, reference, reference, scheme))
        if scheme != "euler":
            progress(f"scenario {number}, fixed dt = {base.numerics.dt * 1e6:g} us (euler)")
            euler = run_paper(number, paper_scenario(number, base.with_numerics(time_scheme="euler"), dt_given=True))
            rows.append(_row(number, None, euler, reference, "euler"))
        for tolerance in tolerances:
            progress(f"scenario {number}, tolerance {tolerance / UM:g} um")
            run = run_paper(number, paper_scenario(number, fixed.with_numerics(tolerance=tolerance), dt_given=True))
            rows.append(_row(number, tolerance, run, reference, scheme))
    return {"mesh_h_um": base.numerics.mesh_h / UM, "dt_us": base.numerics.dt * 1e6, "scheme": scheme, "rows": rows}


def _row(number, tolerance, run, reference, scheme) -> dict:
    gap = path_distance(run["_times"], run["_path"], reference["_times"], reference["_path"])
    summary = run.get("time_steps") or {}
    return {"scenario": number, "scheme": scheme, "tolerance_um": None if tolerance is None else tolerance / UM,
            "outlet": run["cells"][0]["outlet"], "reference_outlet": reference["cells"][0]["outlet"],
            "path_max_um": float(gap.max()) / UM, "path_mean_um": float(gap.mean()) / UM,
            "steps": run["steps"], "reference_steps": reference["steps"], "steps_per_level": summary.get("steps"),
            "levels_us": summary.get("levels_us"), "stepping_s": run["wall_time_s"]["stepping"]}


def tolerance_lines(result: dict) -> list[str]:
    lines = [f"time steps chosen by a tolerance: h = {result['mesh_h_um']:.3g} um, finest dt = {result['dt_us']:g} us, "
             f"against fixed steps of dt in the {result['scheme']} scheme (the paper's literal membrane method)",
             "  scenario  scheme  tolerance  outlet (ref)    path max / mean (um)  steps (ref)    steps per level"
             "   stepping (s)"]
    for row in result["rows"]:
        tolerance = "fixed" if row["tolerance_um"] is None else f"{row['tolerance_um']:g} um"
        levels = "/".join(str(n) for n in row["steps_per_level"]) if row["steps_per_level"] else "-"
        lines.append(f"  {row['scenario']:>8}  {row['scheme']:>6}  {tolerance:>9}  {row['outlet']:>6} "
                     f"({row['reference_outlet']})  "
                     f"{row['path_max_um']:8.3f} / {row['path_mean_um']:.3f}   "
                     f"{row['steps']:>5} ({row['reference_steps']})"
                     f"   {levels:>15}   {row['stepping_s']:8.1f}")
    return lines
