"""The simulator's speed settings (``sim.fast.speed.SpeedSettings``) from the environment: the application reads it, the
simulator never does.

| variable | setting | default |
|---|---|---|
| ``VCYTO_C_KERNELS`` (0, off, false, no: numba's kernels) | ``c_kernels`` | on |
| ``VCYTO_PREFETCH`` (0: the next step's momentum integrals in the step) | ``prefetch`` | on |
| ``VCYTO_SPLIT_SOLVE`` (0: one sequential PARDISO solve) | ``split_solve`` | on |
| ``VCYTO_OWN_SUBSTITUTIONS`` (0: PARDISO's substitutions in the split solve) | ``own_substitutions`` | on |
| ``VCYTO_MKL_RT`` (a ``libmkl_rt`` to load first) | ``mkl_library`` | '' |
| ``KMP_BLOCKTIME`` (Intel OpenMP's idle spin, ms) | ``openmp_blocktime_ms`` | 0 (set when unset) |

Each pair of settings computes the same result (docs/numerics.md); they exist for measurements and comparisons.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from sim.fast import speed
from sim.fast.speed import SpeedSettings


def from_environment(environment: Mapping[str, str] = os.environ) -> SpeedSettings:
    """The settings the ``VCYTO_*`` variables (and ``KMP_BLOCKTIME``) of ``environment`` select."""
    def on(name: str) -> bool:
        return environment.get(name, "1") != "0"

    try:
        blocktime = int(environment.get("KMP_BLOCKTIME", "0"))
    except ValueError:
        blocktime = 0
    return SpeedSettings(c_kernels=environment.get("VCYTO_C_KERNELS", "1").strip().lower()
                         not in ("0", "off", "false", "no"), prefetch=on("VCYTO_PREFETCH"),
                         split_solve=on("VCYTO_SPLIT_SOLVE"), own_substitutions=on("VCYTO_OWN_SUBSTITUTIONS"),
                         mkl_library=environment.get("VCYTO_MKL_RT", ""), openmp_blocktime_ms=blocktime)


def install() -> SpeedSettings:
    """Run the simulator with this process's settings: ``KMP_BLOCKTIME=0`` unless the user set it (before MKL and
    its OpenMP runtime load: ``sim.fast.linalg``'s measurement of spinning threads), then ``from_environment``."""
    os.environ.setdefault("KMP_BLOCKTIME", "0")
    settings = from_environment()
    speed.use(settings)
    return settings
