"""Cell membranes: closed periodic cubic splines with the paper's elastic and bending energy (section 3.1).

A membrane is R material points X_r at uniformly spaced reference arc lengths q_r = r dq, dq = L / R, with
L the perimeter of the initial shape. X_h(q) is the periodic cubic spline through them. The discrete
energy is

    E_h = kappa_e / 2 * integral_0^L (|X_q|^2 - 1) dq + kappa_b / 2 * integral_0^L |X_qq|^2 dq,

a quadratic form in the points because the spline is linear in them: E_h = 1/2 sum_c X_c^T S X_c - kappa_e L / 2
with S = kappa_e K_1 + kappa_b K_2 (R x R, symmetric, circulant). The membrane force on point r is
f_r = -dE_h / dX_r = -(S X)_r. Spread as point forces, <F_h, w> = sum_r f_r . w(X_r), this is the paper's (25)
with w(X_h(q)) replaced by the spline through the values w(X_r): exactly the identification its stability
proof makes in (37) (there D+ X_q stands for d/dq v(X(q))), so the coupled scheme has the discrete power
identity <F_h, v> = -dE_h/dt of the semi-discrete problem.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ..model.scenario import CellType

# 3-point Gauss-Legendre on [0, 1]: exact to degree 5 (|X_q|^2 is degree 4, |X_qq|^2 degree 2)
_GAUSS_T = 0.5 + 0.5 * np.array([-math.sqrt(3 / 5), 0.0, math.sqrt(3 / 5)])
_GAUSS_W = np.array([5 / 18, 8 / 18, 5 / 18])


@lru_cache(maxsize=64)
def _second_derivative_operator(points: int) -> np.ndarray:
    """D2 (R x R) with M = D2 X / dq^2: the spline's nodal second derivatives (uniform knots, periodic).

    The periodic spline conditions read M_{r-1} + 4 M_r + M_{r+1} = 6 (X_{r+1} - 2 X_r + X_{r-1}) / dq^2.
    """
    identity = np.eye(points)
    shift_up, shift_down = np.roll(identity, 1, axis=1), np.roll(identity, -1, axis=1)
    tridiagonal = 4 * identity + shift_up + shift_down
    return 6 * np.linalg.solve(tridiagonal, shift_up - 2 * identity + shift_down)


@lru_cache(maxsize=256)
def _segment_basis(t, points, derivative):
    """Matrix (R, R) giving the ``derivative``-th q-derivative at parameter t in [0, 1] of each interval,
    times dq^derivative, as a linear map of the points (interval r runs from point r to point r + 1)."""
    identity = np.eye(points)
    nxt = np.roll(identity, -1, axis=0)           # row r picks point r + 1
    second = _second_derivative_operator(points)  # M dq^2
    second_next = np.roll(second, -1, axis=0)
    # X(t) = (1-t) X_r + t X_{r+1} + dq^2 [((1-t)^3 - (1-t)) M_r + (t^3 - t) M_{r+1}] / 6
    if derivative == 0:
        return (1 - t) * identity + t * nxt + (((1 - t) ** 3 - (1 - t)) * second + (t**3 - t) * second_next) / 6
    if derivative == 1:
        return (nxt - identity) + ((1 - 3 * (1 - t) ** 2) * second + (3 * t**2 - 1) * second_next) / 6
    if derivative == 2:
        return (1 - t) * second + t * second_next
    if derivative == 3:
        return second_next - second
    raise ValueError(f"derivative must be 0..3 (got {derivative})")


@lru_cache(maxsize=64)
def _energy_matrices(points: int):
    """K1, K2 (R x R, for dq = 1): int |X_q|^2 dq = dq^-1 X^T K1 X and int |X_qq|^2 dq = dq^-3 X^T K2 X."""
    k1 = np.zeros((points, points))
    k2 = np.zeros((points, points))
    for t, w in zip(_GAUSS_T, _GAUSS_W):
        first = _segment_basis(t, points, 1)
        second = _segment_basis(t, points, 2)
        k1 += w * first.T @ first
        k2 += w * second.T @ second
    return k1, k2


def ellipse_by_arc_length(a: float, b: float, points: int, centre=(0.0, 0.0)) -> np.ndarray:
    """``points`` points on an ellipse (semi-axes a along x, b along y) equally spaced in arc length."""
    fine = np.linspace(0, 2 * np.pi, 20 * points + 1)
    speed = np.hypot(a * np.sin(fine), b * np.cos(fine))
    arc = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(fine))])
    targets = np.arange(points) * arc[-1] / points
    angles = np.interp(targets, arc, fine)
    return np.column_stack([centre[0] + a * np.cos(angles), centre[1] + b * np.sin(angles)])


@lru_cache(maxsize=64)
def _area_matrix(points: int) -> np.ndarray:
    """A (R x R, antisymmetric) with area = x^T A y for the spline through (x, y): 1/2 closed integral of
    x y_q - y x_q, exact by Gauss quadrature (the integrand is a degree-5 polynomial per interval)."""
    pair = np.zeros((points, points))
    for t, w in zip(_GAUSS_T, _GAUSS_W):
        pair += w * _segment_basis(t, points, 0).T @ _segment_basis(t, points, 1)
    return 0.5 * (pair - pair.T)


@lru_cache(maxsize=64)
def _perimeter_rows(points: int):
    return tuple((w, _segment_basis(t, points, 1)) for t, w in zip(_GAUSS_T, _GAUSS_W))


def spline_at(points: np.ndarray, interval: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The periodic cubic spline through ``points`` (uniform knots) at parameter t in [0, 1] of ``interval``."""
    count = len(points)
    second = _second_derivative_operator(count) @ points          # M dq^2
    nxt = (interval + 1) % count
    s, u = t[:, None], 1 - t[:, None]
    return (u * points[interval] + s * points[nxt]
            + ((u**3 - u) * second[interval] + (s**3 - s) * second[nxt]) / 6)


