"""`vcyto relax`: the relaxation benchmark, an elliptical membrane relaxing in fluid at rest, on nested meshes.

The scenario (a file: ``examples/scenarios/relaxation.toml``) must have every inlet shut (v_hat = 0); the IDT stays
off. One cell of the named type starts near the channel's centre in fluid at rest and relaxes towards a circle for
``duration``. Per run: the enclosed area at the end over the initial one, and the relaxation time, the time at
which the aspect ratio's excess (a / b - 1, from the polygon's second moments) has fallen to 1/e of its start.

The discrete answer depends on where the cell lies against the mesh (the immersed boundary's translation error: on
the 5 um mesh the relaxation time spans 0.64-0.76 ms over positions within one mesh square, on 2.5 um 0.698-0.711
ms), so one position per mesh samples that error at a point and does not converge. Each mesh therefore runs the
cell at the nodes of an n x n grid of offsets of its centre within one mesh square (``positions``: n = h / h_finest,
at least 2), and a row gives the mean over them (the translation-averaged result) and their spread. All runs take
the same dt (the scenario's, or half the finest mesh's stability limit, ``sim.method.steplimit``, if that is
smaller), so only h changes. For three meshes refined by a constant ratio r: the area's error is known (the exact
solution keeps it: 1 - A / A0), so its observed order is log(e1 / e2) / log(r) and log(e2 / e3) / log(r); the
relaxation time's limit is not, so its observed order is log(|q1 - q2| / |q2 - q3|) / log(r), and its extrapolated
value q3 + (q3 - q2) / (r^p - 1) (Richardson), for each three successive meshes.
"""

from __future__ import annotations

import math
import time

import numpy as np

from sim.method.feib import ImmersedBoundary
from sim.method.openloop import stepping, with_cells
from sim.method.steplimit import limit_of
from sim.model.mesh import MeshSize
from sim.model.scenario import UM, Scenario, ScenarioError

from ..progress import rows_until_interrupted

STABLE_SHARE = 0.5      # of the finest mesh's stability limit: the dt every mesh takes
ROUND_OFF = 1e-9        # a relative area change below this is the round-off of a method that keeps the area


def aspect_ratio(points: np.ndarray) -> float:
    """sqrt(largest / smallest principal second moment of area) of the closed polygon ``points`` (n, 2): a / b for
    an ellipse of semi-axes a >= b."""
    x, y = points[:, 0] - points[:, 0].mean(), points[:, 1] - points[:, 1].mean()
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2
    cx, cy = ((x + xn) * cross).sum() / (6 * area), ((y + yn) * cross).sum() / (6 * area)
    sxx = (x * x + x * xn + xn * xn) @ cross / 12 - area * cx * cx
    syy = (y * y + y * yn + yn * yn) @ cross / 12 - area * cy * cy
    sxy = (x * yn + 2 * x * y + 2 * xn * yn + xn * y) @ cross / 24 - area * cx * cy
    small, large = np.linalg.eigvalsh(np.array([[sxx, sxy], [sxy, syy]]))
    return math.sqrt(large / small)


def relaxation_time(times, ratios) -> float:
    """When the aspect ratio's excess first falls to 1/e of its start (linear in log excess between samples); nan if
    it never does."""
    excess = np.asarray(ratios) - 1.0
    target = excess[0] / math.e
    below = np.nonzero(excess <= target)[0]
    if excess[0] <= 0 or len(below) == 0:
        return math.nan
    k = below[0]
    low, high = math.log(excess[k - 1]), math.log(max(excess[k], 1e-300))
    share = (low - math.log(target)) / (low - high)
    return float(times[k - 1] + share * (times[k] - times[k - 1]))


def check_at_rest(scenario: Scenario):
    moving = [inlet.name for inlet in scenario.channel.inlets if inlet.v_hat != 0]
    if moving:
        raise ScenarioError("channel.inlets", f"the relaxation benchmark needs fluid at rest: set v_hat = 0 on "
                                              f"{', '.join(moving)}")


