"""The split solve (sim/fast/splitsolve.py): exact to round-off, a true separator, and bit-for-bit reproducible
across processes, down to the recordings of a stream with the default numerics."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.fast.linalg import Pardiso, pardiso_available
from sim.fast.splitsolve import moved_parts
from sim.method.fluid import NavierStokes
from sim.model.scenario import UM, Scenario

pytestmark = pytest.mark.skipif(not pardiso_available(), reason="the split solve runs on MKL PARDISO")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fluid():
    return NavierStokes(Scenario().with_numerics(mesh_h=10 * UM, linear_solver="pardiso"))


def test_split_solve_equals_the_sequential_solve_to_round_off(fluid):
    from sim.fast.splitsolve import SplitPardiso
    matrix = fluid.constant_matrix()
    split = SplitPardiso(matrix, fluid.free_x)
    left, right, separator = split.parts
    assert len(left) + len(right) + len(separator) == matrix.shape[0]
    assert abs(matrix[left][:, right]).sum() == 0                 # a true separator
    assert 0.3 < len(left) / (len(left) + len(right)) < 0.7 and len(separator) < 0.05 * matrix.shape[0]
    rhs = np.random.default_rng(1).standard_normal(matrix.shape[0])
    solution = split.solve(rhs)
    assert np.linalg.norm(matrix @ solution - rhs) <= 1e-13 * np.linalg.norm(rhs)
    reference = Pardiso(matrix, symmetric=True).solve(rhs)
    assert np.linalg.norm(solution - reference) <= 1e-12 * np.linalg.norm(reference)
    assert np.array_equal(split.solve(rhs), solution)             # same input, same bits


def test_halves_without_matching_move_their_perturbed_unknowns_to_the_separator(fluid):
    """Without weighted matching (a smaller factor) PARDISO perturbs the pivot of a pressure unknown at a channel
    corner (two free velocities in its row); the split moves such an unknown into the separator and factors the
    rest again: no perturbed pivot is left, the factor is smaller than the matched one, the solve is exact."""
    from sim.fast.splitsolve import SplitPardiso
    matrix = fluid.constant_matrix().tocsr()
    split = SplitPardiso(matrix, fluid.free_x)
    left, right, separator = split.parts
    moved = np.concatenate([half.moved for half in split.halves])
    assert len(moved) >= 1 and np.isin(moved, separator).all()
    assert abs(matrix[left][:, right]).sum() == 0
    for half, unknowns in zip(split.halves, (left, right)):
        assert half.factor.perturbed_pivots == 0 and not half.matched
        with_moved = np.union1d(unknowns, half.moved)
        block = matrix[with_moved][:, with_moved]
        kept_in = Pardiso(block, symmetric=True, matching=False)      # the moved unknowns left in: perturbed
        matched = Pardiso(block, symmetric=True)
        assert kept_in.perturbed_pivots >= 1
        assert half.factor.factor_nonzeros < matched.factor_nonzeros
        kept_in.release()
        matched.release()
    rhs = np.random.default_rng(7).standard_normal(matrix.shape[0])
    assert np.linalg.norm(matrix @ split.solve(rhs) - rhs) <= 1e-13 * np.linalg.norm(rhs)


def test_a_half_that_stays_perturbed_falls_back_to_matching(fluid, monkeypatch):
    import sim.fast.splitsolve as splitsolve
    monkeypatch.setattr(splitsolve, "MAX_MOVES", 0)
    matrix = fluid.constant_matrix()
    split = splitsolve.SplitPardiso(matrix, fluid.free_x)
    assert all(half.matched and len(half.moved) == 0 for half in split.halves)
    assert all(half.factor.perturbed_pivots == 0 for half in split.halves)
    rhs = np.random.default_rng(8).standard_normal(matrix.shape[0])
    assert np.linalg.norm(matrix @ split.solve(rhs) - rhs) <= 1e-13 * np.linalg.norm(rhs)


def test_the_moved_unknowns_are_kept_by_the_store_and_reused(fluid, monkeypatch):
    """A second split of the same matrix with the store installed factors each half once, with the stored
    unknowns moved (no search), and solves to the same bits."""
    import sim.fast.splitsolve as splitsolve
    from sim.fast import store

    class Memory:
        def __init__(self):
            self.entries, self.built = {}, []

        def fetch(self, kind, key, build):
            name = (kind, repr(sorted(key.items())))
            if name not in self.entries:
                self.built.append(kind)
                self.entries[name] = build()
            return self.entries[name]
    memory = Memory()
    previous = store.install(memory)
    try:
        matrix = fluid.constant_matrix()
        rhs = np.random.default_rng(9).standard_normal(matrix.shape[0])
        first = splitsolve.SplitPardiso(matrix, fluid.free_x, single=True)
        expected = first.solve(rhs)
        assert memory.built.count("split-pivots") == 1

        def no_search(*args):
            raise AssertionError("searched again")
        monkeypatch.setattr(splitsolve._Half, "search", classmethod(no_search))
        second = splitsolve.SplitPardiso(matrix, fluid.free_x, single=True)
        assert memory.built.count("split-pivots") == 1
        assert [h.moved.tolist() for h in second.halves] == [h.moved.tolist() for h in first.halves]
        assert np.array_equal(second.solve(rhs), expected)
        monkeypatch.undo()
        searches, original = [], splitsolve._Half.search.__func__

        def counted(cls, *args):
            searches.append(1)
            return original(cls, *args)
        monkeypatch.setattr(splitsolve._Half, "search", classmethod(counted))
        for name, entry in list(memory.entries.items()):    # a stored choice that leaves a pivot perturbed
            if name[0] == "split-pivots":
                memory.entries[name] = {"moved": np.zeros(0, dtype=np.int64), "matched": entry["matched"]}
        for run in range(2):
            third = splitsolve.SplitPardiso(matrix, fluid.free_x, single=True)
            assert all(h.factor.perturbed_pivots == 0 for h in third.halves)   # found again, not used as stored
            assert np.array_equal(third.solve(rhs), expected)
            assert len(searches) == 2                  # two halves searched on the first run; the next reuses it
    finally:
        store.install(previous)


def test_a_split_solver_dropped_before_its_first_solve_is_freed(fluid):
    """The worker thread holds no task or result while it waits: a solver that is built and dropped (a steady
    start never solves with the constant factor) is collected, and its thread ends with it (found by a reviewer:
    a task closing over the solver kept it, its thread and its factors alive)."""
    import gc
    import weakref

    from sim.fast.splitsolve import SplitPardiso
    split = SplitPardiso(fluid.constant_matrix(), fluid.free_x)
    split._both(lambda: None, lambda held=split: held.shape)    # the worker's last task holds the solver
    worker, alive = split._worker, weakref.ref(split)
    del split
    gc.collect()
    assert alive() is None
    worker.join(5)
    assert not worker.is_alive()


def test_refinement_in_place_equals_the_correction_added(fluid):
    """``refine`` (each half's residual rows, solve and update on its own thread, ``sim.fast.kernels``) gives the
    bits of the whole residual computed by scipy, solved, and added to the solution; it reports the largest
    |correction| and |solution|, and NaN for a blow-up."""
    from sim.fast.splitsolve import SplitPardiso
    matrix = fluid.constant_matrix()
    rng = np.random.default_rng(3)
    rhs, guess = rng.standard_normal((2, matrix.shape[0]))
    for single in (False, True):
        split = SplitPardiso(matrix, fluid.free_x, single=single)
        correction = split.solve(rhs - matrix @ guess)
        solution = guess.copy()
        size, scale = split.refine(rhs, solution)
        assert np.array_equal(solution, guess + correction)
        assert size == np.abs(correction).max() and scale == np.abs(solution).max()
        solution[0] = np.inf                          # a blow-up reaches the caller's finiteness check as NaN
        assert all(np.isnan(split.refine(rhs, solution)))


def test_an_interrupt_while_waiting_for_the_other_half_leaves_the_solver_in_step(fluid):
    """Ctrl-C (a real SIGINT) while the main thread waits for the worker's half: the wait goes on until the
    half is done, then the interrupt is raised; the next solve is not handed the interrupted one's result."""
    import signal
    import threading

    from sim.fast.splitsolve import SplitPardiso
    split = SplitPardiso(fluid.constant_matrix(), fluid.free_x)
    rhs = np.random.default_rng(5).standard_normal(split.shape[0])
    expected = split.solve(rhs)
    release = threading.Event()

    def slow():
        release.wait(10)
        return "stale"

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        threading.Timer(0.2, lambda: signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)).start()
        threading.Timer(1.0, release.set).start()
        with pytest.raises(KeyboardInterrupt):
            split._both(lambda: None, slow)           # the main half is done at once: it waits for the worker
    finally:
        signal.signal(signal.SIGINT, previous)
    assert release.is_set()                           # it waited for the worker's task before raising
    assert np.array_equal(split.solve(rhs), expected)


