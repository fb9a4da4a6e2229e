"""The largest stable time step of a cell, from a law fitted to measured limits (docs/results.md, "Stability").

The membrane update is explicit, so each cell has a largest stable dt. It is measured by bisection
(``sim.method.stability.stable_dt``, ``vcyto stability``); the measurements are ``MEASURED``. Two limits act, the lower
one binds: one of the mesh, which the cell's stiffness does not move (the melanoma's at the paper's mesh changes
little when its kappa_e is 4x larger; it falls like h^3.3 with the mesh), and the explicit membrane's, about
proportional to its time scale eta h / kappa_e (a 16x stiffer melanoma on the 6.67 um mesh: 24 us, 100x: 2.9 us,
where the melanoma itself runs at 100 us):

    dt_limit = c_scheme c_method min(A (h / H0)^p, B (eta h / kappa_e) (K0 / kappa_e)^r),

H0 = 10/3 um (the paper's mesh), K0 = 2.8e-4 N/m (the melanoma's kappa_e), c_euler = c_conserving = 1. A, p, B,
r and the factors of the other time schemes and membrane methods measured are fitted by least squares in
logarithms to the limits that were reached (a stable and an unstable dt bracket them), then the law is lowered by
one factor until it lies at or below every measured stable dt (``Law.fit``); it never exceeds 100 us, the largest
step measured (``LARGEST_TRIED``: above it nothing was measured). Where a cell of the same stiffness was measured
on the same mesh, time scheme and membrane method, its measured stable dt is its limit when the law lies below it
(``limit_of``): the law is conservative for the soft RBC, whose limit was not reached at 100 us on any mesh.

With the implicit membrane coupling (``sim.method.coupling``) the limit is not the explicit membrane's: it is that
coupling's own measured limit, the smallest its measurements of the membrane method reached (``implicit_limit``).

This is the one statement of a cell's limit that the tolerance's step cap (``sim.method.adaptive``), the failure hints
(``sim.method.health``) and ``vcyto stability`` use. The bending modulus is not a variable (the cells measured have the
paper's), nor is the viscosity of the mesh's term (measured at the paper's).

The paper's bound (33), dt / h <= eta / (8 C_cell (kappa_e Lambda_1 + kappa_b Lambda_2)), falls like h and like
1 / kappa_e; the measured limits fall like h^3.3 and, for the paper's cells, not with the stiffness, so no multiple
of (33) is a limit on every mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

H0 = 10e-6 / 3          # m: the paper's mesh
K0 = 2.8e-4             # N/m: the melanoma's kappa_e
ETA0 = 6.0e-3           # Pa s: the paper's viscosity
US = 1e-6
LARGEST_TRIED = 100e-6  # s: the largest step the bisections try; the law claims no limit above it


@dataclass(frozen=True)
class Measured:
    """One bisection: the largest stable and the first unstable dt (inf: none up to the largest step tried) of
    a cell with tension modulus ``kappa_e`` on the mesh ``h`` in ``scheme`` with the ``membrane`` method and the
    membrane ``coupling``."""

    cell: str
    h: float
    kappa_e: float
    scheme: str
    membrane: str
    stable: float
    unstable: float
    coupling: str = "explicit"

    @property
    def reached(self) -> bool:
        return math.isfinite(self.unstable)


RBC, MELANOMA = 6.0e-6, 2.8e-4
# bisections to 25 % in the cell's paper-scenario flow, 2 ms trials against a 2 us reference (1, 0.5 and 0.25 us
# for the 16x, 25x and 100x stiffer melanoma), membrane energy within 2x of the reference and the health checks
# passing (``sim.method.stability.stable_dt``), all with the SAW jet taken as the carrier's amplitude; docs/results.md
# "Stability" gives the commands
MEASURED = (
    # the RBC in its scenario's flow, IDT off (no jet: the euler rows are from an earlier `vcyto stability` run)
    Measured("RBC", 20e-6 / 3, RBC, "euler", "conserving", 100 * US, math.inf),
    Measured("RBC", 10e-6 / 3, RBC, "euler", "conserving", 100 * US, math.inf),
    Measured("RBC", 5e-6 / 3, RBC, "euler", "conserving", 100 * US, math.inf),
    Measured("RBC", 20e-6 / 3, RBC, "bdf2", "conserving", 100 * US, math.inf),
    Measured("RBC", 10e-6 / 3, RBC, "bdf2", "conserving", 100 * US, math.inf),
    # the melanoma (and stiffer copies) in the SAW jet
    Measured("melanoma", 5e-6, MELANOMA, "euler", "conserving", 100 * US, math.inf),
    Measured("melanoma", 10e-6 / 3, MELANOMA, "euler", "conserving", 61.28 * US, 69.30 * US),
    Measured("melanoma", 2.5e-6, MELANOMA, "euler", "conserving", 18.06 * US, 20.41 * US),
    Measured("melanoma", 10e-6 / 3, 4 * MELANOMA, "euler", "conserving", 42.50 * US, 48.02 * US),
    Measured("melanoma", 5e-6, MELANOMA, "bdf2", "conserving", 88.49 * US, 100 * US),
    Measured("melanoma", 10e-6 / 3, MELANOMA, "euler", "paper", 37.60 * US, 42.50 * US),
    Measured("melanoma", 10e-6 / 3, MELANOMA, "bdf2", "conserving", 23.06 * US, 26.06 * US),
    Measured("melanoma", 2.5e-6, MELANOMA, "bdf2", "conserving", 9.80 * US, 11.08 * US),
    Measured("melanoma", 5e-6 / 3, MELANOMA, "bdf2", "conserving", 2.89 * US, 3.26 * US),
    Measured("melanoma", 10e-6 / 3, 4 * MELANOMA, "bdf2", "conserving", 20.41 * US, 23.06 * US),
    Measured("melanoma", 20e-6 / 3, 4 * MELANOMA, "euler", "conserving", 100 * US, math.inf),
    Measured("melanoma", 20e-6 / 3, 16 * MELANOMA, "euler", "conserving", 23.71 * US, 27.38 * US),
    Measured("melanoma", 20e-6 / 3, 16 * MELANOMA, "bdf2", "conserving", 11.49 * US, 13.28 * US),
    Measured("melanoma", 20e-6 / 3, 25 * MELANOMA, "euler", "conserving", 13.71 * US, 16.18 * US),
    Measured("melanoma", 20e-6 / 3, 100 * MELANOMA, "euler", "conserving", 2.85 * US, 3.44 * US),
    # the implicit coupling (``sim.method.coupling``) on the 1.67 um mesh, where the explicit coupling fails at 7 us
    # (docs/numerics.md "The membrane coupling"): the conserving method stable at 100 us by the bisection's criterion
    # (`vcyto stability --cells melanoma --mesh-sizes 1.6667um --membrane-coupling implicit`) and through Scenario II
    # from entry to exit; the paper's method (Scenario II from entry to exit) reaches the outlet at 50 us, and at
    # 100 us its membrane intersects itself (its points bunch up: no redistribution)
    Measured("melanoma", 5e-6 / 3, MELANOMA, "euler", "paper", 50 * US, 100 * US, "implicit"),
    Measured("melanoma", 5e-6 / 3, MELANOMA, "euler", "conserving", 100 * US, math.inf, "implicit"),
    # the area kept by the step (``sim.method.multiplier``)
    Measured("melanoma", 10e-6 / 3, MELANOMA, "euler", "multiplier", 48.02 * US, 54.27 * US),
    Measured("melanoma", 10e-6 / 3, MELANOMA, "bdf2", "multiplier", 26.06 * US, 29.45 * US),
)


@dataclass(frozen=True)
class Law:
    """dt_limit = c_scheme c_method min(A (h / H0)^p, B (eta h / kappa_e) (K0 / kappa_e)^r) (module docstring)."""

    mesh_term: float          # A (s): the mesh's limit at the paper's mesh (euler, conserving)
    p: float
    membrane_term: float      # B: the explicit membrane's limit in units of eta h / kappa_e (at kappa_e = K0)
    r: float
    factors: tuple            # ((scheme or membrane method, c), ...): euler and conserving are 1

    @classmethod
    def fit(cls, measured=MEASURED) -> "Law":
        from scipy.optimize import least_squares
        reached = [m for m in measured if m.reached and m.coupling == "explicit"]
        kinds = sorted(({m.scheme for m in reached} - {"euler"}) | ({m.membrane for m in reached} - {"conserving"}))

        def law(x):
            factors = (("euler", 1.0), ("conserving", 1.0)) + tuple((k, math.exp(c)) for k, c in zip(kinds, x[4:]))
            return cls(math.exp(x[0]), float(x[1]), math.exp(x[2]), float(x[3]), factors)

        def residuals(x):
            shape = law(x)
            return [math.log(shape.unbounded(m.h, m.kappa_e, m.scheme, m.membrane) / m.stable) for m in reached]

        fits = [least_squares(residuals, [math.log(50e-6), 3.5, math.log(b), 0.0] + [0.0] * len(kinds))
                for b in (0.5, 2.0, 8.0)]          # min() is not smooth: start from a few membrane terms
        shape = law(min(fits, key=lambda fit: fit.cost).x)
        lower = min(1.0, min(m.stable / shape.unbounded(m.h, m.kappa_e, m.scheme, m.membrane) for m in reached))
        return cls(shape.mesh_term * lower, shape.p, shape.membrane_term * lower, shape.r, shape.factors)

    def unbounded(self, h: float, kappa_e: float, scheme: str, membrane: str, viscosity: float = ETA0) -> float:
        factors = dict(self.factors)
        smallest = min(factors.values())
        law = min(self.mesh_term * (h / H0) ** self.p,
                  self.membrane_term * viscosity * h / kappa_e * (K0 / kappa_e) ** self.r)
        return factors.get(scheme, smallest) * factors.get(membrane, smallest) * law

    def limit(self, h: float, kappa_e: float, scheme: str, membrane: str = "conserving",
              viscosity: float = ETA0) -> float:
        """The largest stable dt (s) of a cell with tension modulus ``kappa_e`` on a mesh of size ``h`` (a scheme or
        a membrane method not measured takes the smallest factor), at most ``LARGEST_TRIED``."""
        return min(self.unbounded(h, kappa_e, scheme, membrane, viscosity), LARGEST_TRIED)


LAW = Law.fit()


def measured_stable(kappa_e: float, h: float, scheme: str, membrane: str) -> float | None:
    """The largest dt measured stable for a cell of tension modulus ``kappa_e`` on the mesh ``h`` in ``scheme`` with
    ``membrane`` (None if no such measurement)."""
    found = [m.stable for m in MEASURED if math.isclose(m.kappa_e, kappa_e, rel_tol=1e-9) and m.coupling == "explicit"
             and math.isclose(m.h, h, rel_tol=1e-6) and m.scheme == scheme and m.membrane == membrane]
    return max(found) if found else None


def limit_of(cell_type, scenario) -> float:
    """The largest stable dt of ``cell_type`` in ``scenario`` (its mesh, time scheme, membrane method and
    viscosity): the law's, or the dt measured stable for such a cell on this mesh where the law lies below that."""
    numerics = scenario.numerics
    method = scenario.membrane_method()
    if numerics.membrane_coupling == "implicit":
        return implicit_limit(method)
    law = LAW.limit(numerics.mesh_h, cell_type.kappa_e, numerics.scheme, method, scenario.fluid.viscosity)
    measured = measured_stable(cell_type.kappa_e, numerics.mesh_h, numerics.scheme, method)
    return law if measured is None or scenario.fluid.viscosity != ETA0 else max(law, measured)


def implicit_limit(membrane: str = "conserving", measured=MEASURED) -> float:
    """The largest stable dt of a cell with the implicit coupling (``sim.method.coupling``) and the ``membrane``
    method: the smallest stable dt of that method's implicit measurements that reached a limit (of every method's,
    when that method was not measured), else ``LARGEST_TRIED`` (stable there)."""
    rows = [m for m in measured if m.coupling == "implicit"]
    rows = [m for m in rows if m.membrane == membrane] or rows
    return min([m.stable for m in rows if m.reached] + [LARGEST_TRIED])
