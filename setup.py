"""The compiled part of vcyto: the split solve's substitution kernels (sim/fast/_substitute.c, sim/fast/supernodal.py)
and the FE-IB step's kernels (sim/fast/_kernels.c, sim/fast/kernels.py).

Everything else is in pyproject.toml. Both extensions are optional: without a C compiler the install goes on, the
split solve uses PARDISO's substitutions (a step ~40 % slower, the same accuracy) and the step's kernels are numba's
(sim/fast/kernels_numba.py: the same results, ~0.4 s more a process to load numba).
"""

import hashlib
from pathlib import Path

from setuptools import Extension, setup

# the library reports the source it was built from: a key part of the results computed through it (sim/fast/kernels.py)
KERNELS_SOURCE = hashlib.sha256(Path(__file__).with_name("sim").joinpath("fast", "_kernels.c").read_bytes()).hexdigest()

setup(ext_modules=[
    Extension("sim.fast._substitute", ["sim/fast/_substitute.c"], extra_compile_args=["-O3"], optional=True),
    Extension("sim.fast._kernels", ["sim/fast/_kernels.c"], extra_compile_args=["-O3", "-ffp-contract=off"],
              define_macros=[("VCYTO_KERNELS_SOURCE", f'"{KERNELS_SOURCE}"')],
              optional=True),
])
