"""The FE-IB step's compiled C kernels (sim/fast/_kernels.c, called through sim.fast.kernels) against numba's
(sim/fast/kernels_numba.py, the reference, itself tested against scikit-fem in tests/test_kernels.py): the same bits
where numba's kernel is exact, round-off for the momentum kernel (numba's is compiled with fastmath); arrays the C
kernels do not take go to numba's; and a warm FE-IB run does not import numba at all."""

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.fast import kernels
from sim.method.taylorhood import TaylorHood
from sim.method.transfer import PointLocator
from sim.model.mesh import channel_mesh
from sim.model.scenario import UM, Scenario

pytestmark = pytest.mark.skipif(not kernels.compiled(), reason="vcyto was installed without its compiled step kernels")
numba_kernels = pytest.importorskip("sim.fast.kernels_numba")
C = kernels._LIBRARY


@pytest.fixture(autouse=True)
def c_only(request, monkeypatch):
    """The comparisons compute with the C kernels, never numba's in their place: ``sim.fast.kernels`` may not fall back
    (tests that are about the fallback are marked ``fallback``)."""
    if "fallback" not in request.keywords:
        def refused():
            raise AssertionError("sim.fast.kernels fell back to numba's kernel")
        monkeypatch.setattr(kernels, "_numba", refused)


@pytest.fixture(scope="module")
def space():
    return TaylorHood(channel_mesh(Scenario().channel, 7 * UM))


def fields(space, count, seed=3):
    rng = np.random.default_rng(seed)
    return [np.ascontiguousarray(rng.standard_normal((2, space.N))) for _ in range(count)]


@pytest.mark.parametrize("back", [None, (0.0, 1.0, 0.0), (0.375, 0.75, -0.125)], ids=["euler", "bdf2", "parabola"])
def test_the_momentum_kernel_agrees_with_numbas_to_round_off(space, back):
    velocity, first, second = fields(space, 3)
    back = None if back is None else (back, (first, second))
    arguments = (space.element_dofs, space.jacobian_rows, space.areas, space.q_phi, space.q_dphi, space.q_weights,
                 velocity, 3.0, 2.0)
    ours, theirs = space.element_buffer(), space.element_buffer()
    kernels.element_momentum(*arguments, ours, back, 1)
    numba_kernels.element_momentum(*arguments, theirs, back, 1)
    scale = np.abs(theirs).max()
    assert np.abs(ours - theirs).max() <= 1e-13 * scale
    assert not np.array_equal(ours, np.zeros_like(ours))
    again = space.element_buffer()
    kernels.element_momentum(*arguments, again, back)          # whatever the threads asked for: the same bits
    assert np.array_equal(again, ours)


def test_the_scatter_and_the_linearised_convection_give_numbas_bits(space):
    (velocity,) = fields(space, 1)
    local = np.random.default_rng(4).standard_normal((space.element_dofs.shape[1], 2, 6))
    positions = np.arange(2 * space.N, dtype=np.int64).reshape(2, space.N)
    positions[0, ::7] = -1                                     # skipped entries
    ours, theirs = np.zeros(2 * space.N), np.zeros(2 * space.N)
    kernels.scatter_momentum(space.element_dofs, local, positions, ours)
    numba_kernels.scatter_momentum(space.element_dofs, local, positions, theirs)
    assert np.array_equal(ours, theirs) and ours.any()
    pattern = space.pattern
    for newton in (False, True):
        blocks = [[np.full(pattern.nnz, np.nan) for _ in range(4)] for _ in range(2)]
        for module, data in zip((kernels, numba_kernels), blocks):
            module.linearised_convection(space.element_dofs, space.inverse_jacobians, space.determinants, space.q_phi,
                                         space.q_dphi, space.q_weights, velocity[0], velocity[1], newton,
                                         space._pattern_positions, *data)
        for ours, theirs in zip(*blocks):
            assert np.array_equal(ours, theirs)