def test_split_solve_vector_kernels_give_scipys_bits():
    """The fused kernels sum in scipy's order: a residual, H^T y and z - H w (from H^T) bit for bit equal to scipy's
    (rows of uneven lengths, some empty, counts not a multiple of the four rows the kernels run side by side), with
    32- or 16-bit indices."""
    import scipy.sparse as sp

    from sim.fast import kernels, splitsolve
    rng = np.random.default_rng(4)
    a = sp.random(301, 400, density=0.05, format="csr", random_state=5)
    rows = rng.permutation(500)[:301]
    rhs, x = rng.standard_normal(500), rng.standard_normal(400)
    out, out32 = np.empty(301), np.empty(301, np.float32)
    kernels.gather_residual(rhs, rows, a.data, a.indices, a.indptr, x, out)
    assert np.array_equal(out, rhs[rows] - a @ x)
    kernels.gather_residual(1e30 * rhs, rows, a.data, a.indices, a.indptr, x, out32)   # rounded, inf past float32
    assert np.array_equal(out32, (1e30 * rhs[rows] - a @ x).astype(np.float32))
    h = sp.random(403, 31, density=0.02, format="csr", random_state=6, dtype=np.float32)
    y, z = rng.standard_normal((2, 403)).astype(np.float32)
    dinv = rng.uniform(1, 2, 403).astype(np.float32)
    z_out, g = np.empty(403, np.float32), np.empty(31, np.float32)
    h_t = h.T.tocsr()
    kernels.transposed_products(y, dinv, z_out, h_t.data, h_t.indices, h_t.indptr, g, np.float32(0))
    assert np.array_equal(g, h_t @ y) and np.array_equal(z_out, dinv * y)
    w = rng.standard_normal(31).astype(np.float32)
    minus = np.empty(403, np.float32)
    assert np.diff(h.indptr).min() == 0 and len(set(np.diff(h.indptr))) > 3       # empty and uneven rows
    kernels.minus_product(z, h_t.data, h_t.indices, h_t.indptr, w, np.empty(403, np.float32), minus, np.float32(0))
    assert np.array_equal(minus, z - h @ w)                 # from H^T, summed as H's rows
    narrow = splitsolve.narrow_indices(h_t)                  # 16-bit indices: the same bits
    assert narrow.indices.dtype == np.uint16
    kernels.transposed_products(y, dinv, z_out, narrow.data, narrow.indices, narrow.indptr, g, np.float32(0))
    kernels.minus_product(z, narrow.data, narrow.indices, narrow.indptr, w, np.empty(403, np.float32), minus,
                          np.float32(0))
    assert np.array_equal(g, h_t @ y) and np.array_equal(minus, z - h @ w)
    widest = sp.csr_matrix((np.ones(2), [3, 65_535], [0, 2]), shape=(1, 65_536))  # the last index 16 bits hold
    assert np.array_equal(splitsolve.narrow_indices(widest).indices, [3, 65_535])
    wide = sp.csr_matrix((np.ones(2), [3, 65_536], [0, 2]), shape=(1, 65_537))
    assert splitsolve.narrow_indices(wide).indices.dtype == wide.indices.dtype      # too many columns for 16 bits


