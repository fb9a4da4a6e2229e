"""Our own substitutions for the split solve's halves: a supernodal single-precision L D L^T and compiled kernels.

PARDISO's sequential substitutions (its phases 331 and 333) of a half of the paper's fluid run at ~0.77 ns an entry
and pass, a tenth of what the last-level cache delivers (a half's single-precision factor is ~10 MB): they are bound
by their code, not by the memory (docs/numerics.md, "Our own substitutions for the halves"). This module keeps the
same factorisation in a layout of its own and substitutes with the C kernels of ``sim/fast/_substitute.c``, compiled
when vcyto is installed (an optional extension: without a compiler, ``available()`` is False and the split solve keeps
PARDISO's substitutions):

- the ordering is PARDISO's (METIS nested dissection, from its analysis phase with ``iparm[4] = 2``), so the factor
  has PARDISO's fill;
- the numerical factorisation is SuperLU's (``scipy.sparse.linalg.splu``) of the permuted half in double precision,
  with the natural column order and diagonal pivots only (``SymmetricMode``, threshold 0): the symmetric L D L^T as
  long as no pivot is zero; a half that would need another pivot is refused (``SolverError``) and keeps PARDISO;
- consecutive columns are grouped into supernodes (dense blocks that may hold zeros: at most ``SLACK`` of the true
  entries more, or any number while the group has at most ``SMALL`` columns, and at most ``WIDEST`` columns); the rows
  below a block's diagonal part are padded to a multiple of 16 and stored column by column, so the kernels' inner
  loops are 16 contiguous values, one AVX-512 vector; the diagonal blocks are kept twice, column by column for the
  forward kernel and row by row for the backward one, so both update a vector per unknown; the values are rounded to
  single precision once.

The kernels take every sum in a fixed order (written out lane by lane in the C source) on the calling thread, and
ctypes releases the GIL while they run: equal inputs give equal bits, and the split solve's two halves run at once.
"""

from __future__ import annotations

import ctypes
import importlib
import logging
from functools import lru_cache

import numpy as np
import scipy
import scipy.sparse as sp

from .kernels import jit_on_first_call
from .linalg import SolverError, _aligned_empty, _mkl_runtime

LANES = 16        # rows a kernel handles in one vector (the C source's LANES)
SLACK = 0.2       # zeros a supernode may hold beyond its true entries, as a fraction of them
SMALL = 16        # a group of at most this many columns may hold as many zeros as true entries
WIDEST = 64       # columns in a supernode at most
LAYOUT = 3        # the stored arrays' layout (a key part of the stored factor)
CHECK = 1e-4      # a factor whose solve of a probe leaves a larger relative residual is refused (~1e-6 measured)

INDEX_TYPES = {"u16": np.uint16, "i32": np.int32}    # the kernels' row indices: 16-bit below 65,535 unknowns
log = logging.getLogger(__name__)
_ARRAYS = ("starts", "diagonal_start", "below_start", "row_start", "diagonal_values", "below_values", "below_rows")
_BACKWARD = ("starts", "diagonal_start", "below_start", "row_start", "diagonal_rows", "below_values", "below_rows")


@lru_cache(maxsize=1)
def _kernels():
    """The compiled kernels (``sim.fast._substitute``) with their argument types, or None when the extension was not
    built (no C compiler at install) or MKL, whose ordering the factor uses, is missing."""
    if _mkl_runtime() is None:
        return None
    try:
        module = importlib.import_module("sim.fast._substitute")
        library = ctypes.CDLL(module.__file__)
        library.vcyto_substitute_layout.restype = ctypes.c_int64
        built_for = library.vcyto_substitute_layout()
    except (ImportError, OSError, AttributeError):
        return None
    if built_for != LAYOUT:         # built from an older source: the split solve keeps PARDISO's substitutions
        log.warning("vcyto's compiled substitution kernels were built from another version of sim/fast/_substitute.c "
                    "(layout %d, this code reads %d): run 'pip install -e .' again to rebuild them; using PARDISO's "
                    "substitutions meanwhile", built_for, LAYOUT)
        return None
    pointer, size = ctypes.c_void_p, ctypes.c_int64
    for index in INDEX_TYPES:
        getattr(library, f"vcyto_forward_{index}").argtypes = [size, size] + [pointer] * 11
        getattr(library, f"vcyto_backward_{index}").argtypes = [size, size] + [pointer] * 12
        getattr(library, f"vcyto_forward_{index}").restype = getattr(library, f"vcyto_backward_{index}").restype = None
    return library


def available() -> bool:
    """Whether the split solve can use these substitutions (the compiled kernels and MKL's ordering are there)."""
    return _kernels() is not None


