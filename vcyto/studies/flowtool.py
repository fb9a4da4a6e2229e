"""`vcyto flow`: the steady flow with the IDT off and on, and where the injection streamline leaves."""

from __future__ import annotations

import time

from sim.method.calibration import FlowPaths, calibrate_streaming_force, injection_streamline
from sim.method.fluid import NavierStokes
from sim.method.transfer import PointLocator
from sim.model.scenario import UM, Scenario

from . import figures


def solve_paths(scenario: Scenario, progress=lambda message: None):
    """Steady flows for IDT off and on with their injection streamlines: (paths, flows, solver)."""
    started = time.perf_counter()
    progress(f"assembling and factoring ({scenario.numerics.mesh_h / UM:.3g} um mesh)")
    solver = NavierStokes(scenario)
    progress("steady flow, IDT off")
    flow_off, path_off = injection_streamline(scenario, 0.0, solver)
    progress("steady flow, IDT on")
    flow_on, path_on = injection_streamline(scenario, 1.0, solver)
    return FlowPaths(path_off, path_on, time.perf_counter() - started), (flow_off, flow_on), solver


def summary(scenario: Scenario, paths: FlowPaths, solver: NavierStokes) -> dict:
    def describe(path):
        return {"outlet": path.outlet, "exit_y_um": path.exit_y / UM, "transit_time_ms": path.transit_time * 1e3}

    return {
        "saw_model": scenario.saw.model,
        "mesh_h_um": scenario.numerics.mesh_h / UM,
        "dofs": solver.space.dofs,
        "idt_off": describe(paths.off),
        "idt_on": describe(paths.on),
        "wall_time_s": paths.wall_time,
    }


def report_lines(result: dict) -> list[str]:
    lines = [f"steady flow, SAW model {result['saw_model']}, h = {result['mesh_h_um']:.3g} um, {result['dofs']:,} DOFs"]
    for key, label in (("idt_off", "IDT off"), ("idt_on", "IDT on ")):
        path = result[key]
        lines.append(f"  {label}: injection streamline leaves by {path['outlet']:>5} "
                     f"at y = {path['exit_y_um']:6.1f} um after {path['transit_time_ms']:.3f} ms")
    lines.append(f"  wall time {result['wall_time_s']:.1f} s")
    return lines


def save_png(path: str, scenario: Scenario, solver: NavierStokes, flows, paths: FlowPaths):
    """Speed field with the streamline, IDT off (left) and on (right)."""
    plt = figures.pyplot()
    locator = PointLocator(solver.space.cmesh, solver.space.velocity_basis.element_dofs)
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.4), constrained_layout=True)
    for axis, flow, line, title in zip(axes, flows, (paths.off, paths.on), ("IDT off", "IDT on")):
        image = figures.show_speed(axis, locator, flow.velocity, scenario)
        axis.plot(line.path[:, 0] / UM, line.path[:, 1] / UM, color="w", lw=1.5)
        figures.draw_device(axis, scenario)
        axis.set_title(f"{title}: leaves by {line.outlet} at y = {line.exit_y / UM:.0f} um")
    figure.colorbar(image, ax=axes, label="speed (m/s)", shrink=0.8)
    figures.save_figure(figure, path)
    plt.close(figure)


def calibrate(scenario: Scenario, progress=lambda message: None) -> dict:
    """Calibrate the streaming force against the envelope jet (see ``sim.method.calibration``)."""
    progress("calibrating the streaming force against the envelope jet (a dozen steady solves)")
    started = time.perf_counter()
    force, exit_y, iterations = calibrate_streaming_force(scenario)
    return {"streaming_force": force, "exit_y_um": exit_y / UM, "iterations": iterations,
            "wall_time_s": time.perf_counter() - started}
