import numpy as np
import pytest
import scipy.sparse as sp

from sim.fast.linalg import Pardiso, SolverError, SuperLU, pardiso_available
from sim.fast.solvers import factorize


def saddle_point(n=60, m=20, seed=0):
    """A symmetric indefinite [[A, B^T], [B, 0]] like the fluid's (A SPD, B full rank)."""
    rng = np.random.default_rng(seed)
    a = sp.random(n, n, density=0.1, random_state=seed)
    a = a @ a.T + n * sp.identity(n)
    b = sp.random(m, n, density=0.2, random_state=seed + 1) + sp.eye(m, n)
    return sp.bmat([[a, b.T], [b, None]], format="csr"), rng.standard_normal(n + m)


@pytest.mark.parametrize("symmetric", [True, False])
def test_back_ends_solve_a_saddle_point_system(symmetric):
    matrix, rhs = saddle_point()
    backends = [SuperLU] + ([Pardiso] if pardiso_available() else [])
    for backend in backends:
        solution = backend(matrix, symmetric=symmetric).solve(rhs)
        assert np.linalg.norm(matrix @ solution - rhs) <= 1e-12 * np.linalg.norm(rhs)


def test_unknown_solver_is_a_clear_error():
    matrix, _ = saddle_point()
    with pytest.raises(SolverError, match="unknown linear solver 'umfpack'"):
        factorize(matrix, "umfpack")
