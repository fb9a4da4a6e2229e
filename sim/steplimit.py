"""The largest stable time step of a cell, from a law fitted to measured limits (docs/results.md, "Stability").

The membrane update is explicit, so each cell has a largest stable dt. It is measured by bisection
(``sim.stability.stable_dt``, ``vcyto stability``); the measurements are ``MEASURED``. The law fitted to them,

    dt_limit = c_scheme * c_method * A * (h / H0)^p * (K0 / kappa_e)^q,

H0 = 10/3 um (the paper's mesh), K0 = 2.8e-4 N/m (the melanoma's tension modulus), c_euler = c_conserving = 1, has
A, p, q, c_bdf2 and c_paper (the paper's literal membrane method) fitted by least squares in logarithms to the limits that were reached (a stable and an unstable dt
bracket them), then lowered by one factor until it lies at or below every measured stable dt (``Law.fit``), and
never above 100 us, the largest step measured (``LARGEST_TRIED``: above it nothing was measured). It is
the one statement of a cell's limit that the tolerance's step cap (``sim.adaptive``), the failure hints
(``sim.health``) and ``vcyto stability`` use. Neither the bending modulus nor the viscosity is a variable: the cells
measured have the paper's bending moduli and fluid. For the soft RBC, whose limit was not reached up to 100 us on
any mesh measured, the law is conservative.

The paper's bound (33), dt / h <= eta / (8 C_cell (kappa_e Lambda_1 + kappa_b Lambda_2)), falls like h and like
1 / kappa_e; the measured limits fall like h^3 to h^4 and far more slowly with the stiffness, so no multiple of (33)
is a limit on every mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

H0 = 10e-6 / 3          # m: the paper's mesh
K0 = 2.8e-4             # N/m: the melanoma's kappa_e
UM, US = 1e-6, 1e-6
LARGEST_TRIED = 100e-6  # s: the largest step the bisections try; the law claims no limit above it


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
    Measured("melanoma", 10e-6 / 3, 4 * MELANOMA, "euler", "conserving", 42.50 * US, 48.02 * US),
)


@dataclass(frozen=True)
class Law:
    """dt_limit = c[scheme] c[membrane method] A (h / H0)^p (K0 / kappa_e)^q (module docstring)."""

    constant: float           # A (s): the limit of a melanoma-stiff conserving cell at the paper's mesh in euler
    p: float
    q: float
    factors: tuple            # ((scheme or membrane method, c), ...): euler and conserving are 1

    @classmethod
    def fit(cls, measured=MEASURED) -> "Law":
        reached = [m for m in measured if m.reached]
        kinds = sorted(({m.scheme for m in reached} - {"euler"}) | ({m.membrane for m in reached} - {"conserving"}))
        rows = [[1.0, math.log(m.h / H0), math.log(K0 / m.kappa_e)] + [float(k in (m.scheme, m.membrane))
                                                                        for k in kinds] for m in reached]
        x = np.linalg.lstsq(np.array(rows), np.log([m.stable for m in reached]), rcond=None)[0]
        factors = (("euler", 1.0), ("conserving", 1.0)) + tuple((k, math.exp(c)) for k, c in zip(kinds, x[3:]))
        shape = cls(math.exp(x[0]), float(x[1]), float(x[2]), factors)
        lower = min(m.stable / shape.limit(m.h, m.kappa_e, m.scheme, m.membrane) for m in reached)
        return cls(shape.constant * min(1.0, lower), shape.p, shape.q, factors)

    def limit(self, h: float, kappa_e: float, scheme: str, membrane: str = "conserving") -> float:
        """The largest stable dt (s) of a cell with tension modulus ``kappa_e`` on a mesh of size ``h`` (a scheme or
        a membrane method not measured takes the smallest factor)."""
        factors = dict(self.factors)
        smallest = min(factors.values())
        law = (factors.get(scheme, smallest) * factors.get(membrane, smallest) * self.constant
               * (h / H0) ** self.p * (K0 / kappa_e) ** self.q)
        return min(law, LARGEST_TRIED)


LAW = Law.fit()


def limit_of(cell_type, scenario) -> float:
    """The law's largest stable dt of ``cell_type`` in ``scenario`` (its mesh, time scheme and viscosity)."""
    numerics = scenario.numerics
    return LAW.limit(numerics.mesh_h, cell_type.kappa_e, numerics.scheme, scenario.membrane_method())