def test_location_interpolation_and_spreading_give_numbas_bits(space):
    locator = PointLocator(space.cmesh, space.element_dofs)
    rng = np.random.default_rng(5)
    (x0, x1), (y0, y1) = (locator.grid_x[0], locator.grid_x[-1]), (locator.grid_y[0], locator.grid_y[-1])
    points = np.column_stack([rng.uniform(x0 - 5 * UM, x1 + 5 * UM, 400), rng.uniform(y0 - 5 * UM, y1 + 5 * UM, 400)])
    points[:3] = [[x0, y0], [x1, y1], [np.nan, y0]]               # the corners, and a NaN (outside)
    located = []
    for module in (kernels, numba_kernels):
        elements, reference = np.empty(len(points), dtype=np.int64), np.empty((len(points), 2))
        module.locate(points, locator.grid_x, locator.grid_y, locator.square_elements, locator.origins,
                      locator.inverse_jacobians, elements, reference)
        located.append((elements, reference))
    (elements, reference), (their_elements, their_reference) = located
    assert np.array_equal(elements, their_elements) and np.array_equal(reference, their_reference, equal_nan=True)
    assert (elements < 0).any() and (elements >= 0).any()
    (values,) = fields(space, 1)
    forces = rng.standard_normal((len(points), 2))
    out = [np.empty((len(points), 2)) for _ in range(2)]
    spread = [np.zeros((2, space.N)) for _ in range(2)]
    for module, interpolated, load in zip((kernels, numba_kernels), out, spread):
        module.interpolate_p2(elements, reference, space.element_dofs, values, interpolated)
        module.spread_p2(elements, reference, space.element_dofs, forces, load)
    assert np.array_equal(out[0], out[1], equal_nan=True) and np.isnan(out[0][elements < 0]).all()
    assert np.array_equal(spread[0], spread[1]) and spread[0].any()


def test_the_self_intersection_test_gives_numbas_answers():
    angles = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    circle = np.column_stack([np.cos(angles), np.sin(angles)])
    figure_eight = np.column_stack([np.sin(2 * angles), np.sin(angles)])
    bow = circle.copy()
    bow[[5, 25]] = bow[[25, 5]]
    for polygon in (circle, figure_eight, bow):
        assert kernels.first_self_intersection(polygon) == tuple(numba_kernels.first_self_intersection(polygon))
    assert kernels.first_self_intersection(circle) == (-1, -1)
    assert kernels.first_self_intersection(figure_eight) != (-1, -1)


def random_csr(rng, rows, columns, density, dtype, empty_rows=True):
    matrix = sp.random(rows, columns, density=density, random_state=rng, format="csr", dtype=np.float64)
    if empty_rows:
        matrix = sp.csr_matrix(matrix.multiply((rng.random((rows, 1)) > 0.1)))
    matrix.sort_indices()
    return matrix.astype(dtype)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rows=st.integers(0, 41), columns=st.integers(1, 30),
       single=st.booleans(), narrow=st.booleans(), diagonal=st.booleans())
def test_the_split_solves_vector_kernels_give_numbas_bits(seed, rows, columns, single, narrow, diagonal):
    """Every precision and index type the C library compiles (float32/64, 16/32-bit indices), row counts that are
    and are not multiples of the four rows run side by side, empty rows, no rows, and no diagonal (the split
    solve's empty float64 stand-in, whatever the vectors' precision)."""
    rng = np.random.default_rng(seed)
    dtype = np.float32 if single else np.float64
    index = np.uint16 if narrow else np.int32
    zero = dtype(0)
    h_t = random_csr(rng, columns, rows, 0.4, dtype)          # H^T: a row per separator unknown
    h_indices = h_t.indices.astype(index)
    a = random_csr(rng, rows, rows + 7, 0.3, np.float64)
    a_indices = a.indices.astype(index)
    rhs, x = rng.standard_normal(rows + 7), rng.standard_normal(rows + 7)
    unknowns = rng.permutation(rows + 7)[:rows].astype(np.int64)
    y, dinv, w = (rng.standard_normal(n).astype(dtype) for n in (rows, rows, columns))
    if not diagonal:
        dinv = np.zeros(0)
    solution = rng.standard_normal(rows + 7)
    results = []
    for module in (kernels, numba_kernels):
        gathered, plain = np.empty(rows, dtype=dtype), np.empty(rows, dtype=dtype)
        module.gather_residual(rhs, unknowns, a.data, a_indices, a.indptr, x, gathered)
        module.gather_residual(rhs, unknowns, np.zeros(0), np.zeros(1, np.int32), np.zeros(1, np.int32), rhs, plain)
        z, g = np.full(rows, 7, dtype=dtype), np.empty(columns, dtype=dtype)      # z kept without a diagonal
        module.transposed_products(y, dinv, z, h_t.data, h_indices, h_t.indptr, g, zero)
        out, sums = np.empty(rows, dtype=dtype), np.empty(rows, dtype=dtype)
        module.minus_product(z, h_t.data, h_indices, h_t.indptr, w, sums, out, zero)
        updated = solution.copy()
        extremes = module.scatter_add(updated, unknowns, out, True)
        results.append((gathered, plain, z, g, out, updated, np.array(extremes)))
    for ours, theirs in zip(*results):
        assert ours.dtype == theirs.dtype and np.array_equal(ours, theirs, equal_nan=True)


