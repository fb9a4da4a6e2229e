"""`vcyto stability`: the largest stable dt per cell type and mesh size, beside the stability law's limit (the one the
tolerance's cap and the failure hints use, ``sim.method.steplimit``), the paper's dt and its bound (33)."""

from __future__ import annotations

import time

from sim.method.fluid import NavierStokes
from sim.method.stability import actuation_for, paper_bound, stable_dt
from sim.method.steplimit import limit_of
from sim.model.mesh import MeshSize
from sim.model.scenario import UM, Scenario

from ..progress import rows_until_interrupted

PAPER_DT = {"RBC": 2.5e-6, "melanoma": 25e-6}


def stability_map(scenario: Scenario, cells, mesh_sizes, progress) -> dict:
    rows, interrupted = rows_until_interrupted(lambda rows: _measure(scenario, cells, mesh_sizes, progress, rows))
    return {"rows": rows, "interrupted": interrupted,
            "criterion": "health checks pass and membrane energy within 2x of a 2 us reference run over 2 ms (at "
                         "least 20 steps); bisection to 25 %"}


def _measure(scenario, cells, mesh_sizes, progress, rows):
    for asked in mesh_sizes:
        size = MeshSize.of(scenario.channel, asked)
        h = size.largest
        meshed = scenario.with_numerics(mesh_h=h)
        starts = {}
        for name in cells:
            cell_type = meshed.cell_type(name)
            actuation = actuation_for(cell_type)
            progress.note(f"{name} at h = {h / UM:.3g} um: reference run and bisection")
            started = time.perf_counter()
            if actuation not in starts:
                starts[actuation] = NavierStokes(meshed).steady(actuation)
            result = stable_dt(meshed, cell_type, start=starts[actuation])
            rows.append({
                "cell": name, "mesh_h_um": h / UM, "mesh": size.describe(), "dofs": size.dofs,
                "time_scheme": meshed.numerics.scheme, "membrane_method": meshed.membrane_method(),
                "membrane_coupling": meshed.numerics.membrane_coupling,
                "stable_dt_us": result.stable_dt * 1e6,
                "unstable_dt_us": result.unstable_dt * 1e6 if result.unstable_dt != float("inf") else None,
                "failure": result.failure, "trials": result.trials,
                "paper_dt_us": PAPER_DT.get(name, float("nan")) * 1e6,
                "law_us": limit_of(cell_type, meshed) * 1e6,
                "bound_33_us": paper_bound(cell_type, meshed) * 1e6,
                "wall_time_s": time.perf_counter() - started,
            })


def report_lines(result: dict) -> list[str]:
    couplings = sorted({row.get("membrane_coupling", "explicit") for row in result["rows"]}) or ["explicit"]
    lines = [f"largest stable dt (FE-IB, {' and '.join(couplings)} membrane coupling, " + result["criterion"] + ")",
             f"  {'cell':<9} {'h (um)':>7} {'DOFs':>9} {'scheme':<6} {'stable dt':>11} {'unstable dt':>12} "
             f"{'law':>9} {'paper dt':>9} {'(33), C=1':>10}  what failed"]
    for row in result["rows"]:
        unstable = f"{row['unstable_dt_us']:.3g} us" if row["unstable_dt_us"] else "> tried"
        stable = f"{row['stable_dt_us']:.3g} us" + ("" if row["unstable_dt_us"] else "+")
        lines.append(f"  {row['cell']:<9} {row['mesh_h_um']:7.4g} {row['dofs']:>9,} {row['time_scheme']:<6} "
                     f"{stable:>11} {unstable:>12} {row['law_us']:6.3g} us {row['paper_dt_us']:6.3g} us "
                     f"{row['bound_33_us']:7.3g} us  {row['failure'] or '-'}")
    lines.append("  law: the limit the tolerance's step cap and the failure hints use (docs/results.md, \"Stability\")")
    if result.get("interrupted"):
        lines.append("  PARTIAL: interrupted; the rows not listed were not measured")
    return lines
