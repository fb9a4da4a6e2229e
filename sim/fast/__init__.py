"""The machinery: how the method's arithmetic is done fast (compiled and numba kernels, the linear solvers and
their registry, the split solve, the speed settings, the store of reusable results). Imports nothing of the model
or the method (an import contract in pyproject.toml)."""
