"""Sparse direct solvers behind one small interface: factor once, back-solve many times.

The fluid matrix of the `imex` and `stokes` treatments never changes, so a step costs one back-solve
of a factorisation computed at start-up. Two back-ends:

- ``pardiso``: Intel MKL PARDISO through ctypes (the ``mkl`` wheel ships ``libmkl_rt``), real
  symmetric indefinite (``mtype=-2``, upper triangle only) or unsymmetric (``mtype=11``), zero-based
  CSR, iterative refinement off. The fastest back-solve measured here (docs/numerics.md, "Linear solvers").
- ``superlu``: scipy's SuperLU with a symmetric minimum-degree ordering; always available.

``sim.fast.solvers.factorize(matrix, solver="auto", symmetric=...)`` picks one: PARDISO when MKL loads, SuperLU
otherwise. This module imports nothing of the model or the method (an import contract in ``pyproject.toml``).
"""

from __future__ import annotations

import ctypes
import glob
import os
import site
import sys
from contextlib import contextmanager
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from . import speed
from .store import digest, discard_directory, keep_directory, stored_directory


class SolverError(RuntimeError):
    """A factorisation or back-solve failed (singular matrix, missing library, bad input)."""


@lru_cache(maxsize=1)
def _mkl_runtime():
    """Load ``libmkl_rt`` from this environment, or return None when MKL is not installed.

    MKL brings Intel's OpenMP runtime, which then also runs numba's parallel kernels (its GNU-compatible
    entry points come first); its threads spin for 200 ms after every parallel region (KMP_BLOCKTIME),
    so each step's momentum kernel left a thread spinning through the next back-solve, on a core the
    split solve's second thread needed (measured: 100 ms of CPU per 100 ms after a step; steps 10-40 %
    slower, by how the threads landed). So the application runs with KMP_BLOCKTIME=0 unless the user set it
    (``SpeedSettings.openmp_blocktime_ms``): idle threads sleep at once (docs/numerics.md, "Linear solvers").
    ``SpeedSettings.mkl_library`` names a library to try first (read on the first call)."""
    names = [speed.current().mkl_library]
    for root in {sys.prefix, site.getuserbase()}:
        names += sorted(glob.glob(os.path.join(root, "lib", "libmkl_rt.so*")), key=len)
        names += sorted(glob.glob(os.path.join(root, "Library", "bin", "mkl_rt*.dll")), key=len)
    names += ["libmkl_rt.so.2", "libmkl_rt.so.3", "libmkl_rt.so"]
    for name in filter(None, names):
        try:
            library = ctypes.CDLL(name)
        except OSError:
            continue
        library.pardiso.restype = None
        return library
    return None


@contextmanager
def spinning_openmp_threads(milliseconds: int = 200):
    """Within the block, Intel OpenMP's idle threads spin ``milliseconds`` (for teams the calling thread
    starts), then back to the process's setting (``SpeedSettings.openmp_blocktime_ms``). The benchmarks
    give PARDISO's parallel substitution its own best setting (threads hot between calls) while they time it.
    Does nothing when that runtime is not loaded."""
    runtime = None
    if _mkl_runtime() is not None:
        try:
            runtime = ctypes.CDLL("libiomp5.so")
        except OSError:
            runtime = None
    if runtime is not None:
        runtime.kmp_set_blocktime(ctypes.c_int(int(milliseconds)))
    try:
        yield
    finally:
        if runtime is not None:
            runtime.kmp_set_blocktime(ctypes.c_int(int(speed.current().openmp_blocktime_ms)))


