"""The fast FE-IB step (``sim.method.feib``, ``sim.method.fluid``, ``sim.fast.kernels``) held to the plain one
(``sim.method.reference``): the same steps, Euler and BDF2, to round-off; and each fast kernel, the C ones and numba's,
held to what the reference computes in its place (scikit-fem's assembly, ``basis.probes``, numpy expressions)."""

from dataclasses import replace

import numpy as np
import pytest

from sim.fast import kernels, speed
from sim.method.feib import ImmersedBoundary, State, new_cell
from sim.method.reference import Level, ReferenceStep
from sim.method.taylorhood import TaylorHood
from sim.method.transfer import PointLocator
from sim.model.scenario import UM, Scenario

STEPS = 3


def scenario_of(scheme: str, area_constraint: str = "pressure") -> Scenario:
    """A coarse mesh, double precision (the default mixed precision refines to a tolerance, not to round-off),
    no redistribution or projection (they follow the step: ``sim.method.feib.settle``)."""
    return Scenario().with_numerics(mesh_h=10 * UM, time_scheme=scheme, precision="double",
                                    area_constraint=area_constraint, redistribute=False)


@pytest.mark.parametrize("scheme, area_constraint", [("euler", "none"), ("euler", "pressure"),
                                                     ("bdf2", "pressure")])
def test_the_fast_step_is_the_reference_step_to_round_off(scheme, area_constraint):
    """Three steps with the SAW on and an RBC: velocity, pressure and membrane points agree to round-off."""
    scenario = scenario_of(scheme, area_constraint)
    plant = ImmersedBoundary(scenario)
    reference = ReferenceStep(scenario)
    start = plant.start(0.0)
    cell = new_cell(scenario, scenario.cell_type("RBC"), 1, start.flow.time, centre=(100 * UM, 80 * UM), warn=False)
    state = State(start.flow, (cell,))
    levels = [Level(start.flow.time, start.flow.velocity, start.flow.pressure, (cell.membrane.points,))]
    for _ in range(STEPS):
        state = plant.step(state, actuation=1.0)
        before = levels[-2] if len(levels) > 1 else None
        levels.append(reference.step(levels[-1], [cell.membrane], actuation=1.0, before=before))
        fast, plain = state.flow, levels[-1]
        assert fast.time == pytest.approx(plain.time, rel=1e-15)
        velocity_scale, pressure_scale = np.abs(plain.velocity).max(), np.abs(plain.pressure).max()
        assert np.abs(fast.velocity - plain.velocity).max() <= 2e-11 * velocity_scale      # measured: <= 4e-12
        assert np.abs(fast.pressure - plain.pressure).max() <= 1e-9 * pressure_scale       # measured: <= 1.1e-10
        moved = state.cells[0].membrane.points
        assert np.abs(moved - plain.points[0]).max() <= 1e-12 * scenario.channel.height
        assert np.abs(moved - levels[-2].points[0]).max() > 1e-3 * UM          # the cell moved
    assert np.abs(levels[-1].velocity - levels[0].velocity).max() > 1e-6 * velocity_scale   # the jet, the force


def test_the_reference_is_a_different_step_when_the_scheme_differs():
    """The comparison can fail: the reference's Euler step is not the fast BDF2 step."""
    plant = ImmersedBoundary(scenario_of("bdf2"))
    reference = ReferenceStep(scenario_of("euler"))
    start = plant.start(0.0)
    first = Level(start.flow.time, start.flow.velocity, start.flow.pressure, ())
    fast = plant.step(plant.step(start, 1.0), 1.0).flow
    plain = reference.step(reference.step(first, [], 1.0), [], 1.0, before=first)
    assert np.abs(fast.velocity - plain.velocity).max() > 1e-6 * np.abs(plain.velocity).max()


def test_the_reference_refuses_what_it_leaves_out():
    with pytest.raises(ValueError, match="streaming"):
        ReferenceStep(replace(Scenario(), saw=replace(Scenario().saw, model="streaming")))


# ---------------------------------------------------------------------- each kernel, C and numba's

@pytest.fixture(params=["c", "numba"])
def implementation(request, monkeypatch):
    if request.param == "c" and kernels._LIBRARY is None:
        pytest.skip("vcyto was installed without its compiled step kernels")
    if request.param == "numba":
        pytest.importorskip("numba")
    monkeypatch.setattr(speed, "_settings", replace(speed.current(), c_kernels=request.param == "c"))
    assert kernels.compiled() == (request.param == "c")
    return request.param


@pytest.fixture(scope="module")
def reference():
    return ReferenceStep(Scenario().with_numerics(mesh_h=7 * UM, time_scheme="bdf2"))


@pytest.fixture(scope="module")
def space(reference):
    return TaylorHood(reference.cmesh)


@pytest.mark.parametrize("scheme", ["euler", "bdf2"])
def test_the_momentum_kernels_give_the_references_load(implementation, reference, space, scheme):
    plain = ReferenceStep(replace(reference.scenario, numerics=replace(reference.scenario.numerics,
                                                                        time_scheme=scheme)))
    rng = np.random.default_rng(11)
    velocity, back = rng.standard_normal((2, 2, space.N)) * 1e-3
    expected = plain.momentum(velocity, back if scheme == "bdf2" else velocity)
    out = np.zeros(2 * space.N)
    weights = (0.0, 1.0, 0.0), (back, back)           # bdf2's v^{m-1}: the earlier velocity itself
    space.momentum_load(velocity, plain.mass_coefficient(), plain.scenario.fluid.density,
                        np.arange(2 * space.N).reshape(2, -1), out, back=weights if scheme == "bdf2" else None)
    assert np.abs(out.reshape(2, -1) - expected).max() <= 1e-12 * np.abs(expected).max()


