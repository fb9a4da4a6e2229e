"""A bit-for-bit reproducible back-solve on two cores: the channel cut in two, each half solved on its own thread.

PARDISO's parallel substitution (``iparm[24] = 2``) is twice as fast as its sequential one but its
reductions make the last bits of a solution vary from run to run. Here the parallelism is ours and static:

The unknowns are split by their x coordinate into a left part I1, a right part I2 and the separator S (the
left unknowns coupled to right ones, a line of nodes across the channel), so that

    A = [[A1, 0, C1], [0, A2, C2], [C1^T, C2^T, A_S]]

Each A_i is factored by its own sequential PARDISO (A_i^{-1} = G_i D_i^{-1} F_i: the forward (phase 331),
diagonal (332) and backward (333) substitutions, with G_i = F_i^T for a symmetric matrix). With
H_i = D_i^{-1} F_i C_i (sparse: a few hundred thousand entries) and the dense separator matrix
K = A_S - sum_i (F_i C_i)^T H_i (kept as its inverse: a dense product per solve), a solve is

    thread i:  y_i = F_i b_i,  z_i = D_i^{-1} y_i,  g_i = H_i^T y_i
    both:      x_S = K^{-1} (b_S - g_1 - g_2)
    thread i:  x_i = G_i (z_i - H_i x_S)

Every operation runs in a fixed order on one thread with one MKL thread, so equal inputs give equal bits,
whatever the machine's load; the two halves stream their factors through memory at the same time. With
``single=True`` the factors, H and the halves' vectors are single precision (the inner solve of
``sim.fast.linalg.MixedPrecision``); the separator's solve stays double. Single-precision halves factored without
matching substitute with our own compiled kernels where they are installed (``sim.fast.supernodal``: a supernodal
factor in PARDISO's ordering, kept in ``sim.fast.store``; ~1.6x faster than PARDISO's sequential substitutions), else
with PARDISO's; ``VCYTO_OWN_SUBSTITUTIONS=0`` keeps PARDISO's.

The halves are factored at once when the solver is built; the coupling (H_i and K: one forward and one
diagonal substitution per separator unknown) on the first solve, through ``sim.fast.store`` so an application
can keep it between runs (the key names the matrix, the cut, MKL's version and a probe of both factors).
PARDISO's partial substitutions with several right-hand sides give wrong columns after the first (measured
with MKL 2026.2), hence one column at a time.

Pivots: the halves are factored without PARDISO's weighted matching (and scaling), which gives a factor ~15 %
smaller at the paper's mesh (4.20 M entries against 4.97 M) and so a back-solve streaming 15 % fewer bytes.
Without matching PARDISO perturbs a pivot it finds too small, and the factor is then that of a slightly
different matrix (the partial substitutions do no refinement: a single-precision split solve was 3 % off).
At every mesh we tried, that is one pressure unknown per half, at a corner of the channel (its row holds two
free velocities: the corner element's other velocity unknowns lie on the walls). ``_Half.search`` finds such
an unknown from the residual of a solve (``_perturbed_unknown``), moves it into the separator (which may hold
any unknowns: the cut stays a separator) and factors the rest again; a half still perturbed after
``MAX_MOVES`` moves is factored as it is, with matching, as before. The moved unknowns are kept through
``sim.fast.store`` (a warm start factors each half once).
"""

from __future__ import annotations

import ctypes
import math
import queue
import threading
from typing import NamedTuple

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from . import kernels, speed, supernodal
from .linalg import Pardiso, SolverError, _aligned_empty, _mkl_runtime, mkl_version, narrow
from .store import code_digest, digest, reuse

MIN_UNKNOWNS = 20_000        # below this a plain sequential PARDISO solve is as fast
MAX_MOVES = 4                # unknowns with perturbed pivots moved out of a half before it falls back to matching


