"""The Taylor-Hood P2/P1 discretisation of the channel (paper (2)): the spaces on a channel mesh, the constant
matrices (mass, Laplace, divergence blocks; cached on disk through ``sim.fast.store``) and the quadrature tables of
the numba kernels that assemble the convection terms. ``sim.method.fluid`` steps Navier-Stokes on it.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from skfem import Basis, BilinearForm, ElementTriP1, ElementTriP2, FacetBasis, Functional, asm
from skfem.helpers import dot, grad
from skfem.quadrature import get_quadrature

from ..fast import kernels
from ..fast.store import code_digest, digest, reuse
from ..model.mesh import ChannelMesh


@BilinearForm
def mass_form(u, v, w):
    return u * v


@BilinearForm
def _laplace(u, v, w):
    return dot(grad(u), grad(v))


@BilinearForm
def _d_dx(u, q, w):
    return grad(u)[0] * q


@BilinearForm
def _d_dy(u, q, w):
    return grad(u)[1] * q


@BilinearForm
def _advection(u, v, w):
    return (w.ux * grad(u)[0] + w.uy * grad(u)[1]) * v


@BilinearForm
def _weighted_mass(u, v, w):
    return w.weight * u * v


_FORMS = {"mass": (mass_form, False), "laplace": (_laplace, False), "d_dx": (_d_dx, True), "d_dy": (_d_dy, True)}


def _constant_matrices(velocity_basis, pressure_basis) -> dict:
    """The P2 mass and Laplace matrices and the P2/P1 divergence blocks (CSR), through the set-up store
    (``sim.fast.store``: assembling them is ~0.2-0.5 s at the paper's mesh), keyed by the mesh's nodes and
    elements, the quadrature, the forms' bytecode and scikit-fem's version."""
    import skfem

    def assemble() -> dict:
        arrays = {}
        for name, (form, mixed) in _FORMS.items():
            matrix = (asm(form, velocity_basis, pressure_basis) if mixed else asm(form, velocity_basis)).tocsr()
            matrix.sort_indices()
            arrays.update({f"{name}_data": matrix.data, f"{name}_indices": matrix.indices,
                           f"{name}_indptr": matrix.indptr, f"{name}_shape": np.array(matrix.shape)})
        return arrays

    mesh = velocity_basis.mesh
    key = {"mesh": digest(mesh.p, mesh.t), "velocity": "P2", "pressure": "P1", "intorder": 5,
           "quadrature": digest(*velocity_basis.quadrature), "skfem": skfem.__version__,
           "forms": code_digest(*(form.form for form, _ in _FORMS.values()))}
    stored = reuse("matrices", key, assemble)
    return {name: sp.csr_matrix((stored[f"{name}_data"], stored[f"{name}_indices"], stored[f"{name}_indptr"]),
                                shape=tuple(stored[f"{name}_shape"])) for name in _FORMS}


class TaylorHood:
    """The P2/P1 spaces on a channel mesh, their constant matrices and the quadrature for the kernels."""

    def __init__(self, cmesh: ChannelMesh):
        self.cmesh = cmesh
        mesh = cmesh.mesh
        self.velocity_basis = Basis(mesh, ElementTriP2(), intorder=5)
        self.pressure_basis = Basis(mesh, ElementTriP1(), quadrature=self.velocity_basis.quadrature)
        self.N = self.velocity_basis.N
        self.P = self.pressure_basis.N
        self.nodes = self.velocity_basis.doflocs
        matrices = _constant_matrices(self.velocity_basis, self.pressure_basis)
        self.mass, self.laplace = matrices["mass"], matrices["laplace"]
        self.divergence = (matrices["d_dx"], matrices["d_dy"])
        self._kernel_tables()

    @property
    def dofs(self) -> int:
        return 2 * self.N + self.P

    def _kernel_tables(self):
        element = ElementTriP2()
        points, weights = get_quadrature(element.refdom, 5)
        self.q_weights = np.ascontiguousarray(weights)
        values = [element.lbasis(points, i) for i in range(6)]
        self.q_phi = np.ascontiguousarray(np.array([v[0] for v in values]).T)              # (nq, 6)
        self.q_dphi = np.ascontiguousarray(np.array([v[1] for v in values]).transpose(2, 0, 1))  # (nq, 6, 2)
        mapping = self.cmesh.mesh.mapping()
        centre = np.array([[1 / 3], [1 / 3]])
        self.inverse_jacobians = np.ascontiguousarray(mapping.invDF(centre)[:, :, :, 0].transpose(2, 0, 1))
        self.determinants = np.ascontiguousarray(mapping.detDF(centre)[:, 0])
        # the momentum kernel's layout (``kernels._element_momentum``): a00, a01, a10, a11 as rows, and |det J|
        self.jacobian_rows = np.ascontiguousarray(self.inverse_jacobians.reshape(-1, 4).T)
        self.areas = np.abs(self.determinants)
        self.element_dofs = np.ascontiguousarray(self.velocity_basis.element_dofs.astype(np.int64))
        self._identity_positions = np.arange(2 * self.N, dtype=np.int64).reshape(2, self.N)
        self._scratch = None
        self._pattern = None

    def momentum_load(self, velocity, mass_coefficient, convection_coefficient, positions, out, back=None):
        """Add (m w - k (u . grad) u, phi_i) to ``out[positions[c, i]]``: u = w = v, or BDF2's fields from the velocity
        one step back ``back`` (``kernels.element_momentum``)."""
        if self._scratch is None:
            self._scratch = self.element_buffer()
        self.element_momentum(velocity, mass_coefficient, convection_coefficient, self._scratch, back)
        return self.scatter_momentum(self._scratch, positions, out)

    def element_buffer(self) -> np.ndarray:
        """A buffer for ``element_momentum``: (elements, 2, 6)."""
        return np.empty((self.element_dofs.shape[1], 2, 6))

    def element_momentum(self, velocity, mass_coefficient, convection_coefficient, out, back=None,
                         threads: int | None = None) -> np.ndarray:
        """``momentum_load``'s element integrals into ``out`` (``element_buffer``), on ``threads`` of numba's
        (``kernels.element_momentum``: the same bits with any number)."""
        return kernels.element_momentum(self.element_dofs, self.jacobian_rows, self.areas, self.q_phi, self.q_dphi,
                                        self.q_weights, velocity, mass_coefficient, convection_coefficient, out,
                                        back, threads)

    def scatter_momentum(self, local, positions, out):
        """Add ``element_momentum``'s values ``local`` to ``out[positions[c, i]]`` (element by element, in order)."""
        kernels.scatter_momentum(self.element_dofs, local, positions, out)
        return out

    def convection_load(self, velocity: np.ndarray) -> np.ndarray:
        """The vector (2, N) of integrals ((v . grad) v) . phi_i."""
        out = np.zeros(2 * self.N)
        self.momentum_load(velocity, 0.0, -1.0, self._identity_positions, out)
        return out.reshape(2, self.N)

    def convection_matrices(self, velocity: np.ndarray, newton: bool):
        """Blocks [[Cxx, Cxy], [Cyx, Cyy]] of the linearised convection about ``velocity``, all on ``pattern``.

        Picard/Oseen: C = (v . grad) on the diagonal. Newton adds (. grad) v: C_ab += (d_b v_a) phi_j phi_i.
        Every block keeps the full P2 sparsity pattern (explicit zeros included), so a factorisation of the
        linearised system can be refactored in place from one iteration to the next (numba kernel).
        """
        pattern = self.pattern
        data = [np.empty(pattern.nnz) for _ in range(4)]
        kernels.linearised_convection(self.element_dofs, self.inverse_jacobians, self.determinants, self.q_phi,
                                      self.q_dphi, self.q_weights, velocity[0], velocity[1], newton,
                                      self._pattern_positions, *data)
        xx, xy, yx, yy = (sp.csr_matrix((d, pattern.indices, pattern.indptr), shape=pattern.shape) for d in data)
        return [[xx, xy], [yx, yy]]

    def convection_matrices_reference(self, velocity: np.ndarray, newton: bool):
        """The same blocks assembled with scikit-fem forms (the oracle of the kernel's test)."""
        fields = {"ux": self.velocity_basis.interpolate(velocity[0]),
                  "uy": self.velocity_basis.interpolate(velocity[1])}
        advection = asm(_advection, self.velocity_basis, **fields)
        blocks = [[advection, 0 * advection], [0 * advection, advection]]
        if newton:
            for a, component in enumerate(("ux", "uy")):
                for b in range(2):
                    blocks[a][b] = blocks[a][b] + asm(_weighted_mass, self.velocity_basis,
                                                      weight=fields[component].grad[b])
        return blocks

    @property
    def pattern(self) -> sp.csr_matrix:
        """The scalar P2 sparsity pattern: every pair of nodes sharing an element."""
        if self._pattern is None:
            dofs = self.element_dofs
            rows = np.repeat(dofs, 6, axis=0).ravel()
            cols = np.tile(dofs, (6, 1)).ravel()
            pattern = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(self.N, self.N))
            pattern.sum_duplicates()
            pattern.sort_indices()
            self._pattern = pattern
            self._pattern_keys = np.repeat(np.arange(self.N, dtype=np.int64), np.diff(pattern.indptr)) * self.N \
                + pattern.indices
            dofs = self.element_dofs.T                     # (ne, 6)
            pairs = dofs[:, :, None] * self.N + dofs[:, None, :]
            self._pattern_positions = np.ascontiguousarray(np.searchsorted(self._pattern_keys, pairs))
        return self._pattern

    def on_pattern(self, matrix) -> sp.csr_matrix:
        """``matrix`` (or zeros) re-expressed on ``pattern``, explicit zeros kept."""
        pattern = self.pattern
        data = np.zeros(pattern.nnz)
        if matrix is not None:
            coo = matrix.tocoo()
            positions = np.searchsorted(self._pattern_keys, coo.row.astype(np.int64) * self.N + coo.col)
            data = np.bincount(positions, weights=coo.data, minlength=pattern.nnz).astype(np.float64, copy=False)
        return sp.csr_matrix((data, pattern.indices, pattern.indptr), shape=pattern.shape)

    def boundary_flux(self, velocity: np.ndarray, name: str) -> float:
        """Outward volume flux (m^2/s) of ``velocity`` through the named boundary."""
        facets = self.cmesh.boundary(name)
        if len(facets) == 0:
            return 0.0
        basis = FacetBasis(self.cmesh.mesh, ElementTriP2(), facets=facets, intorder=4)

        @Functional
        def flux(w):
            return w.ux * w.n[0] + w.uy * w.n[1]

        return float(flux.assemble(basis, ux=basis.interpolate(velocity[0]), uy=basis.interpolate(velocity[1])))
