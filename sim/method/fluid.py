"""Incompressible Navier-Stokes with Taylor-Hood P2/P1 elements and backward Euler (paper (1), (26)).

Weak form (paper (2)): rho (v^{m+1} - v^m)/dt + rho c(v) + eta (grad v, grad w) - (p, div w) = <F, w>,
(q, div v^{m+1}) = 0, with v = inflow on the inlets, the SAW data on the lower wall, 0 on the other
walls, and the natural do-nothing condition eta dv/dn - p n = 0 on the outlets.

Convection treatments (``Numerics.convection``), c(v) = (v . grad) v evaluated as follows:

- ``imex``:     c(v^m) on the right-hand side; the matrix never changes and is factored once, so a step
                is one numba load kernel plus one back-solve. First order in dt, like backward Euler.
- ``oseen``:    (v^m . grad) v^{m+1}; one solve per step, but the matrix is assembled (numba) and
                refactored every step (same sparsity pattern: the ordering is reused).
- ``implicit``: c(v^{m+1}), the paper's (26), solved to ``nonlinear_tolerance``: fixed-point iterations
                on the constant factorisation (each costs one back-solve), switching to Newton's method
                when they do not contract (large dt * |grad v|).
- ``stokes``:   no convection.

Unknowns are laid out [v_x (N), v_y (N), p (P)] with N scalar P2 nodes and P P1 nodes. The pressure
is scaled inside the saddle-point matrix so both blocks have comparable entries; states hold SI values.
"""

from __future__ import annotations

import logging
import os
import sys
import time as clock
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from skfem import ElementTriP2, FacetBasis, LinearForm, asm

from ..fast import kernels
from ..fast.gathered import GatheredMatrix, block_rows, gathered
from ..fast.helper import helper, prefetch_wanted
from ..fast.linalg import mkl_version
from ..fast.solvers import factorize, resolved_solver_name
from ..fast.store import digest, module_digest, reuse
from ..model.boundary import inflow_velocity, saw_jet_factor, saw_window_profile
from ..model.drive import lagged
from ..model.mesh import channel_mesh
from ..model.scenario import Scenario
from .taylorhood import TaylorHood, mass_form
from .timeschemes import TimeScheme, earlier_at, lagrange_weights, scheme_named


def solver_code_digest() -> str:
    """The code that computes a flow (this module, the kernels, the assembly, the linear solvers, which
    substitutions the split solve runs, ours or PARDISO's, and which step kernels, C or numba's), as a key part of
    the flows stored through ``sim.fast.store``: a changed kernel or solver, whose bits differ, misses instead of giving
    a warm run other bits than a cold one."""
    from ..fast.kernels import implementation
    from ..fast.splitsolve import substitutions
    return f"{_python_code_digest()}:{substitutions()}:{implementation()}"


@lru_cache(maxsize=1)
def _python_code_digest() -> str:
    from ..fast import gathered, helper, kernels, linalg, solvers, splitsolve, supernodal
    from . import taylorhood, timeschemes
    return module_digest(sys.modules[__name__], gathered, helper, kernels, linalg, solvers, splitsolve, supernodal,
                         taylorhood, timeschemes)

log = logging.getLogger(__name__)
_NOTHING = np.zeros(0)          # an absent load for ``kernels.free_rhs``


class NumericalBlowUp(RuntimeError):
    """The solution stopped being a solution: non-finite values or a diverging nonlinear solve."""


@dataclass(frozen=True)
class Flow:
    """The fluid state at one time: velocity (2, N) at P2 nodes, pressure (P,) at P1 nodes (SI)."""

    time: float
    velocity: np.ndarray
    pressure: np.ndarray
    streaming_level: float = 0.0
    iterations: int = 0
    history: tuple = ()     # bdf2: (time, velocity) of the last two earlier steps, the latest first (() at a start)


@dataclass
class StepTimings:
    """Wall time spent in each part of the fluid steps so far (seconds)."""

    load: float = 0.0
    solve: float = 0.0
    assemble: float = 0.0
    factor: float = 0.0
    steps: int = 0
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class _System:
    """A factored reduced matrix with the lifts of the inflow and of the unit SAW jet."""

    factor: object
    lift_inflow: np.ndarray
    lift_jet: np.ndarray


