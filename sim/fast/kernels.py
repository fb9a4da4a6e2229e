"""The FE-IB step's kernels: compiled C (``sim/fast/_kernels.c``) where the install built it, else numba's.

The kernels themselves, their layouts and their arithmetic are those of ``sim.fast.kernels_numba`` (the reference,
tested against scikit-fem): the P2 momentum load's element integrals and their scatter, the linearised convection,
the immersed boundary's point location, interpolation and spreading, a membrane's first self-intersection, the split
solve's vector work and the fluid step's glue. The C library has the same functions with the same arguments. It
exists because numba costs every process that steps the plant ~0.35-0.5 s before its first step (importing numba,
its compiler's set-up and loading each cached kernel: ``docs/numerics.md``, "The step's kernels"); with the C
kernels an FE-IB run never imports numba.

The C kernels give numba's bits wherever numba's kernel is exact (every one but the momentum kernel, which numba
compiles with ``fastmath``: there the two agree to round-off; ``tests/test_c_kernels.py``). Which one computed a
result is part of the keys of stored results (``implementation``), so a warm start never mixes them.

``SpeedSettings.c_kernels`` False (``sim.fast.speed``) uses numba's kernels. The C library is an optional
extension (``setup.py``): without a compiler, or when it was built from another layout of the functions' arguments,
numba's are used. An array the C kernels do not take (another dtype, not contiguous) goes to numba's kernel.
"""

from __future__ import annotations

import functools
import importlib
import logging
import math

import numpy as np

from . import speed

LAYOUT = 1            # the C functions' argument lists (``sim/fast/_kernels.c``'s LAYOUT)
log = logging.getLogger(__name__)


def _load_compiled():
    """The compiled module ``sim.fast._kernels``, or None (not built, or built for another layout)."""
    try:
        module = importlib.import_module("sim.fast._kernels")
    except ImportError:
        return None
    if module.layout() != LAYOUT:
        log.warning("vcyto's compiled step kernels were built from another version of sim/fast/_kernels.c (layout %d, "
                    "this code calls %d): run 'pip install -e .' again to rebuild them; using numba's meanwhile",
                    module.layout(), LAYOUT)
        return None
    return module


_LIBRARY = _load_compiled()


def _compiled_kernels():
    """The C library when it is built and the speed settings want it, else None (numba's kernels)."""
    return _LIBRARY if speed.current().c_kernels else None


def _numba():
    """``sim.fast.kernels_numba``, imported (with numba) on first use."""
    from . import kernels_numba
    return kernels_numba


def compiled() -> bool:
    """Whether this process's kernels are the compiled C ones."""
    return _compiled_kernels() is not None


def implementation() -> str:
    """Which kernels compute, for the keys of stored results: ``c-``, the SHA-256 of the C source the library was
    built from and the compiler's version, or ``numba-`` and a digest of ``sim.fast.kernels_numba``'s code (imports
    numba)."""
    library = _compiled_kernels()
    if library is not None:
        return "c-" + "_".join(library.source().split())      # one word (keys are split on spaces by their tests)
    from .store import module_digest
    return f"numba-{module_digest(_numba())}"


def _call(name: str, *arguments, takes: bool = True):
    """The C kernel ``name`` on ``arguments``, or numba's when the C one does not take them (TypeError, or
    ``takes`` False: arguments the caller knows it would compute differently)."""
    library = _compiled_kernels()
    if library is not None and takes:
        try:
            return getattr(library, name)(*arguments)
        except TypeError:
            pass
    return getattr(_numba(), name)(*arguments)


class jit_on_first_call:
    """A function numba compiles (``numba.njit(**options)``, its on-disk cache included) on its first call, so that
    importing the module that defines it does not import numba: for kernels only a cold set-up runs
    (``sim.fast.supernodal``'s factor layout). ``py_func`` is the Python function (``sim.fast.store.code_digest`` names
    it)."""

    def __init__(self, **options):
        self._options = options
        self.py_func = None
        self._compiled = None

    def __call__(self, *arguments):
        if self.py_func is None:                  # the decoration: @jit_on_first_call(cache=True)
            (self.py_func,) = arguments
            functools.update_wrapper(self, self.py_func)
            return self
        if self._compiled is None:
            from numba import njit
            self._compiled = njit(**self._options)(self.py_func)
        return self._compiled(*arguments)


# ---------------------------------------------------------------------- the momentum load and the convection

def element_momentum(element_dofs, jacobian_rows, areas, phi, dphi, weights, velocity, mass_coefficient,
                     convection_coefficient, out, back=None, threads: int | None = None):
    """Each element's integrals (m w - k (u . grad) u) . phi_i into ``out`` (ne, 2, 6); ``sim.fast.kernels_numba``'s
    ``element_momentum`` (its docstring: ``back``, BDF2's velocity one step back). ``threads``: numba's threads for
    the call (1: the calling thread alone); the C kernel always runs on the calling thread (~0.5 ms at the paper's
    mesh), without the GIL."""
    library = _compiled_kernels()
    if library is None:
        return _numba().element_momentum(element_dofs, jacobian_rows, areas, phi, dphi, weights, velocity,
                                         mass_coefficient, convection_coefficient, out, back, threads)
    if back is None:
        bdf2, (w0, w1, w2), (a, b) = False, (0.0, 0.0, 0.0), (velocity, velocity)
    else:
        bdf2, (w0, w1, w2), (a, b) = True, back[0], back[1]
    general = bool(w0 != 0.0 or w2 != 0.0 or w1 != 1.0)
    rows = [np.ascontiguousarray(field[k], dtype=np.float64) for field in (velocity, a, b) for k in (0, 1)]
    # never numba's instead (fastmath: other last bits under the C kernels' key): inputs made what C takes, an
    # ``out`` it cannot write raises
    element_dofs = np.ascontiguousarray(element_dofs, dtype=np.int64)
    jacobian_rows, areas, phi, dphi, weights = (np.ascontiguousarray(array, dtype=np.float64)
                                                for array in (jacobian_rows, areas, phi, dphi, weights))
    library.element_momentum(element_dofs, jacobian_rows, areas, phi, dphi, weights, *rows, float(w0), float(w1),
                             float(w2), general, bdf2, float(mass_coefficient), float(convection_coefficient), out)
    return out


