"""The README's install builds the compiled substitution kernels (sim/fast/_substitute.c) and step kernels
(sim/fast/_kernels.c), optional extensions, wherever it can: a check kept apart from tests/test_supernodal.py and
tests/test_c_kernels.py, whose tests are skipped without them."""

import platform
import shutil
import sys
import sysconfig
from pathlib import Path

import pytest

from sim.fast import kernels, supernodal


def test_the_kernels_were_built_where_a_compiler_is():
    """The README's install builds the kernels (an optional extension); where a C compiler is, it must have."""
    headers = Path(sysconfig.get_paths()["include"], "Python.h")
    if sys.platform != "linux" or platform.machine() != "x86_64" or shutil.which("cc") is None \
            or not headers.is_file():
        pytest.skip("the check is for Linux x86_64 with a C compiler and Python's headers")
    assert supernodal.available()
    assert kernels.compiled(), "sim.fast._kernels was not built (or VCYTO_C_KERNELS=0 is set)"
