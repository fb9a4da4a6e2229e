"""The speed settings: which of several implementations of the same computation the machinery runs.

Each setting picks between implementations that give the same result (the same bits, or round-off where the
module that reads it says so); none changes what is computed. ``sim`` reads no environment: the application builds
one ``SpeedSettings`` (vcyto: from its ``VCYTO_*`` variables, ``vcyto.speedsettings``) and installs it with
``use``; without that the defaults hold. Which implementations computed a stored result is part of its key
(``sim.fast.kernels.implementation``, ``sim.fast.splitsolve.substitutions``), so a warm start never mixes them.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass


@dataclass(frozen=True)
class SpeedSettings:
    """c_kernels: the compiled C step kernels where the install built them (``sim.fast.kernels``), else numba's.
    prefetch: a fluid step computes the next step's momentum integrals on a helper thread (``sim.method.fluid``), else
    in the step. split_solve: a large symmetric reproducible PARDISO system is solved as two halves on two threads
    (``sim.fast.splitsolve``), else sequentially. own_substitutions: a single-precision split solve substitutes with
    the compiled kernels of ``sim.fast.supernodal``, else with PARDISO's. mkl_library: a ``libmkl_rt`` to load before
    the ones found in the environment's prefix ('' for none). openmp_blocktime_ms: how long Intel OpenMP's idle
    threads spin in this process (its ``KMP_BLOCKTIME``, which the application sets before MKL loads); the
    benchmarks change it for a block and restore this value."""

    c_kernels: bool = True
    prefetch: bool = True
    split_solve: bool = True
    own_substitutions: bool = True
    mkl_library: str = ""
    openmp_blocktime_ms: int = 0


_settings = SpeedSettings()


def use(settings: SpeedSettings) -> SpeedSettings:
    """Run with ``settings`` from now on; returns the previous ones."""
    global _settings
    if not isinstance(settings, SpeedSettings):
        raise TypeError(f"speed settings must be a SpeedSettings, not {type(settings).__name__}")
    previous, _settings = _settings, settings
    return previous


def current() -> SpeedSettings:
    """The settings in use."""
    return _settings


@contextmanager
def using(settings: SpeedSettings):
    """``settings`` within the block, the previous ones after it."""
    previous = use(settings)
    try:
        yield settings
    finally:
        use(previous)