def separator_split(matrix: sp.csr_matrix, x: np.ndarray, band=(0.35, 0.65)):
    """(I1, I2, S) index arrays: a cut x <= t with the smallest separator near the middle (best balanced
    among cuts within 10 % of the smallest). S is the left unknowns coupled to a right one; none of I1 is."""
    pattern = sp.csr_matrix((np.ones(matrix.nnz, dtype=np.int32), matrix.indices, matrix.indptr), shape=matrix.shape)
    order = np.sort(x)
    low, high = order[int(band[0] * len(x))], order[int(band[1] * len(x))]
    candidates = []
    for cut in np.unique(x[(x >= low) & (x <= high)]):
        left = x <= cut
        separator = left & (pattern @ (~left).astype(np.int32) > 0)
        candidates.append((int(separator.sum()), abs(2 * int(left.sum()) - len(x)), cut, separator, left))
    if not candidates:
        raise SolverError("no cut across the domain found for the split solve")
    smallest = min(c[0] for c in candidates)
    size, _, cut, separator, left = min((c for c in candidates if c[0] <= 1.1 * smallest), key=lambda c: c[1])
    return np.flatnonzero(left & ~separator), np.flatnonzero(~left), np.flatnonzero(separator)


def own_substitutions_wanted() -> bool:
    """Whether a single-precision split solve substitutes with our own kernels (``sim.fast.supernodal``: compiled at
    install) instead of PARDISO's; ``SpeedSettings.own_substitutions`` False (``sim.fast.speed``) keeps PARDISO's (the
    benchmark compares both)."""
    return speed.current().own_substitutions and supernodal.available()


def substitutions() -> str:
    """Which substitutions a default split solve runs, for the keys of results computed through it: ``own-<layout>``
    (``sim.fast.supernodal``) or ``pardiso``."""
    return f"own-{supernodal.LAYOUT}" if own_substitutions_wanted() else "pardiso"


def _one_mkl_thread():
    library = _mkl_runtime()
    library.MKL_Set_Num_Threads_Local.restype = ctypes.c_int
    library.MKL_Set_Num_Threads_Local(ctypes.c_int(1))


def _perturbed_unknown(block: sp.csr_matrix, factor: Pardiso) -> int:
    """The unknown of ``block`` whose pivot PARDISO perturbed in ``factor`` (unmatched, released or not).

    A factor exact for A + d e_k e_k^T solves to x with residual b - A x = d x_k e_k: zero but at k. A single-
    precision factor's residual also shows the unknowns k was pivoted with, as large (measured: two velocities
    beside the pressure unknown that double precision names), so k is read from a double-precision
    factorisation of the block; only if that one is unperturbed, from ``factor`` itself (factored again)."""
    double = Pardiso(block, symmetric=True, reproducible=True, matching=False)
    try:
        if double.perturbed_pivots == 0:
            double.release()
            double = Pardiso(block, symmetric=True, reproducible=True, single=factor.single,
                             matching=False)
        probe = np.random.default_rng(18).uniform(1.0, 2.0, block.shape[0])
        solution = double.phase(333, double.phase(332, double.phase(331, probe)))
        return int(np.argmax(np.abs(probe - block @ solution)))
    finally:
        double.release()


def moved_parts(cut, moved: np.ndarray):
    """The cut's (left, right, separator) with the unknowns ``moved`` taken out of the halves and put into the
    separator: each sorted, as ``np.setdiff1d`` and ``np.union1d`` give them (the same arrays), without sorting
    the halves again (tens of thousands of unknowns against a few moved: ~15 ms of a level's set-up)."""
    left, right, separator = cut
    moved = np.unique(np.asarray(moved, dtype=np.int64))
    extra = moved[~np.isin(moved, separator)]
    return (left[~np.isin(left, moved)], right[~np.isin(right, moved)],
            np.sort(np.concatenate([separator, extra])) if len(extra) else separator)


