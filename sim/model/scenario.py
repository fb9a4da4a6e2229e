"""The scenario: frozen, validated descriptions of the device, the fluid, the SAW model and the numerics.

All quantities are SI (metres, seconds, kilograms, pascal seconds). The defaults are the paper's
(section 4, with the readings in docs/physics.md). Every class checks its own fields in
``__post_init__`` and raises ``ScenarioError`` naming the field; ``Scenario`` checks what spans parts
(an inlet outside the wall, overlapping outlets, a mesh that does not resolve an inlet).

One concept, kept in one module though it is over 400 lines: the scenario's dataclasses are one tree
(``Scenario`` holds a ``Channel`` of ``Inlet``s and ``Outlet``s, a ``Fluid``, a ``Saw``, ``Numerics`` and
``CellType``s) whose cross-part checks and ``with_*`` copies need all of them; splitting it would spread one
validated structure over modules that import each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, is_dataclass, replace

from ..fast.names import LINEAR_SOLVERS, PRECISIONS  # the machinery's choices a scenario names

UM = 1e-6

CONVECTIONS = ("imex", "oseen", "implicit", "stokes")
SAW_MODELS = ("paper", "envelope", "streaming")
PROFILE_READINGS = ("paper", "peak")
INITIAL_FLOWS = ("steady", "rest")
TIME_SCHEMES = ("auto", "euler", "bdf2")
COUPLINGS = ("explicit", "implicit")
AREA_CONSTRAINTS = ("none", "pressure", "projection", "pressure+projection", "multiplier", "pressure+multiplier",
                    "multiplier+projection", "pressure+multiplier+projection")
# the two membrane methods a user picks between (``--membrane``): field values each one sets
MEMBRANE_METHODS = {
    "paper": {"area_constraint": "none", "redistribute": False},
    "conserving": {"area_constraint": "pressure+projection", "redistribute": True},
    "multiplier": {"area_constraint": "pressure+multiplier+projection", "redistribute": True},
}


class ScenarioError(ValueError):
    """An invalid scenario value; ``str(error)`` is one line naming the field and the fix."""

    def __init__(self, field_name: str, message: str):
        self.field = field_name
        super().__init__(f"{field_name}: {message}")

    def within(self, prefix: str) -> "ScenarioError":
        """The same error with ``prefix.`` prepended to the field path."""
        return ScenarioError(f"{prefix}.{self.field}", str(self).split(": ", 1)[1])


def _positive(owner, *names):
    for name in names:
        value = getattr(owner, name)
        if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ScenarioError(name, f"must be a positive number (got {value!r})")


def _choice(owner, name, choices):
    value = getattr(owner, name)
    if value not in choices:
        raise ScenarioError(name, f"must be one of {', '.join(choices)} (got {value!r})")


def _interval(owner, name):
    low, high = getattr(owner, name)
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ScenarioError(name, f"must be an interval (low, high) with low < high (got {(low, high)!r})")


@dataclass(frozen=True)
class Inlet:
    """An inflow boundary {0} x (low, high) with the paper's profile v_hat m(y) (y - low)(high - y).

    ``tilt`` is the angle of the inflow velocity to the x axis (positive: upward). ``cutoff`` is the
    width epsilon over which the smooth cut-off m rises from 0 at the wall to 1.
    """

    name: str
    span: tuple[float, float]
    v_hat: float
    tilt: float = 0.0
    cutoff: float = 3e-6

    def __post_init__(self):
        object.__setattr__(self, "span", tuple(float(v) for v in self.span))
        _interval(self, "span")
        if not (math.isfinite(self.v_hat) and self.v_hat >= 0):
            raise ScenarioError("v_hat", f"must be a non-negative speed in m/s (got {self.v_hat!r})")
        if not abs(self.tilt) < math.pi / 2:
            raise ScenarioError("tilt", f"must lie in (-pi/2, pi/2) so the flow enters (got {self.tilt!r})")
        if not (0 <= self.cutoff <= (self.span[1] - self.span[0]) / 2 * (1 + 1e-9)):
            raise ScenarioError("cutoff", "must lie in [0, half the inlet width]")


@dataclass(frozen=True)
class Outlet:
    """A do-nothing outflow boundary {length} x (low, high)."""

    name: str
    span: tuple[float, float]

    def __post_init__(self):
        object.__setattr__(self, "span", tuple(float(v) for v in self.span))
        _interval(self, "span")


@dataclass(frozen=True)
class SawWindow:
    """The boundary (low, high) x {0} through which the SAW acts; ``cutoff`` as for inlets."""

    span: tuple[float, float] = (135e-6, 165e-6)
    cutoff: float = 3e-6

    def __post_init__(self):
        object.__setattr__(self, "span", tuple(float(v) for v in self.span))
        _interval(self, "span")
        if not (0 <= self.cutoff <= (self.span[1] - self.span[0]) / 2 * (1 + 1e-9)):
            raise ScenarioError("cutoff", "must lie in [0, half the window width]")


def _paper_inlets():
    tilt = math.pi / 6
    return (
        Inlet("inlet1", (30e-6, 80e-6), 5.0e-2, +tilt),
        Inlet("inlet2", (100e-6, 130e-6), 1.0e-2, 0.0),
        Inlet("inlet3", (150e-6, 200e-6), 10.0e-2, -tilt),
    )


def _paper_outlets():
    return (Outlet("lower", (20e-6, 100e-6)), Outlet("upper", (120e-6, 200e-6)))


@dataclass(frozen=True)
class Channel:
    """The rectangle (0, length) x (0, height) with inlets on x = 0 and outlets on x = length.

    ``profile_reading`` says how to read the paper's profile formula: ``paper`` measures lengths in
    units of 10 um (docs/physics.md, "Inflow length unit"), ``peak`` takes v_hat as the peak speed of the
    parabola.
    ``injection_inlet`` names the inlet cells enter through.
    """

    length: float = 300e-6
    height: float = 220e-6
    inlets: tuple[Inlet, ...] = field(default_factory=_paper_inlets)
    outlets: tuple[Outlet, ...] = field(default_factory=_paper_outlets)
    saw_window: SawWindow = field(default_factory=SawWindow)
    profile_reading: str = "paper"
    injection_inlet: str = "inlet2"

    def __post_init__(self):
        _positive(self, "length", "height")
        _choice(self, "profile_reading", PROFILE_READINGS)
        object.__setattr__(self, "inlets", tuple(self.inlets))
        object.__setattr__(self, "outlets", tuple(self.outlets))
        if not self.inlets:
            raise ScenarioError("inlets", "at least one inlet is needed")
        if len(self.outlets) < 1:
            raise ScenarioError("outlets", "at least one outlet is needed")
        self._check_spans("inlets", self.inlets, self.height)
        self._check_spans("outlets", self.outlets, self.height)
        low, high = self.saw_window.span
        if low <= 0 or high >= self.length:
            raise ScenarioError("saw_window.span", f"must lie inside the lower wall (0, {self.length:g}) m")
        if self.injection_inlet not in [inlet.name for inlet in self.inlets]:
            raise ScenarioError("injection_inlet", f"names no inlet (got {self.injection_inlet!r})")

    @staticmethod
    def _check_spans(kind, boundaries, height):
        names = [b.name for b in boundaries]
        if len(set(names)) != len(names):
            raise ScenarioError(kind, f"names must be unique (got {names})")
        for index, boundary in enumerate(boundaries):
            low, high = boundary.span
            if low < 0 or high > height:
                raise ScenarioError(f"{kind}[{index}].span",
                                    f"{boundary.name!r} ({low:g}, {high:g}) m lies outside the wall (0, {height:g}) m")
        ordered = sorted(boundaries, key=lambda b: b.span[0])
        for first, second in zip(ordered, ordered[1:]):
            if second.span[0] < first.span[1]:
                raise ScenarioError(kind, f"{first.name!r} and {second.name!r} overlap")

    def inlet(self, name: str) -> Inlet:
        return next(inlet for inlet in self.inlets if inlet.name == name)

    def breakpoints_y(self) -> list[float]:
        """Ordinates the mesh must contain so inlets and outlets begin and end at vertices."""
        points = {0.0, self.height}
        for boundary in self.inlets + self.outlets:
            points.update(boundary.span)
        return sorted(points)


@dataclass(frozen=True)
class Fluid:
    """A Newtonian fluid, the same inside and outside the cells (paper section 4)."""

    density: float = 1.0e3
    viscosity: float = 6.0e-3

    def __post_init__(self):
        _positive(self, "density", "viscosity")


@dataclass(frozen=True)
class Saw:
    """The surface acoustic wave actuation (docs/physics.md, "SAW models").

    ``paper``: the jet v_2 = 2 pi a f m(x) on the window while the IDT is on: the amplitude of the paper's
    100 MHz wall velocity, never its phase at a step time (the paper's computation at its steps);
    ``envelope``: another name of the same jet;
    ``streaming``: a time-averaged body force ``streaming_force`` * m(x) * exp(-y / attenuation_length)
    (N/m^3, directed into the channel) that follows the IDT through a first-order lag ``spin_up_time``.
    """

    model: str = "paper"
    amplitude: float = 1.0e-9
    frequency: float = 100.0e6
    streaming_force: float = 5.7e7
    attenuation_length: float = 60e-6
    spin_up_time: float = 0.2e-3

    def __post_init__(self):
        _choice(self, "model", SAW_MODELS)
        _positive(self, "amplitude", "frequency", "attenuation_length")
        if not (math.isfinite(self.streaming_force) and self.streaming_force >= 0):
            raise ScenarioError("streaming_force",
                                f"must be a non-negative force density (got {self.streaming_force!r})")
        if not (math.isfinite(self.spin_up_time) and self.spin_up_time >= 0):
            raise ScenarioError("spin_up_time", f"must be >= 0 s (got {self.spin_up_time!r})")

    @property
    def jet_speed(self) -> float:
        """Peak normal speed 2 pi a f of the Dirichlet models (0.628 m/s with the paper's values)."""
        return 2 * math.pi * self.amplitude * self.frequency


@dataclass(frozen=True)
class Numerics:
    """Discretisation: mesh size, time step, convection treatment, linear solver, start state.

    ``mesh_h`` is the target edge length of the right-isosceles triangulation; the paper's 10/3 um
    gives 90 x 66 squares and 54,243 Taylor-Hood DOFs. ``membrane_spacing`` is the initial distance of
    membrane points in units of ``mesh_h``; ``max_area_change`` the relative change of a cell's enclosed
    area at which the health checks stop a run. ``reproducible`` keeps runs bit-for-bit identical (the
    back-solve's substitutions run sequentially); False lets them run in parallel: faster, but the last
    bits of the results then vary from run to run. ``precision`` is that of the constant fluid matrix's
    factorisation: ``mixed`` (PARDISO's single-precision factors and back-solves, each step refined in
    double precision from the last step's solution: within ~5e-7 of the double-precision solve, ~10 %
    faster a step; docs/numerics.md) or ``double``; other solvers always use double.

    Cells keeping their size (docs/numerics.md, "Cells that keep their size"): ``area_constraint`` is ``none`` (the
    paper's literal method, which leaks area), ``pressure`` (an interior pressure, the Lagrange multiplier
    of the area constraint, balances the membrane force's area-changing part), ``multiplier`` (each cell's
    interior pressure is solved with the fluid so that the step keeps its area: ``sim.method.multiplier``; imex or
    stokes convection), ``projection`` (after each step the membrane moves along its normal to restore the
    area) or a combination joined by ``+`` in that order. ``redistribute`` re-spaces a
    membrane's points equally along its spline, ``membrane_spacing`` apart, whenever a spacing leaves
    ``spacing_band`` (both in units of ``mesh_h``).

    ``tolerance`` > 0 (m) lets the FE-IB plant pick each step from the levels dt, 2 dt, 4 dt, 8 dt (a cell type's
    stability cap between them; 16 dt for cells far from it: ``sim.method.adaptive.level_multiples``) by an
    error estimate on the membrane positions, for at most that centroid path error per transit
    (``sim.method.adaptive``); 0 keeps the fixed step dt.

    ``time_scheme`` is the FE-IB step's time discretisation: ``euler`` (the paper's first-order step:
    backward Euler for the fluid, the membrane force at the old positions, the membrane moved by the new
    velocity), ``bdf2`` (second order: BDF2 for the fluid and the membrane, the force at the positions
    extrapolated to the new time, the convection extrapolated; docs/numerics.md, "A second-order step") or
    ``auto`` (the default: ``bdf2`` with a ``tolerance``, ``euler`` with fixed steps; ``bdf2`` needs the
    convection treatment imex or stokes).

    ``membrane_coupling`` is how the membrane force enters the step: ``explicit`` (the paper's: the force of the old
    positions; each cell has a largest stable dt, ``sim.steplimit``) or ``implicit`` (the force of the new positions,
    through a small system per cell and one more back-solve a step: stable at far larger steps; ``sim.method.coupling``,
    docs/numerics.md "The membrane coupling"); implicit needs the convection treatment imex or stokes.

    ``max_stretch`` is the operational meaning of the paper's Remark 2.4 ("membranes torn apart"): a
    membrane whose length exceeds ``max_stretch`` times its resting length L is torn apart and the health
    checks stop the run saying the flow is too fast for it. The paper's energy has no rupture law, so
    this is a stand-in; the default 20 lies above every stretch the paper's scenarios and IDT pulses
    produce (at most 5.3 and 8.3 at the paper's mesh, 10 for an under-resolved RBC on the 6.67 um mesh of
    ``vcyto tradeoff --fast``; docs/results.md "Stability at the extremes").
    """

    mesh_h: float = 10e-6 / 3
    dt: float = 2.5e-6
    convection: str = "imex"
    linear_solver: str = "auto"
    initial_flow: str = "steady"
    nonlinear_tolerance: float = 1e-10
    max_nonlinear_iterations: int = 30
    membrane_spacing: float = 0.5
    max_area_change: float = 0.75
    reproducible: bool = True
    precision: str = "mixed"
    area_constraint: str = "pressure+projection"
    redistribute: bool = True
    spacing_band: tuple[float, float] = (0.3, 0.7)
    max_stretch: float = 20.0
    tolerance: float = 0.0
    time_scheme: str = "auto"
    membrane_coupling: str = "explicit"

    def __post_init__(self):
        _positive(self, "mesh_h", "dt", "nonlinear_tolerance", "membrane_spacing", "max_area_change")
        if isinstance(self.tolerance, bool) or not (isinstance(self.tolerance, (int, float))
                                                    and math.isfinite(self.tolerance) and self.tolerance >= 0):
            raise ScenarioError("tolerance", f"must be a length >= 0: the path error per transit that picks the "
                                             f"time step (0: the fixed step dt), e.g. 1um (got {self.tolerance!r})")
        if isinstance(self.max_stretch, bool) or not (isinstance(self.max_stretch, (int, float))
                                                      and math.isfinite(self.max_stretch) and self.max_stretch > 1):
            raise ScenarioError("max_stretch", f"must be a number > 1: the membrane length, in resting lengths, at "
                                               f"which a membrane counts as torn apart (got {self.max_stretch!r})")
        _choice(self, "area_constraint", AREA_CONSTRAINTS)
        if not isinstance(self.redistribute, bool):
            raise ScenarioError("redistribute", f"must be true or false (got {self.redistribute!r})")
        object.__setattr__(self, "spacing_band", tuple(float(v) for v in self.spacing_band))
        low, high = self.spacing_band if len(self.spacing_band) == 2 else (math.nan, math.nan)
        if not (0 < low < self.membrane_spacing < high):
            raise ScenarioError("spacing_band", f"must be two numbers low < membrane_spacing ({self.membrane_spacing}) "
                                                f"< high, in units of mesh_h (got {self.spacing_band!r})")
        _choice(self, "convection", CONVECTIONS)
        _choice(self, "linear_solver", LINEAR_SOLVERS)
        _choice(self, "precision", PRECISIONS)
        _choice(self, "initial_flow", INITIAL_FLOWS)
        _choice(self, "time_scheme", TIME_SCHEMES)
        _choice(self, "membrane_coupling", COUPLINGS)
        if self.membrane_coupling == "implicit" and self.convection not in ("imex", "stokes"):
            raise ScenarioError("membrane_coupling", f"implicit needs the convection treatment imex or stokes (got "
                                                     f"convection {self.convection!r}); use membrane_coupling = "
                                                     f"\"explicit\" with it")
        if "multiplier" in self.area_constraint and self.convection not in ("imex", "stokes"):
            raise ScenarioError("area_constraint", f"the multiplier needs the convection treatment imex or stokes (got "
                                                   f"convection {self.convection!r}); drop \"multiplier\" with it")
        if "multiplier" in self.area_constraint and self.membrane_coupling == "implicit":
            raise ScenarioError("area_constraint", "the multiplier keeps the area of the explicit coupling's step: "
                                                   "with membrane_coupling = \"implicit\" drop \"multiplier\" (or "
                                                   "take the explicit coupling)")
        if self.scheme == "bdf2" and self.convection not in ("imex", "stokes"):
            raise ScenarioError("time_scheme", f"bdf2 needs the convection treatment imex or stokes (got convection "
                                               f"{self.convection!r}); use time_scheme = \"euler\" with it")
        if not isinstance(self.reproducible, bool):
            raise ScenarioError("reproducible", f"must be true or false (got {self.reproducible!r})")
        if not (isinstance(self.max_nonlinear_iterations, int) and self.max_nonlinear_iterations >= 1):
            raise ScenarioError("max_nonlinear_iterations", "must be an integer >= 1")

    @property
    def scheme(self) -> str:
        """The time scheme the FE-IB step uses: ``time_scheme``, with ``auto`` resolved (bdf2 with a tolerance and
        a constant matrix, i.e. convection imex or stokes; euler otherwise)."""
        if self.time_scheme != "auto":
            return self.time_scheme
        return "bdf2" if self.tolerance > 0 and self.convection in ("imex", "stokes") else "euler"


@dataclass(frozen=True)
class CellType:
    """A kind of cell: membrane moduli (kappa_e N/m, kappa_b N m), initial shape, optical signature and sort class.

    The shape is an ellipse with semi-axes (along x, along y); equal axes give a circle. ``target``: whether the
    sorter should send this type to the sorted (upper) outlet (true class II, e.g. a labelled melanoma cell) or
    let it pass to the default (lower) one (class I). The detector sees only ``fluorescence``, so a target type
    needs a brightness above the detector's gate to be found.
    """

    name: str
    kappa_e: float
    kappa_b: float
    semi_axes: tuple[float, float]
    fluorescence: float = 0.0
    target: bool = False

    def __post_init__(self):
        object.__setattr__(self, "semi_axes", tuple(float(v) for v in self.semi_axes))
        _positive(self, "kappa_e")
        if not (math.isfinite(self.fluorescence) and self.fluorescence >= 0):
            raise ScenarioError("fluorescence", f"must be a finite brightness >= 0 (got {self.fluorescence!r})")
        if not isinstance(self.target, bool):
            raise ScenarioError("target", f"must be true or false (got {self.target!r})")
        if not (math.isfinite(self.kappa_b) and self.kappa_b >= 0):
            raise ScenarioError("kappa_b", f"must be >= 0 (got {self.kappa_b!r})")
        if len(self.semi_axes) != 2 or not all(math.isfinite(v) and v > 0 for v in self.semi_axes):
            raise ScenarioError("semi_axes", f"must be two positive lengths (got {self.semi_axes!r})")

    @property
    def perimeter(self) -> float:
        a, b = self.semi_axes
        h = ((a - b) / (a + b)) ** 2
        terms = 1 + h / 4 + h**2 / 64 + h**3 / 256 + 25 * h**4 / 16384 + 49 * h**5 / 65536
        return math.pi * (a + b) * terms

    @property
    def diameter(self) -> float:
        return 2 * max(self.semi_axes)

    @property
    def area(self) -> float:
        return math.pi * self.semi_axes[0] * self.semi_axes[1]


# The RBC is an ellipse of diameter 7.5 um and perimeter 19.8 um, semi-axes 3.75, 2.5 um (docs/physics.md, "RBC shape")
RBC = CellType("RBC", kappa_e=6.0e-6, kappa_b=2.0e-19, semi_axes=(3.75e-6, 2.5e-6), fluorescence=0.0)
MELANOMA = CellType("melanoma", kappa_e=2.8e-4, kappa_b=1.2e-16, semi_axes=(8.0e-6, 8.0e-6), fluorescence=1.0,
                    target=True)


# the cells across the narrowest inlet or outlet below which the profile is not resolved
MIN_CELLS_ACROSS = 2


@dataclass(frozen=True)
class Scenario:
    """Everything the plant needs to know, in SI units."""

    channel: Channel = field(default_factory=Channel)
    fluid: Fluid = field(default_factory=Fluid)
    saw: Saw = field(default_factory=Saw)
    numerics: Numerics = field(default_factory=Numerics)
    cell_types: tuple[CellType, ...] = (RBC, MELANOMA)

    def __post_init__(self):
        object.__setattr__(self, "cell_types", tuple(self.cell_types))
        if not self.cell_types:
            raise ScenarioError("cell_types", "at least one cell type is needed (omit cell_types for the paper's "
                                              "RBC and melanoma)")
        names = [cell.name for cell in self.cell_types]
        if not names:
            raise ScenarioError("cell_types",
                                "needs at least one [[cell_types]] entry (or none at all for the defaults)")
        if len(set(names)) != len(names):
            raise ScenarioError("cell_types", f"names must be unique (got {names})")
        narrowest = min(self.channel.inlets + self.channel.outlets, key=lambda b: b.span[1] - b.span[0])
        width = narrowest.span[1] - narrowest.span[0]
        if self.numerics.mesh_h > width / MIN_CELLS_ACROSS * (1 + 1e-9):
            raise ScenarioError(
                "numerics.mesh_h",
                f"{self.numerics.mesh_h / UM:.3g} um does not resolve {narrowest.name!r} ({width / UM:.3g} um wide): "
                f"use mesh_h <= {width / MIN_CELLS_ACROSS / UM:.3g} um")
        window = self.channel.saw_window.span
        if self.numerics.mesh_h > (window[1] - window[0]) / MIN_CELLS_ACROSS * (1 + 1e-9):
            raise ScenarioError("numerics.mesh_h", "does not resolve the SAW window: use a finer mesh")

    def cell_type(self, name: str) -> CellType:
        for cell in self.cell_types:
            if cell.name == name:
                return cell
        raise ScenarioError("cells", f"unknown cell type {name!r}; known: {', '.join(c.name for c in self.cell_types)}")

    def with_numerics(self, **changes) -> "Scenario":
        return replace(self, numerics=replace(self.numerics, **changes))

    def with_inlets_shut(self) -> "Scenario":
        """The device with every inlet's speed set to zero: fluid at rest unless a membrane moves it."""
        inlets = tuple(replace(inlet, v_hat=0.0) for inlet in self.channel.inlets)
        return replace(self, channel=replace(self.channel, inlets=inlets))

    def with_membrane(self, method: str) -> "Scenario":
        """The scenario with the membrane method ``paper`` (literal, leaks), ``conserving`` (keeps area) or
        ``multiplier`` (conserving, with the area kept by the step itself: ``sim.method.multiplier``)."""
        if method not in MEMBRANE_METHODS:
            raise ScenarioError("membrane", f"must be one of {', '.join(MEMBRANE_METHODS)} (got {method!r})")
        return self.with_numerics(**MEMBRANE_METHODS[method])

    def membrane_method(self) -> str:
        """``paper``, ``conserving`` or ``custom`` (any other combination of the fields)."""
        chosen = {"area_constraint": self.numerics.area_constraint, "redistribute": self.numerics.redistribute}
        return next((name for name, fields in MEMBRANE_METHODS.items() if fields == chosen), "custom")

    def with_saw(self, **changes) -> "Scenario":
        return replace(self, saw=replace(self.saw, **changes))


def as_dict(obj):
    """A plain-data view (dicts, lists, numbers, strings) of a scenario or any of its parts."""
    if is_dataclass(obj):
        return {f.name: as_dict(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [as_dict(item) for item in obj]
    return obj