def test_location_interpolation_and_spreading_are_scikit_fems_probes(implementation, reference, space):
    rng = np.random.default_rng(12)
    channel = reference.scenario.channel
    points = rng.uniform([1e-9, 1e-9], [channel.length - 1e-9, channel.height - 1e-9], size=(300, 2))
    probes = reference.velocity.probes(points.T)
    locator = PointLocator(space.cmesh, space.velocity_basis.element_dofs)
    values, forces = rng.standard_normal((2, space.N)), rng.standard_normal((300, 2))
    assert np.abs(locator.interpolate(values, points) - (probes @ values.T)).max() <= 1e-13 * np.abs(values).max()
    spread = locator.spread(forces, points, np.zeros((2, space.N)))
    assert np.abs(spread - (probes.T @ forces).T).max() <= 1e-13 * np.abs(forces).sum()


def _crossing(a, b, c, d) -> bool:
    def side(p, q, r):
        return np.sign((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))
    return side(a, b, c) * side(a, b, d) < 0 and side(c, d, a) * side(c, d, b) < 0


@pytest.mark.parametrize("seed", range(4))
def test_the_self_intersection_kernel_finds_the_first_crossing_pair(implementation, seed):
    rng = np.random.default_rng(seed)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 24))
    points = np.stack([np.cos(angles), np.sin(angles)], axis=1) * rng.uniform(0.8, 1.2, (24, 1))
    if seed % 2:
        points[[3, 15]] = points[[15, 3]]                     # two points swapped: the polygon crosses itself
    n = len(points)
    pairs = [(i, j) for i in range(n) for j in range(i + 2, n) if not (i == 0 and j == n - 1)
             and _crossing(points[i], points[(i + 1) % n], points[j], points[(j + 1) % n])]
    found = tuple(int(k) for k in kernels.first_self_intersection(np.ascontiguousarray(points)))
    assert found == (pairs[0] if pairs else (-1, -1))
    assert bool(pairs) == bool(seed % 2)


def test_the_fluid_steps_glue_is_its_numpy_expression(implementation):
    rng = np.random.default_rng(13)
    n, p = 40, 7
    momentum, continuity, inflow, jet = rng.standard_normal(n), rng.standard_normal(p), *rng.standard_normal((2, n))
    free = np.sort(rng.choice(n, 25, replace=False)).astype(np.int64)
    rhs = np.empty(25 + p)
    kernels.free_rhs(momentum, free, continuity, rhs)
    assert np.array_equal(rhs, np.concatenate([momentum[free], continuity]))
    vector, out = rng.standard_normal(25 + p), rhs.copy()
    kernels.subtract_scaled(out, 0.3, vector)
    assert np.array_equal(out, rhs - 0.3 * vector)
    solution, velocity = rng.standard_normal(25 + p), np.empty(n)
    kernels.boundary_velocity(0.5, inflow, 2.0, jet, free, solution, velocity)
    expected = 0.5 * inflow + 2.0 * jet
    expected[free] = solution[:25]
    assert np.array_equal(velocity, expected)
    back = np.empty(25 + p)
    kernels.free_solution(velocity, free, solution[25:], 4.0, back)
    assert np.allclose(back, np.concatenate([velocity[free], solution[25:] / 4.0]), rtol=1e-15, atol=0)


def test_the_split_solves_vector_kernels_are_their_numpy_expressions(implementation):
    import scipy.sparse as sp
    rng = np.random.default_rng(14)
    matrix = sp.random(30, 20, density=0.2, random_state=15, format="csr")
    rows, x, rhs = np.sort(rng.choice(50, 30, replace=False)).astype(np.int64), rng.standard_normal(20), \
        rng.standard_normal(50)
    out = np.empty(30)
    kernels.gather_residual(rhs, rows, matrix.data, matrix.indices, matrix.indptr, x, out)
    assert np.abs(out - (rhs[rows] - matrix @ x)).max() <= 1e-14 * np.abs(rhs).max() * 10
    transpose = matrix.T.tocsr()                              # H = ``matrix`` (30 x 20), given by H^T in CSR
    y, dinv = rng.standard_normal(30), rng.standard_normal(30)
    z, g = np.empty(30), np.empty(20)
    kernels.transposed_products(y, dinv, z, transpose.data, transpose.indices, transpose.indptr, g, 0.0)
    assert np.array_equal(z, dinv * y) and np.allclose(g, transpose @ y, rtol=1e-14, atol=1e-14)
    w, sums, minus = rng.standard_normal(20), np.empty(30), np.empty(30)
    kernels.minus_product(y, transpose.data, transpose.indices, transpose.indptr, w, sums, minus, 0.0)
    assert np.allclose(minus, y - matrix @ w, rtol=1e-14, atol=1e-14)
    solution = rng.standard_normal(50)
    target = solution.copy()
    target[rows] += out
    kernels.scatter_add(solution, rows, out, True)
    assert np.array_equal(solution, target)