SCRIPT = """
import hashlib, numpy as np
from sim.method.fluid import NavierStokes
from sim.model.scenario import UM, Scenario
fluid = NavierStokes(Scenario().with_numerics(mesh_h=5 * UM))
state = fluid.steady(0.0)
for _ in range(5):
    state = fluid.step(state, actuation=1.0)
factor = fluid._constant.factor
print(type(factor).__name__, type(factor.inner).__name__, hashlib.sha256(state.velocity.tobytes()).hexdigest())
"""


def test_default_steps_are_bit_identical_in_two_processes():
    outputs = [subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, cwd=ROOT,
                              check=True).stdout.split() for _ in range(2)]
    # 5 um: ~24,000 unknowns; the default is the split solve in single precision, refined in double
    assert outputs[0][:2] == ["MixedPrecision", "SplitPardiso"]
    assert outputs[0] == outputs[1]


def _scrub(message):
    """A decoded Foxglove message with its wall-clock timestamps cleared (log times start at the run's wall-clock
    start; the simulated time is in every message)."""
    for field, value in message.ListFields():
        if field.message_type is None:
            continue
        if field.message_type.full_name == "google.protobuf.Timestamp":
            message.ClearField(field.name)
        elif field.is_repeated:
            for item in value:
                _scrub(item)
        else:
            _scrub(value)
    return message.SerializeToString()