def common_dt(scenario: Scenario, cell_type, mesh_sizes) -> float:
    finest = scenario.with_numerics(mesh_h=min(mesh_sizes))
    return min(scenario.numerics.dt, STABLE_SHARE * limit_of(cell_type, finest))


def relax_once(scenario: Scenario, cell_type, duration: float, offset=(0.0, 0.0)) -> dict:
    """One run: the cell at the channel's centre moved by ``offset`` (m) in fluid at rest, IDT off, for
    ``duration``."""
    started = time.perf_counter()
    plant = ImmersedBoundary(scenario)
    centre = (scenario.channel.length / 2 + offset[0], scenario.channel.height / 2 + offset[1])
    state = with_cells(plant, plant.fluid.rest(), [(cell_type, centre)])
    first = state.cells[0].membrane
    times, ratios = [0.0], [aspect_ratio(first.points)]
    for state in stepping(plant.step, state, 0.0, until=duration):
        times.append(state.time)
        ratios.append(aspect_ratio(state.cells[0].membrane.points))
    return {"steps": state.step, "aspect_ratio": [ratios[0], ratios[-1]],
            "area_ratio": state.cells[0].membrane.area() / first.area(),
            "relaxation_time_ms": relaxation_time(times, ratios) * 1e3, "wall_time_s": time.perf_counter() - started}


def positions(h: float, finest: float) -> list[tuple[float, float]]:
    """Offsets of the cell's centre on an n x n grid within one mesh square of size ``h`` (n = h / finest, at
    least 2): the positions a mesh's row averages over."""
    count = max(2, round(h / finest))
    return [(i * h / count, j * h / count) for i in range(count) for j in range(count)]


def relax_on_mesh(scenario: Scenario, cell_type, duration: float, finest: float) -> dict:
    """The runs at every position of ``positions`` on the scenario's mesh: their means and spreads."""
    size = MeshSize.of(scenario.channel, scenario.numerics.mesh_h)
    runs = [relax_once(scenario, cell_type, duration, offset) for offset in positions(size.largest, finest)]
    times = [run["relaxation_time_ms"] for run in runs]
    areas = [run["area_ratio"] for run in runs]
    return {"mesh_h_um": size.largest / UM, "dofs": size.dofs, "dt_us": scenario.numerics.dt * 1e6,
            "positions": len(runs), "steps": runs[0]["steps"],
            "aspect_ratio": [float(np.mean([run["aspect_ratio"][k] for run in runs])) for k in (0, 1)],
            "area_ratio": float(np.mean(areas)), "area_ratio_range": [float(np.min(areas)), float(np.max(areas))],
            "relaxation_time_ms": float(np.mean(times)),            # nan, as the range, if a position never got there
            "relaxation_time_range_ms": [float(np.min(times)), float(np.max(times))],
            "wall_time_s": sum(run["wall_time_s"] for run in runs)}


def observed_order(values, ratio: float) -> tuple[float, float]:
    """(order, extrapolated value) of three values on meshes refined by ``ratio`` (nan where undefined)."""
    q1, q2, q3 = values
    if not all(math.isfinite(q) for q in values) or q2 == q3 or q1 == q2:
        return math.nan, math.nan
    order = math.log(abs(q1 - q2) / abs(q2 - q3)) / math.log(ratio)
    return order, q3 + (q3 - q2) / (ratio ** order - 1) if order > 0 else math.nan