def _structure(space: TaylorHood, free: np.ndarray, dirichlet: np.ndarray) -> GatheredMatrix:
    """The ``GatheredMatrix`` of ``space`` with these Dirichlet unknowns: kept on the space (the levels of a
    tolerance share it) and through ``sim.fast.store`` (``sim.fast.gathered.gathered``)."""
    known = getattr(space, "_structures", None)
    if known is None:
        known = space._structures = {}
    name = digest(free, dirichlet)
    if name not in known:
        known[name] = gathered(space.mass, space.laplace, sp.hstack(space.divergence).tocsr(), free, dirichlet)
    return known[name]


class NavierStokes:
    """The channel flow of a scenario: ``initial_flow``, ``step`` and ``steady``.

    ``actuation`` in [0, 1] is the IDT drive (0 off, 1 on) applying to the new time level; ``load`` is an
    optional (2, N) vector of forces <F, phi_i> (the membrane hook of paper (25)).
    """

    def __init__(self, scenario: Scenario, space: TaylorHood | None = None, like: "NavierStokes | None" = None):
        """``like``: a solver of the same device (channel, SAW, fluid) whose mesh, unknowns and boundary data this
        one shares (the levels of a tolerance: only the time step differs, and only the constant matrix is built
        again; ~25 ms a level less at the paper's mesh)."""
        started = clock.perf_counter()
        self.scenario = scenario
        self._ahead = None                  # (flow, future): the next step's element integrals (``_prefetch``)
        self._ahead_buffer = self._inline_buffer = None
        if like is not None:
            if (like.scenario.channel, like.scenario.saw, like.scenario.fluid, like.scenario.numerics.mesh_h) != \
                    (scenario.channel, scenario.saw, scenario.fluid, scenario.numerics.mesh_h):
                raise ValueError("NavierStokes(like=...): the other solver is of another device or mesh")
            space = like.space
        self.space = space or TaylorHood(channel_mesh(scenario.channel, scenario.numerics.mesh_h))
        self.timings = StepTimings()
        self.timings.assemble = clock.perf_counter() - started
        if like is None:
            self._dirichlet_split()
            self._boundary_vectors()
        else:
            for name in self._SHARED:
                setattr(self, name, getattr(like, name))
        self._constant_system()

    # what a solver of the same device and mesh shares (``like``): the unknowns' split and the boundary data
    _SHARED = ("dirichlet_nodes", "dirichlet", "free", "free_velocity", "free_x", "positions", "inflow", "jet",
               "streaming_unit_load")

    # ------------------------------------------------------------------ set-up
    def _dirichlet_split(self):
        space, cmesh = self.space, self.space.cmesh
        outlet_facets = np.concatenate([cmesh.boundary(o.name) for o in self.scenario.channel.outlets])
        dirichlet_facets = np.setdiff1d(cmesh.mesh.boundary_facets(), outlet_facets)
        nodes = np.unique(space.velocity_basis.get_dofs(facets=dirichlet_facets).all())
        self.dirichlet_nodes = nodes
        self.dirichlet = np.concatenate([nodes, nodes + space.N])
        self.free = np.setdiff1d(np.arange(space.dofs), self.dirichlet)
        self.free_velocity = self.free[self.free < 2 * space.N]
        x_of_unknown = np.concatenate([space.nodes[0], space.nodes[0], space.pressure_basis.doflocs[0]])
        self.free_x = x_of_unknown[self.free]
        positions = np.full(2 * space.N, -1, dtype=np.int64)
        positions[self.free_velocity] = np.arange(len(self.free_velocity))
        self.positions = positions.reshape(2, space.N)

    def _boundary_vectors(self):
        space, channel, saw = self.space, self.scenario.channel, self.scenario.saw
        x, y = space.nodes
        on_bottom = np.isclose(y, 0.0, atol=1e-9 * channel.height)
        self.inflow = self._projected_inflow()
        self.jet = np.zeros((2, space.N))
        self.jet[1, on_bottom] = saw.jet_speed * saw_window_profile(channel, x[on_bottom])
        self.streaming_unit_load = np.zeros((2, space.N))
        if saw.model == "streaming":
            @LinearForm
            def body_force(v, w):
                x1, x2 = w.x
                return saw.streaming_force * saw_window_profile(channel, x1) * np.exp(-x2 / saw.attenuation_length) * v
            self.streaming_unit_load[1] = asm(body_force, space.velocity_basis)

    def _projected_inflow(self) -> np.ndarray:
        """The L2 projection of the inflow profiles onto the P2 traces on the inlets (paper section 3.1).

        Inlet end nodes are wall nodes and keep the value 0. The projection keeps the inflow flux far
        closer to the exact profile's than nodal interpolation where the cut-off is barely resolved.
        """
        space, channel = self.space, self.scenario.channel
        cmesh = space.cmesh
        facets = np.concatenate([cmesh.boundary(inlet.name) for inlet in channel.inlets])
        basis = FacetBasis(cmesh.mesh, ElementTriP2(), facets=facets, intorder=10)
        mass = asm(mass_form, basis).tocsr()
        wall_nodes = space.velocity_basis.get_dofs(facets=cmesh.boundary("wall")).all()
        nodes = np.setdiff1d(space.velocity_basis.get_dofs(facets=facets).all(), wall_nodes)
        inflow = np.zeros((2, space.N))
        for component in range(2):
            @LinearForm
            def profile(v, w):
                return inflow_velocity(channel, w.x[1])[component] * v
            load = asm(profile, basis)
            inflow[component, nodes] = spla.spsolve(mass[nodes][:, nodes].tocsc(), load[nodes])
        return inflow

    def _constant_system(self):
        space, fluid, numerics = self.space, self.scenario.fluid, self.scenario.numerics
        self.stiffness = fluid.viscosity * space.laplace
        # backward Euler: rho/dt M; BDF2: rho (3 v^{m+1} - 4 v^m + v^{m-1}) / (2 dt), so 3 rho / (2 dt) M
        self.mass_coefficient = fluid.density / numerics.dt * self.scheme.mass
        structure = _structure(space, self.free, self.dirichlet)
        self.pressure_scale = structure.velocity_largest(self.mass_coefficient, fluid.viscosity) \
            / structure.divergence_largest
        self._scaled_divergence = None
        self.solver_name = resolved_solver_name(numerics.linear_solver)
        self._reusable = {}
        self._constant = None
        if numerics.convection in ("imex", "stokes", "implicit"):
            # the same entries in the same order as _assembled(a, a) gives, a = c M + mu L: gathered, not assembled
            rows, lift = structure.assembled(self.mass_coefficient, fluid.viscosity, self.pressure_scale)
            self._constant = self._factored(rows, lift, symmetric=True)

    @property
    def _divergence(self) -> sp.csr_matrix:
        """s [Bx, By], s = ``pressure_scale`` (built when first needed)."""
        if self._scaled_divergence is None:
            bx, by = self.space.divergence
            self._scaled_divergence = sp.hstack([bx, by]).tocsr() * self.pressure_scale
        return self._scaled_divergence

    def _assembled(self, block_xx, block_yy, off_xy=None, off_yx=None):
        """The free rows of [[A, -s B^T], [-s B, 0]], A = [[A_xx, A_xy], [A_yx, A_yy]]: (free columns, Dirichlet
        columns)."""
        momentum = sp.bmat([[block_xx, off_xy], [off_yx, block_yy]], format="csr")
        return block_rows(momentum, self._divergence, self.free, self.dirichlet)

    def _system(self, block_xx, block_yy, off_xy=None, off_yx=None, symmetric=False, reuse=None):
        """Factor the free-free block of [[A, -s B^T], [-s B, 0]], A = [[A_xx, A_xy], [A_yx, A_yy]].

        ``reuse`` names a slot ('oseen', 'newton') whose last factorisation is refactored in place when
        the sparsity pattern is unchanged (the ordering is reused).
        """
        rows, lift = self._assembled(block_xx, block_yy, off_xy, off_yx)
        return self._factored(rows, lift, symmetric, reuse)

    def _factored(self, rows, lift, symmetric=False, reuse=None):
        started = clock.perf_counter()
        previous = self._reusable.get(reuse)
        numerics = self.scenario.numerics
        factor = factorize(rows, numerics.linear_solver, symmetric=symmetric,
                           previous=previous, reproducible=numerics.reproducible,
                           coordinates=self.free_x if symmetric else None,
                           precision=numerics.precision if symmetric else "double")
        if reuse:
            self._reusable[reuse] = factor
        self.timings.factor += clock.perf_counter() - started
        return _System(factor, lift @ self.inflow.ravel()[self.dirichlet], lift @ self.jet.ravel()[self.dirichlet])

    # ------------------------------------------------------------------ boundary data
    def jet_weight(self, time: float, actuation: float) -> float:
        """The factor of the SAW jet in the Dirichlet data: boundary velocity = inflow + weight * jet."""
        saw = self.scenario.saw
        if saw.model == "streaming" or actuation == 0.0:
            return 0.0
        return actuation * saw_jet_factor(saw)

    def streaming_level(self, previous_level: float, actuation: float, dt: float) -> float:
        """The streaming drive after ``dt``: a first-order lag towards ``actuation``."""
        saw = self.scenario.saw
        if saw.model != "streaming":
            return 0.0
        return lagged(previous_level, actuation, dt, saw.spin_up_time)

    # ------------------------------------------------------------------ solves
    def _free_rhs(self, momentum=None, continuity=None):
        """A reduced right-hand side gathered from a momentum load (2, N) and a continuity load (P,)."""
        rhs = np.empty(len(self.free))
        kernels.free_rhs(_NOTHING if momentum is None else np.ascontiguousarray(momentum, dtype=float).ravel(),
                         self.free_velocity, _NOTHING if continuity is None else np.asarray(continuity, dtype=float),
                         rhs)
        return rhs

    def _free_solution(self, velocity, pressure) -> np.ndarray:
        """The reduced unknowns of a velocity (2, N) and pressure: the inverse of what ``_solve`` returns."""
        out = np.empty(len(self.free))
        kernels.free_solution(np.ascontiguousarray(velocity, dtype=float).ravel(), self.free_velocity,
                              np.asarray(pressure, dtype=float), float(self.pressure_scale), out)
        return out

    def _solve(self, system, rhs, inflow_weight=1.0, jet_weight=0.0, near=None, once=False):
        """Solve ``system`` for the reduced ``rhs`` with boundary velocity inflow_weight * inflow + jet_weight * jet.

        ``near`` (velocity, pressure) is a solution close to this one (the last step's): the mixed-precision
        solve refines from it (``sim.fast.linalg.MixedPrecision``); direct solves ignore it. ``once``: one back-solve
        of the factorisation, unrefined (single precision with ``precision = "mixed"``: ~1e-6 relative)."""
        if inflow_weight:
            kernels.subtract_scaled(rhs, float(inflow_weight), system.lift_inflow)
        if jet_weight:
            kernels.subtract_scaled(rhs, float(jet_weight), system.lift_jet)
        guess = None if near is None else self._free_solution(*near)
        started = clock.perf_counter()
        if once:
            free_solution = np.asarray(getattr(system.factor, "inner", system.factor).solve(rhs), dtype=np.float64)
        else:
            free_solution = system.factor.solve(rhs, guess)
        self.timings.solve += clock.perf_counter() - started
        velocity = np.empty((2, self.space.N))
        kernels.boundary_velocity(float(inflow_weight), np.ascontiguousarray(self.inflow, dtype=float).ravel(),
                                  float(jet_weight), np.ascontiguousarray(self.jet, dtype=float).ravel(),
                                  self.free_velocity, free_solution, velocity.ravel())
        n_velocity = len(self.free_velocity)
        return velocity, free_solution[n_velocity:] * self.pressure_scale

    def _check(self, velocity, time, what):
        if not np.all(np.isfinite(velocity)):
            raise NumericalBlowUp(f"non-finite fluid velocity at t = {time:.6g} s after the {what} solve: "
                                  "the time step is too large for this flow; reduce numerics.dt")

    def step(self, state: Flow, actuation: float = 0.0, load: np.ndarray | None = None,
             ahead: "bool | NavierStokes" = True) -> Flow:
        """Advance one step of size ``numerics.dt`` from ``state``: backward Euler, or BDF2 (``numerics.scheme``).
        ``ahead``: start the next step's momentum integrals from the result (``prefetch``: a caller that knows the
        next step is another solver's asks that one).

        BDF2 takes rho (3 v^{m+1} - 4 v^m + v^{m-1}) / (2 dt) for the time derivative and the convection of
        2 v^m - v^{m-1} (imex); v^{m-1} is the velocity at t - dt from ``state.history`` (``value_back``); a
        state without history (a start) takes v^{m-1} = v^m."""
        numerics = self.scenario.numerics
        dt = numerics.dt
        new_time = state.time + dt
        treatment = numerics.convection
        started = clock.perf_counter()
        level = self.streaming_level(state.streaming_level, actuation, dt)
        if level:
            load = level * self.streaming_unit_load if load is None else load + level * self.streaming_unit_load
        rhs = self._free_rhs(load)
        self.space.scatter_momentum(self._element_momentum(state), self.positions, rhs)
        self.timings.load += clock.perf_counter() - started
        jet = self.jet_weight(new_time, actuation)
        iterations = 1
        if treatment in ("imex", "stokes"):
            velocity, pressure = self._solve(self._constant, rhs, 1.0, jet, near=(state.velocity, state.pressure))
        elif treatment == "oseen":
            system = self._linearised(state.velocity, newton=False, with_mass=True)
            velocity, pressure = self._solve(system, rhs, 1.0, jet)
        else:
            velocity, pressure, iterations = self._implicit(state, rhs, jet, new_time)
        self._check(velocity, new_time, treatment)
        self.timings.steps += 1
        velocity.flags.writeable = pressure.flags.writeable = False     # a step's result stays as it was computed
        history = self.scheme.carried((state.time, state.velocity), state.history)
        flow = Flow(new_time, velocity, pressure, level, iterations, history)
        if ahead is True:
            self.prefetch(flow)
        elif ahead:
            ahead.prefetch(flow)
        return flow

    # ------------------------------------------------------------------ the momentum integrals, computed ahead
    @property
    def scheme(self) -> TimeScheme:
        """The time scheme of the steps (``sim.method.timeschemes``)."""
        return scheme_named(self.scenario.numerics.scheme)

    def _momentum_back(self, state: Flow):
        """bdf2's velocity one step back for the momentum integrals of a step from ``state`` (``kernels.
        element_momentum``'s ``back``: the weights of v^m and the earlier velocities, and those two); None for euler
        or without history (a start: v^{m-1} = v^m, the euler integrals)."""
        numerics = self.scenario.numerics
        if not scheme_named(numerics.scheme).kept or not state.history:
            return None
        times, earlier = [t for t, _ in state.history], [v for _, v in state.history]
        target = state.time - numerics.dt
        index = earlier_at(state.time, times, target)
        if index is not None:                                 # an earlier velocity itself: taken as it is
            return (0.0, 1.0, 0.0), (earlier[index], earlier[index])
        weights = lagrange_weights([state.time, *times], target) + [0.0] * (2 - len(times))
        return tuple(weights), (earlier[0], earlier[-1])

    def _element_integrals(self, state: Flow, out: np.ndarray, threads: int | None = None) -> np.ndarray:
        explicit = self.scenario.fluid.density if self.scenario.numerics.convection == "imex" else 0.0
        return self.space.element_momentum(state.velocity, self.mass_coefficient, explicit, out,
                                           self._momentum_back(state), threads)

    def _element_momentum(self, state: Flow) -> np.ndarray:
        """The element integrals of the momentum load of a step from ``state``: the ones ``prefetch`` computed
        ahead when they are of this state, else computed here."""
        flow, local = self._finish_ahead()
        if flow is state and local is not None:
            return local
        if self._inline_buffer is None:
            self._inline_buffer = self.space.element_buffer()
        return self._element_integrals(state, self._inline_buffer)

    def prefetch(self, flow: Flow):
        """Start computing the element integrals of the step from ``flow`` on the helper thread (alone: one of numba's
        threads), while the caller moves the membranes, runs the controller and records (~1 ms of the other core a
        step; ``kernels.element_momentum``: the same bits as computed in the step). A speculation: a next step
        from another state or by another solver (an adaptive run's other level) computes its own."""
        self._finish_ahead()                   # an earlier one not taken (its buffer is this one's)
        if not prefetch_wanted():
            return
        if self._ahead_buffer is None:
            self._ahead_buffer = self.space.element_buffer()
        try:
            future = helper().submit(self._element_integrals, flow, self._ahead_buffer, 1)
        except RuntimeError:                   # the interpreter is shutting down: the next step computes them
            return
        self._ahead = (flow, future, os.getpid())
        clock.sleep(0)      # lets the helper take the GIL now, to start its kernel (which runs without it)

    def _finish_ahead(self):
        """(flow, integrals) of the pending ``prefetch`` (integrals None when there are none to take: not started,
        so cancelled, and computed faster by the step on all threads; failed; or inherited through a fork, whose
        helper thread the child does not have), and none pending after it. (None, None) without one."""
        ahead, self._ahead = self._ahead, None
        if ahead is None:
            return None, None
        flow, future, pid = ahead
        if pid != os.getpid() or future.cancel():
            return flow, None
        try:
            return flow, future.result()        # (one for another state is waited for too: it writes the buffer)
        except Exception:                       # computed again by the step, where an error is reported as usual
            return flow, None

    def _linearised(self, velocity, newton, with_mass):
        """The factored system linearised about ``velocity`` (Oseen, or Newton's Jacobian)."""
        started = clock.perf_counter()
        density = self.scenario.fluid.density
        space = self.space
        blocks = space.convection_matrices(velocity, newton)
        base = space.on_pattern(self.stiffness + self.mass_coefficient * space.mass if with_mass else self.stiffness)
        for row in blocks:
            for block in row:
                block.data *= density
        blocks[0][0].data += base.data
        blocks[1][1].data += base.data
        self.timings.assemble += clock.perf_counter() - started
        return self._system(blocks[0][0], blocks[1][1], blocks[0][1], blocks[1][0],
                            reuse=("newton" if newton else "oseen") + ("-mass" if with_mass else ""))

    def _implicit(self, state, rhs, jet, time):
        """Solve (26) with c(v^{m+1}) to ``nonlinear_tolerance``: fixed point, then Newton if needed.

        ``rhs`` holds rho/dt M v^m + loads (reduced); each fixed-point iterate costs one back-solve.
        """
        numerics, density = self.scenario.numerics, self.scenario.fluid.density
        previous = state.velocity
        scale = np.linalg.norm(rhs) + 1e-300
        convection = self._free_rhs(self.space.convection_load(previous))
        residuals = []
        near = (state.velocity, state.pressure)
        for iteration in range(1, numerics.max_nonlinear_iterations + 1):
            velocity, pressure = self._solve(self._constant, rhs - density * convection, 1.0, jet, near)
            near = (velocity, pressure)
            new_convection = self._free_rhs(self.space.convection_load(velocity))
            # the residual of (26) at the new iterate is rho (c(v_new) - c(v_old))
            residuals.append(density * np.linalg.norm(new_convection - convection) / scale)
            convection = new_convection
            if residuals[-1] <= numerics.nonlinear_tolerance:
                return velocity, pressure, iteration
            if iteration >= 3 and residuals[-1] > 0.5 * residuals[-2]:
                log.info("fixed-point iterations contract too slowly at t = %.6g s; switching to Newton", time)
                break
        momentum = self.mass_coefficient * (self.space.mass @ previous.T).T
        velocity, pressure, newton_iterations = self._newton(velocity, pressure, momentum, jet, time, with_mass=True)
        return velocity, pressure, len(residuals) + newton_iterations

    def _newton(self, velocity, pressure, momentum, jet, time, with_mass):
        """Newton's method for (m M + eta L) v + rho c(v) - B^T p = momentum, B v = 0, v = data on Gamma_D."""
        numerics = self.scenario.numerics
        velocity = velocity.copy()
        boundary = self.inflow + jet * self.jet
        velocity.ravel()[self.dirichlet] = boundary.ravel()[self.dirichlet]
        target = momentum
        sizes = []
        for iteration in range(1, numerics.max_nonlinear_iterations + 1):
            residual = self._residual(velocity, pressure, target, with_mass)
            continuity = self.pressure_scale * self._divergence_of(velocity)
            system = self._linearised(velocity, newton=True, with_mass=with_mass)
            correction, pressure_correction = self._solve(system, self._free_rhs(-residual, continuity), 0.0, 0.0)
            velocity = velocity + correction
            pressure = pressure + pressure_correction
            self._check(velocity, time, "Newton")
            sizes.append(np.linalg.norm(correction) / (np.linalg.norm(velocity) + 1e-300))
            # quadratic convergence predicts the next correction as s_k^3 / s_{k-1}^2: stop when that is small
            predicted = sizes[-1] ** 3 / sizes[-2] ** 2 if len(sizes) > 1 and sizes[-1] < sizes[-2] else np.inf
            if sizes[-1] <= numerics.nonlinear_tolerance:
                return velocity, pressure, iteration
            if predicted <= numerics.nonlinear_tolerance:
                # one more correction with the same factorisation (no refactor): it removes the linear
                # solver's rounding error as iterative refinement would
                residual = self._residual(velocity, pressure, target, with_mass)
                continuity = self.pressure_scale * self._divergence_of(velocity)
                correction, pressure_correction = self._solve(system, self._free_rhs(-residual, continuity), 0.0, 0.0)
                return velocity + correction, pressure + pressure_correction, iteration
        raise NumericalBlowUp(f"the nonlinear solve did not converge in {numerics.max_nonlinear_iterations} Newton "
                              f"iterations at t = {time:.6g} s: reduce numerics.dt or the inflow speeds")

    def _divergence_of(self, velocity):
        bx, by = self.space.divergence
        return bx @ velocity[0] + by @ velocity[1]

    def _residual(self, velocity, pressure, target, with_mass):
        """Momentum residual (2, N): (m M + eta L) v + rho c(v) - B^T p - target."""
        space = self.space
        operator = self.stiffness @ velocity.T
        if with_mass:
            operator = operator + self.mass_coefficient * (space.mass @ velocity.T)
        bx, by = space.divergence
        residual = operator.T + self.scenario.fluid.density * space.convection_load(velocity) - target
        residual[0] -= bx.T @ pressure
        residual[1] -= by.T @ pressure
        return residual

    def steady(self, actuation: float = 0.0, load: np.ndarray | None = None) -> Flow:
        """The steady flow for a constant IDT drive: Newton's method from the boundary data (interior at rest).

        The first Newton step from rest is an Oseen-like solve about the boundary data, which already
        lands near the Stokes flow; a separate Stokes factorisation would cost more than it saves.
        """
        started = clock.perf_counter()
        level = actuation if self.scenario.saw.model == "streaming" else 0.0
        forcing = level * self.streaming_unit_load if load is None else load + level * self.streaming_unit_load
        jet = self.jet_weight(0.0, actuation)

        def solve():
            # Newton's first system analysed afresh, not refactored on an earlier steady solve's analysis (PARDISO's
            # matching and ordering come from that matrix's values): a start's bits must not depend on what this
            # solver solved before, or the stored start would depend on which run stored it
            self._reusable.pop("newton", None)
            velocity, pressure = np.zeros((2, self.space.N)), np.zeros(self.space.P)
            velocity, pressure, iterations = self._newton(velocity, pressure, forcing, jet, 0.0, with_mass=False)
            return {"velocity": velocity, "pressure": pressure, "iterations": np.array(iterations)}

        if load is None:        # a stored start flow: everything it depends on is in the key (sim.fast.store)
            # what the steady flow depends on: the device, the fluid, the SAW and the numerics of Newton's
            # method (not the convection treatment of steps, the cells or the membrane method); dt and the time
            # scheme only through the pressure scale of the systems Newton solves, which sets the last bits (without
            # it in the key a --tolerance run, bdf2, would take the start a fixed-step euler run had stored, and its
            # digits would depend on which of the two had run first)
            scene, numerics = self.scenario, self.scenario.numerics
            newton = {name: getattr(numerics, name) for name in
                      ("mesh_h", "linear_solver", "nonlinear_tolerance", "max_nonlinear_iterations", "reproducible")}
            key = {"channel": repr(scene.channel), "fluid": repr(scene.fluid), "saw": repr(scene.saw),
                   "numerics": repr(newton), "pressure_scale": float(self.pressure_scale).hex(),
                   "actuation": float(actuation), "solver": self.solver_name,
                   "mkl": mkl_version(), "nodes": digest(self.space.nodes), "inflow": digest(self.inflow, self.jet),
                   "code": solver_code_digest()}
            result = reuse("steady-flow", key, solve)
        else:
            result = solve()
        self.timings.extra["steady"] = self.timings.extra.get("steady", 0.0) + clock.perf_counter() - started
        return Flow(0.0, result["velocity"].copy(), result["pressure"].copy(), level, int(result["iterations"]))

    def use_boundary_velocity(self, velocity: np.ndarray):
        """Impose ``velocity`` (2, N) on the Dirichlet boundary instead of the scenario's inflow.

        The SAW jet still adds to it. Used for manufactured solutions and custom inflow data.
        """
        self.inflow = np.array(velocity, dtype=float)
        self._constant_system()

    def response(self, load: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The change (velocity (2, N), pressure) of an imex or stokes step's solution for an extra load (2, N): one
        back-solve of the constant matrix with homogeneous boundary data (the step is affine in its load;
        ``sim.method.multiplier``), unrefined: with mixed precision ~1e-6 of the response, which only the area
        constraint's small pressures multiply."""
        if self._constant is None or self.scenario.numerics.convection not in ("imex", "stokes"):
            raise ValueError(f"the {self.scenario.numerics.convection} treatment's step is not affine in its load")
        return self._solve(self._constant, self._free_rhs(load), 0.0, 0.0, once=True)

    def backsolve(self, rhs: np.ndarray) -> np.ndarray:
        """One bare back-solve of the constant factorisation (the benchmarks' yardstick); with mixed precision
        the single-precision back-solve that each refinement correction costs."""
        if self._constant is None:
            raise ValueError(f"the {self.scenario.numerics.convection} treatment has no constant factorisation")
        factor = self._constant.factor
        return getattr(factor, "inner", factor).solve(rhs)

    def load_response(self, load: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The velocity (2, N) and pressure (P,) that ``load`` (2, N) adds to a step's solution: the constant system
        solved for it alone, zero on the Dirichlet boundary (imex and stokes, whose step is linear in the load). One
        back-solve (``backsolve``: with mixed precision the single-precision one, ~1e-6 relative, unrefined: the
        response is a small part of a step's flow)."""
        started = clock.perf_counter()
        free_solution = self.backsolve(self._free_rhs(load))
        self.timings.solve += clock.perf_counter() - started
        velocity = np.empty((2, self.space.N))
        kernels.boundary_velocity(0.0, np.ascontiguousarray(self.inflow, dtype=float).ravel(), 0.0,
                                  np.ascontiguousarray(self.jet, dtype=float).ravel(), self.free_velocity,
                                  free_solution, velocity.ravel())
        return velocity, free_solution[len(self.free_velocity):] * self.pressure_scale

    def constant_matrix(self) -> sp.csr_matrix:
        """The reduced (Dirichlet-free) matrix of the imex/stokes treatments, pressure scaled."""
        a = self.mass_coefficient * self.space.mass + self.stiffness
        momentum = sp.block_diag([a, a], format="csr")
        full = sp.bmat([[momentum, -self._divergence.T], [-self._divergence, None]], format="csr")
        return full[self.free][:, self.free].tocsr()

    def rest(self) -> Flow:
        return Flow(0.0, np.zeros((2, self.space.N)), np.zeros(self.space.P))

    def initial_flow(self, actuation: float = 0.0) -> Flow:
        """The start state the scenario asks for: the steady flow (default) or fluid at rest."""
        if self.scenario.numerics.initial_flow == "rest":
            return self.rest()
        return self.steady(actuation)

    def divergence_norm(self, velocity: np.ndarray) -> float:
        """max_q |(q_i, div v)| over P1 basis functions: zero to round-off for a solution."""
        bx, by = self.space.divergence
        return float(np.abs(bx @ velocity[0] + by @ velocity[1]).max())
