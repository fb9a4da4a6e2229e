"""Taylor-Hood Navier-Stokes: manufactured solutions, Poiseuille flow, mass conservation, treatments."""

from dataclasses import replace

import numpy as np
import pytest
from skfem import Basis, ElementTriP1, ElementTriP2, FacetBasis, Functional, LinearForm, asm

from sim.fast import speed
from sim.method.fluid import NavierStokes
from sim.model.boundary import inlet_flux
from sim.model.scenario import UM, Channel, Inlet, Outlet, Scenario

# ---------------------------------------------------------------- manufactured solution
# stream function psi = A sin(a x) sin(b y): u = psi_y, v = -psi_x (divergence free), p = P0 cos(a x) cos(b y)
LENGTH, HEIGHT = 300 * UM, 220 * UM
A_WAVE, B_WAVE = 2 * np.pi / LENGTH, 2 * np.pi / HEIGHT
AMPLITUDE = 0.05 / B_WAVE          # peak speed 0.05 m/s: Reynolds number ~ 1, like the device
PRESSURE = 5.0          # comparable to the viscous stress eta U / L, so neither error dominates
RHO, ETA = 1.0e3, 6.0e-3


def exact_velocity(x, y):
    return np.array([AMPLITUDE * B_WAVE * np.sin(A_WAVE * x) * np.cos(B_WAVE * y),
                     -AMPLITUDE * A_WAVE * np.cos(A_WAVE * x) * np.sin(B_WAVE * y)])


def exact_gradient(x, y):
    """[[du/dx, du/dy], [dv/dx, dv/dy]]."""
    a, b, s = A_WAVE, B_WAVE, AMPLITUDE
    return np.array([[s * a * b * np.cos(a * x) * np.cos(b * y), -s * b * b * np.sin(a * x) * np.sin(b * y)],
                     [s * a * a * np.sin(a * x) * np.sin(b * y), -s * a * b * np.cos(a * x) * np.cos(b * y)]])


def exact_pressure(x, y):
    return PRESSURE * np.cos(A_WAVE * x) * np.cos(B_WAVE * y)


def forcing(x, y):
    """f = rho (u . grad) u - eta laplace u + grad p for the steady equations."""
    a, b, s = A_WAVE, B_WAVE, AMPLITUDE
    u = exact_velocity(x, y)
    convection = RHO * s * s * np.array([a * b * b * np.sin(a * x) * np.cos(a * x),
                                         a * a * b * np.sin(b * y) * np.cos(b * y)])
    pressure_gradient = PRESSURE * np.array([-a * np.sin(a * x) * np.cos(b * y), -b * np.cos(a * x) * np.sin(b * y)])
    return convection + ETA * (a * a + b * b) * u + pressure_gradient


def manufactured_errors(h):
    scenario = Scenario().with_numerics(mesh_h=h)
    solver = NavierStokes(scenario)
    space = solver.space
    solver.use_boundary_velocity(exact_velocity(*space.nodes))
    basis = space.velocity_basis
    load = np.array([asm(LinearForm(lambda v, w, c=c: forcing(*w.x)[c] * v), basis) for c in range(2)])
    # do-nothing outlets: the exact solution's traction eta du/dn - p n enters as a boundary load
    for outlet in scenario.channel.outlets:
        facets = FacetBasis(space.cmesh.mesh, ElementTriP2(), facets=space.cmesh.boundary(outlet.name), intorder=6)
        traction = [lambda x, y: ETA * exact_gradient(x, y)[0, 0] - exact_pressure(x, y),
                    lambda x, y: ETA * exact_gradient(x, y)[1, 0]]
        load += np.array([asm(LinearForm(lambda v, w, t=t: t(*w.x) * v), facets) for t in traction])
    flow = solver.steady(0.0, load=load)

    fine = Basis(space.cmesh.mesh, ElementTriP2(), intorder=8)
    pressure_basis = fine.with_element(ElementTriP1())
    ux, uy = fine.interpolate(flow.velocity[0]), fine.interpolate(flow.velocity[1])
    p = pressure_basis.interpolate(flow.pressure)

    @Functional
    def velocity_l2(w):
        exact = exact_velocity(*w.x)
        return (w.ux - exact[0]) ** 2 + (w.uy - exact[1]) ** 2

    @Functional
    def velocity_h1(w):
        g = exact_gradient(*w.x)
        return ((w.ux.grad[0] - g[0, 0]) ** 2 + (w.ux.grad[1] - g[0, 1]) ** 2
                + (w.uy.grad[0] - g[1, 0]) ** 2 + (w.uy.grad[1] - g[1, 1]) ** 2)

    @Functional
    def pressure_l2(w):
        return (w.p - exact_pressure(*w.x)) ** 2

    return (np.sqrt(velocity_l2.assemble(fine, ux=ux, uy=uy)), np.sqrt(velocity_h1.assemble(fine, ux=ux, uy=uy)),
            np.sqrt(pressure_l2.assemble(pressure_basis, p=p)))