class _Half:
    """One side of the cut: its sequential factorisation and H = D^{-1} F C."""

    def __init__(self, factor: Pardiso, moved=(), matched: bool = False):
        _one_mkl_thread()
        self.factor = factor
        single = factor.single
        self.moved = np.array(moved, dtype=np.int64)   # unknowns moved to the separator (``search``)
        self.matched = matched                         # factored with PARDISO's weighted matching
        self._agreement = 1e-6 if single else 1e-13
        # the substitutions' vectors and H in the factor's precision: no conversions between the phases, and
        # half the bytes for H's products in single precision
        self.dtype = np.float32 if single else np.float64
        n = factor.shape[0]
        # fixed aligned buffers handed to PARDISO directly (its results can depend on the alignment)
        self.source, self.y, self.z, self.x = (_aligned_empty(n, dtype=self.dtype) for _ in range(4))
        self.zero = self.dtype(0)
        self.h_t = self.sums = None
        self.w = self.g = None         # the separator's solution and H^T y, in the factor's precision
        self.rows = None               # (this half's unknowns, A's rows of them in CSR): set by SplitPardiso
        self.dinv = self._diagonal(n)

    @classmethod
    def factored(cls, matrix: sp.csr_matrix, unknowns: np.ndarray, single: bool, matched: bool, moved=(),
                 block: sp.csr_matrix | None = None, kept: bool = True):
        """The half of ``unknowns`` (rows and columns of ``matrix``; ``block``: those, if already taken out)
        factored as it is; ``kept``: restored from ``sim.fast.store`` or kept there (``Pardiso``)."""
        _one_mkl_thread()
        block = matrix[unknowns][:, unknowns].tocsr() if block is None else block
        return cls(Pardiso(block, symmetric=True, reproducible=True, single=single, matching=matched, kept=kept),
                   moved, matched)

    @classmethod
    def own(cls, matrix: sp.csr_matrix, unknowns: np.ndarray, moved=()):
        """The half of ``unknowns`` with our own single-precision factor and substitutions (``sim.fast.supernodal``),
        restored from ``sim.fast.store`` or built and kept there; ``SolverError`` when the factor cannot take it."""
        block = matrix[unknowns][:, unknowns].tocsr()
        built = []

        def build():
            built.append(True)
            return supernodal.factor_arrays(block)
        factor = supernodal.SupernodalLDL(reuse("supernodal-factor", supernodal.stored_key(block), build))
        factor.restored = not built
        return cls(factor, moved, matched=False)

    @classmethod
    def search(cls, matrix: sp.csr_matrix, unknowns: np.ndarray, single: bool, stored: bool = True):
        """The half of ``unknowns`` factored without weighted matching, its pivots unperturbed: an unknown whose
        pivot PARDISO perturbs is moved to the separator and the rest factored again (at most ``MAX_MOVES``
        times; then the half as it is, with matching). Module docstring, "Pivots". ``stored``: keep the unmatched
        factor through ``sim.fast.store`` (not when our own substitutions replace it: ~47 MB a time step saved)."""
        moved = []
        while True:
            keep = np.setdiff1d(unknowns, moved) if moved else unknowns
            block = matrix[keep][:, keep].tocsr()
            half = cls.factored(matrix, keep, single, matched=False, moved=moved, block=block, kept=False)
            if half.factor.perturbed_pivots == 0:
                if stored:
                    half.factor.keep()       # the one a later run restores (a perturbed one is not kept)
                return half
            half.factor.release()
            if len(moved) == MAX_MOVES:
                return cls.factored(matrix, unknowns, single, matched=True)
            moved.append(int(keep[_perturbed_unknown(block, half.factor)]))

    def _diagonal(self, n: int) -> np.ndarray | None:
        """PARDISO's diagonal substitution (phase 332) as a vector when it is one (1x1 pivots: checked on two
        random vectors to 1e-13, 1e-6 in single precision), else None: 332 costs a quarter of a half's
        solve, a product almost nothing."""
        dinv = self.factor.phase(332, np.ones(n))
        for probe in np.random.default_rng(18).uniform(1.0, 2.0, size=(2, n)):
            exact = self.factor.phase(332, probe)
            if not np.all(np.abs(dinv * probe - exact) <= self._agreement * np.abs(exact)):
                return None
        return dinv.astype(self.dtype)

    def _solve_diagonal(self, vector: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        if self.dinv is None:
            return self.factor.phase(332, vector, out)
        return np.multiply(self.dinv, vector, out=out)

    def _column(self, coupling: sp.csc_matrix, j: int) -> np.ndarray:
        dense = np.zeros(coupling.shape[0])
        start, end = coupling.indptr[j], coupling.indptr[j + 1]
        dense[coupling.indices[start:end]] = coupling.data[start:end]
        return dense

    def probe(self, coupling: sp.csc_matrix) -> np.ndarray:
        """F C e_0: names this factorisation in the key of the stored coupling (a different factor misses)."""
        return self.factor.phase(331, self._column(coupling, 0))

    def coupling(self, coupling: sp.csc_matrix) -> tuple[sp.csr_matrix, np.ndarray]:
        """H = D^{-1} F C (sparse) and (F C)^T H (dense, this half's share of the separator's Schur complement)."""
        _one_mkl_thread()
        columns_e, columns_h = [], []
        for j in range(coupling.shape[1]):
            e = self.factor.phase(331, self._column(coupling, j))
            columns_e.append(sp.csc_matrix(e[:, None]))
            columns_h.append(sp.csc_matrix(self._solve_diagonal(e)[:, None]))
        h = sp.hstack(columns_h, format="csr")
        return h, (sp.hstack(columns_e, format="csc").T @ h).toarray()

    def use(self, h: sp.csr_matrix):
        """Keep H for the solves: as H^T in CSR only (``kernels.minus_product`` reads H w from it), with 16-bit
        indices when H has at most 65,536 rows (fewer bytes streamed a solve; the same bits)."""
        h = h.astype(self.dtype)
        h.sort_indices()
        self.h_t = narrow_indices(h.T.tocsr())
        self.w, self.g = np.zeros(h.shape[1], dtype=self.dtype), np.zeros(h.shape[1], dtype=self.dtype)
        self.sums = np.zeros(h.shape[0], dtype=self.dtype)

    def forward(self, rhs: np.ndarray, x: np.ndarray | None) -> np.ndarray:
        """y = F (rhs - A x) on this half's rows (rhs alone without x), z = D^{-1} y; returns H^T y (a buffer
        the next call overwrites)."""
        unknowns, rows = self.rows
        if x is None:
            kernels.gather_residual(rhs, unknowns, _NONE, _NO_INDICES, _NO_INDICES, rhs, self.source)
        else:
            kernels.gather_residual(rhs, unknowns, rows.data, rows.indices, rows.indptr, x, self.source)
        self.factor.substitute(331, self.source, self.y)
        if self.dinv is None:
            self.factor.substitute(332, self.y, self.z)
        h_t = self.h_t
        kernels.transposed_products(self.y, _NONE if self.dinv is None else self.dinv, self.z,
                                    h_t.data, h_t.indices, h_t.indptr, self.g, self.zero)
        return self.g

    def backward(self, separator_solution: np.ndarray, solution: np.ndarray, accumulate: bool):
        """This half's unknowns of the solve, written into (``accumulate``: added to) ``solution``; the largest
        |change| and |solution| there (``kernels.scatter_add``)."""
        narrow(self.w, separator_solution)
        h_t = self.h_t
        kernels.minus_product(self.z, h_t.data, h_t.indices, h_t.indptr, self.w, self.sums, self.source, self.zero)
        self.factor.substitute(333, self.source, self.x)
        return kernels.scatter_add(solution, self.rows[0], self.x, accumulate)


_NONE = np.zeros(0)
_NO_INDICES = np.zeros(1, dtype=np.int32)


class Compressed(NamedTuple):
    """A CSR matrix's arrays as the vector kernels read them (``sim.fast.kernels``)."""
    data: np.ndarray
    indices: np.ndarray
    indptr: np.ndarray


def narrow_indices(matrix: sp.csr_matrix) -> Compressed:
    """``matrix``'s CSR arrays, with 16-bit column indices when it has at most 65,536 columns: a sixth fewer bytes
    for a double-precision entry, a third for a single-precision one, which the kernels stream every solve."""
    indices = matrix.indices.astype(np.uint16) if matrix.shape[1] <= 65536 else matrix.indices
    return Compressed(matrix.data, indices, matrix.indptr)


class _Worker(threading.Thread):
    """A daemon thread with one MKL thread that runs the tasks it is given, one at a time."""

    def __init__(self):
        super().__init__(daemon=True)
        self.tasks, self.results = queue.SimpleQueue(), queue.SimpleQueue()
        self.start()

    def run(self):
        _one_mkl_thread()
        while (task := self.tasks.get()) is not None:
            try:
                outcome = (True, task())
            except Exception as error:  # handed back to the caller's thread
                outcome = (False, error)
            # hold nothing while waiting: a task's closure (or its result) kept here would keep its solver, and so
            # this thread and the solver's factors, alive after the caller dropped it
            task = None
            self.results.put(outcome)
            outcome = None

    def submit(self, task):
        self.tasks.put(task)

    def result(self):
        """The running task's result (its exception raised here). An interrupt while waiting (Ctrl-C) waits on
        until the task is done, then goes on: a result left in the queue would be taken as the next task's, and
        the task may still be writing into its caller's arrays."""
        interrupted = None
        while True:
            try:
                ok, value = self.results.get()
                break
            except KeyboardInterrupt as error:
                interrupted = error
        if interrupted is not None:
            raise interrupted
        if not ok:
            raise value
        return value


class SplitPardiso:
    """A symmetric matrix solved by two sequential PARDISO halves on two threads (module docstring)."""

    def __init__(self, matrix: sp.spmatrix, x: np.ndarray, single: bool = False, matching: bool = False,
                 own: bool | None = None):
        """``matching=True`` factors the halves with PARDISO's weighted matching, as they are (no unknown moved: kept
        for the benchmark's comparison). ``own``: whether single-precision halves use our
        own substitutions (``sim.fast.supernodal``) where they can; None: ``own_substitutions_wanted()``."""
        matrix = sp.csr_matrix(matrix)
        self.single = single
        self.matching = matching
        self.own = own_substitutions_wanted() if own is None else bool(own) and supernodal.available()
        self.shape = matrix.shape
        self.symmetric = True
        self._worker = _Worker()
        self._digest = digest(matrix.data, matrix.indices, matrix.indptr)
        x = np.asarray(x, dtype=float)
        stored = reuse("split-cut", {"layout": 1, "matrix": self._digest, "x": digest(x),
                                    "code": code_digest(separator_split)},
                       lambda: dict(zip(("left", "right", "separator"), separator_split(matrix, x))))
        cut = tuple(np.asarray(stored[name], dtype=np.int64) for name in ("left", "right", "separator"))
        self.halves, self.parts = self._factored_halves(matrix, cut)
        left, right, separator = self.parts
        self._rows = [matrix[p] for p in self.parts]      # for residuals computed where they are used
        couplings = [matrix[p][:, separator].tocsc() for p in (left, right)]
        for half, unknowns, rows in zip(self.halves, self.parts, self._rows):
            half.rows = (unknowns, narrow_indices(rows))
        # the calling thread, which also runs the Python between the phases, takes the half with the smaller
        # factor (the halves' factors differ by ~4 % at the paper's mesh: a step 0.7-0.9 % faster, three
        # in-process A/B runs); which thread runs a half does not change its bits
        smaller = min((0, 1), key=lambda i: self.halves[i].factor.factor_nonzeros)
        self._by_thread = (self.halves[smaller], self.halves[1 - smaller])
        self.factor_nonzeros = sum(h.factor.factor_nonzeros for h in self.halves)
        self.separator_size = len(separator)
        self._schur = None
        self._pending = (matrix, couplings)      # the coupling is computed on the first solve (``_couple``)

    def _factored_halves(self, matrix: sp.csr_matrix, cut):
        """Both halves factored (``_Half.search``, each on its own thread) and the parts with their moved unknowns
        in the separator. Which unknowns move is kept through ``sim.fast.store``: a later run factors each half once."""
        left, right, separator = cut
        single = self.single
        if self.matching:
            return self._both(lambda: _Half.factored(matrix, left, single, True),
                              lambda: _Half.factored(matrix, right, single, True)), cut
        key = {"layout": 1, "matrix": self._digest, "cut": digest(*cut),
               "mkl": mkl_version(), "single": single, "max_moves": MAX_MOVES}
        searched = []

        kept = not (single and self.own)   # our own substitutions replace the unmatched halves (``_own_or``)

        def search():
            searched[:] = self._both(lambda: _Half.search(matrix, left, single, kept),
                                     lambda: _Half.search(matrix, right, single, kept))
            return {"moved": np.concatenate([h.moved for h in searched]),
                    "matched": np.array([h.matched for h in searched])}

        def factored(stored):
            moved, matched = np.asarray(stored["moved"], dtype=np.int64), stored["matched"]
            parts = moved_parts(cut, moved)
            sides = [(parts[i], bool(matched[i]), np.unique(moved[np.isin(moved, side)]))
                     for i, side in enumerate((left, right))]
            # PARDISO's halves just factored by the search, if any: ours replace the unmatched ones
            pardiso = tuple(searched) or (None, None)
            halves = self._both(lambda: self._own_or(pardiso[0], matrix, *sides[0]),
                                lambda: self._own_or(pardiso[1], matrix, *sides[1]))
            return halves, parts

        halves, parts = factored(reuse("split-pivots", key, search))
        # a stored choice that does not hold for this factorisation (PARDISO's is deterministic for the key's
        # matrix and MKL version, so this is a safety net): search again, kept under a key of its own; should
        # that one not hold either, search here and keep nothing
        for again in (lambda: reuse("split-pivots", {**key, "searched_again": True}, search), search):
            if not any(half.factor.perturbed_pivots and not half.matched for half in halves):
                break
            for half in halves:
                half.factor.release()
            searched.clear()
            halves, parts = factored(again())
        return halves, parts

    def _own_or(self, half: _Half | None, matrix: sp.csr_matrix, unknowns: np.ndarray, matched: bool, moved):
        """The half of ``unknowns`` with our own substitutions when they are wanted and can take it (single precision,
        factored without matching), else ``half`` (PARDISO's), factored here when it is None."""
        if self.single and not matched and self.own:
            try:
                own = _Half.own(matrix, unknowns, moved)
            except SolverError:
                pass
            except BaseException:           # anything else (an interrupt, memory): PARDISO's half is freed first
                if half is not None:
                    half.factor.release()
                raise
            else:
                if half is not None:
                    half.factor.release()
                return own
        return half if half is not None else _Half.factored(matrix, unknowns, self.single, matched, moved)

    def _couple(self):
        """H of each half and the separator's Schur complement: from the store (sim.fast.store) or computed."""
        matrix, couplings = self._pending
        key = {"layout": 3, "matrix": self._digest, "parts": digest(*self.parts),
               "mkl": mkl_version(), "single": self.single,
               "factors": digest(*(h.probe(c) for h, c in zip(self.halves, couplings)))}
        stored = reuse("split-solve", key, lambda: self._coupling(matrix, couplings))
        for i, half in enumerate(self.halves):
            half.use(sp.csr_matrix((stored[f"h{i}_data"], stored[f"h{i}_indices"], stored[f"h{i}_indptr"]),
                                   shape=(len(self.parts[i]), self.separator_size)))
        self._schur = stored["schur_inverse"]
        self.factor_nonzeros += sum(len(h.h_t.data) for h in self.halves)
        self._pending = None

    def _coupling(self, matrix, couplings) -> dict:
        """The arrays a later run can reuse: each half's H and the LU factors of the separator's Schur complement."""
        first, second = self._both(lambda: self.halves[0].coupling(couplings[0]),
                                   lambda: self.halves[1].coupling(couplings[1]))
        separator = self.parts[2]
        schur = matrix[separator][:, separator].toarray() - first[1] - second[1]
        # its inverse, applied as a dense product: 0.03 ms against an LU solve's 0.17 ms (329 unknowns)
        arrays = {"schur_inverse": sla.inv(schur, check_finite=False)}
        for i, (h, _) in enumerate((first, second)):
            arrays.update({f"h{i}_data": h.data, f"h{i}_indices": h.indices, f"h{i}_indptr": h.indptr})
        return arrays

    def _both(self, on_main, on_worker):
        """Run two tasks at once, one here and one on the worker thread; both results."""
        self._worker.submit(on_worker)
        try:
            first = self._in_main(on_main)
        finally:
            second = self._worker.result()
        return first, second

    @staticmethod
    def _in_main(task):
        """Run ``task`` on this thread with one MKL thread, then give MKL back its global setting."""
        library = _mkl_runtime()
        library.MKL_Set_Num_Threads_Local.restype = ctypes.c_int
        previous = library.MKL_Set_Num_Threads_Local(ctypes.c_int(1))
        try:
            return task()
        finally:
            library.MKL_Set_Num_Threads_Local(ctypes.c_int(previous))

    def solve(self, rhs: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        if rhs.ndim != 1:
            return np.column_stack([self.solve(column) for column in rhs.T])
        solution = np.empty(self.shape[0])
        self._solve(rhs, None, solution, accumulate=False)
        return solution

    def refine(self, rhs: np.ndarray, solution: np.ndarray) -> tuple[float, float]:
        """One correction of ``sim.fast.linalg.MixedPrecision`` in place: solution += S (rhs - A solution), each half
        on its own thread from its residual to its share of the update. Returns the largest |correction| and
        the largest |solution| after it (NaN when a value is not finite)."""
        return self._solve(rhs, solution, solution, accumulate=True)

    def _solve(self, rhs: np.ndarray, x: np.ndarray | None, out: np.ndarray, accumulate: bool):
        """The solve of rhs (minus A x) written into (``accumulate``: added to) ``out``: the module docstring's
        steps, every vector operation in ``sim.fast.kernels`` on the thread of its half."""
        if self._schur is None:
            self._couple()
        separator = self.parts[2]
        first, second = self._by_thread
        g_first, g_second = self._both(lambda: first.forward(rhs, x), lambda: second.forward(rhs, x))
        if first is not self.halves[0]:             # the separator's sums in the halves' order, whoever ran them
            g_first, g_second = g_second, g_first
        separator_rhs = (rhs[separator] if x is None else rhs[separator] - self._rows[2] @ x) - g_first - g_second
        separator_solution = self._schur @ separator_rhs
        extremes = self._both(lambda: first.backward(separator_solution, out, accumulate),
                              lambda: second.backward(separator_solution, out, accumulate))
        extremes += (kernels.scatter_add(out, separator, separator_solution, accumulate),)
        sizes, scales = zip(*extremes)
        if any(math.isnan(value) for value in sizes + scales):
            return math.nan, math.nan
        return max(sizes), max(scales)

    def release(self):
        if self._worker is not None:
            self._worker.submit(None)
            self._worker = None
        for half in getattr(self, "halves", ()):
            half.factor.release()

    def __del__(self):
        try:
            self.release()
        except Exception:  # interpreter shutdown: nothing sensible to report
            pass
