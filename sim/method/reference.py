"""The paper's semi-implicit FE-IB step written plainly: numpy, scipy and scikit-fem, nothing else.

This is the page to read first. ``sim.method.feib`` and ``sim.method.fluid`` compute the same step fast (matrices
gathered and factored once, compiled kernels, a split solve on two threads); ``tests/test_reference.py`` holds them to
this one to round-off. Here everything is assembled and solved afresh each step.

One step of size dt from (v^m, X^m), the paper's scheme (``euler``), with mu the viscosity and rho the density:

  f_r = -dE_h/dX_r at X^m                                                membrane forces (25)
  <F_h, w> = sum_r f_r . w(X_r^m)                                        spreading
  rho/dt (v^{m+1}, w) + mu (grad v^{m+1}, grad w) - (p^{m+1}, div w)
      = rho/dt (v^m, w) - rho ((v^m . grad) v^m, w) + <F_h, w>
  (div v^{m+1}, q) = 0,  v^{m+1} = inflow + jet(t^{m+1}) on inlets, walls and the SAW window   (26)
  X_r^{m+1} = X_r^m + dt v^{m+1}(X_r^m)                                   (27)

``bdf2`` replaces rho/dt (v^{m+1} - v^m) by rho (3 v^{m+1} - 4 v^m + v^{m-1}) / (2 dt), convects with
u* = 2 v^m - v^{m-1}, takes the forces and the velocity at X* = 2 X^m - X^{m-1} and moves the points to
X^{m+1} = (4 X^m - X^{m-1}) / 3 + 2 dt / 3 v^{m+1}(X*). Without an earlier level (a start, a new cell) v^{m-1} = v^m
and a cell takes the Euler update. The outlets are do-nothing boundaries. Interpolation is scikit-fem's own
(``basis.probes``); spreading is its transpose. With ``numerics.area_constraint`` asking for it the forces include
the interior pressure (``Membrane.pressure_balanced``); the points' redistribution and the area projection that
follow a step (``sim.method.feib.settle``) are not part of it. The SAW model ``streaming`` (a body force) is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve
from skfem import Basis, BilinearForm, ElementTriP1, ElementTriP2, FacetBasis, LinearForm, asm, condense
from skfem.helpers import dot, grad

from ..model.boundary import inflow_velocity, saw_jet_factor, saw_window_profile
from ..model.mesh import channel_mesh
from ..model.scenario import Scenario


@BilinearForm
def mass(u, v, w):
    return u * v


@BilinearForm
def laplace(u, v, w):
    return dot(grad(u), grad(v))


@BilinearForm
def d_dx(u, q, w):                # (div (u, 0), q): rows are the pressure tests
    return grad(u)[0] * q


@BilinearForm
def d_dy(u, q, w):                # (div (0, u), q)
    return grad(u)[1] * q


@LinearForm
def convection(v, w):             # ((u . grad) c, v) for one velocity component c
    return (w.ux * w.c.grad[0] + w.uy * w.c.grad[1]) * v


@dataclass(frozen=True)
class Level:
    """A time level: the P2 velocity (2, N), the P1 pressure (P,) and each cell's points (n, 2)."""

    time: float
    velocity: np.ndarray
    pressure: np.ndarray
    points: tuple