def pardiso_ordering(block: sp.csr_matrix) -> np.ndarray:
    """PARDISO's fill-reducing permutation of a symmetric matrix (METIS, without weighted matching, as the split's
    halves are factored): ``order`` with ``block[order][:, order]`` the matrix PARDISO factors."""
    library = _mkl_runtime()
    if library is None:
        raise SolverError("MKL PARDISO is not available for the ordering of our own substitutions")
    stored = sp.triu(block, format="csr")
    stored.sum_duplicates()
    stored.sort_indices()
    n = stored.shape[0]
    data = np.ascontiguousarray(stored.data, dtype=np.float64)
    indptr = np.ascontiguousarray(stored.indptr, dtype=np.int32)
    indices = np.ascontiguousarray(stored.indices, dtype=np.int32)
    handle, iparm = np.zeros(64, dtype=np.int64), np.zeros(64, dtype=np.int32)
    iparm[[0, 1, 4, 9, 34]] = (1, 2, 2, 8, 1)     # own iparm, METIS, return the permutation, 1e-8, zero-based
    permutation = np.zeros(n, dtype=np.int32)
    scratch = np.zeros(n)
    error = ctypes.c_int32(0)
    one = ctypes.c_int32(1)
    integers = ctypes.POINTER(ctypes.c_int32)

    def call(phase: int) -> int:
        library.pardiso(handle.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ctypes.byref(one), ctypes.byref(one),
                        ctypes.byref(ctypes.c_int32(-2)), ctypes.byref(ctypes.c_int32(phase)),
                        ctypes.byref(ctypes.c_int32(n)), ctypes.c_void_p(data.ctypes.data),
                        indptr.ctypes.data_as(integers), indices.ctypes.data_as(integers),
                        permutation.ctypes.data_as(integers), ctypes.byref(one), iparm.ctypes.data_as(integers),
                        ctypes.byref(ctypes.c_int32(0)), ctypes.c_void_p(scratch.ctypes.data),
                        ctypes.c_void_p(scratch.ctypes.data), ctypes.byref(error))
        return error.value

    status = call(11)
    call(-1)
    if status != 0:
        raise SolverError(f"PARDISO's analysis failed with error {status} (the ordering of our own substitutions)")
    # ``perm`` lists the rows in factor order (measured: its inverse as the order gives a factor ~10x larger)
    return permutation.astype(np.int64)


@jit_on_first_call(cache=True)
def _group(indptr, indices, n, slack, small, widest):
    """Consecutive columns of L (CSC, sorted rows) grouped into supernodes (module docstring): their first columns
    (and n), and each group's rows (its diagonal part's columns first) at rows[row_ptr[s]:row_ptr[s + 1]]."""
    starts = np.empty(n + 1, dtype=np.int64)
    row_ptr = np.empty(n + 1, dtype=np.int64)
    rows = np.empty(indices.shape[0], dtype=np.int64)      # a group's rows are at most its columns' entries
    current = np.empty(n, dtype=np.int64)
    merged = np.empty(n, dtype=np.int64)
    count = indptr[1] - indptr[0]
    current[:count] = indices[indptr[0]:indptr[1]]
    true = count
    groups = 0
    starts[0] = 0
    row_ptr[0] = 0
    for column in range(1, n):
        width = column - starts[groups]
        a, b = indptr[column], indptr[column + 1]
        if width < widest:
            i, j, m = 0, a, 0                              # the union of the group's rows and the column's
            while i < count or j < b:
                if j >= b or (i < count and current[i] < indices[j]):
                    merged[m] = current[i]
                    i += 1
                elif i >= count or indices[j] < current[i]:
                    merged[m] = indices[j]
                    j += 1
                else:
                    merged[m] = current[i]
                    i += 1
                    j += 1
                m += 1
            stored, grown = (width + 1) * m, true + (b - a)
            if stored <= (1 + slack) * grown or (width + 1 <= small and stored <= 2 * grown):
                current[:m] = merged[:m]
                count, true = m, grown
                continue
        rows[row_ptr[groups]:row_ptr[groups] + count] = current[:count]
        row_ptr[groups + 1] = row_ptr[groups] + count
        groups += 1
        starts[groups] = column
        count = b - a
        current[:count] = indices[a:b]
        true = count
    rows[row_ptr[groups]:row_ptr[groups] + count] = current[:count]
    row_ptr[groups + 1] = row_ptr[groups] + count
    groups += 1
    starts[groups] = n
    return starts[:groups + 1].copy(), row_ptr[:groups + 1].copy(), rows[:row_ptr[groups]].copy()