def test_manufactured_solution_converges_at_taylor_hood_rates():
    sizes = np.array([10, 5, 2.5]) * UM          # uniform grids: every device breakpoint is a multiple of 10 um
    errors = np.array([manufactured_errors(h) for h in sizes])
    rates = [np.polyfit(np.log(sizes), np.log(errors[:, k]), 1)[0] for k in range(3)]
    velocity_l2, velocity_h1, pressure_l2 = rates
    assert velocity_l2 == pytest.approx(3.0, abs=0.1)
    assert velocity_h1 == pytest.approx(2.0, abs=0.1)
    assert pressure_l2 == pytest.approx(2.0, abs=0.1)


# ---------------------------------------------------------------- Poiseuille flow
def straight_channel(peak=0.02, h=10 * UM, **numerics):
    channel = Channel(length=200 * UM, height=100 * UM, inlets=(Inlet("inlet", (0.0, 100 * UM), peak, 0.0, 0.0),),
                      outlets=(Outlet("outlet", (0.0, 100 * UM)),), profile_reading="peak", injection_inlet="inlet")
    return Scenario(channel=channel).with_numerics(mesh_h=h, **numerics)


def poiseuille(nodes, scenario):
    height, peak = scenario.channel.height, scenario.channel.inlets[0].v_hat
    x, y = nodes
    velocity = np.array([4 * peak * y * (height - y) / height**2, 0 * y])
    gradient = 8 * scenario.fluid.viscosity * peak / height**2
    return velocity, gradient * (scenario.channel.length - x)


def test_poiseuille_flow_is_reproduced_to_round_off():
    scenario = straight_channel()
    solver = NavierStokes(scenario)
    flow = solver.steady(0.0)
    velocity, _ = poiseuille(solver.space.nodes, scenario)
    _, pressure = poiseuille(solver.space.cmesh.mesh.p, scenario)
    assert np.abs(flow.velocity - velocity).max() <= 1e-12 * np.abs(velocity).max()
    assert np.abs(flow.pressure - pressure).max() <= 1e-9 * np.abs(pressure).max()


@pytest.mark.parametrize("convection", ["imex", "oseen", "implicit", "stokes"])
@pytest.mark.parametrize("precision", ["double", "mixed"])
def test_poiseuille_flow_is_a_fixed_point_of_every_treatment(convection, precision):
    """To round-off in double precision; mixed precision (single-precision factors refined once a step) adds
    up to ~1e-7 in the first step from rest pressure, which the steps then damp (docs/numerics.md)."""
    scenario = straight_channel(convection=convection, dt=25e-6, precision=precision)
    solver = NavierStokes(scenario)
    velocity, _ = poiseuille(solver.space.nodes, scenario)
    state = solver.rest()
    state = type(state)(0.0, velocity, state.pressure)
    for _ in range(3):
        state = solver.step(state)
    mixed = precision == "mixed" and convection in ("imex", "stokes", "implicit") and solver.solver_name == "pardiso"
    assert np.abs(state.velocity - velocity).max() <= (5e-7 if mixed else 1e-11) * np.abs(velocity).max()


# ---------------------------------------------------------------- mass conservation
def net_outflow(solver, velocity):
    names = [b.name for b in solver.scenario.channel.inlets + solver.scenario.channel.outlets] + ["wall"]
    return {name: solver.space.boundary_flux(velocity, name) for name in names}


