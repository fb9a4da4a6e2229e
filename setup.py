"""The compiled part of vcyto: the split solve's substitution kernels (sim/_substitute.c, sim/supernodal.py).

Everything else is in pyproject.toml. The extension is optional: without a C compiler the install goes on and
the split solve uses PARDISO's substitutions (a step ~40 % slower, the same accuracy).
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("sim._substitute", ["sim/_substitute.c"], extra_compile_args=["-O3"], optional=True)])