def test_scatter_add_reports_a_value_that_is_not_finite():
    solution = np.zeros(4)
    for module in (kernels, numba_kernels):
        assert np.isnan(module.scatter_add(solution.copy(), np.arange(2), np.array([1.0, np.inf]), False)).all()
        assert module.scatter_add(solution.copy(), np.arange(2), np.array([1.0, -3.0]), True) == (3.0, 3.0)


def test_the_fluid_steps_glue_gives_numbas_bits():
    rng = np.random.default_rng(6)
    free = rng.permutation(50)[:30].astype(np.int64)
    momentum, continuity, velocity, pressure = (rng.standard_normal(n) for n in (50, 12, 50, 12))
    inflow, jet, solution = (rng.standard_normal(n) for n in (50, 50, 42))
    results = []
    for module in (kernels, numba_kernels):
        rhs, empty_rhs, scaled, boundary, still, free_out = (np.full(n, np.nan) for n in (42, 42, 42, 50, 50, 42))
        module.free_rhs(momentum, free, continuity, rhs)
        module.free_rhs(np.zeros(0), free, np.zeros(0), empty_rhs)
        scaled[:] = rhs
        module.subtract_scaled(scaled, 0.3, solution)
        module.boundary_velocity(0.7, inflow, -1.5, jet, free, solution, boundary)
        module.boundary_velocity(0.0, inflow, 0.0, jet, free, solution, still)
        module.free_solution(velocity, free, pressure, 1e-3, free_out)
        results.append((rhs, empty_rhs, scaled, boundary, still, free_out))
    for ours, theirs in zip(*results):
        assert np.array_equal(ours, theirs) and np.isfinite(ours).all()


@pytest.mark.fallback
def test_arrays_the_c_kernels_do_not_take_go_to_numbas():
    """Another dtype (64-bit indices) or a strided array: numba's kernel computes it, with its result."""
    rng = np.random.default_rng(7)
    a = random_csr(rng, 9, 12, 0.5, np.float64)
    rhs, x = rng.standard_normal(12), rng.standard_normal(12)
    rows = np.arange(9, dtype=np.int64)
    with pytest.raises(TypeError, match="indices|'H'|'i'"):
        C.gather_residual(rhs, rows, a.data, a.indices.astype(np.int64), a.indptr, x, np.empty(9))
    ours, theirs = np.empty(9), np.empty(9)
    kernels.gather_residual(rhs, rows, a.data, a.indices.astype(np.int64), a.indptr, x, ours)
    numba_kernels.gather_residual(rhs, rows, a.data, a.indices, a.indptr, x, theirs)
    assert np.array_equal(ours, theirs)
    strided = np.zeros(24)[::2]
    kernels.subtract_scaled(strided, 2.0, np.ones(12))
    assert np.array_equal(strided, np.full(12, -2.0))
    raw = np.zeros(8 * 12 + 1, np.uint8)
    misaligned = raw[1:].view(np.float64)
    assert not misaligned.flags.aligned
    with pytest.raises(TypeError, match="aligned"):
        C.subtract_scaled(misaligned, 2.0, np.ones(12))
    kernels.subtract_scaled(misaligned, 2.0, np.ones(12))
    assert np.array_equal(misaligned, np.full(12, -2.0))
    # a sum started from -0.0: numba's keeps its sign on an empty row, so numba's kernel computes it
    h_t = sp.csr_matrix((np.ones(1), [0], [0, 0, 1]), shape=(2, 3))
    for zero in (-0.0, 0.0):
        g = np.empty(2)
        kernels.transposed_products(np.ones(3), np.zeros(0), np.empty(3), h_t.data, h_t.indices.astype(np.int32),
                                    h_t.indptr.astype(np.int32), g, zero)
        assert np.array_equal(g, [0.0, 1.0]) and math.copysign(1.0, g[0]) == math.copysign(1.0, zero)


