"""The area constraint as a Lagrange multiplier inside the coupled FE-IB step (``area_constraint`` with
``multiplier``; docs/numerics.md, "Cells that keep their size").

Each cell c carries an interior pressure lambda_c whose force lambda_c dA_c/dX (the area gradient: the outward
normal times the arc length each point carries) is spread with the membrane forces. The fluid step is affine in
its load, so

  v^{m+1} = v_0 + sum_c lambda_c w_c,

v_0 the step with the membrane forces (the usual solve) and w_c the response to cell c's unit pressure (one more
back-solve of the constant matrix each, with homogeneous boundary data: ``NavierStokes.response``). The points move
with v^{m+1} as the time scheme says, X_c^{m+1}(lambda) = P_c + a_c J_c v^{m+1} (euler: P = X^m, a = dt; bdf2:
P = (4 X^m - X^{m-1}) / 3, a = 2 dt / 3; J_c the interpolation at the points the forces were spread from), and
lambda solves

  A_c(X_c^{m+1}(lambda)) = A_c^0   for every cell in the channel,

A^0 the area the cell was born with: a small system, quadratic in lambda because the spline's area is a quadratic
form of its points, solved by Newton's method (2-3 iterations to round-off). The membrane then moves with the
velocity of the fluid step that felt the pressure: the area is kept by the coupled step itself, nothing is
corrected afterwards, and the time scheme's own area error is absorbed with the spatial one.

Why it is needed: in the continuum a uniform pressure jump across a closed membrane moves no fluid; Taylor-Hood's
continuous P1 pressure cannot jump, so the discrete response w_c is not zero and the velocity interpolated at the
points lets fluid through the membrane (its flux is the integral of div v over the cell, which vanishes only
against P1 functions). lambda_c w_c is the one flow of that kind that cancels the flux.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .fluid import NumericalBlowUp

NEWTON_ITERATIONS = 8


@dataclass(frozen=True)
class Update:
    """How one cell's points follow the new velocity: X^{m+1} = base + scale * (velocity at the located points)."""

    membrane: object          # the cell's Membrane (its area form and the area it was born with)
    base: np.ndarray          # P (R, 2)
    scale: float              # a
    located: tuple            # (elements, reference) of the points the forces were spread from
    gradient_at: np.ndarray   # the points the pressure's force acts at (those the forces were evaluated at)


def area_pressures(fluid, locator, flow, updates: list[Update], inside) -> tuple:
    """The flow with each cell's interior pressure added (velocity and pressure) and the pressures (Pa).

    ``inside(points)``: the points' weights of force (1 in the channel, 0 through an outlet), as for the
    membrane forces."""
    responses, velocities = [], []
    for update in updates:
        gradient = update.membrane.with_points(update.gradient_at).area_gradient() * inside(update.gradient_at)[:, None]
        load = np.zeros((2, fluid.space.N))
        locator.spread_located(gradient, *update.located, load)
        responses.append(fluid.response(load))
    for update in updates:
        velocities.append([update.scale * locator.interpolate_located(velocity, *update.located)
                           for velocity, _ in responses])
    drifts = [update.base + update.scale * locator.interpolate_located(flow.velocity, *update.located)
              for update in updates]
    pressures = _solve_areas(updates, drifts, velocities, flow.time)
    velocity = flow.velocity + sum(p * w for p, (w, _) in zip(pressures, responses))
    pressure = flow.pressure + sum(p * q for p, (_, q) in zip(pressures, responses))
    velocity.flags.writeable = pressure.flags.writeable = False
    return replace(flow, velocity=velocity, pressure=pressure), pressures


def _solve_areas(updates, drifts, velocities, time) -> np.ndarray:
    """Newton's method for the pressures that give every cell its initial area after the step."""
    count = len(updates)
    pressures = np.zeros(count)
    for _ in range(NEWTON_ITERATIONS):
        points = [drift + sum(p * w for p, w in zip(pressures, moved)) for drift, moved in zip(drifts, velocities)]
        residual = np.array([u.membrane.area(x) - u.membrane.initial_area for u, x in zip(updates, points)])
        if np.all(np.abs(residual) <= 1e-14 * np.array([u.membrane.initial_area for u in updates])):
            return pressures
        jacobian = np.empty((count, count))
        for c, (update, x) in enumerate(zip(updates, points)):
            gradient = update.membrane.with_points(x).area_gradient()
            jacobian[c] = [float(np.sum(gradient * w)) for w in velocities[c]]
        try:
            pressures = pressures - np.linalg.solve(jacobian, residual)
        except np.linalg.LinAlgError:
            pressures = np.full(count, math.nan)
        if not np.all(np.isfinite(pressures)):
            raise NumericalBlowUp(f"the cells' interior pressures of the area constraint have no finite solution at "
                                  f"t = {time:.6g} s (the fluid's response to them moves no area): the step is too "
                                  "large for this flow; reduce numerics.dt")
    return pressures
