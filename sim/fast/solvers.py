"""The linear solvers by name: ``factorize`` picks a back-end of ``sim.fast.linalg`` (PARDISO, SuperLU) or the split
solve of ``sim.fast.splitsolve`` for a matrix, as the scenario's ``numerics.solver`` and ``numerics.precision`` ask.

The list of names is ``sim.fast.names`` (the scenario checks its choice against it); the back-ends import nothing of
the model or the method.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp

from . import speed
from .linalg import MixedPrecision, Pardiso, SolverError, SuperLU, pardiso_available
from .names import LINEAR_SOLVERS, PRECISIONS
from .splitsolve import MIN_UNKNOWNS, SplitPardiso

SOLVERS = LINEAR_SOLVERS              # the one list: sim.fast.names


def factorize(matrix: sp.spmatrix, solver: str = "auto", symmetric: bool = False, previous=None,
              reproducible: bool = True, coordinates: np.ndarray | None = None, precision: str = "double"):
    """Factor ``matrix`` with the named back-end ('auto' prefers PARDISO); returns an object with ``solve``.

    With ``previous`` (an earlier PARDISO factorisation of a matrix with the same sparsity pattern, e.g. the
    previous Newton or Oseen matrix) only the numerical factorisation is redone: ~3x cheaper.
    With ``coordinates`` (the x coordinate of each unknown) a large symmetric reproducible PARDISO system is
    solved by two sequential halves on two threads (``sim.fast.splitsolve``): reproducible at the parallel speed.
    ``precision="mixed"`` (PARDISO only) factors in single precision and refines in double
    (``MixedPrecision``); other back-ends and refactorisations stay in double precision.
    """
    if solver not in SOLVERS:
        raise SolverError(f"unknown linear solver {solver!r}: choose one of {', '.join(SOLVERS)}")
    if isinstance(previous, Pardiso) and previous.symmetric == symmetric and previous.same_pattern(matrix):
        return previous.refactor(matrix)
    if precision not in PRECISIONS:
        raise SolverError(f"unknown precision {precision!r}: choose one of {', '.join(PRECISIONS)}")
    if solver == "pardiso" or (solver == "auto" and pardiso_available()):
        single = precision == "mixed"
        if pardiso_available() and symmetric and reproducible and coordinates is not None and split_wanted(matrix):
            factor = SplitPardiso(matrix, coordinates, single=single)
        else:
            factor = Pardiso(matrix, symmetric=symmetric, reproducible=reproducible, single=single)
        return MixedPrecision(matrix, factor) if single else factor
    return SuperLU(matrix, symmetric=symmetric)


def split_wanted(matrix) -> bool:
    """Whether the two-thread split solve pays: a large matrix, two cores; ``SpeedSettings.split_solve`` False
    (``sim.fast.speed``) turns it off."""
    if not speed.current().split_solve:
        return False
    return matrix.shape[0] >= MIN_UNKNOWNS and (os.cpu_count() or 1) >= 2


def resolved_solver_name(solver: str) -> str:
    """The back-end ``factorize`` will use for ``solver`` on this machine."""
    if solver == "auto":
        return "pardiso" if pardiso_available() else "superlu"
    return solver