@jit_on_first_call(cache=True)
def _blocks(starts, row_ptr, rows, indptr, indices, values, n, lanes):
    """The supernodes' values in the kernels' layout (the C source's header): the diagonal blocks' strict lower
    triangles column by column and row by row, the rows below them padded to a multiple of ``lanes`` (padding rows
    index n) column by column, and the offsets of each."""
    groups = starts.shape[0] - 1
    diagonal_start = np.zeros(groups + 1, dtype=np.int64)
    below_start = np.zeros(groups + 1, dtype=np.int64)
    row_start = np.zeros(groups + 1, dtype=np.int64)
    for s in range(groups):
        width = starts[s + 1] - starts[s]
        padded = -(-(row_ptr[s + 1] - row_ptr[s] - width) // lanes) * lanes
        diagonal_start[s + 1] = diagonal_start[s] + width * (width - 1) // 2
        below_start[s + 1] = below_start[s] + width * padded
        row_start[s + 1] = row_start[s] + padded
    by_columns = np.zeros(diagonal_start[groups])
    by_rows = np.zeros(diagonal_start[groups])
    below = np.zeros(below_start[groups])
    below_rows = np.full(row_start[groups], n, dtype=np.int64)
    place = np.empty(n, dtype=np.int64)                    # a row's place in the current group's rows
    for s in range(groups):
        first, width = starts[s], starts[s + 1] - starts[s]
        group = rows[row_ptr[s]:row_ptr[s + 1]]
        padded = row_start[s + 1] - row_start[s]
        for p in range(group.shape[0]):
            place[group[p]] = p
        below_rows[row_start[s]:row_start[s] + group.shape[0] - width] = group[width:]
        for j in range(width):
            for e in range(indptr[first + j], indptr[first + j + 1]):
                k = place[indices[e]]                      # L[group[k], first + j]
                if k >= width:
                    below[below_start[s] + j * padded + (k - width)] = values[e]
                elif k > j:                                # strict lower: (k, j) column j at j (2 width - j - 1) / 2
                    by_columns[diagonal_start[s] + j * (2 * width - j - 1) // 2 + (k - j - 1)] = values[e]
                    by_rows[diagonal_start[s] + k * (k - 1) // 2 + j] = values[e]
    return diagonal_start, below_start, row_start, by_columns, by_rows, below, below_rows


def factor_arrays(block: sp.csr_matrix) -> dict:
    """The supernodal single-precision L D L^T of ``block`` in PARDISO's ordering, as the arrays ``SupernodalLDL``
    takes (and ``sim.fast.store`` keeps). ``SolverError`` when it needs a pivot off the diagonal or has a zero one."""
    from scipy.sparse.linalg import splu

    n = block.shape[0]
    if n == 0:
        raise SolverError("an empty half: nothing for our own substitutions to factor")
    order = pardiso_ordering(block)
    permuted = sp.csr_matrix(block)[order][:, order].tocsc()
    try:
        lu = splu(permuted, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    except RuntimeError as error:                     # an exactly singular pivot
        raise SolverError(f"SuperLU could not factor the half with diagonal pivots: {error}") from None
    if not (np.array_equal(lu.perm_r, np.arange(n)) and np.array_equal(lu.perm_c, np.arange(n))):
        raise SolverError("the half needs off-diagonal pivots: our own substitutions cannot take it")
    lower = lu.L.tocsc()
    lower.sort_indices()
    diagonal = lu.U.diagonal()
    if not np.all(np.isfinite(diagonal)) or np.any(diagonal == 0) or not np.all(np.isfinite(lower.data)):
        raise SolverError("a zero or non-finite pivot in the half: our own substitutions cannot take it")
    indptr, indices = lower.indptr.astype(np.int64), lower.indices.astype(np.int64)
    starts, row_ptr, rows = _group(indptr, indices, n, SLACK, SMALL, WIDEST)
    diagonal_start, below_start, row_start, by_columns, by_rows, below, below_rows = _blocks(
        starts, row_ptr, rows, indptr, indices, lower.data, n, LANES)
    arrays = {"order": order, "starts": starts, "diagonal_start": diagonal_start, "below_start": below_start,
              "row_start": row_start, "diagonal_values": by_columns.astype(np.float32),
              "diagonal_rows": by_rows.astype(np.float32), "below_values": below.astype(np.float32),
              "below_rows": below_rows.astype(np.uint16 if n < 65535 else np.int32),
              "pivots": (1.0 / diagonal).astype(np.float32), "true_entries": np.array(lower.nnz, dtype=np.int64)}
    _check(block, SupernodalLDL(arrays))
    return arrays


def _check(block: sp.csr_matrix, factor: "SupernodalLDL"):
    """``SolverError`` unless the factor solves ``block`` to single precision: a pivot that is zero to round-off (not
    exactly) passes SuperLU and gives a factor of another matrix (PARDISO would perturb it; ``sim.fast.splitsolve``
    moves such unknowns out of the halves before they get here)."""
    probe = np.random.default_rng(18).uniform(1.0, 2.0, block.shape[0])
    solution = factor.phase(333, factor.phase(332, factor.phase(331, probe)))
    error = np.linalg.norm(block @ solution - probe) / np.linalg.norm(probe)
    if not error <= CHECK:
        raise SolverError(f"our own factor of the half solves it to {error:.1e} only (a pivot zero to round-off?)")


def stored_key(block: sp.csr_matrix) -> dict:
    """What ``factor_arrays`` of ``block`` depends on, for ``sim.fast.store``: the matrix, the code, MKL (the ordering)
    and SciPy (SuperLU)."""
    from .linalg import mkl_version
    from .store import code_digest, digest
    return {"layout": LAYOUT, "block": digest(block.data, block.indices, block.indptr), "mkl": mkl_version(),
            "scipy": scipy.__version__, "code": code_digest(factor_arrays, _group, _blocks, pardiso_ordering),
            "grouping": (SLACK, SMALL, WIDEST, LANES)}


class SupernodalLDL:
    """A single-precision L D L^T with PARDISO's partial substitutions (module docstring), for ``sim.fast.splitsolve``.

    ``arrays``: ``factor_arrays``'s. ``substitute`` takes 331 (forward, y = L^-1 P b), 332 (diagonal, D^-1 y) and
    333 (backward, P^T L^-T z) on float32 vectors; ``phase`` any vector."""

    single = True
    perturbed_pivots = 0
    restored = False          # set by ``sim.fast.splitsolve`` when the arrays came from ``sim.fast.store``

    def __init__(self, arrays: dict):
        library = _kernels()
        if library is None:
            raise SolverError("our own substitutions are not available (vcyto was installed without its compiled "
                              "kernels, or without MKL)")
        index = {np.dtype(t): name for name, t in INDEX_TYPES.items()}.get(np.asarray(arrays["below_rows"]).dtype)
        if index is None:
            raise SolverError(f"row indices of type {np.asarray(arrays['below_rows']).dtype}: uint16 or int32")
        self._forward_kernel = getattr(library, f"vcyto_forward_{index}")
        self._backward_kernel = getattr(library, f"vcyto_backward_{index}")
        self.order = np.ascontiguousarray(arrays["order"], dtype=np.int64)
        n = len(self.order)
        self.shape = (n, n)
        kept = {name: np.ascontiguousarray(arrays[name]) for name in set(_ARRAYS + _BACKWARD)}
        self._arrays = tuple(kept.values())              # held for the kernels' pointers
        self.pivots = np.ascontiguousarray(arrays["pivots"], dtype=np.float32)
        self.factor_nonzeros = int(arrays["true_entries"])
        self._supernodes = len(arrays["starts"]) - 1
        self._forward = [kept[name].ctypes.data for name in _ARRAYS] + [self.order.ctypes.data]
        self._backward = [kept[name].ctypes.data for name in _BACKWARD] + [self.order.ctypes.data]
        self._work = _aligned_empty(n + 1, dtype=np.float32)
        longest = int(np.diff(arrays["row_start"]).max()) if self._supernodes else 0
        self._gathered = _aligned_empty(max(longest, LANES), dtype=np.float32)

    def substitute(self, phase: int, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """One partial substitution from ``source`` into ``target`` (contiguous float32 arrays of n, not the same)."""
        n = self.shape[0]
        if source.ctypes.data == target.ctypes.data:
            raise SolverError("a substitution cannot write into its source")
        if source.dtype != np.float32 or target.dtype != np.float32 or len(source) != n or len(target) != n \
                or not (source.flags.c_contiguous and target.flags.c_contiguous):
            raise SolverError(f"a substitution takes contiguous float32 vectors of {n} values")
        if phase == 331:
            self._forward_kernel(n, self._supernodes, *self._forward, source.ctypes.data, self._work.ctypes.data,
                                 target.ctypes.data)
        elif phase == 332:
            np.multiply(self.pivots, source, out=target)
        elif phase == 333:
            self._backward_kernel(n, self._supernodes, *self._backward, source.ctypes.data, self._work.ctypes.data,
                                  self._gathered.ctypes.data, target.ctypes.data)
        else:
            raise SolverError(f"no partial substitution {phase}: 331, 332 or 333")
        return target

    def phase(self, phase: int, rhs: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``substitute`` for any vector: the result as float64 (or written into ``out``)."""
        source = np.ascontiguousarray(rhs, dtype=np.float32)
        target = np.empty(self.shape[0], dtype=np.float32)
        self.substitute(phase, source, target)
        if out is None:
            return target.astype(np.float64)
        out[:] = target
        return out

    def release(self):
        """Nothing to free (numpy owns the arrays); PARDISO's factors have this."""

    def keep(self):
        """Kept through ``sim.fast.store`` when built (``sim.fast.splitsolve``); PARDISO's factors have this."""