@pytest.mark.parametrize("model", ["paper", "envelope", "streaming"])
def test_volume_flux_in_equals_flux_out(coarse_scenario, model):
    scenario = coarse_scenario.with_saw(model=model)
    solver = NavierStokes(scenario)
    for actuation in (0.0, 1.0):
        flow = solver.steady(actuation)
        fluxes = net_outflow(solver, flow.velocity)
        inflow = -sum(fluxes[i.name] for i in scenario.channel.inlets)
        jet = -fluxes["wall"]       # the SAW window is part of the wall facets
        outflow = sum(fluxes[o.name] for o in scenario.channel.outlets)
        assert inflow + jet == pytest.approx(outflow, rel=1e-10)
        for inlet in scenario.channel.inlets:
            # nodal interpolation of the 3 um cut-off on a 5 um mesh: flux within 1 % of the exact profile's
            assert -fluxes[inlet.name] == pytest.approx(inlet_flux(inlet, "paper"), rel=1e-2)
        if model == "streaming" or actuation == 0.0:
            assert abs(jet) <= 1e-12 * outflow          # a body force adds no mass
        else:
            assert jet > 0.3 * inflow                   # the Dirichlet jet injects mass (docs/physics.md, "SAW models")


def test_steady_flow_is_discretely_divergence_free(coarse_scenario):
    solver = NavierStokes(coarse_scenario)
    flow = solver.steady(1.0)
    scale = np.abs(flow.velocity).max() * coarse_scenario.numerics.mesh_h
    assert solver.divergence_norm(flow.velocity) <= 1e-12 * scale


# ---------------------------------------------------------------- treatments agree on a transient
TRANSIENT_STEPS = 20


def switch_on_transient(convection, scenario):
    """Start from the steady flow with the IDT off, switch it on, run TRANSIENT_STEPS steps."""
    solver = NavierStokes(scenario.with_numerics(convection=convection))
    state = solver.steady(0.0)
    for _ in range(TRANSIENT_STEPS):
        state = solver.step(state, actuation=1.0)
    return state


@pytest.fixture(scope="module")
def transients(coarse_scenario):
    scenario = coarse_scenario.with_saw(model="envelope").with_numerics(dt=2.5e-6)
    return {c: switch_on_transient(c, scenario) for c in ("implicit", "oseen", "imex", "stokes")}


def relative_difference(a, b):
    return np.linalg.norm(a.velocity - b.velocity) / np.linalg.norm(b.velocity)


def test_implicit_oseen_and_imex_agree_on_a_short_transient(transients):
    reference = transients["implicit"]
    assert relative_difference(transients["oseen"], reference) <= 1e-3
    assert relative_difference(transients["imex"], reference) <= 2e-3
    # dropping convection altogether is a visibly different flow: the comparison can fail
    assert relative_difference(transients["stokes"], reference) >= 10 * relative_difference(transients["imex"],
                                                                                            reference)


def test_implicit_treatment_solves_its_nonlinear_system(transients):
    assert 1 < transients["implicit"].iterations < 30


@pytest.mark.parametrize("numerics", [{"dt": 2.5e-6}, {"dt": 20e-6, "time_scheme": "bdf2"}, {"dt": 1e-3}])
def test_the_gathered_constant_matrix_is_the_block_assembly_bit_for_bit(numerics):
    """The constant treatments' matrix of a step (``sim.fast.gathered.GatheredMatrix``: gathered from the positions of
    its entries, as every --tolerance level builds its own) has the block assembly's entries, order and bits, so its
    factorisation, its kept entry in the cache and every solve are the same; the pressure scale too."""
    from sim.method.fluid import _structure
    fluid = NavierStokes(Scenario().with_numerics(mesh_h=20 * UM / 3, **numerics))
    a = fluid.mass_coefficient * fluid.space.mass + fluid.stiffness
    assembled = fluid._assembled(a, a)
    viscosity = fluid.scenario.fluid.viscosity
    gathered = _structure(fluid.space, fluid.free, fluid.dirichlet).assembled(fluid.mass_coefficient, viscosity,
                                                                               fluid.pressure_scale)
    for ours, theirs in zip(gathered, assembled):
        for part in ("indptr", "indices", "data"):
            assert np.array_equal(getattr(ours, part), getattr(theirs, part)), part
    bx, by = fluid.space.divergence
    assert fluid.pressure_scale == abs(a).max() / max(abs(bx).max(), abs(by).max())
    assert np.array_equal(fluid._constant.factor.solve(np.ones(len(fluid.free))),
                          fluid._factored(*assembled, symmetric=True).factor.solve(np.ones(len(fluid.free))))