def relaxation(scenario: Scenario, cell_name: str, duration: float, mesh_sizes, progress) -> dict:
    """The benchmark on each of ``mesh_sizes`` (coarsest first), with the observed orders for each three successive
    meshes refined by one ratio."""
    check_at_rest(scenario)
    cell_type = scenario.cell_type(cell_name)
    sizes = sorted((MeshSize.of(scenario.channel, h).largest for h in mesh_sizes), reverse=True)
    dt = common_dt(scenario, cell_type, sizes)
    base = scenario.with_numerics(dt=dt)

    def measure(rows):
        for h in sizes:
            progress.note(f"{cell_name} at h = {h / UM:.4g} um, {len(positions(h, sizes[-1]))} positions, "
                          f"dt = {dt * 1e6:.3g} us")
            rows.append(relax_on_mesh(base.with_numerics(mesh_h=h), cell_type, duration, sizes[-1]))

    rows, interrupted = rows_until_interrupted(measure)
    result = {"cell": cell_name, "duration_ms": duration * 1e3, "dt_us": dt * 1e6,
              "method": scenario.membrane_method(), "area_constraint": scenario.numerics.area_constraint,
              "redistribute": scenario.numerics.redistribute, "rows": rows, "interrupted": interrupted, "orders": {}}
    ratios = [a / b for a, b in zip(sizes, sizes[1:])][:max(len(rows) - 1, 0)]
    losses = [1 - row["area_ratio"] for row in rows]
    if len(rows) >= 2 and max(abs(loss) for loss in losses) > ROUND_OFF:
        result["orders"]["area_loss"] = [math.log(a / b) / math.log(r) if a > 0 and b > 0 else math.nan
                                         for a, b, r in zip(losses, losses[1:], ratios)]
    times = [row["relaxation_time_ms"] for row in rows]
    triples = [k for k in range(len(rows) - 2) if math.isclose(ratios[k], ratios[k + 1], rel_tol=1e-6)]
    if triples:
        result["orders"]["relaxation_time_ms"] = [
            dict(zip(("order", "extrapolated"), observed_order(times[k:k + 3], ratios[k])), finest_um=sizes[k + 2] / UM,
                 increments=[times[k + 1] - times[k], times[k + 2] - times[k + 1]]) for k in triples]
    return result


def report_lines(result: dict) -> list[str]:
    lines = [f"relaxation of a {result['cell']} in fluid at rest for {result['duration_ms']:g} ms, dt = "
             f"{result['dt_us']:.3g} us on every mesh, membrane method {result['method']} (area constraint "
             f"{result['area_constraint']}, redistribution {'on' if result['redistribute'] else 'off'}); each row "
             f"the mean over the cell's positions within one mesh square (range in brackets)",
             f"  {'h (um)':>7} {'DOFs':>9} {'positions':>9} {'steps':>6} {'aspect ratio':>15} {'area kept':>10} "
             f"{'relaxation time (ms)':>30}"]
    for row in result["rows"]:
        start, end = row["aspect_ratio"]
        low, high = row["relaxation_time_range_ms"]
        lines.append(f"  {row['mesh_h_um']:7.4g} {row['dofs']:>9,} {row['positions']:>9} {row['steps']:>6} "
                     f"{start:7.3f} -> {end:5.3f} {100 * row['area_ratio']:9.3f}% {row['relaxation_time_ms']:10.5f} "
                     f"[{low:.4f}, {high:.4f}]")
    orders = result["orders"]
    if orders.get("area_loss"):
        lines.append("  area loss (1 - A/A0; 0 is exact): observed order "
                     + ", ".join(f"{order:.2f}" for order in orders["area_loss"]) + " between successive meshes")
    elif result["rows"]:
        largest = max(abs(1 - row["area_ratio"]) for row in result["rows"])
        lines.append(f"  area kept to round-off on every mesh (|1 - A/A0| <= {largest:.1e})")
    for entry in orders.get("relaxation_time_ms", []):
        first, second = entry["increments"]
        text = f"  relaxation time to h = {entry['finest_um']:.4g} um: increments {first:+.5f}, {second:+.5f} ms, "
        if math.isfinite(entry["order"]) and entry["order"] > 0:
            lines.append(text + f"observed order {entry['order']:.2f}, extrapolated {entry['extrapolated']:.5g} ms")
        else:
            lines.append(text + "not shrinking: no observed order")
    if result["interrupted"]:
        lines.append("  PARTIAL: interrupted; the rows not listed were not measured")
    return lines
