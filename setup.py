"""The compiled part of vcyto: the split solve's substitution kernels (sim/_substitute.c, sim/supernodal.py) and the
FE-IB step's kernels (sim/_kernels.c, sim/kernels.py).

Everything else is in pyproject.toml. Both extensions are optional: without a C compiler the install goes on, the
split solve uses PARDISO's substitutions (a step ~40 % slower, the same accuracy) and the step's kernels are numba's
(sim/kernels_numba.py: the same results, ~0.4 s more a process to load numba).
"""

import hashlib
from pathlib import Path

from setuptools import Extension, setup

# the library reports the source it was built from: a key part of the results computed through it (sim/kernels.py)
KERNELS_SOURCE = hashlib.sha256(Path(__file__).with_name("sim").joinpath("_kernels.c").read_bytes()).hexdigest()

setup(ext_modules=[
    Extension("sim._substitute", ["sim/_substitute.c"], extra_compile_args=["-O3"], optional=True),
    Extension("sim._kernels", ["sim/_kernels.c"], extra_compile_args=["-O3", "-ffp-contract=off"],
              define_macros=[("VCYTO_KERNELS_SOURCE", f'"{KERNELS_SOURCE}"')],
              optional=True),
])
