"""The speed settings: built by the application from the environment, never read from it by ``sim``; each setting
selects what it names (C or numba kernels, the momentum helper thread, the split solve, our substitutions)."""

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from sim.fast import kernels, speed
from sim.fast.linalg import Pardiso, pardiso_available
from sim.fast.speed import SpeedSettings
from vcyto.speedsettings import from_environment

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("environment, expected", [
    ({}, SpeedSettings()),
    ({"VCYTO_C_KERNELS": " Off "}, SpeedSettings(c_kernels=False)),
    ({"VCYTO_C_KERNELS": "1"}, SpeedSettings()),
    ({"VCYTO_PREFETCH": "0"}, SpeedSettings(prefetch=False)),
    ({"VCYTO_SPLIT_SOLVE": "0"}, SpeedSettings(split_solve=False)),
    ({"VCYTO_OWN_SUBSTITUTIONS": "0"}, SpeedSettings(own_substitutions=False)),
    ({"VCYTO_MKL_RT": "/opt/mkl/libmkl_rt.so.2"}, SpeedSettings(mkl_library="/opt/mkl/libmkl_rt.so.2")),
    ({"KMP_BLOCKTIME": "200"}, SpeedSettings(openmp_blocktime_ms=200)),
    ({"KMP_BLOCKTIME": "infinite"}, SpeedSettings()),
])
def test_the_application_builds_the_settings_from_the_environment(environment, expected):
    assert from_environment(environment) == expected


def test_the_settings_are_frozen_and_only_settings_are_installed():
    with pytest.raises(AttributeError):
        SpeedSettings().prefetch = False
    with pytest.raises(TypeError, match="SpeedSettings"):
        speed.use({"prefetch": False})
    before = speed.current()
    with speed.using(replace(before, prefetch=not before.prefetch)) as inside:
        assert speed.current() is inside and inside.prefetch != before.prefetch
    assert speed.current() is before


def test_no_module_of_sim_reads_or_writes_the_environment():
    offending = [f"{path.name}:{number}" for path in sorted((ROOT / "sim").rglob("*.py"))
                 for number, line in enumerate(path.read_text().splitlines(), 1)
                 if "os.environ" in line or "getenv" in line or "putenv" in line]
    assert offending == []


def test_sim_alone_ignores_the_variables_and_leaves_the_environment_as_it_was():
    """Imported without vcyto, with every variable set to its 'off', sim runs with the defaults and sets no
    KMP_BLOCKTIME while it loads MKL."""
    program = ("import os, scipy.sparse as sp; from sim.fast import kernels, speed; "
               "from sim.fast.linalg import Pardiso, pardiso_available\n"
               "if pardiso_available(): Pardiso(sp.identity(3, format='csr'), symmetric=True).solve([1.0, 2, 3])\n"
               "print(speed.current() == speed.SpeedSettings(), 'KMP_BLOCKTIME' in os.environ)")
    environment = {"PATH": "/usr/bin:/bin", "VCYTO_C_KERNELS": "0", "VCYTO_PREFETCH": "0", "VCYTO_SPLIT_SOLVE": "0",
                   "VCYTO_OWN_SUBSTITUTIONS": "0"}
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=120,
                          env=environment, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "False"]


def test_the_command_installs_the_settings_of_its_environment(monkeypatch, tmp_path):
    from vcyto.cli import main
    monkeypatch.setattr(speed, "_settings", SpeedSettings())           # restored after the test
    monkeypatch.setenv("VCYTO_PREFETCH", "0")
    monkeypatch.setenv("VCYTO_SPLIT_SOLVE", "0")
    assert main(["cache", "info"]) == 0
    assert speed.current() == replace(from_environment(), prefetch=False, split_solve=False)
    assert not speed.current().prefetch and not speed.current().split_solve


@pytest.mark.skipif(not pardiso_available(), reason="the split solve runs on MKL PARDISO")
def test_split_solve_off_factors_one_sequential_pardiso(monkeypatch):
    from sim.fast.solvers import factorize
    from sim.fast.splitsolve import MIN_UNKNOWNS, SplitPardiso
    n = MIN_UNKNOWNS + 10
    matrix = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n), format="csr")
    coordinates = np.linspace(0.0, 1.0, n)
    if (os.cpu_count() or 1) >= 2:
        assert isinstance(factorize(matrix, symmetric=True, coordinates=coordinates), SplitPardiso)
    monkeypatch.setattr(speed, "_settings", replace(speed.current(), split_solve=False))
    factor = factorize(matrix, symmetric=True, coordinates=coordinates)
    assert isinstance(factor, Pardiso) and not isinstance(factor, SplitPardiso)


@pytest.mark.skipif(not kernels._LIBRARY, reason="vcyto was installed without its compiled step kernels")
def test_c_kernels_off_names_numbas_in_the_keys(monkeypatch):
    assert kernels.compiled() and kernels.implementation().startswith("c-")
    monkeypatch.setattr(speed, "_settings", replace(speed.current(), c_kernels=False))
    assert not kernels.compiled() and kernels.implementation().startswith("numba-")