class Membrane:
    """A closed membrane: material points (R, 2), reference length L and the moduli of its cell type.

    ``initial_area`` is the area the cell was born with (the target of the area constraints, kept
    through redistribution); ``redistributions`` counts how often its points were redistributed.
    """

    def __init__(self, points: np.ndarray, cell_type: CellType, reference_length: float | None = None):
        points = np.asarray(points, dtype=float)
        if points.ndim != 2 or points.shape[1] != 2 or len(points) < 4:
            raise ValueError("a membrane needs at least 4 points as an (R, 2) array")
        self.cell_type = cell_type
        self.count = len(points)
        self.reference_length = float(reference_length) if reference_length else polygon_perimeter(points)
        self.dq = self.reference_length / self.count
        k1, k2 = _energy_matrices(self.count)
        self.stiffness = cell_type.kappa_e * k1 / self.dq + cell_type.kappa_b * k2 / self.dq**3
        self._area_matrix = _area_matrix(self.count)
        self.points = points
        self.initial_area = self.area()
        self.redistributions = 0

    @classmethod
    def of(cls, cell_type: CellType, centre, spacing: float, minimum_points: int = 16) -> "Membrane":
        """The initial shape of ``cell_type`` at ``centre`` with material points about ``spacing`` apart."""
        count = max(minimum_points, math.ceil(cell_type.perimeter / spacing))
        points = ellipse_by_arc_length(*cell_type.semi_axes, count, centre)
        return cls(points, cell_type, reference_length=cell_type.perimeter)

    def forces(self, points: np.ndarray | None = None) -> np.ndarray:
        """f_r = -dE_h/dX_r (R, 2) in newtons."""
        return -self.stiffness @ (self.points if points is None else points)

    def energy(self, points: np.ndarray | None = None) -> float:
        x = self.points if points is None else points
        return 0.5 * float(np.sum(x * (self.stiffness @ x))) - 0.5 * self.cell_type.kappa_e * self.reference_length

    def evaluate(self, samples_per_interval: int = 8, derivative: int = 0) -> np.ndarray:
        """The spline (or its q-derivative) at ``samples_per_interval`` points per interval, (R * s, 2)."""
        rows = []
        for t in np.arange(samples_per_interval) / samples_per_interval:
            rows.append(_segment_basis(t, self.count, derivative) @ self.points / self.dq**derivative)
        return np.stack(rows, axis=1).reshape(-1, 2)

    def area(self, points: np.ndarray | None = None) -> float:
        """Area enclosed by the spline (1/2 closed integral of x y_q - y x_q), exact."""
        x = self.points if points is None else points
        return float(x[:, 0] @ self._area_matrix @ x[:, 1])

    def area_gradient(self) -> np.ndarray:
        """dA/dX_r (R, 2): the outward normal times the arc length each point carries."""
        return np.column_stack([self._area_matrix @ self.points[:, 1], -self._area_matrix @ self.points[:, 0]])

    def perimeter(self) -> float:
        return float(self.spacing().sum())

    def spacing(self) -> np.ndarray:
        """Arc length of the spline between neighbouring material points (R,), by 3-point Gauss quadrature.

        Measured along the membrane, not as chords: across the tip of a stretched filament thinner than the
        spacing, neighbouring points are closer as the crow flies than along the membrane.
        """
        total = np.zeros(self.count)
        for w, first in _perimeter_rows(self.count):
            xq = first @ self.points
            total += w * np.hypot(xq[:, 0], xq[:, 1])
        return total

    def centroid(self) -> np.ndarray:
        """Centroid of the enclosed region of the material-point polygon."""
        return polygon_centroid(self.points)

    def with_points(self, points: np.ndarray) -> "Membrane":
        clone = object.__new__(Membrane)
        clone.__dict__.update(self.__dict__)
        clone.points = points
        return clone

    # ------------------------------------------------------------------ area conservation
    def pressure_balanced(self, forces: np.ndarray) -> tuple[np.ndarray, float]:
        """The forces plus an interior pressure p dA/dX that removes their component along dA/dX.

        p = -(f . g) / (g . g) with g = dA/dX: the Lagrange multiplier of the area constraint for forces
        that act through a mobility proportional to the identity. The balanced forces do no work on the
        enclosed area (their power on a uniform dilation is zero); the returned p (Pa) is the pressure
        jump the membrane itself carries, which a continuous pressure space cannot represent.
        """
        gradient = self.area_gradient()
        pressure = -float(np.sum(forces * gradient)) / float(np.sum(gradient * gradient))
        return forces + pressure * gradient, pressure

    def with_area(self, target: float) -> "Membrane":
        """The membrane moved along dA/dX (the normal) by the one displacement that restores ``target``.

        The area is a quadratic form, so A(X + s g) = A + s g.g' + s^2 A(g) and s is a root of a quadratic.
        """
        gradient = self.area_gradient()
        a, b, c = self.area(gradient), float(np.sum(gradient * gradient)), self.area() - target
        step = -2 * c / (b + math.sqrt(max(b * b - 4 * a * c, 0.0)))      # the root nearest zero, stably
        return self.with_points(self.points + step * gradient)

    def resampled(self, spacing: float, minimum_points: int = 16, passes: int = 4) -> "Membrane":
        """The same spline carried by points equally spaced in arc length about ``spacing`` apart.

        The reference length L (the material) is kept and shared equally: dq = L / R'. The stretching
        energy of a given shape is least when |X_q| is uniform, so the redistribution releases tangential
        stretch imbalance (the membrane material slides along itself) and never adds energy. Where the
        spline has a feature finer than ``spacing`` (the tip of a filament thinner than it), the new spline
        cannot follow it and its arc lengths differ from the old ones: then the resampling is repeated on
        the new spline (at most ``passes`` times) until every spacing is within 10 % of the mean.
        """
        return self.resampled_carrying(spacing, (), minimum_points, passes)[0]

    def resampled_carrying(self, spacing: float, carried: tuple = (), minimum_points: int = 16,
                           passes: int = 4) -> tuple["Membrane", tuple]:
        """``resampled``, and each of ``carried`` (point arrays matching this membrane's, such as its points at
        earlier steps) taken to the same spline parameters: its spline at the parameters of the new points."""
        membrane = self
        for _ in range(passes):
            membrane, whole, fraction = membrane._resampled_once(spacing, minimum_points)
            carried = tuple(spline_at(points, whole, fraction) for points in carried)
            lengths = membrane.spacing()
            if lengths.max() < 1.1 * lengths.mean() and lengths.min() > 0.9 * lengths.mean():
                break
        membrane.initial_area = self.initial_area
        membrane.redistributions = self.redistributions + 1
        return membrane, carried

    def _resampled_once(self, spacing: float, minimum_points: int):
        samples = 32
        interval = np.repeat(np.arange(self.count), samples)
        t = np.tile(np.arange(samples) / samples, self.count)
        dense = spline_at(self.points, interval, t)
        chords = np.hypot(*(np.roll(dense, -1, axis=0) - dense).T)
        arc = np.concatenate([[0.0], np.cumsum(chords)])
        count = max(minimum_points, math.ceil(arc[-1] / spacing))
        parameter = np.interp(np.arange(count) * arc[-1] / count, arc, np.arange(len(arc)) / samples)
        parameter = np.minimum(parameter, self.count - 1e-12)
        whole = np.floor(parameter).astype(int)
        fraction = parameter - whole
        return Membrane(spline_at(self.points, whole, fraction), self.cell_type, self.reference_length), whole, fraction


def polygon_perimeter(points: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)))


def polygon_centroid(points: np.ndarray) -> np.ndarray:
    following = np.concatenate([points[1:], points[:1]])
    cross = points[:, 0] * following[:, 1] - following[:, 0] * points[:, 1]
    area = 0.5 * cross.sum()
    if abs(area) < 1e-300:
        return points.mean(axis=0)
    return (cross @ (points + following)) / (6 * area)