def scatter_momentum(element_dofs, local, positions, out):
    """Add ``element_momentum``'s values ``local`` to ``out[positions[c, dof]]`` element by element (positions < 0
    skipped)."""
    _call("scatter_momentum", element_dofs, local, positions, out)


def linearised_convection(element_dofs, inverse_jacobians, determinants, phi, dphi, weights, ux, uy, newton,
                          positions, xx, xy, yx, yy):
    """The convection linearised about u on a fixed CSR pattern, its four blocks' data overwritten (Oseen; Newton
    adds (d_b u_a) phi_j phi_i)."""
    _call("linearised_convection", element_dofs, inverse_jacobians, determinants, phi, dphi, weights,
          np.ascontiguousarray(ux), np.ascontiguousarray(uy), bool(newton), positions, xx, xy, yx, yy)


# ---------------------------------------------------------------------- the immersed boundary

def locate(points, grid_x, grid_y, square_elements, origins, inverse_jacobians, elements, reference):
    """The triangle of a tensor-grid triangulation holding each point (-1 outside) and its reference coordinates."""
    _call("locate", points, grid_x, grid_y, square_elements, origins, inverse_jacobians, elements, reference)


def interpolate_p2(elements, reference, element_dofs, values, out):
    """out[k, c] = sum_i values[c, dof_i] phi_i(point k) (NaN outside the mesh)."""
    _call("interpolate_p2", elements, reference, element_dofs, values, out)


def spread_p2(elements, reference, element_dofs, forces, out):
    """out[c, dof_i] += forces[k, c] phi_i(point k): the exact adjoint of ``interpolate_p2``."""
    _call("spread_p2", elements, reference, element_dofs, forces, out)


def first_self_intersection(points):
    """Index pair (i, j) of the first two non-adjacent edges of the closed polygon that cross, else (-1, -1)."""
    return _call("first_self_intersection", points)


# ---------------------------------------------------------------------- the split solve's vector work

def gather_residual(rhs, rows, data, indices, indptr, x, out):
    """out[k] = rhs[rows[k]] - (A x)_k, A's rows in CSR (none given: out[k] = rhs[rows[k]]); in ``out``'s precision."""
    _call("gather_residual", rhs, rows, data, indices, indptr, x, out)


def _plus_zero(zero) -> bool:
    """Whether ``zero`` is +0 (the C kernels start every sum there; numba's start from ``zero`` itself)."""
    return zero == 0 and math.copysign(1.0, zero) > 0


def transposed_products(y, dinv, z, data, indices, indptr, g, zero):
    """z = dinv * y (when ``dinv`` has entries) and g = H^T y, summed in ``zero``'s type (the C kernel: in y's,
    so it takes a ``zero`` of that type)."""
    kind = y.dtype.type
    takes = _plus_zero(zero) and (type(zero) is kind or (type(zero) is float and kind is np.float64))
    if len(dinv) == 0:
        dinv = _NO_DIAGONAL.get(y.dtype, dinv)        # an absent diagonal of y's type, which the C kernel asks for
    _call("transposed_products", y, dinv, z, data, indices, indptr, g, zero, takes=takes)


def minus_product(z, data, indices, indptr, w, sums, out, zero):
    """out = z - H w, H given by its transpose in CSR, summed in ``sums``'s type from ``zero``."""
    _call("minus_product", z, data, indices, indptr, w, sums, out, zero, takes=_plus_zero(zero))


_NO_DIAGONAL = {np.dtype(np.float32): np.zeros(0, np.float32), np.dtype(np.float64): np.zeros(0)}


def scatter_add(solution, rows, x, accumulate):
    """solution[rows[k]] (+)= x[k]; the largest |x[k]| and |solution[rows[k]]| after it (NaN when not finite)."""
    return _call("scatter_add", solution, rows, x, bool(accumulate))


# ---------------------------------------------------------------------- the fluid step's glue

def free_rhs(momentum, free_velocity, continuity, out):
    """out = [momentum[free_velocity], continuity] (zeros where either is empty)."""
    _call("free_rhs", momentum, free_velocity, continuity, out)


def subtract_scaled(out, weight, vector):
    """out -= weight * vector."""
    _call("subtract_scaled", out, float(weight), vector)


def boundary_velocity(inflow_weight, inflow, jet_weight, jet, free_velocity, solution, out):
    """out = inflow_weight * inflow + jet_weight * jet, then out[free_velocity] = solution[:len(free_velocity)]."""
    _call("boundary_velocity", float(inflow_weight), inflow, float(jet_weight), jet, free_velocity, solution, out)


def free_solution(velocity, free_velocity, pressure, pressure_scale, out):
    """out = [velocity[free_velocity], pressure / pressure_scale]."""
    _call("free_solution", velocity, free_velocity, pressure, float(pressure_scale), out)
