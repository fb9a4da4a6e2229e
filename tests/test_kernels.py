"""The step's kernels (``sim.fast.kernels``: the C ones where built, else numba's) against scikit-fem's own assembly and
evaluation (the oracles); numba's own are held to the C ones' results in tests/test_c_kernels.py."""

import numpy as np
import pytest
from skfem import LinearForm, asm
from skfem.helpers import grad

from sim.method.taylorhood import TaylorHood
from sim.method.transfer import PointLocator
from sim.model.mesh import channel_mesh
from sim.model.scenario import UM, Scenario


@pytest.fixture(scope="module", params=[10 / 3, 7.0], ids=["paper-grid", "graded-grid"])
def space(request):
    return TaylorHood(channel_mesh(Scenario().channel, request.param * UM))


BACKS = {"euler": None,                                     # u = w = v
         "bdf2-equal-steps": (0.0, 1.0, 0.0),               # b = the last earlier velocity itself
         "bdf2-parabola": (0.375, 0.75, -0.125)}            # b = the parabola through three, as lagrange_weights gives


@pytest.mark.parametrize("weights", BACKS.values(), ids=BACKS.keys())
def test_momentum_load_matches_scikit_fem_assembly(space, weights):
    """(m w - k (u . grad) u, phi): u = w = v (euler), or BDF2's one pass: u = 2 v - b, w = (4 v - b) / 3 with b the
    velocity one step back, formed in the kernel from v and two earlier velocities."""
    rng = np.random.default_rng(1)
    velocity, first, second = (rng.standard_normal((2, space.N)) for _ in range(3))
    if weights is None:
        convected = carried = velocity
        back = None
    else:
        before = weights[0] * velocity + weights[1] * first + weights[2] * second
        convected, carried = 2 * velocity - before, (4 * velocity - before) / 3
        back = (weights, (first, second))
    basis = space.velocity_basis
    fields = {"ux": basis.interpolate(convected[0]), "uy": basis.interpolate(convected[1]),
              "wx": basis.interpolate(carried[0]), "wy": basis.interpolate(carried[1])}
    mass, convection = 3.0, 2.0

    def component(c):
        @LinearForm
        def form(v, w):
            u, m = (w.ux, w.uy), (w.wx, w.wy)
            advected = w.ux * grad(u[c])[0] + w.uy * grad(u[c])[1]
            return (mass * m[c] - convection * advected) * v
        return asm(form, basis, **fields)

    expected = np.array([component(0), component(1)])
    out = np.zeros(2 * space.N)
    positions = np.arange(2 * space.N).reshape(2, space.N)
    space.momentum_load(velocity, mass, convection, positions, out, back=back)
    assert np.abs(out.reshape(2, -1) - expected).max() <= 1e-12 * np.abs(expected).max()


def test_momentum_load_skips_and_reorders_by_positions(space):
    velocity = np.random.default_rng(2).standard_normal((2, space.N))
    full = np.zeros(2 * space.N)
    identity = np.arange(2 * space.N).reshape(2, space.N)
    space.momentum_load(velocity, 1.0, 1.0, identity, full)
    keep = np.random.default_rng(3).random(2 * space.N) < 0.5
    positions = np.full(2 * space.N, -1)
    positions[keep] = np.arange(keep.sum())[::-1]
    reduced = np.zeros(keep.sum())
    space.momentum_load(velocity, 1.0, 1.0, positions.reshape(2, -1), reduced)
    assert np.allclose(reduced[::-1], full[keep], rtol=0, atol=1e-14 * np.abs(full).max())


def test_interpolation_matches_scikit_fem_probes(space):
    rng = np.random.default_rng(4)
    channel = Scenario().channel
    points = rng.uniform([1e-12, 1e-12], [channel.length - 1e-12, channel.height - 1e-12], size=(400, 2))
    values = rng.standard_normal((2, space.N))
    locator = PointLocator(space.cmesh, space.velocity_basis.element_dofs)
    probes = space.velocity_basis.probes(points.T)
    expected = np.stack([probes @ values[0], probes @ values[1]], axis=1)
    assert np.abs(locator.interpolate(values, points) - expected).max() <= 1e-13 * np.abs(values).max()


def test_points_outside_the_channel_are_reported_not_extrapolated(space):
    locator = PointLocator(space.cmesh, space.velocity_basis.element_dofs)
    outside = np.array([[-1e-6, 100e-6], [150e-6, 221e-6], [301e-6, 50e-6]])
    elements, _ = locator.locate(outside)
    assert (elements == -1).all()
    assert np.isnan(locator.interpolate(np.ones((1, space.N)), outside)).all()


@pytest.mark.parametrize("newton", [False, True])
def test_linearised_convection_kernel_matches_scikit_fem_forms(space, newton):
    velocity = np.random.default_rng(5).standard_normal((2, space.N))
    fast = space.convection_matrices(velocity, newton)
    reference = space.convection_matrices_reference(velocity, newton)
    scale = max(abs(block).max() for row in reference for block in row)
    for a in range(2):
        for b in range(2):
            assert abs(fast[a][b] - reference[a][b]).max() <= 1e-12 * scale


@pytest.mark.parametrize("weights", BACKS.values(), ids=BACKS.keys())
def test_element_integrals_are_the_same_bits_on_one_thread_or_all(space, weights):
    """The fluid step computes the next step's element integrals ahead on one helper thread, or here on all of
    numba's: each block of elements is computed alone, so the two give the same bits (numba's kernel, called
    directly: ``sim.fast.kernels`` runs the C one where it is built, on the calling thread whatever is asked)."""
    import numba

    from sim.fast import kernels_numba
    rng = np.random.default_rng(5)
    velocity, first, second = (rng.standard_normal((2, space.N)) for _ in range(3))
    back = None if weights is None else (weights, (first, second))
    arguments = (space.element_dofs, space.jacobian_rows, space.areas, space.q_phi, space.q_dphi, space.q_weights,
                 velocity, 3.0, 2.0)
    one, every, here = space.element_buffer(), space.element_buffer(), space.element_buffer()
    threads = numba.get_num_threads()
    kernels_numba.element_momentum(*arguments, one, back, threads=1)
    assert numba.get_num_threads() == threads                   # the caller's setting restored
    kernels_numba.element_momentum(*arguments, every, back)
    assert np.array_equal(one, every) and np.abs(every).max() > 0
    space.element_momentum(velocity, 3.0, 2.0, here, back, threads=1)     # whichever kernels sim.fast.kernels runs
    assert np.abs(here - every).max() <= 1e-13 * np.abs(every).max()