def test_the_momentum_kernel_never_hands_its_work_to_numbas():
    """Numba's momentum kernel has other last bits (fastmath), which the C kernels' key would hide: inputs of other
    types are converted, an output C cannot write raises."""
    space = TaylorHood(channel_mesh(Scenario().channel, 20 * UM))
    (velocity,) = fields(space, 1)
    out = space.element_buffer()
    kernels.element_momentum(space.element_dofs.astype(np.int32), space.jacobian_rows, space.areas, space.q_phi,
                             space.q_dphi, space.q_weights, np.asfortranarray(velocity), 1.0, 1.0, out)
    expected = space.element_buffer()
    kernels.element_momentum(space.element_dofs, space.jacobian_rows, space.areas, space.q_phi, space.q_dphi,
                             space.q_weights, velocity, 1.0, 1.0, expected)
    assert np.array_equal(out, expected)
    with pytest.raises(TypeError, match="writable|C-contiguous"):
        kernels.element_momentum(space.element_dofs, space.jacobian_rows, space.areas, space.q_phi, space.q_dphi,
                                 space.q_weights, velocity, 1.0, 1.0, np.empty((2, 6, len(space.areas))).T)


def test_inconsistent_sizes_and_indices_are_refused_with_the_kernels_name(space):
    with pytest.raises(ValueError, match="subtract_scaled: vector shorter than out"):
        kernels.subtract_scaled(np.zeros(5), 1.0, np.ones(3))
    with pytest.raises(ValueError, match="scatter_add: .*a row outside solution"):
        kernels.scatter_add(np.zeros(4), np.array([0, 4]), np.ones(2), True)
    with pytest.raises(ValueError, match="boundary_velocity: .*each free velocity in out"):
        kernels.boundary_velocity(1.0, np.ones(4), 0.0, np.ones(4), np.array([1, -1]), np.ones(2), np.empty(4))
    with pytest.raises(ZeroDivisionError, match="free_solution"):
        kernels.free_solution(np.ones(4), np.array([0, 1]), np.ones(2), 0.0, np.empty(4))
    dofs = space.element_dofs.copy()
    dofs[3, 5] = space.N                                   # one past the velocity fields
    (velocity,) = fields(space, 1)
    with pytest.raises(ValueError, match="element_momentum: an element's dof outside"):
        kernels.element_momentum(dofs, space.jacobian_rows, space.areas, space.q_phi, space.q_dphi, space.q_weights,
                                 velocity, 1.0, 1.0, space.element_buffer())
    with pytest.raises(ValueError, match="element_momentum: element_dofs \\(6, ne\\)"):    # phi transposed
        kernels.element_momentum(space.element_dofs, space.jacobian_rows, space.areas, space.q_phi.T.copy(),
                                 space.q_dphi, space.q_weights, velocity, 1.0, 1.0, space.element_buffer())
    with pytest.raises(ValueError, match="transposed_products: CSR arrays of inconsistent sizes"):
        kernels.transposed_products(np.ones(3), np.ones(3), np.empty(3), np.ones(2), np.zeros(2, np.int32),
                                    np.array([0, 1, 2, 9], np.int32), np.empty(3), 0.0)
    with pytest.raises(ValueError, match="element_momentum: element_dofs \\(6, ne\\)"):
        kernels.element_momentum(np.zeros((5, 4), np.int64), np.zeros((4, 4)), np.zeros(4), np.zeros((3, 6)),
                                 np.zeros((3, 6, 2)), np.zeros(3), np.zeros((2, 10)), 1.0, 1.0, np.empty((4, 2, 6)))


@pytest.mark.fallback
def test_the_implementation_names_the_source_and_the_switch_uses_numbas():
    assert kernels.implementation() == "c-" + "_".join(C.source().split()) and len(C.source().split()[0]) == 64
    program = ("from vcyto import speedsettings; speedsettings.install(); "
               "from sim.fast import kernels; print(kernels.compiled(), kernels.implementation()[:6])")
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "VCYTO_C_KERNELS": "0"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False", "numba-"]


WARM_RUN = textwrap.dedent("""
    import sys
    from vcyto.cli import main
    status = main(["paper", "2", "--mesh-h", "5um", "--quiet"])
    print("numba" in sys.modules, status)
""")


def test_a_warm_feib_run_does_not_import_numba():
    """The point of the C kernels: a process that steps the plant with its set-up in the cache never loads numba
    (~0.35-0.5 s a process). The first run fills the session's cache (a cold set-up may use numba: the supernodal
    factor's layout); the second must not."""
    runs = [subprocess.run([sys.executable, "-c", WARM_RUN], capture_output=True, text=True, timeout=600)
            for _ in range(2)]
    for done in runs:
        assert done.returncode == 0, done.stderr
    assert runs[1].stdout.split()[-2:] == ["False", "0"], runs[1].stdout[-500:]
