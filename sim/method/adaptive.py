"""Time steps chosen by a tolerance: each FE-IB step takes dt from the levels dt0, 2 dt0, 4 dt0, 8 dt0, per cell type
the largest multiple of dt0 within its stability cap where that lies between two of them, and 16 dt0 for cells
far from their stability limit (``level_multiples``).

``numerics.tolerance`` is a centroid path error per transit (m), against fixed steps of dt0 in the same time
scheme. With the second-order scheme (bdf2, the default with a tolerance) the local error of a cell's area
centroid is estimated by Milne's device: the difference between the centroid after the step and the parabola
through its last three values, times 2/11 (``_ratio_bdf2``); its rate per distance grows like dt^2. With the
paper's first-order step (``time_scheme = "euler"``) the membrane update X' = X + dt v^{m+1}(X) is first
order; its local error is estimated from what the step computes anyway:

    e = dt / 2 | mean_r ( [v^{m+1}(X_r) - v^m(X_r)] - [v^{m+1}(X_r + dt v^{m+1}(X_r)) - v^{m+1}(X_r)] ) |,

the difference between the update and a trapezoidal one (the flow's change in time at the points minus
its change along their motion), averaged over a cell's points inside the channel: the error of its
centroid, whose path the tolerance is about; the largest over the cells in the channel. Local errors add up along a
path, so a step is within budget when e <= SAFETY * tolerance * (distance the cell moved) / channel length:
a transit then accumulates at most about SAFETY * tolerance. The tolerance is stated against the finest
level (the reference dt0): since e / distance grows like dt^p (p the order), a ratio q measured at dt_k
predicts q (m_j^p - 1) / m_k^p for level j (dt_j = m_j dt0) against the finest one; the next step takes the
coarsest level (at most one up) where that is <= 1 (no step is repeated). A new cell, or a change of the IDT
drive (the flow jumps before any estimate has seen it), starts from the finest level; with no cell in the channel the
coarsest level is used. A step never ends after a redistribution of a cell's points that the trend of its
spacing predicts (``_before_redistribution``), and a coarser step that redistributes anyway is retaken at the
finest level: that event changes the membrane's forces at once, and only the finest level puts it where the
reference puts it.

Never above the stability limit of the cells in the channel: the law fitted to measured limits
(``sim.method.steplimit``: it lies at or below every measured limit, in the run's time scheme, on the run's mesh). A
cell type whose limit lies between two levels has its own level at the largest multiple of dt0 within it (the melanoma
at the paper's mesh with bdf2), so that it is held there, not at the power of two below. The coarse level (16 dt0)
follows an accuracy rule, not a stability one: only for cells whose membrane relaxes slowly against it
(``level_multiples``). Each level's fluid matrix is factored once, when first needed, on the same mesh. A finest
step dt0 above a cell type's limit is taken anyway (it is the step asked for) with a warning in the log.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from .fluid import NavierStokes
from .health import membrane_time_step
from .membrane import polygon_centroid
from .steplimit import limit_of
from .timeschemes import lagrange, scheme_named

logger = logging.getLogger(__name__)

LEVELS = 4                    # the powers of two: dt0, 2 dt0, 4 dt0, 8 dt0
COARSE = 16                   # and 16 dt0, for soft cells only (``level_multiples``)
COARSE_SHARE = 1 / 3          # the coarse level only within this share of every cell's membrane time scale
SAFETY = {1: 0.3, 2: 0.6}     # the share of the tolerance a transit's local errors may add up to, by the order
LOOK_AHEAD = 1.0              # steps of a level over which a predicted redistribution keeps that level out


class AdaptiveSteps:
    """The steps of an ``ImmersedBoundary`` plant with ``numerics.tolerance``: wraps its step (``step``), choosing the
    level, and so dt, of each and estimating its error."""

    def __init__(self, plant):
        self.plant = plant
        numerics = plant.scenario.numerics
        self.tolerance = numerics.tolerance
        self.multiples = level_multiples(plant.scenario)
        self.levels = [numerics.dt * m for m in self.multiples]
        self._fluids = {0: plant.fluid}
        self._limits: dict[str, float] = {}                   # cell type: its stability limit (``steplimit``)
        self._known: set[int] = set()
        self._actuation: float | None = None
        self.level = len(self.levels) - 1
        self.ratio = float("nan")
        self.history: list[tuple[float, float]] = []          # (time, dt) whenever dt changes
        self.steps = [0] * len(self.levels)
        self.order = scheme_named(numerics.scheme).order
        self._tracks: dict[int, list] = {}                    # bdf2: the last three (time, area centroid) per cell
        self._spacings: dict[int, list] = {}                  # the last two spacing extremes per cell
        self.retaken = 0                                      # coarse steps retaken at the finest level

    # ------------------------------------------------------------------ levels
    def fluid(self, level: int) -> NavierStokes:
        """The fluid solver of ``level`` (factored on first use, on the plant's mesh; timings shared)."""
        if level not in self._fluids:
            base = self.plant.fluid
            numerics = self.plant.scenario.numerics
            fluid = NavierStokes(self.plant.scenario.with_numerics(dt=self.levels[level], tolerance=0.0,
                                                                   time_scheme=numerics.scheme), like=base)
            base.timings.factor += fluid.timings.factor
            fluid.timings = base.timings
            self._fluids[level] = fluid
        return self._fluids[level]

    def stable_level(self, cells) -> int:
        """The coarsest level within every present cell type's stability limit (``sim.method.steplimit``); the coarse
        level (``COARSE`` dt0) only within ``COARSE_SHARE`` of every present membrane's time scale
        (``sim.method.health.membrane_time_step``, eta dq / kappa_e; ``level_multiples``)."""
        cap = soft = math.inf
        viscosity = self.plant.scenario.fluid.viscosity
        for cell in cells:
            cell_type = cell.membrane.cell_type
            if cell_type.name not in self._limits:
                self._limits[cell_type.name] = limit_of(cell_type, self.plant.scenario)
            cap = min(cap, self._limits[cell_type.name])
            soft = min(soft, COARSE_SHARE * membrane_time_step(cell.membrane, viscosity))
        return max([0] + [k for k, (multiple, dt) in enumerate(zip(self.multiples, self.levels))
                          if dt <= cap * (1 + 1e-9) and (multiple < COARSE or dt <= soft)])

    def choose(self, state, active, until, actuation: float | None = None) -> int:
        """The level of the next step: the estimate's; the finest for a new cell or when the IDT drive changes
        (the flow jumps: no estimate has seen it yet); capped by stability and ``until``."""
        ids = {cell.id for cell in active}
        switched = actuation is not None and self._actuation is not None and actuation != self._actuation
        if active and (ids - self._known or switched):
            self.level = 0           # and it stays there until an estimate lets it up (bdf2: after three steps)
        self._known, self._actuation = ids, actuation
        level = self._estimated_level(active, state.time)
        if until is not None:
            room = until - state.time
            while level > 0 and self.levels[level] > room + 1e-6 * self.levels[0]:
                level -= 1
        return level

    def _estimated_level(self, active, time: float) -> int:
        """The estimate's level (the coarsest with nobody in the channel) capped by stability and by a predicted
        redistribution: ``choose``'s level but for a new cell, a changed drive and the end of a control period."""
        level = len(self.levels) - 1 if not active else self.level
        return min(level, self.stable_level(active), self._before_redistribution(active, time))

    def _before_redistribution(self, active, time: float) -> int:
        """The coarsest level whose step ends before any cell's point spacing is predicted to leave the band
        (``numerics.spacing_band``: the redistribution it triggers changes the membrane's forces at once, so
        its time must be the finest level's, as in the reference; a step that ends later would move it by up
        to that step). The prediction follows the line through the spacings' last two values, over ``LOOK_AHEAD``
        steps; a coarser step it misses is retaken at the finest level (``step``)."""
        numerics = self.plant.scenario.numerics
        if not numerics.redistribute:
            return len(self.levels) - 1
        low, high = numerics.spacing_band
        level = len(self.levels) - 1
        for cell in active:
            trend = self._spacings.get(cell.id)
            if trend is None or len(trend) < 2:
                continue
            (t0, low0, high0, _), (t1, low1, high1, _) = trend
            if t1 <= t0:
                continue
            for k in range(level, 0, -1):
                ahead = LOOK_AHEAD * self.levels[k] / (t1 - t0)
                if low1 + (low1 - low0) * ahead >= low and high1 + (high1 - high0) * ahead <= high:
                    break
                level = k - 1
        return level

    def _track_spacing(self, cells, time: float):
        """The last two (time, spacing min, max, redistributions) of each cell in the channel (a redistribution
        starts its trend again)."""
        tracks = {}
        for cell in cells:
            if not cell.in_channel:
                continue
            measures = cell.measures
            entry = (time, measures.spacing_min, measures.spacing_max, cell.membrane.redistributions)
            trend = [e for e in self._spacings.get(cell.id, []) if e[3] == entry[3]]
            tracks[cell.id] = (trend + [entry])[-2:]
        self._spacings = tracks

    # ------------------------------------------------------------------ the step
    def step(self, state, actuation: float = 0.0, until: float | None = None):
        """One step of the level ``choose`` picks. A step above the finest in which a cell's points were
        redistributed is retaken at the finest level (states are values: the first is dropped), so every
        redistribution happens at the end of a finest-level step, as in the reference."""
        active = [cell for cell in state.cells if cell.in_channel]
        level = self.choose(state, active, until, actuation)
        samples = [self._sample(state.flow.velocity, cell.membrane.points) for cell in active] \
            if self.order == 1 else None
        # the next step's momentum integrals start as the flow is known, at the level the estimate now gives
        # (``_prefetch`` starts them again in the rare case the step's own estimate changes that level)
        ahead = self._fluids.get(self._estimated_level(active, state.time), False)
        new = self.plant.step(state, actuation, self.levels[level], self.fluid(level), ahead=ahead)
        if level > 0 and _redistributed(active, new):
            self.retaken += 1
            level = 0
            new = self.plant.step(state, actuation, self.levels[level], self.fluid(level), ahead=ahead)
        dt = self.levels[level]
        if self.order == 2:
            ids = {cell.id for cell in active}
            ratios = [self._ratio_bdf2(cell, new.time) for cell in new.cells if cell.id in ids]
        else:
            ratios = [self._ratio(sample, new.flow.velocity, dt) for sample in samples]
        known = [ratio for ratio in ratios if ratio is not None]
        if known:
            self.ratio = max(known)
            next_level = self._next_level(level, self.ratio, ceiling=max(level + 1, self.level))
            # a cell without an estimate (new, or just redistributed) holds the level: no step up for it
            self.level = next_level if len(known) == len(ratios) else min(next_level, self.level)
        self._track_spacing(new.cells, new.time)
        if not self.history or self.history[-1][1] != dt:
            self.history.append((state.time, dt))
        self.steps[level] += 1
        self._prefetch(new, ahead)
        return new

    def _prefetch(self, state, started):
        """Start the next step's momentum integrals (``NavierStokes.prefetch``) at the level ``choose`` will most
        likely pick (all it knows now: not the end of a control period, nor a new cell or a changed drive), when
        that level's solver exists and is not ``started``'s (the solver the step already started them on)."""
        level = self._estimated_level([cell for cell in state.cells if cell.in_channel], state.time)
        if level in self._fluids and self._fluids[level] is not started:
            self._fluids[level].prefetch(state.flow)

    def _next_level(self, level: int, ratio: float, ceiling: int | None = None) -> int:
        """The coarsest level up to ``ceiling`` (default: one above ``level``, the level the step took) whose
        error relative to the finest level's is within budget. A step held below the estimate's level (by a
        predicted redistribution, the end of a control period or the stability cap) may go back to it at once.

        The error rate grows like dt^p: ``ratio`` measured at dt_k = m_k dt0 predicts
        ratio / m_k^p (m_j^p - 1) for level j against the finest level (the reference the tolerance is
        stated against)."""
        if not math.isfinite(ratio):
            return 0
        ceiling = min(len(self.levels) - 1, level + 1 if ceiling is None else ceiling)
        growth = [m ** self.order for m in self.multiples]   # the error rate per distance grows like dt^order
        rate = ratio / growth[level]
        fitting = [j for j in range(ceiling + 1) if rate * (growth[j] - 1) <= 1]
        return max(fitting)

    def _ratio_bdf2(self, cell, time: float) -> float:
        """bdf2: the local error of a cell's centroid over its budget for the step (Milne's device).

        The area centroid is extrapolated to the new time by the parabola through its last three values; for
        equal steps BDF2's local error is -2/9 dt^3 c^(3) and the parabola's dt^3 c^(3), so the error is 2/11 of
        their difference (for unequal steps, of the parabola's error at the step's nodes, see ``_milne``). A cell
        gives no estimate (None: the level goes no higher; a new cell starts at the finest) until it has three
        earlier centroids; a redistribution of its points moves its polygon's centroid a little at once, so its
        track then starts again. A cell that has left is left out (0); one partly through an outlet gives no
        estimate (its exit is still to be settled)."""
        track = self._tracks.setdefault(cell.id, [])
        if not cell.in_channel:
            del self._tracks[cell.id]
            return 0.0
        if (cell.membrane.points[:, 0] >= self.plant.scenario.channel.length).any():
            track.clear()
            return None
        centroid = polygon_centroid(cell.membrane.points)
        redistributions = cell.membrane.redistributions
        if track and track[-1][2] != redistributions:
            track.clear()
        ratio = None
        if len(track) == 3:
            (t0, c0, _), (t1, c1, _), (t2, c2, _) = track
            predicted = lagrange((t0, t1, t2), (c0, c1, c2), time)
            error = _milne(time, t0, t1, t2) * float(np.linalg.norm(centroid - predicted))
            distance = float(np.linalg.norm(centroid - c2))
            budget = SAFETY[self.order] * self.tolerance * distance / self.plant.scenario.channel.length
            ratio = error / budget if budget > 0 else (0.0 if error == 0 else math.inf)
        track.append((time, centroid, redistributions))
        del track[:-3]
        return ratio

    def _sample(self, velocity, points):
        """The points inside the channel, located, and the old velocity there."""
        locator = self.plant.locator
        points = points[points[:, 0] < self.plant.scenario.channel.length]
        elements, reference = locator.locate(points)
        keep = elements >= 0
        points, elements, reference = points[keep], elements[keep], reference[keep]
        return points, elements, reference, locator.interpolate_located(velocity, elements, reference)

    def _ratio(self, sample, velocity, dt) -> float:
        """The local error estimate of one cell over its budget for the step (module docstring)."""
        points, elements, reference, old = sample
        if len(points) == 0:
            return 0.0
        locator = self.plant.locator
        new = locator.interpolate_located(velocity, elements, reference)
        moved = self.plant._inside(points + dt * new)
        moved_elements, moved_reference = locator.locate(moved)
        inside = moved_elements >= 0
        along = np.zeros_like(new)
        along[inside] = locator.interpolate_located(velocity, moved_elements[inside], moved_reference[inside]) \
            - new[inside]
        error = 0.5 * dt * float(np.linalg.norm(((new - old) - along).mean(axis=0)))
        distance = dt * float(np.linalg.norm(new, axis=1).mean())
        budget = SAFETY[self.order] * self.tolerance * distance / self.plant.scenario.channel.length
        return error / budget if budget > 0 else (0.0 if error == 0 else math.inf)

    def reset(self):
        """Forget every cell, the IDT drive and the level (a new run on the same plant: ``FeibPlant.reset``)."""
        self._known, self._actuation, self._tracks, self._spacings = set(), None, {}, {}
        self.level, self.ratio, self.history = len(self.levels) - 1, float("nan"), []
        self.steps = [0] * len(self.levels)
        self.retaken = 0

    # ------------------------------------------------------------------ reporting
    def summary(self, end_time: float) -> dict:
        """The dt used over time: steps and simulated time per level, and the changes (time, dt)."""
        changes = self.history + [(end_time, math.nan)]
        share = [0.0] * len(self.levels)
        for (start, dt), (stop, _) in zip(changes[:-1], changes[1:]):
            share[self.levels.index(dt)] += stop - start
        return {"tolerance_um": self.tolerance * 1e6, "scheme": self.plant.scenario.numerics.scheme,
                "levels_us": [dt * 1e6 for dt in self.levels],
                "steps": list(self.steps), "retaken": self.retaken, "time_ms": [t * 1e3 for t in share],
                "changes": [(round(t * 1e3, 6), dt * 1e6) for t, dt in self.history]}


def level_multiples(scenario) -> list[int]:
    """The levels as multiples of dt0: the powers of two 1, 2, 4, 8, for each cell type of ``scenario`` the largest
    multiple of dt0 within its stability limit (``sim.method.steplimit``) when that falls between two of them, and
    ``COARSE`` (16 dt0, 40 us by default).

    The coarse level is taken only when it lies within ``COARSE_SHARE`` of the membrane time scale eta dq / kappa_e
    of every cell in the channel (``AdaptiveSteps.stable_level``): an RBC alone (0.4-3.3 ms on the 1.67-6.67 um
    meshes), or an empty channel. This is an accuracy rule: the centroid's error estimate does not see a membrane's
    shape relaxing within a step. Scenario II on the 6.67 um mesh (the melanoma's time scale 71 us, its stability
    limit above 100 us) came 1.17 um off at 1 um with 40 us steps, 1.22 um with a 35 us level, 0.51 um held at 20 us
    (docs/numerics.md). The flow
    alone is stable far above 16 dt0 (measured to 320 us, the IDT switched every 1 ms). A cell type whose limit
    lies below dt0 is logged as a warning: its steps are dt0, above its limit."""
    multiples = {2 ** k for k in range(LEVELS)} | {COARSE}
    dt = scenario.numerics.dt
    for cell_type in scenario.cell_types:
        limit = limit_of(cell_type, scenario)
        if limit < dt * (1 - 1e-9):
            logger.warning("the finest step %.4g us is above the stability limit of a %s on this mesh (%.4g us, "
                           "docs/results.md \"Stability\"): use a smaller dt", dt * 1e6, cell_type.name, limit * 1e6)
        cap = math.floor(limit / dt * (1 + 1e-9))
        if 1 < cap < 2 ** (LEVELS - 1):
            multiples.add(cap)
    return sorted(multiples)


def _redistributed(active, new) -> bool:
    """Whether a step from ``active`` (the cells in the channel before it) to the state ``new`` redistributed some
    cell's points."""
    before = {cell.id: cell.membrane.redistributions for cell in active}
    return any(cell.id in before and cell.membrane.redistributions != before[cell.id] for cell in new.cells)


def _milne(time: float, t0: float, t1: float, t2: float) -> float:
    """BDF2's local error over the difference between its step and the parabola through (t0, t1, t2) taken
    to ``time`` (Milne's device): with c3 the third derivative and dt = time - t2, the parabola's error is
    (t - t0)(t - t1)(t - t2) c3 / 6 and BDF2's 2/9 dt^3 c3 of the other sign, so the factor is
    (2/9 dt^3) / (|prod| / 6 + 2/9 dt^3): 2/11 for equal steps."""
    dt = time - t2
    bdf2 = 2 / 9 * dt ** 3
    return bdf2 / (abs((time - t0) * (time - t1) * dt) / 6 + bdf2)
