"""Mixed precision (sim/fast/linalg.py MixedPrecision): single-precision factors refined to the double solve's
answer within the stated tolerance, one correction a step when the flow changes slowly, a clear error when
refinement fails; and no OpenMP thread left spinning after a step (docs/numerics.md, "Linear solvers")."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_linalg import saddle_point

from sim.fast.linalg import MixedPrecision, Pardiso, SolverError, pardiso_available
from sim.fast.solvers import factorize
from sim.method.fluid import NavierStokes
from sim.model.scenario import UM, Scenario, ScenarioError

pytestmark = pytest.mark.skipif(not pardiso_available(), reason="mixed precision runs on MKL PARDISO")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fluid():
    return NavierStokes(Scenario().with_numerics(mesh_h=10 * UM, precision="double"))


def test_single_precision_alone_is_inaccurate_and_refinement_restores_double(fluid):
    matrix = fluid.constant_matrix()
    rhs = np.random.default_rng(2).standard_normal(matrix.shape[0])
    single = Pardiso(matrix, symmetric=True, single=True)
    crude = single.solve(rhs)
    assert single.iparm[27] == 1 and crude.dtype == np.float64
    error = np.linalg.norm(matrix @ crude - rhs) / np.linalg.norm(rhs)
    assert 1e-10 < error < 1e-5                               # single precision: ~1e-7, not 1e-15
    mixed = factorize(matrix, "pardiso", symmetric=True, precision="mixed")
    assert isinstance(mixed, MixedPrecision)
    solution = mixed.solve(rhs)
    exact = Pardiso(matrix, symmetric=True).solve(rhs)
    assert np.linalg.norm(solution - exact) <= 1e-9 * np.linalg.norm(exact)
    assert mixed.corrections == 2                             # from zero: the solve, then one correction
    nearby = exact * (1 + 1e-2)                               # a guess as close as the last time step's
    before = mixed.corrections
    # one correction; what is left is the single solve's ~1e-6 of the 1e-2 change
    assert np.linalg.norm(mixed.solve(rhs, nearby) - exact) <= 2e-8 * np.linalg.norm(exact)
    assert mixed.corrections - before == 1


def test_refinement_that_does_not_converge_is_a_clear_error():
    matrix, rhs = saddle_point()

    class FifthWay:                                           # an inner solve that is off by a factor of 5
        shape, symmetric, factor_nonzeros = matrix.shape, True, 0

        def __init__(self):
            self._exact = Pardiso(matrix, symmetric=True)

        def solve(self, vector):
            return 0.2 * self._exact.solve(vector)

        def release(self):
            pass

    with pytest.raises(SolverError, match="did not converge.*numerics.precision = 'double'"):
        MixedPrecision(matrix, FifthWay()).solve(rhs)


def test_unknown_precision_is_a_clear_error():
    with pytest.raises(ScenarioError, match="precision"):
        Scenario().with_numerics(precision="quad")
    matrix, _ = saddle_point()
    with pytest.raises(SolverError, match="unknown precision 'quad'"):
        factorize(matrix, "pardiso", symmetric=True, precision="quad")


def test_split_solve_in_single_precision_refined(fluid):
    from sim.fast.splitsolve import SplitPardiso
    matrix = fluid.constant_matrix()
    split = SplitPardiso(matrix, fluid.free_x, single=True)
    assert all(half.dinv is not None for half in split.halves)   # D is diagonal in single precision too
    rhs = np.random.default_rng(3).standard_normal(matrix.shape[0])
    guess = np.random.default_rng(4).standard_normal(matrix.shape[0])
    # the residual computed per half on its own thread gives the bits of the whole residual's solve
    direct = split.solve(rhs - matrix @ guess)
    refined_once = guess.copy()
    split.refine(rhs, refined_once)
    assert np.array_equal(refined_once, guess + direct)
    exact = Pardiso(matrix, symmetric=True).solve(rhs)
    refined = MixedPrecision(matrix, split).solve(rhs)
    assert np.linalg.norm(refined - exact) <= 1e-9 * np.linalg.norm(exact)


def test_mixed_steps_follow_the_double_steps_through_an_idt_pulse():
    """20 steps off, 40 with the IDT on, 20 off at h = 10 um: the velocity within 5e-7 of double precision's
    at every step (the refinement's tolerance 0.1 times the single solve's ~1e-6), about one correction
    a step."""
    scenario = Scenario().with_numerics(mesh_h=10 * UM)
    runs = {}
    for precision in ("double", "mixed"):
        fluid = NavierStokes(scenario.with_numerics(precision=precision))
        state, velocities = fluid.steady(0.0), []
        for actuation in [0.0] * 20 + [1.0] * 40 + [0.0] * 20:
            state = fluid.step(state, actuation=actuation)
            velocities.append(state.velocity)
        runs[precision] = (velocities, fluid._constant.factor)
    worst = max(np.max(np.abs(d - m)) / np.max(np.abs(d)) for d, m in zip(runs["double"][0], runs["mixed"][0]))
    assert 0 < worst <= 5e-7
    factor = runs["mixed"][1]
    assert factor.solves == 80 and factor.corrections <= 1.2 * factor.solves


SPIN = """
import time
from vcyto import speedsettings
speedsettings.install()                     # as the vcyto command does, before MKL loads
from sim.method.fluid import NavierStokes
from sim.model.scenario import UM, Scenario
fluid = NavierStokes(Scenario().with_numerics(mesh_h=10 * UM))
state = fluid.steady(0.0)
for _ in range(3):
    state = fluid.step(state)
time.sleep(0.3)
state = fluid.step(state)
started = time.process_time()
time.sleep(0.2)
print(time.process_time() - started)
"""


def test_no_openmp_thread_spins_after_a_step():
    """Intel OpenMP runs numba's kernels once MKL is loaded; with its default 200 ms spin a thread burnt a core
    through the next back-solve (100 ms of CPU per 100 ms after a step). vcyto sets KMP_BLOCKTIME=0
    (``vcyto.speedsettings.install``)."""
    environment = {k: v for k, v in __import__("os").environ.items() if k != "KMP_BLOCKTIME"}
    cpu = float(subprocess.run([sys.executable, "-c", SPIN], capture_output=True, text=True, cwd=ROOT,
                               check=True, env=environment).stdout)
    assert cpu < 0.05, f"{cpu * 1e3:.0f} ms of CPU in a 200 ms sleep after a step: a thread is spinning"


def test_a_blown_up_right_hand_side_gives_inf_without_a_numpy_warning(fluid):
    """Values beyond single precision's range (a blow-up) become inf in the factor's buffers without numpy's
    overflow warning (sim prints nothing); the step's finiteness check then reports the blow-up."""
    import warnings
    matrix = fluid.constant_matrix()
    huge = np.full(matrix.shape[0], 1e300)
    for solver in (Pardiso(matrix, symmetric=True, single=True),
                   factorize(matrix, "pardiso", symmetric=True, precision="mixed")):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            solution = solver.solve(huge)
        assert not np.all(np.isfinite(solution))
