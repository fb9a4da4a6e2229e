"""The implicit membrane coupling: the membrane force taken at the new positions (docs/numerics.md, "The membrane
coupling").

The explicit step (``sim.method.feib``) spreads the force F(X*) of the points X* (X^m, or bdf2's extrapolation),
solves the fluid and moves the points with the new velocity interpolated at X*:

    X^{m+1} = B + tau J u^{m+1},    A u^{m+1} = b + S F(X*),

(euler: B = X^m, tau = dt; bdf2: B = (4 X^m - X^{m-1}) / 3, tau = 2 dt / 3). The membrane force of the paper's energy
is linear in the points, F(X) = -L X (L = K, the energy's stiffness, per coordinate; with the area constraint's
interior pressure L = P K, P the projection off the area gradient at X*, and zero rows for points past the outlet).
Taking it at the new points, F(X^{m+1}), with S and J kept at X*, gives for the displacement D = X^{m+1} - X*

    (I + tau M L) D = E,    E = X^E - X*,    M = J A^{-1} S,

X^E the explicit step's new points: the fluid's matrix is the same, only the membrane's unknowns are new. M, the
membranes' mobility, costs one back-solve per application. This step solves the system with an approximate
mobility M~ (``Mobility``), a small dense system per cell, and gives the fluid the force at the new points: one more
back-solve, u^{m+1} = u^E + A^{-1} S (F(X* + D) - F(X*)). The new points are X* + D: a mode of the membrane that the
explicit step multiplies by 1 - a (a = tau m k, m the mode's mobility, k its stiffness, unstable for a > 2) is
multiplied by (1 + (r - 1) a) / (1 + r a), r = m~ / m, which lies in (-1, 1) for every a when r > 1/2: stable at any
step when M~ errs by less than half below M. ``iterations`` > 0 refine D towards the exact system's solution, each by
the residual of that system (one back-solve each), E + tau J A^{-1} S F-change - D, through M~.

M~ is the discrete fluid's own response to a point force at reference positions in the middle of the channel,
averaged over the positions of the source within a mesh square and taken as a function of the offset between two
points: M~(x, y) = mean_s G_s(y_s + x - y), G_s the velocity at a point of a unit force at y_s (A^{-1} S, two
back-solves a source, once per fluid matrix). It has the discretisation's response at the mesh scale, where the stiff
modes live, and the fluid's inertia at the step's dt; it omits the walls (which lower the mobility: M~ errs high,
the safe way) and the dependence on where in its mesh square a point lies (the average errs both ways: for a melanoma
on the 1.67 um mesh m~ / m spans 0.22-2.9 over its modes, and the frozen one-step amplification at 100 us is 1.02-1.5
with M~ as it is, 1.000 with it doubled: ``SAFETY``).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from .fluid import Flow, NavierStokes

SUBDIVISIONS = 3            # the sources of M~: a SUBDIVISIONS^2 grid of positions in one mesh square
SAFETY = 2.0                # M~ scaled by this: it errs high, where the step stays stable (module docstring)


class Mobility:
    """M~ of a fluid solver (module docstring): ``matrix(points)`` gives the (2R, 2R) mobility of R points, the
    layout [x_0, y_0, x_1, y_1, ...]."""

    def __init__(self, fluid: NavierStokes, locator, subdivisions: int = SUBDIVISIONS, safety: float = SAFETY):
        channel, h = fluid.scenario.channel, fluid.scenario.numerics.mesh_h
        grid_x, grid_y = locator.grid_x, locator.grid_y
        i = int(np.searchsorted(grid_x, channel.length / 2)) - 1
        j = int(np.searchsorted(grid_y, channel.height / 2)) - 1
        fractions = (np.arange(subdivisions) + 0.5) / subdivisions
        width, height = grid_x[i + 1] - grid_x[i], grid_y[j + 1] - grid_y[j]
        self.sources = np.array([(grid_x[i] + a * width, grid_y[j] + b * height) for a in fractions for b in fractions])
        self.locator = locator
        self.safety = safety
        self.mesh_h = h
        fields = []
        for source in self.sources:
            elements, reference = locator.locate(source[None, :])
            responses = []
            for direction in (0, 1):
                load = np.zeros((2, fluid.space.N))
                force = np.zeros((1, 2))
                force[0, direction] = 1.0
                locator.spread_located(force, elements, reference, load)
                responses.append(fluid.load_response(load)[0])
            fields.append(np.concatenate(responses))       # (4, N): [u_x, u_y] of a force along x, then along y
        self.fields = fields

    def matrix(self, points: np.ndarray) -> np.ndarray:
        """M~ (2R, 2R) of ``points`` (R, 2): symmetric, entry [2a + i, 2b + d] the velocity component i at point a
        of a unit force along d at point b."""
        count = len(points)
        offsets = (points[:, None, :] - points[None, :, :]).reshape(-1, 2)
        total = np.zeros((count * count, 4))
        for source, values in zip(self.sources, self.fields):
            sampled = self.locator.interpolate(values, source + offsets)
            total += np.nan_to_num(sampled)          # offsets that leave the channel: no coupling
        total *= self.safety / len(self.sources)
        # total[ab] = (u_x, u_y of a force along x, u_x, u_y of a force along y) -> block [[xx, xy], [yx, yy]]
        blocks = total.reshape(count, count, 2, 2).transpose(0, 3, 1, 2).reshape(2 * count, 2 * count)
        return 0.5 * (blocks + blocks.T)


def force_operator(membrane, numerics, inside: np.ndarray) -> np.ndarray:
    """L (2R, 2R), F(X) = -L X in the layout [x_0, y_0, ...]: the energy's stiffness per coordinate, projected off
    the area gradient when the interior pressure balances the force, zero rows for points past the outlet."""
    operator = np.kron(membrane.stiffness, np.eye(2))
    if "pressure" in numerics.area_constraint:
        gradient = membrane.area_gradient().ravel()
        unit = gradient / np.linalg.norm(gradient)
        operator = operator - np.outer(unit, unit @ operator)
    return operator * np.repeat(inside.astype(float), 2)[:, None]


class ImplicitCoupling:
    """The implicit coupling of an ``ImmersedBoundary`` plant: one ``Mobility`` per fluid solver (per time step level),
    built when first needed."""

    def __init__(self, plant, iterations: int = 0):
        self.plant = plant
        self.iterations = iterations
        self._mobilities: dict[int, tuple[NavierStokes, Mobility]] = {}
        self.defect = 0.0         # the last step's largest |D - (E + tau J A^-1 S dF)| (m): how far from the exact

    def mobility(self, fluid: NavierStokes) -> Mobility:
        known = self._mobilities.get(id(fluid))
        if known is None or known[0] is not fluid:
            known = self._mobilities[id(fluid)] = (fluid, Mobility(fluid, self.plant.locator))
        return known[1]

    def correct(self, fluid: NavierStokes, flow: Flow, membranes, at, explicit, located, inside, taus):
        """The new points of each cell and the flow with the force at them: ``membranes`` (the cells' membranes,
        their points X^m), ``at`` (X*), ``explicit`` (X^E), ``located`` ((elements, reference) of X*), ``inside``
        (points inside the channel) and ``taus`` (each cell's tau, module docstring)."""
        mobility = self.mobility(fluid)
        numerics = fluid.scenario.numerics
        systems, operators, moves = [], [], []
        for membrane, points, new, mask, tau in zip(membranes, at, explicit, inside, taus):
            operator = force_operator(membrane.with_points(points), numerics, mask)
            system = np.eye(len(operator)) + tau * mobility.matrix(points) @ operator
            factor = sla.lu_factor(system)
            systems.append(factor)
            operators.append(operator)
            moves.append(sla.lu_solve(factor, (new - points).ravel()))
        velocity, pressure = flow.velocity, flow.pressure
        change = np.zeros_like(velocity)
        pressure_change = np.zeros_like(pressure)
        self.defect = 0.0
        for iteration in range(self.iterations + 1):
            load = np.zeros((2, fluid.space.N))
            for move, operator, (elements, reference) in zip(moves, operators, located):
                self.plant.locator.spread_located(-(operator @ move).reshape(-1, 2), elements, reference, load)
            change, pressure_change = fluid.load_response(load)
            residuals = []
            for move, points, new, tau, (elements, reference) in zip(moves, at, explicit, taus, located):
                follows = self.plant.locator.interpolate_located(change, elements, reference)
                residuals.append((new - points + tau * follows).ravel() - move)
            self.defect = max((float(np.abs(r).max()) for r in residuals), default=0.0)
            if iteration < self.iterations:
                moves = [move + sla.lu_solve(factor, residual)
                         for move, factor, residual in zip(moves, systems, residuals)]
        new_points = [points + move.reshape(-1, 2) for points, move in zip(at, moves)]
        corrected = Flow(flow.time, velocity + change, pressure + pressure_change, flow.streaming_level,
                         flow.iterations, flow.history)
        corrected.velocity.flags.writeable = corrected.pressure.flags.writeable = False
        return new_points, corrected