def mcap_content(path):
    """Every message of a recording, wall-clock fields aside: (topic, log time from the first, content)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory
    decode = DecoderFactory()
    content, origin = [], None
    with open(path, "rb") as handle:
        for schema, channel, message in make_reader(handle).iter_messages(log_time_order=False):
            origin = message.log_time if origin is None else origin
            if channel.message_encoding == "json":
                data = {k: v for k, v in json.loads(message.data).items() if k not in ("wall_time", "diagnostics")}
            else:
                data = _scrub(decode.decoder_for(channel.message_encoding, schema)(message.data))
            content.append((channel.topic, message.log_time - origin, data))
    return content


def test_two_feib_streams_give_identical_recordings(tmp_path):
    """The paper's mesh (the split solve), a melanoma for 0.5 ms: every message equal, wall clock aside; the first
    run fills an empty set-up cache, the second takes everything from it (a warm start is a cold one, bit for bit)."""
    environment = {**os.environ, "VCYTO_CACHE": "on", "VCYTO_CACHE_DIR": str(tmp_path / "cache")}
    recordings = []
    for run in ("cold", "warm"):
        output = tmp_path / run
        result = subprocess.run([sys.executable, "-m", "vcyto.cli", "stream", "--cells", "melanoma", "--dt", "25us",
                                 "--max-time", "0.5", "--allow-partial", "--no-viewer", "--quiet", "--output",
                                 str(output)],
                                capture_output=True, text=True, cwd=ROOT, env=environment)
        assert result.returncode == 0, result.stderr
        recordings.append(next(output.glob("*.mcap")))
    first, second = (mcap_content(path) for path in recordings)
    assert sum(len(m[-1]["step"]) for m in first if m[0] == "/loop/steps") == 20
    assert first == second


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 2), min_size=1, max_size=300), st.lists(st.integers(0, 299), max_size=6),
       st.booleans())
def test_moved_parts_are_numpys_set_operations(sides, picks, listed):
    """``moved_parts`` (a level's split without sorting its halves again) gives the arrays ``np.setdiff1d`` and
    ``np.union1d`` give: the halves without the moved unknowns, the separator with them, all sorted; unknowns moved
    twice or already in the separator included."""
    sides = np.array(sides)
    cut = tuple(np.flatnonzero(sides == side) for side in range(3))
    moved = np.array([pick % len(sides) for pick in picks], dtype=np.int64)
    parts = moved_parts(cut, list(moved) if listed else moved)
    expected = (np.setdiff1d(cut[0], moved), np.setdiff1d(cut[1], moved), np.union1d(cut[2], moved))
    for got, want in zip(parts, expected):
        assert got.dtype == want.dtype and np.array_equal(got, want)
