"""The largest stable time step of a cell, from a law fitted to measured limits (docs/results.md, "Stability").

The membrane update is explicit, so each cell has a largest stable dt. It is measured by bisection
(``sim.stability.stable_dt``, ``vcyto stability``); the measurements are ``MEASURED``. The law fitted to them,

    dt_limit = T_scheme * (h / H0)^p * (K0 / kappa_e)^q * (eta / ETA0),

with H0 = 10/3 um (the paper's mesh), K0 = 2.8e-4 N/m (the melanoma's tension modulus), ETA0 = 6 mPa s, has
its exponents p (mesh) and q (stiffness) fitted by least squares in logarithms to the limits that were
reached (a stable and an unstable dt bracket them), one constant per time scheme, and then each constant
lowered until the law lies at or below every measured stable dt of its scheme (``Law.fit``). It is the one
statement of a cell's limit that the tolerance's step cap (``sim.adaptive``), the failure hints
(``sim.health``) and ``vcyto stability`` use. The viscosity enters as in every explicit membrane time scale
(eta dq / kappa_e); it was not varied in the measurements. The bending modulus is not a variable of the law:
the cells measured have the paper's bending moduli.

The paper's bound (33), dt / h <= eta / (8 C_cell (kappa_e Lambda_1 + kappa_b Lambda_2)), falls like h; the
measured limits fall like h^p with p about 3.5 (the melanoma, 54 us at 3.33 um, 5 us at 1.67 um), so no
multiple of (33) is a limit on every mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

H0 = 10e-6 / 3          # m: the paper's mesh
K0 = 2.8e-4             # N/m: the melanoma's kappa_e
ETA0 = 6.0e-3           # Pa s: the paper's viscosity
UM, US = 1e-6, 1e-6


@dataclass(frozen=True)
class Measured:
    """One bisection: the largest stable and the first unstable dt (inf: none up to the largest step tried) of
    a cell with tension modulus ``kappa_e`` on the mesh ``h`` in ``scheme`` with the ``membrane`` method."""

    cell: str
    h: float
    kappa_e: float
    scheme: str
    membrane: str
    stable: float
    unstable: float

    @property
    def reached(self) -> bool:
        return math.isfinite(self.unstable)


RBC, MELANOMA = 6.0e-6, 2.8e-4
# bisections to 25 % in the cell's paper-scenario flow, 2 ms trials against a 2 us reference (1 us for the
# stiffest), membrane energy within 2x of the reference and the health checks passing (``sim.stability``);
# docs/results.md "Stability" gives the commands
MEASURED = (
    Measured("melanoma", 10e-6 / 3, MELANOMA, "euler", "conserving", 54.3 * US, 61.3 * US),
    Measured("melanoma", 10e-6 / 3, MELANOMA, "euler", "paper", 37.6 * US, 42.5 * US),
    Measured("melanoma", 5e-6 / 3, MELANOMA, "euler", "conserving", 4.71 * US, 5.32 * US),
    Measured("melanoma", 5e-6 / 3, MELANOMA, "euler", "paper", 6.0 * US, 6.8 * US),
    Measured("RBC", 20e-6 / 3, RBC, "euler", "conserving", 100 * US, math.inf),
    Measured("RBC", 10e-6 / 3, RBC, "euler", "conserving", 100 * US, math.inf),
    Measured("RBC", 5e-6 / 3, RBC, "euler", "conserving", 100 * US, math.inf),
    Measured("melanoma", 20e-6 / 3, MELANOMA, "euler", "conserving", 100 * US, math.inf),
    Measured("melanoma", 5e-6, MELANOMA, "euler", "conserving", 100 * US, math.inf),
    Measured("melanoma", 10e-6 / 3, MELANOMA, "bdf2", "conserving", 23.06 * US, 26.06 * US),
    Measured("melanoma", 5e-6, MELANOMA, "bdf2", "conserving", 88.49 * US, 100 * US),
)


@dataclass(frozen=True)
class Law:
    """dt_limit = constants[scheme] (h / H0)^p (K0 / kappa_e)^q (eta / ETA0) (module docstring)."""

    constants: dict
    p: float
    q: float

    @classmethod
    def fit(cls, measured=MEASURED) -> "Law":
        reached = [m for m in measured if m.reached]
        schemes = sorted({m.scheme for m in reached})
        rows = [[math.log(m.h / H0), math.log(K0 / m.kappa_e)] + [float(m.scheme == s) for s in schemes]
                for m in reached]
        values = [math.log(m.stable) for m in reached]
        matrix = np.array(rows)
        # q is fitted only where the stiffness was varied; else the explicit membrane's 1 (eta dq / kappa_e)
        varied = len({m.kappa_e for m in reached}) > 1
        if not varied:
            values = [v - r[1] for v, r in zip(values, rows)]
            matrix = np.delete(matrix, 1, axis=1)
        solution = np.linalg.lstsq(matrix, np.array(values), rcond=None)[0]
        p, q = float(solution[0]), (float(solution[1]) if varied else 1.0)
        shape = cls({s: 1.0 for s in schemes}, p, q)
        constants = {s: min(m.stable / shape.limit(m.h, m.kappa_e, s) for m in reached if m.scheme == s)
                     for s in schemes}
        return cls(constants, p, q)

    def limit(self, h: float, kappa_e: float, scheme: str, viscosity: float = ETA0) -> float:
        """The largest stable dt (s) of a cell with tension modulus ``kappa_e`` on a mesh of size ``h``."""
        constant = self.constants.get(scheme, min(self.constants.values()))
        return constant * (h / H0) ** self.p * (K0 / kappa_e) ** self.q * (viscosity / ETA0)


LAW = Law.fit()


def limit_of(cell_type, scenario) -> float:
    """The law's largest stable dt of ``cell_type`` in ``scenario`` (its mesh, time scheme and viscosity)."""
    numerics = scenario.numerics
    return LAW.limit(numerics.mesh_h, cell_type.kappa_e, numerics.scheme, scenario.fluid.viscosity)
