"""The constant matrix of a fluid step gathered from its entries' positions instead of assembled.

The implicit-in-time treatments with a constant matrix (``imex``, ``stokes``) factor the free rows of
[[a, 0, -s Bx^T], [0, a, -s By^T], [-s Bx, -s By, 0]], a = c M + mu L, once per time step size; ``GatheredMatrix``
builds it for any c from where each entry comes from (``tagged_structure``), with the block assembly's entries,
order and bits (``block_rows`` is that assembly).
"""

from __future__ import annotations

import numpy as np
import scipy
import scipy.sparse as sp

from .store import code_digest, digest, reuse


class GatheredMatrix:
    """Where each entry of the constant treatments' reduced matrix comes from, so that the matrix of any time step
    is gathered instead of assembled (two block assemblies and three slicings: ~0.15 s at the paper's mesh).

    The matrix is the free rows of [[a, 0, -s Bx^T], [0, a, -s By^T], [-s Bx, -s By, 0]] with a = c M + mu L
    (c the mass coefficient, which the step sets, mu the viscosity, s the pressure scale); its free columns are
    the system, its Dirichlet columns the lift. An entry of a velocity block is c m + mu l at one position of
    the union of the P2 mass and Laplace patterns (m or l zero where that matrix has no entry), one of a
    divergence block -(s b) at one position of [Bx, By]. ``source`` holds those positions (the divergence's after
    the union's) in the order the block assembly gives; as that assembly's sparse sum does, a velocity entry whose
    value is exactly zero is left out. So ``assembled`` gives the assembly's entries, order and bits."""

    def __init__(self, mass: sp.csr_matrix, laplace: sp.csr_matrix, divergence: sp.csr_matrix, arrays: dict):
        # the union's values come from these, -1 (no entry) reading the appended zero
        self._mass = np.append(mass.data, 0.0)[arrays["union_mass"]]
        self._laplace = np.append(laplace.data, 0.0)[arrays["union_laplace"]]
        self.divergence_largest = float(abs(divergence).max())    # [Bx, By]: the largest of either block
        divergence = divergence.data
        self._parts = {}
        for name in ("rows", "lift"):         # each entry's values gathered once; a step only scales and adds
            source = arrays[f"{name}_source"]
            velocity = source < len(self._mass)
            at = source[velocity]
            self._parts[name] = (arrays[f"{name}_indptr"], arrays[f"{name}_indices"], tuple(arrays[f"{name}_shape"]),
                                 velocity, ~velocity, self._mass[at], self._laplace[at],
                                 divergence[source[~velocity] - len(self._mass)])

    def velocity_largest(self, mass_coefficient: float, viscosity: float) -> float:
        """max |a_ij|, a = c M + mu L."""
        return float(np.abs(mass_coefficient * self._mass + viscosity * self._laplace).max())

    def assembled(self, mass_coefficient: float, viscosity: float, scale: float):
        """(system, lift) for these coefficients: ``block_rows`` of a = c M + mu L."""
        return tuple(self._gathered(*self._parts[name], mass_coefficient, viscosity, scale)
                     for name in ("rows", "lift"))

    @staticmethod
    def _gathered(indptr, indices, shape, velocity, coupling, mass, laplace, divergence, mass_coefficient, viscosity,
                  scale) -> sp.csr_matrix:
        values = np.empty(len(velocity))
        momentum = mass_coefficient * mass
        momentum += viscosity * laplace             # c m + mu l, as the sparse sum computes it
        values[velocity] = momentum
        values[coupling] = -(divergence * scale)       # the divergence blocks' entries
        if (momentum == 0.0).any():
            kept = coupling | (values != 0.0)
            rows = np.repeat(np.arange(shape[0]), np.diff(indptr))[kept]
            indptr = np.concatenate(([0], np.cumsum(np.bincount(rows, minlength=shape[0])))).astype(indptr.dtype)
            indices, values = indices[kept], values[kept]
        return sp.csr_matrix((values, indices, indptr), shape=shape)


def positions(pattern: sp.csr_matrix, within: sp.csr_matrix) -> np.ndarray:
    """For each entry of ``pattern`` (canonical CSR), its position in ``within`` (canonical, same shape), or -1."""
    def keys(matrix):
        rows = np.repeat(np.arange(matrix.shape[0], dtype=np.int64), np.diff(matrix.indptr))
        return rows * matrix.shape[1] + matrix.indices
    wanted, present = keys(pattern), keys(within)
    at = np.minimum(np.searchsorted(present, wanted), len(present) - 1)
    return np.where(present[at] == wanted, at, -1)


def tagged_structure(mass: sp.csr_matrix, laplace: sp.csr_matrix, divergence: sp.csr_matrix, free: np.ndarray,
                      dirichlet: np.ndarray) -> dict:
    """``GatheredMatrix``'s arrays: the block assembly (``block_rows``) done on matrices whose values are
    their entries' positions (+1, exact in float64), so each entry of the result names its source."""
    union = (abs(mass) + abs(laplace)).tocsr()       # the sum's pattern (its zero entries go later, by value)
    union = sp.csr_matrix((np.ones(union.nnz), union.indices, union.indptr), shape=union.shape)
    union.sum_duplicates()
    union.sort_indices()
    arrays = {"union_mass": positions(union, mass), "union_laplace": positions(union, laplace)}
    tags_velocity = sp.csr_matrix((np.arange(1, union.nnz + 1, dtype=np.float64), union.indices, union.indptr),
                                  shape=union.shape)
    tags_divergence = sp.csr_matrix((np.arange(union.nnz + 1, union.nnz + divergence.nnz + 1, dtype=np.float64),
                                     divergence.indices, divergence.indptr), shape=divergence.shape)
    momentum = sp.bmat([[tags_velocity, None], [None, tags_velocity]], format="csr")
    # the assembly's own blocks (the divergence's tags come out negated, as its values do)
    for name, part in zip(("rows", "lift"), block_rows(momentum, tags_divergence, free, dirichlet)):
        arrays.update({f"{name}_indptr": part.indptr, f"{name}_indices": part.indices,
                       f"{name}_source": np.abs(part.data).astype(np.int64) - 1, f"{name}_shape": np.array(part.shape)})
    return arrays


def block_rows(momentum: sp.csr_matrix, divergence: sp.csr_matrix, free: np.ndarray, dirichlet: np.ndarray):
    """The free rows of [[momentum, -D^T], [-D, 0]] (D the scaled divergence): (their free columns, their Dirichlet
    columns). The one block assembly of every system the fluid solver factors, and of ``GatheredMatrix``'s tags."""
    rows = sp.bmat([[momentum, -divergence.T], [-divergence, None]], format="csr")[free]
    return rows[:, free].tocsr(), rows[:, dirichlet].tocsr()


def gathered(mass: sp.csr_matrix, laplace: sp.csr_matrix, divergence: sp.csr_matrix, free: np.ndarray,
             dirichlet: np.ndarray) -> GatheredMatrix:
    """The ``GatheredMatrix`` of these P2 mass and Laplace matrices, the divergence blocks [Bx, By] and these
    Dirichlet unknowns, through ``sim.fast.store`` (keyed by the sparsity patterns, the unknowns and the code)."""
    key = {"layout": 1, "unknowns": digest(free, dirichlet), "scipy": scipy.__version__,
           "patterns": digest(*(a for m in (mass, laplace, divergence) for a in (m.indptr, m.indices))),
           "code": code_digest(tagged_structure, positions, block_rows)}
    return GatheredMatrix(mass, laplace, divergence, reuse("fluid-structure", key, lambda: tagged_structure(
        mass, laplace, divergence, free, dirichlet)))