class ReferenceStep:
    """The FE-IB step of ``scenario`` on its channel mesh (the same P2/P1 numbering as ``sim.method.taylorhood``)."""

    def __init__(self, scenario: Scenario):
        if scenario.saw.model == "streaming":
            raise ValueError("the reference step leaves out the streaming SAW model")
        self.scenario = scenario
        self.cmesh = channel_mesh(scenario.channel, scenario.numerics.mesh_h)
        self.velocity = Basis(self.cmesh.mesh, ElementTriP2(), intorder=5)
        self.pressure = Basis(self.cmesh.mesh, ElementTriP1(), quadrature=self.velocity.quadrature)
        self.N, self.P = self.velocity.N, self.pressure.N
        self.M, self.K = asm(mass, self.velocity), asm(laplace, self.velocity)
        self.B = [asm(d_dx, self.velocity, self.pressure), asm(d_dy, self.velocity, self.pressure)]
        self.dirichlet = self._dirichlet_nodes()
        self.inflow, self.jet = self._inflow(), self._jet()

    def _dirichlet_nodes(self) -> np.ndarray:
        outlets = np.concatenate([self.cmesh.boundary(o.name) for o in self.scenario.channel.outlets])
        facets = np.setdiff1d(self.cmesh.mesh.boundary_facets(), outlets)
        return np.unique(self.velocity.get_dofs(facets=facets).all())

    def _inflow(self) -> np.ndarray:
        """The inflow profiles L2-projected onto the P2 traces of the inlets (their end nodes are walls: 0)."""
        channel = self.scenario.channel
        facets = np.concatenate([self.cmesh.boundary(inlet.name) for inlet in channel.inlets])
        trace = FacetBasis(self.cmesh.mesh, ElementTriP2(), facets=facets, intorder=10)
        nodes = np.setdiff1d(self.velocity.get_dofs(facets=facets).all(),
                             self.velocity.get_dofs(facets=self.cmesh.boundary("wall")).all())
        trace_mass = asm(mass, trace).tocsr()[nodes][:, nodes].tocsc()
        inflow = np.zeros((2, self.N))
        for axis in (0, 1):
            load = asm(LinearForm(lambda v, w: inflow_velocity(channel, w.x[1])[axis] * v), trace)
            inflow[axis, nodes] = spsolve(trace_mass, load[nodes])
        return inflow

    def _jet(self) -> np.ndarray:
        """The SAW jet at full drive: 2 pi a f m_ac(x) upwards on the lower wall (times c(t) while driven)."""
        x, y = self.velocity.doflocs
        bottom = np.isclose(y, 0.0, atol=1e-9 * self.scenario.channel.height)
        jet = np.zeros((2, self.N))
        jet[1, bottom] = self.scenario.saw.jet_speed * saw_window_profile(self.scenario.channel, x[bottom])
        return jet

    # ------------------------------------------------------------------ the step
    def forces(self, membrane, points: np.ndarray) -> np.ndarray:
        """f_r = -dE_h/dX_r at ``points`` (25), with the interior pressure when the area constraint asks."""
        moved = membrane.with_points(points)
        forces = moved.forces()
        if "pressure" in self.scenario.numerics.area_constraint:
            forces, _ = moved.pressure_balanced(forces)
        return forces

    def mass_coefficient(self) -> float:
        """rho / dt (euler) or 3 rho / (2 dt) (bdf2): the mass matrix's factor in the step's matrix."""
        numerics = self.scenario.numerics
        return self.scenario.fluid.density / numerics.dt * (1.5 if numerics.scheme == "bdf2" else 1.0)

    def momentum(self, v: np.ndarray, v_back: np.ndarray) -> np.ndarray:
        """The explicit momentum load (2, N): (c w - rho (u . grad) u, phi_i), c the mass coefficient, w = u = v^m
        (euler) or w = (4 v^m - v^{m-1}) / 3, u = 2 v^m - v^{m-1} (bdf2)."""
        bdf2 = self.scenario.numerics.scheme == "bdf2"
        w, u = ((4 * v - v_back) / 3, 2 * v - v_back) if bdf2 else (v, v)
        ux, uy = (self.velocity.interpolate(component) for component in u)
        convected = [asm(convection, self.velocity, ux=ux, uy=uy, c=self.velocity.interpolate(u[a])) for a in (0, 1)]
        return np.array([self.mass_coefficient() * (self.M @ w[a]) - self.scenario.fluid.density * convected[a]
                         for a in (0, 1)])

    def step(self, now: Level, membranes, actuation: float = 0.0, before: Level | None = None) -> Level:
        """The level after one step from ``now`` (``before``: the level one step back, for bdf2)."""
        numerics, fluid = self.scenario.numerics, self.scenario.fluid
        dt, bdf2 = numerics.dt, numerics.scheme == "bdf2"
        v, v_back = now.velocity, (before.velocity if bdf2 and before is not None else now.velocity)
        backs = before.points if bdf2 and before is not None else (None,) * len(now.points)
        at = [X if back is None else 2 * X - back for X, back in zip(now.points, backs)]
        if any((X[:, 0] >= self.scenario.channel.length).any() for X in at):
            raise ValueError("the reference step takes cells inside the channel only")
        probes = [self.velocity.probes(X.T) for X in at]          # the interpolation matrices at the points
        load = np.zeros((2, self.N))
        for membrane, X, probe in zip(membranes, at, probes):
            load += (probe.T @ self.forces(membrane, X)).T           # spreading: the transpose of interpolation
        c = self.mass_coefficient()
        rhs = np.concatenate([*(self.momentum(v, v_back) + load), np.zeros(self.P)])
        A = c * self.M + fluid.viscosity * self.K
        system = sp.bmat([[A, None, -self.B[0].T], [None, A, -self.B[1].T], [-self.B[0], -self.B[1], None]], "csc")
        time = now.time + dt
        weight = actuation * saw_jet_factor(self.scenario.saw) if actuation else 0.0
        boundary = np.concatenate([(self.inflow + weight * self.jet).ravel(), np.zeros(self.P)])
        D = np.concatenate([self.dirichlet, self.dirichlet + self.N])
        solution = boundary.copy()
        free = np.setdiff1d(np.arange(len(rhs)), D)
        solution[free] = spsolve(*condense(system, rhs, x=boundary, D=D)[:2])
        velocity, pressure = solution[:2 * self.N].reshape(2, self.N), solution[2 * self.N:]
        points = []
        for X, back, probe in zip(now.points, backs, probes):
            moved = probe @ velocity.T                                # v^{m+1} at X (euler) or X* (bdf2)
            points.append(X + dt * moved if back is None else (4 * X - back) / 3 + 2 * dt / 3 * moved)
        return Level(time, velocity, pressure, tuple(points))
