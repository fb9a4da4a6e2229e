"""Our own substitutions for the split solve's halves (sim/fast/supernodal.py, sim/fast/_substitute.c): they solve to
single precision like PARDISO's, give the same bits for the same input on either thread, refuse a factor they cannot
take, and the split solve falls back to PARDISO's without them."""

import threading
from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from sim.fast import kernels, speed, supernodal
from sim.fast.linalg import Pardiso, SolverError, pardiso_available
from sim.model.scenario import UM, Scenario

pytestmark = pytest.mark.skipif(not supernodal.available(),
                                reason="vcyto was installed without its compiled substitution kernels or MKL")


def laplacian(m: int) -> sp.csr_matrix:
    """The 5-point Laplacian of an m x m grid plus a small shift: symmetric positive definite, and its nested-dissection
    factor has wide dense supernodes (the separators) as well as thin ones."""
    one = sp.diags([-np.ones(m - 1), 2.0 * np.ones(m), -np.ones(m - 1)], [-1, 0, 1])
    return (sp.kronsum(one, one) + 0.01 * sp.eye(m * m)).tocsr()


def solve(factor, rhs):
    return factor.phase(333, factor.phase(332, factor.phase(331, rhs)))


def test_a_solve_is_accurate_to_single_precision_with_every_kind_of_supernode():
    matrix = laplacian(60)
    arrays = supernodal.factor_arrays(matrix)
    widths = np.diff(arrays["starts"])
    below = np.diff(arrays["row_start"])
    # both of the backward kernel's paths (four columns at once, and the rest), both of the forward kernel's (64 rows
    # at once, and 16)
    assert widths.max() >= 8 and (widths % 4).any() and (below >= 64).any() and (below % 64).any()
    factor = supernodal.SupernodalLDL(arrays)
    rhs = np.random.default_rng(3).standard_normal(matrix.shape[0])
    exact = sp.linalg.spsolve(matrix.tocsc(), rhs)
    error = np.linalg.norm(solve(factor, rhs) - exact) / np.linalg.norm(exact)
    assert 1e-9 < error < 1e-4             # single precision: neither exact nor off


def test_the_partial_substitutions_are_the_factors_triangles():
    """331 is L^-1 P b and 333 is P^T L^-T z for the same unit lower triangular L: (L^-1 P b) . (L^-1 P c) read back
    through 333 of the other side, i.e. <F b, F c> = <b, G F c> with G = F^T."""
    matrix = laplacian(30)
    factor = supernodal.SupernodalLDL(supernodal.factor_arrays(matrix))
    b, c = np.random.default_rng(4).standard_normal((2, matrix.shape[0]))
    left = factor.phase(331, b) @ factor.phase(331, c)
    right = b @ factor.phase(333, factor.phase(331, c))
    assert abs(left - right) <= 1e-5 * abs(left)
    # and D: the diagonal substitution is the factor's pivots
    assert np.array_equal(factor.phase(332, np.ones(matrix.shape[0])), factor.pivots.astype(np.float64))


def test_same_input_same_bits_on_either_thread():
    matrix = laplacian(40)
    factor = supernodal.SupernodalLDL(supernodal.factor_arrays(matrix))
    rhs = np.random.default_rng(5).standard_normal(matrix.shape[0])
    here = solve(factor, rhs)
    there = []
    worker = threading.Thread(target=lambda: there.append(solve(factor, rhs)))
    worker.start()
    worker.join()
    assert np.array_equal(here, there[0]) and np.array_equal(here, solve(factor, rhs))


def test_a_factor_that_needs_another_pivot_is_refused(monkeypatch):
    """A zero on the diagonal (a saddle point's pressure block in an order that eliminates it first) needs a pivot off
    the diagonal, which SuperLU's diagonal-only factorisation does not take: a SolverError, not a wrong factor."""
    velocity = laplacian(10)
    coupling = sp.random(20, 100, density=0.1, random_state=np.random.default_rng(6)) + sp.eye(20, 100)
    saddle = sp.bmat([[velocity, coupling.T], [coupling, None]], format="csr")
    assert np.linalg.matrix_rank(saddle.toarray()) == 120              # regular: only the order is wrong
    monkeypatch.setattr(supernodal, "pardiso_ordering", lambda block: np.r_[100:120, 0:100])   # zero pivots first
    with pytest.raises(SolverError, match="pivot"):
        supernodal.factor_arrays(saddle)


def test_bad_vectors_are_refused():
    factor = supernodal.SupernodalLDL(supernodal.factor_arrays(laplacian(10)))
    vector = np.ones(100, dtype=np.float32)
    with pytest.raises(SolverError, match="float32 vectors of 100"):
        factor.substitute(331, np.ones(100), np.empty(100, dtype=np.float32))
    with pytest.raises(SolverError, match="cannot write into its source"):
        factor.substitute(333, vector, vector)
    with pytest.raises(SolverError, match="331, 332 or 333"):
        factor.substitute(33, vector, np.empty(100, dtype=np.float32))


@pytest.fixture(scope="module")
def fluid():
    from sim.method.fluid import NavierStokes
    return NavierStokes(Scenario().with_numerics(mesh_h=10 * UM, linear_solver="pardiso"))