def _aligned_empty(size: int, alignment: int = 64, dtype=np.float64) -> np.ndarray:
    """An uninitialised array whose data starts on an ``alignment``-byte boundary."""
    itemsize = np.dtype(dtype).itemsize
    raw = np.empty(size + alignment // itemsize, dtype=dtype)
    offset = (-raw.ctypes.data % alignment) // itemsize
    return raw[offset: offset + size]


@lru_cache(maxsize=1)
def mkl_version() -> str:
    """MKL's version string ('' without MKL): factorisations, and what is derived from them, depend on it."""
    library = _mkl_runtime()
    if library is None:
        return ""
    buffer = ctypes.create_string_buffer(256)
    library.mkl_get_version_string(buffer, ctypes.c_int(len(buffer)))
    return buffer.value.decode(errors="replace").strip()


def pardiso_available() -> bool:
    return _mkl_runtime() is not None


class Pardiso:
    """One MKL PARDISO factorisation of a square sparse matrix.

    ``symmetric=True`` factors the real symmetric indefinite matrix (LDL^T with Bunch-Kaufman pivoting
    and weighted matching), which halves the factor's size and so the memory traffic of a back-solve.
    ``matching=False`` (symmetric only) leaves out the weighted matching and scaling: a smaller factor and a
    quicker analysis, but PARDISO may then perturb a pivot it finds too small (``perturbed_pivots``), which
    makes the factor that of a slightly different matrix (``sim.fast.splitsolve`` moves such an unknown out).
    ``single=True`` factors and substitutes in single precision (``iparm[27] = 1``): half the bytes of
    factor, solutions to ~1e-6 relative; meant as the inner solver of ``MixedPrecision``. Inputs and
    outputs stay float64.

    ``kept=True``: the factorisation is restored from ``sim.fast.store`` when an application keeps it there (MKL's
    ``pardiso_handle_restore``: 5 ms against 140 ms for a half of the paper's split solve), else computed and
    kept (``keep``). The key names the stored matrix, the parameters and MKL's version; PARDISO's sequential
    factorisation is deterministic, so a restored factor gives the bits a fresh one gives.
    """

    KIND = "pardiso-factor"

    _INT = ctypes.c_int32

    def __init__(self, matrix: sp.spmatrix, symmetric: bool = False, reproducible: bool = True,
                 single: bool = False, matching: bool = True, kept: bool = False):
        library = _mkl_runtime()
        if library is None:
            raise SolverError("MKL PARDISO is not available: install the 'mkl' package or use solver='superlu'")
        self._pardiso = library.pardiso
        self.symmetric = symmetric
        self.mtype = -2 if symmetric else 11
        self.single = single
        self._dtype = np.float32 if single else np.float64
        stored = sp.triu(matrix, format="csr") if symmetric else sp.csr_matrix(matrix)
        stored.sum_duplicates()
        stored.sort_indices()
        self.shape = stored.shape
        self._data = np.ascontiguousarray(stored.data, dtype=self._dtype)
        self._indptr = np.ascontiguousarray(stored.indptr, dtype=np.int32)
        self._indices = np.ascontiguousarray(stored.indices, dtype=np.int32)
        self._handle = np.zeros(64, dtype=np.int64)
        self._rhs_buffer = self._solution_buffer = self._phase_buffers = None
        self.iparm = np.zeros(64, dtype=np.int32)
        self.iparm[0] = 1      # we supply iparm
        self.iparm[1] = 2      # METIS nested dissection ordering
        self.iparm[7] = 0      # no iterative refinement beyond what perturbed pivots require
        self.iparm[9] = 8 if symmetric else 13   # pivot perturbation 1e-8 / 1e-13
        matched = int(matching or not symmetric)
        self.iparm[10] = matched   # scaling (for a symmetric matrix it goes with the matching)
        self.iparm[12] = matched   # weighted matching
        self.iparm[17] = -1    # report the number of non-zeros in the factor
        # forward/backward substitution: 1 = sequential, bit-for-bit reproducible (12 ms here);
        # 2 = parallel, 2x faster but its reductions make the last bits vary from run to run
        self.iparm[24] = 1 if reproducible else 2
        self.iparm[27] = 1 if single else 0
        self.iparm[34] = 1     # zero-based indexing
        self._inputs = self.iparm.tolist()     # the parameters as given (PARDISO writes outputs into iparm)
        self._key = None
        self._refactored = False
        self.restored = kept and self._restore()
        if not self.restored:
            self._call(12, np.zeros(self.shape[0], dtype=self._dtype))
        self.factor_nonzeros = int(self.iparm[17])
        self.perturbed_pivots = int(self.iparm[13])
        if kept and not self.restored:
            self.keep()

    def key(self) -> dict:
        """What the factorisation depends on: the stored matrix, the input parameters, MKL's version."""
        if self._key is None:
            self._key = {"layout": 1, "matrix": digest(self._data, self._indptr, self._indices), "mtype": self.mtype,
                         "iparm": self._inputs, "mkl": mkl_version()}
        return self._key

    def _handle_call(self, name: str, directory: str) -> int:
        error = self._INT(0)
        getattr(_mkl_runtime(), name)(self._handle.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
                                      os.fsencode(directory), ctypes.byref(error))
        return error.value

    def _restore(self) -> bool:
        """Restore the factorisation kept in the store; False when there is none or it cannot be read."""
        entry = stored_directory(self.KIND, self.key())
        if entry is None:
            return False
        directory, arrays = entry
        stored = np.asarray(arrays.get("iparm", ()), dtype=np.int32)
        error = self._handle_call("pardiso_handle_restore", directory) if stored.shape == self.iparm.shape else None
        if error != 0:
            # (MKL may hold memory for a restore that failed half-way; a handle it could not fill is not released)
            self._handle[:] = 0
            discard_directory(self.KIND, self.key(), "PARDISO could not restore it" +
                              (f" (error {error})" if error is not None else " (its parameters do not fit)"))
            return False
        self.iparm[:] = stored
        return True

    def keep(self):
        """Keep this factorisation in the store (``sim.fast.store.keep_directory``) for a later run to restore (not
        after ``refactor``: its ordering is the first matrix's)."""
        if self._refactored:
            return
        key = self.key()

        def write(directory: str) -> dict:
            error = self._handle_call("pardiso_handle_store", directory)
            if error != 0:
                raise OSError(f"PARDISO could not store its factorisation in {directory} (error {error})")
            return {"iparm": self.iparm.copy()}
        keep_directory(self.KIND, key, write)

    def _call(self, phase: int, rhs: np.ndarray, solution: np.ndarray | None = None) -> np.ndarray:
        solution = np.zeros_like(rhs) if solution is None else solution
        error = self._INT(0)
        nrhs = 1 if rhs.ndim == 1 else rhs.shape[1]
        if rhs.dtype != self._dtype or solution.dtype != self._dtype:
            raise SolverError(f"PARDISO phase {phase}: vectors must be {np.dtype(self._dtype).name}")
        pointer_int = ctypes.POINTER(self._INT)
        address = ctypes.c_void_p      # float64 or float32 data, by iparm[27]
        self._pardiso(
            self._handle.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
            ctypes.byref(self._INT(1)), ctypes.byref(self._INT(1)), ctypes.byref(self._INT(self.mtype)),
            ctypes.byref(self._INT(phase)), ctypes.byref(self._INT(self.shape[0])),
            address(self._data.ctypes.data),
            self._indptr.ctypes.data_as(pointer_int), self._indices.ctypes.data_as(pointer_int),
            None, ctypes.byref(self._INT(nrhs)), self.iparm.ctypes.data_as(pointer_int),
            ctypes.byref(self._INT(0)), address(rhs.ctypes.data),
            address(solution.ctypes.data), ctypes.byref(error),
        )
        if error.value != 0:
            raise SolverError(f"PARDISO phase {phase} failed with error {error.value}")
        return solution

    def solve(self, rhs: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        """Back-solve (``guess`` is not used: a direct solve needs none). The right-hand side goes through one
        persistent buffer: MKL's results can depend on the memory alignment of its inputs, and a fixed buffer
        makes equal inputs give equal bits."""
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.ndim != 1:
            return self._call(33, np.asfortranarray(rhs, dtype=self._dtype)).astype(np.float64)
        if self._rhs_buffer is None or len(self._rhs_buffer) != len(rhs):
            self._rhs_buffer = _aligned_empty(len(rhs), dtype=self._dtype)
            self._solution_buffer = _aligned_empty(len(rhs), dtype=self._dtype)
        narrow(self._rhs_buffer, rhs)
        self._call(33, self._rhs_buffer, self._solution_buffer)
        return self._solution_buffer.astype(np.float64)

    def phase(self, phase: int, rhs: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """One partial substitution of a vector: 331 forward, 332 diagonal, 333 backward (A^-1 = 333 332 331).

        Inputs and outputs go through fixed aligned buffers (see ``solve``); the result is written to ``out``
        (or a new array)."""
        if self._phase_buffers is None or len(self._phase_buffers[0]) != len(rhs):
            self._phase_buffers = (_aligned_empty(len(rhs), dtype=self._dtype),
                                   _aligned_empty(len(rhs), dtype=self._dtype))
        source, target = self._phase_buffers
        narrow(source, rhs)
        self._call(phase, source, target)
        if out is None:
            return target.astype(np.float64)
        out[:] = target
        return out

    def substitute(self, phase: int, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """One partial substitution (see ``phase``) from ``source`` into ``target``: the caller's own fixed,
        aligned buffers of the factor's precision, used as they are (no copies)."""
        return self._call(phase, source, target)

    def same_pattern(self, matrix: sp.spmatrix) -> bool:
        stored = sp.triu(matrix, format="csr") if self.symmetric else matrix
        return (stored.shape == self.shape and stored.nnz == len(self._data)
                and np.array_equal(stored.indptr, self._indptr) and np.array_equal(stored.indices, self._indices))

    def refactor(self, matrix: sp.spmatrix) -> "Pardiso":
        """Numerical factorisation of a matrix with the same sparsity pattern, reusing the ordering."""
        stored = sp.triu(matrix, format="csr") if self.symmetric else sp.csr_matrix(matrix)
        stored.sort_indices()
        self._data = np.ascontiguousarray(stored.data, dtype=self._dtype)
        self._key, self._refactored = None, True
        self._call(22, np.zeros(self.shape[0], dtype=self._dtype))
        self.perturbed_pivots = int(self.iparm[13])
        return self

    def release(self):
        if self._handle.any():
            self._call(-1, np.zeros(self.shape[0], dtype=self._dtype))
            self._handle[:] = 0

    def __del__(self):
        try:
            self.release()
        except Exception:  # interpreter shutdown: nothing sensible to report
            pass


class SuperLU:
    """scipy's SuperLU factorisation; symmetric-mode minimum degree on A^T + A by default."""

    def __init__(self, matrix: sp.spmatrix, symmetric: bool = False, ordering: str = "MMD_AT_PLUS_A",
                 reproducible: bool = True):
        # symmetric mode with a relaxed diagonal threshold keeps the fill-reducing ordering on the
        # saddle-point matrix (the default threshold pivots it away: 2x the fill, 2x the back-solve)
        options = {"SymmetricMode": True, "DiagPivotThresh": 0.1} if ordering == "MMD_AT_PLUS_A" else {}
        try:
            self._lu = spla.splu(sp.csc_matrix(matrix), permc_spec=ordering, options=options)
        except RuntimeError as error:
            raise SolverError(f"SuperLU factorisation failed: {error}") from None
        self.shape = matrix.shape
        self.symmetric = symmetric
        self.factor_nonzeros = int(self._lu.L.nnz + self._lu.U.nnz)

    def solve(self, rhs: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        return self._lu.solve(rhs)

    def release(self):
        self._lu = None


def _largest(vector: np.ndarray) -> float:
    """max |v_i| without a temporary array (NaN when any entry is NaN)."""
    return max(vector.max(), -vector.min())


class MixedPrecision:
    """A double-precision solve from a single-precision factorisation, by iterative refinement.

    x_0 = ``guess`` (the previous time step's solution; zero without one), then
    x_{k+1} = x_k + S (b - A x_k) with S the single-precision solve and the residual in double precision.
    S is accurate to ~1e-6 relative (the matrix is well conditioned: measured 7.5e-7 at the paper's mesh),
    so each correction shrinks the error ~1e6-fold: the refinement stops after the correction d_k with
    ||d_k||_inf <= ``tolerance`` ||x_{k+1}||_inf, which leaves an error of ~1e-6 ``tolerance`` ||x||_inf:
    with the default 0.1, within 5e-7 of the double-precision solve (measured in Scenario II, where a step's
    solution moves 2.4 % of its largest value, median, 8 % at most: 2e-8 median, 4.7e-7 at worst), 2,500
    times below the imex treatment's own error (1.25e-3). A time step costs one residual and one
    single-precision back-solve; a larger change (a start from rest, an IDT switching on) a second.
    Every operation has a fixed order, so equal inputs give equal bits.
    """

    TOLERANCE = 0.1
    MAX_CORRECTIONS = 4

    def __init__(self, matrix: sp.spmatrix, inner, tolerance: float = TOLERANCE):
        self._matrix = sp.csr_matrix(matrix, dtype=np.float64)
        self._inner = inner
        self.tolerance = tolerance
        self.shape, self.symmetric = inner.shape, inner.symmetric
        self.factor_nonzeros = inner.factor_nonzeros
        self.solves = self.corrections = 0        # totals, for the benchmarks

    def solve(self, rhs: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        if rhs.ndim != 1:
            return np.column_stack([self.solve(column) for column in rhs.T])
        solution = np.zeros_like(rhs) if guess is None else np.array(guess, dtype=np.float64)
        self.solves += 1
        refine = getattr(self._inner, "refine", None)       # the split solve's: residual to update, in parallel
        for _ in range(self.MAX_CORRECTIONS):
            if refine is not None:
                size, scale = refine(rhs, solution)
            else:
                correction = self._inner.solve(rhs - self._matrix @ solution)
                solution += correction
                size, scale = _largest(correction), _largest(solution)
            self.corrections += 1
            if not (np.isfinite(size) and np.isfinite(scale)):
                return solution                   # the caller's finiteness check reports it with its cause
            if size <= self.tolerance * scale:
                return solution
        raise SolverError(f"mixed-precision refinement did not converge in {self.MAX_CORRECTIONS} corrections "
                          f"(last {size:.3g} of {scale:.3g}): the single-precision factorisation is too "
                          "inaccurate for this matrix; set numerics.precision = 'double'")

    @property
    def inner(self):
        """The single-precision factorisation (its ``solve`` is one correction's back-solve)."""
        return self._inner

    def release(self):
        self._inner.release()


def narrow(target: np.ndarray, values: np.ndarray) -> None:
    """``target[:] = values``; into single precision a value beyond its range becomes inf without numpy's
    overflow warning (``sim`` prints nothing): the step's finiteness check then reports the blow-up and its
    cause."""
    with np.errstate(over="ignore"):
        target[:] = values