def test_a_solver_like_another_steps_as_one_built_alone_and_refuses_another_device():
    """``NavierStokes(scenario, like=other)`` (a --tolerance level) shares the other's mesh, unknowns and boundary
    data and builds only its constant matrix: its steps are those of a solver built from scratch, bit for bit;
    a solver of another channel is refused."""
    scenario = Scenario().with_numerics(mesh_h=20 * UM / 3, time_scheme="bdf2")
    base = NavierStokes(scenario)
    level = scenario.with_numerics(dt=4 * scenario.numerics.dt)
    shared, alone = NavierStokes(level, like=base), NavierStokes(level)
    assert shared.space is base.space and shared.free is base.free and shared.inflow is base.inflow
    start = base.steady(1.0)
    one, other = shared.step(start, actuation=1.0), alone.step(start, actuation=1.0)
    assert np.array_equal(one.velocity, other.velocity) and np.array_equal(one.pressure, other.pressure)
    assert not np.array_equal(one.velocity, base.step(start, actuation=1.0).velocity)    # another dt: it can fail
    with pytest.raises(ValueError, match="another device or mesh"):
        NavierStokes(scenario.with_inlets_shut(), like=base)


@pytest.mark.parametrize("scheme", ["euler", "bdf2"])
def test_steps_are_the_same_bits_with_the_momentum_computed_ahead_or_in_the_step(scheme, monkeypatch):
    """Each step starts the next one's element integrals on a helper thread (``NavierStokes.prefetch``): a
    speculation on the state it returned. Stepping on from it, stepping again from an earlier state (a retaken
    step: the speculation is not of it), and with the helper switched off (``SpeedSettings.prefetch``) give the same
    bits; a step's velocity and pressure are read-only, so a speculation's input cannot change under it."""

    def run(prefetch: bool):
        monkeypatch.setattr(speed, "_settings", replace(speed.current(), prefetch=prefetch))
        solver = NavierStokes(Scenario().with_numerics(mesh_h=6 * UM, time_scheme=scheme))
        computed, original = [], solver._element_integrals
        solver._element_integrals = lambda state, out, threads=None: (computed.append(threads),
                                                                       original(state, out, threads))[1]

        def step(state):
            new = solver.step(state, actuation=1.0)
            if solver._ahead is not None:      # started for sure (a speculation not started is cancelled)
                solver._ahead[1].result()
            return new
        start = solver.steady(0.0)
        first = step(start)
        second = step(first)
        retaken = step(first)                  # from an earlier state: not the speculated one
        third = step(retaken)
        return [s.velocity for s in (first, second, retaken, third)], [third.pressure], computed

    ahead, pressures, computed_ahead = run(True)
    here, pressures_here, computed_here = run(False)
    assert all(np.array_equal(a, b) for a, b in zip(ahead + pressures, here + pressures_here))
    assert np.array_equal(ahead[1], ahead[2])                # the retaken step is the same step
    # ahead: after each of the four steps, on the helper (one thread); here: the start's and the retaken step's
    assert computed_ahead == [None, 1, 1, None, 1, 1] and computed_here == [None] * 4
    for array in (ahead[0], pressures[0]):
        with pytest.raises(ValueError):
            array[0] = 1.0


def test_the_helper_finishes_its_tasks_when_stopped_and_then_refuses_new_ones():
    """The fluid's helper thread (a daemon: it holds no process open) finishes what it was given when stopped (at
    exit, so the teardown never meets it inside a kernel), ends, and refuses later work; a cancelled task never
    runs and an exception reaches the caller."""
    import threading
    import time

    from sim.fast.helper import Helper
    helper = Helper()
    started = threading.Event()
    slow = helper.submit(lambda: (started.set(), time.sleep(0.2), "done")[2])
    started.wait(5)
    skipped = helper.submit(lambda: "ran")
    failing = helper.submit(lambda: 1 / 0)
    assert skipped.cancel() and not slow.cancel()
    helper.stop()
    assert slow.result(timeout=0) == "done" and skipped.cancelled()
    with pytest.raises(ZeroDivisionError):
        failing.result(timeout=0)
    assert not helper._thread.is_alive() and helper._thread.daemon
    with pytest.raises(RuntimeError):
        helper.submit(lambda: None)