@pytest.mark.skipif(not pardiso_available(), reason="the split solve runs on MKL PARDISO")
@pytest.mark.parametrize("way", ["own", "switched off", "not built", "refused"])
def test_the_split_solve_uses_them_or_pardisos(fluid, monkeypatch, way):
    """Single precision, halves without matching: our substitutions, solving like PARDISO's; with
    ``SpeedSettings.own_substitutions`` off, without the compiled kernels, or with a factor they refuse: PARDISO's."""
    import sim.fast.splitsolve as splitsolve
    if way == "switched off":
        monkeypatch.setattr(speed, "_settings", replace(speed.current(), own_substitutions=False))
    elif way == "not built":
        monkeypatch.setattr(supernodal, "_kernels", lambda: None)
    elif way == "refused":
        def refuse(block):
            raise SolverError("refused")
        monkeypatch.setattr(supernodal, "factor_arrays", refuse)
    matrix = fluid.constant_matrix().tocsr()
    split = splitsolve.SplitPardiso(matrix, fluid.free_x, single=True)
    kinds = {type(half.factor) for half in split.halves}
    assert kinds == ({supernodal.SupernodalLDL} if way == "own" else {Pardiso})
    rhs = np.random.default_rng(7).standard_normal(matrix.shape[0])
    exact = Pardiso(matrix, symmetric=True).solve(rhs)
    solution = split.solve(rhs)
    assert np.linalg.norm(solution - exact) <= 1e-5 * np.linalg.norm(exact)
    assert np.array_equal(split.solve(rhs), solution)
    split.release()


def test_both_kinds_of_row_index_give_the_same_bits():
    """A half below 65,535 unknowns keeps 16-bit row indices (half the bytes); larger ones 32-bit: the same kernel."""
    arrays = supernodal.factor_arrays(laplacian(40))
    assert arrays["below_rows"].dtype == np.uint16
    wide = supernodal.SupernodalLDL({**arrays, "below_rows": arrays["below_rows"].astype(np.int32)})
    narrow = supernodal.SupernodalLDL(arrays)
    rhs = np.random.default_rng(8).standard_normal(1600)
    assert np.array_equal(solve(wide, rhs), solve(narrow, rhs))
    with pytest.raises(SolverError, match="uint16 or int32"):
        supernodal.SupernodalLDL({**arrays, "below_rows": arrays["below_rows"].astype(np.int64)})


@pytest.mark.skipif(not pardiso_available(), reason="the split solve runs on MKL PARDISO")
@pytest.mark.parametrize("own", [True, False])
def test_pardisos_half_factors_are_kept_only_where_they_are_used(fluid, own):
    """Our own factor replaces PARDISO's unmatched halves, so a store keeps ours and not theirs (a time step's cache
    ~30 MB instead of ~80); with PARDISO's substitutions it keeps PARDISO's halves, as before."""
    import sim.fast.splitsolve as splitsolve
    from sim.fast import store

    class Memory:
        def __init__(self):
            self.fetched, self.directories = [], []

        def fetch(self, kind, key, build):
            self.fetched.append(kind)
            return build()

        def keep_directory(self, kind, key, write):
            self.directories.append(kind)

    memory = Memory()
    previous = store.install(memory)
    try:
        split = splitsolve.SplitPardiso(fluid.constant_matrix(), fluid.free_x, single=True, own=own)
        split.release()
    finally:
        store.install(previous)
    assert ("supernodal-factor" in memory.fetched) == own
    assert memory.directories.count(Pardiso.KIND) == (0 if own else 2)


def test_a_library_built_from_another_source_is_not_used(monkeypatch, caplog):
    """After an update without a rebuild the library may read another layout: a warning that says how to rebuild,
    and PARDISO's substitutions meanwhile (never a crash or wrong results)."""
    import ctypes

    real = ctypes.CDLL

    class Stale:
        def __init__(self, path):
            self._library = real(path)
            self.vcyto_substitute_layout = lambda: supernodal.LAYOUT - 1

        def __getattr__(self, name):
            return getattr(self._library, name)
    monkeypatch.setattr(ctypes, "CDLL", Stale)
    supernodal._kernels.cache_clear()
    try:
        with caplog.at_level("WARNING", logger="sim.fast.supernodal"):
            assert not supernodal.available()
        assert "pip install -e ." in caplog.text and f"this code reads {supernodal.LAYOUT}" in caplog.text
    finally:
        monkeypatch.undo()
        supernodal._kernels.cache_clear()
    assert supernodal.available()


def test_stored_flows_name_the_substitutions_that_computed_them(monkeypatch):
    """Ours and PARDISO's give other last bits, so a flow stored by one must not be restored by the other: the key
    part of stored flows (``solver_code_digest``) names them."""
    from sim.method.fluid import solver_code_digest
    ours = solver_code_digest()
    monkeypatch.setattr(speed, "_settings", replace(speed.current(), own_substitutions=False))
    theirs = solver_code_digest()
    assert ours != theirs and ours.split(":")[1] == f"own-{supernodal.LAYOUT}" and theirs.split(":")[1] == "pardiso"
    assert ours.split(":")[2] == theirs.split(":")[2] == kernels.implementation()     # which step kernels: C or numba
