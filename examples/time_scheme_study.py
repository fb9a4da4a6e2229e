"""How far is each time scheme and step from the converged path? The measurement behind docs/numerics.md,
"A second-order step".

    python examples/time_scheme_study.py                        # Scenario II (melanoma, IDT on), paper mesh
    python examples/time_scheme_study.py 3.33 RBC 0             # Scenario I (RBC, IDT off)
    python examples/time_scheme_study.py 3.33 melanoma 1 bdf2:1.25,euler:2.5,bdf2:10

Arguments: mesh h (um), cell type, IDT drive, and the runs as SCHEME:DT (dt in us, comma-separated; default
bdf2:1.25,euler:2.5,bdf2:2.5,bdf2:5,bdf2:10,bdf2:20). Every run has the default (conserving) membrane and
fixed steps; each is compared with the first run (the finest) by the centroid distance at the run's own
times to the reference path interpolated there (max / mean, um; as `vcyto tradeoff` measures it). Prints;
writes nothing. About 90 s at the paper mesh with the default runs.
"""

from __future__ import annotations

import sys
import time

from membrane_update_study import distance, path

from sim.method.feib import ImmersedBoundary
from sim.method.health import HealthError, NumericalBlowUp
from sim.model.scenario import UM, Scenario


def main(arguments):
    mesh_h = float(arguments[0]) * UM if arguments else 10 * UM / 3
    cell_type = arguments[1] if len(arguments) > 1 else "melanoma"
    drive = float(arguments[2]) if len(arguments) > 2 else 1.0
    specs = (arguments[3] if len(arguments) > 3 else "bdf2:1.25,euler:2.5,bdf2:2.5,bdf2:5,bdf2:10,bdf2:20").split(",")
    runs = {}
    for spec in specs:
        scheme, dt = spec.split(":")
        started = time.perf_counter()
        scenario = Scenario().with_numerics(mesh_h=mesh_h, dt=float(dt) * 1e-6, time_scheme=scheme)
        try:
            runs[spec] = path(ImmersedBoundary, scenario, cell_type, drive)
        except (NumericalBlowUp, HealthError) as error:
            print(f"{spec:>11s}: unstable: {str(error)[:110]}", flush=True)
            continue
        times = runs[spec][0]
        print(f"{spec:>11s}: {runs[spec][2]} outlet, {len(times) - 1} steps ({time.perf_counter() - started:.1f} s)",
              flush=True)
    reference = specs[0]
    print(f"\ncentroid path distance to {reference} (max / mean, um):")
    for spec, run in runs.items():
        print(f"  {spec:>11s}  {'%.2f / %.2f' % distance(run, runs[reference])}")


if __name__ == "__main__":
    main(sys.argv[1:])
