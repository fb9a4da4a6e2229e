"""The summary figure of a sweep: the plotted metric over one parameter (a line) or two (a heat map, or a
scatter for random sampling), other parameters averaged over."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .. import units
from .model import Sweep, float_or_nan


def save_plot(path: Path, sweep: Sweep, rows: list[dict]) -> None:
    """The plotted metric over the first parameter (a line) or the first two (a heat map; random sampling: a
    scatter coloured by the metric); other parameters are averaged over. Failed points are left out."""
    from ..studies.figures import pyplot, save_figure
    plt = pyplot()
    values = {point.id: dict(point.values) for point in sweep.points}
    names = [parameter.name for parameter in sweep.parameters][:2]
    quantities = [parameter.quantity for parameter in sweep.parameters][:2]
    samples = [([_axis_value(values[row["point"]][name], quantity) for name, quantity in zip(names, quantities)],
                float_or_nan(row.get(sweep.plot))) for row in rows if row["status"] == "ok" and row["point"] in values]
    averaged = [parameter.name for parameter in sweep.parameters[2 if len(names) == 2 else 1:]]
    figure, axis = plt.subplots(figsize=(6.4, 4.8))
    if len(names) == 1:
        _line(axis, samples, names[0], sweep.plot)
    elif sweep.sampling == "grid":
        _heat_map(figure, axis, samples, names, sweep.plot)
    else:
        _scatter(figure, axis, samples, names, sweep.plot)
    title = f"{sweep.plot} ({Path(sweep.path).stem})"
    axis.set_title(title + (f"\nmean over {', '.join(averaged)}" if averaged else ""))
    figure.tight_layout()
    save_figure(figure, path)
    plt.close(figure)


def _axis_value(value, quantity=None):
    """A parameter value as a number on an axis, or its text for a categorical axis; a text with a unit of the
    parameter's ``quantity`` (dimension, unit of its bare numbers) in the unit of its bare numbers."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if quantity is not None:
        dimension, unit = quantity
        try:
            return units.parse_quantity(str(value), dimension, unit) / (units.unit_factor(unit, dimension)
                                                                        if unit else 1.0)
        except units.QuantityError:
            pass
    return str(value)


def _axis(values):
    """Sorted distinct values, their positions on an axis (numbers as they are, text as categories 0, 1, ...)
    and tick labels."""
    distinct = sorted(set(values), key=lambda v: (isinstance(v, str), v))
    numeric = all(isinstance(v, float) for v in distinct)
    positions = {v: (v if numeric else float(i)) for i, v in enumerate(distinct)}
    return distinct, positions, [f"{v:.4g}" if isinstance(v, float) else v for v in distinct]


def _means(samples, count: int) -> dict:
    """The mean metric per combination of the first ``count`` coordinates (NaN where every sample is NaN)."""
    table = {}
    for coordinates, metric in samples:
        table.setdefault(tuple(coordinates[:count]), []).append(metric)
    return {key: float(np.mean([m for m in v if math.isfinite(m)])) if any(map(math.isfinite, v)) else math.nan
            for key, v in table.items()}


def _line(axis, samples, name, metric):
    means = _means(samples, 1)
    distinct, positions, labels = _axis([key[0] for key in means])
    axis.plot([positions[v] for v in distinct], [means[(v,)] for v in distinct], "o-")
    if not all(isinstance(v, float) for v in distinct):
        axis.set_xticks([positions[v] for v in distinct], labels)
    axis.set_xlabel(name)
    axis.set_ylabel(metric)
    axis.grid(alpha=0.3)


def _heat_map(figure, axis, samples, names, metric):
    means = _means(samples, 2)
    xs, _, x_labels = _axis([key[0] for key in means])
    ys, _, y_labels = _axis([key[1] for key in means])
    grid = np.full((len(ys), len(xs)), np.nan)
    for (x, y), value in means.items():
        grid[ys.index(y), xs.index(x)] = value
    image = axis.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
    for (row, column), value in np.ndenumerate(grid):
        if math.isfinite(value):
            shade = image.norm(value) if image.norm.vmax > image.norm.vmin else 0.0
            axis.text(column, row, f"{value:.2g}", ha="center", va="center", fontsize=7,
                      color="black" if shade > 0.6 else "white")
    axis.set_xticks(range(len(xs)), x_labels, rotation=45)
    axis.set_yticks(range(len(ys)), y_labels)
    axis.set_xlabel(names[0])
    axis.set_ylabel(names[1])
    figure.colorbar(image, ax=axis, label=metric)


def _scatter(figure, axis, samples, names, metric):
    axes = [_axis([coordinates[i] for coordinates, _ in samples]) for i in (0, 1)]
    points = axis.scatter([axes[0][1][c[0]] for c, _ in samples], [axes[1][1][c[1]] for c, _ in samples],
                          c=[m for _, m in samples], cmap="viridis")
    for (distinct, positions, labels), ticks in zip(axes, (axis.set_xticks, axis.set_yticks)):
        if not all(isinstance(v, float) for v in distinct):
            ticks([positions[v] for v in distinct], labels)
    axis.set_xlabel(names[0])
    axis.set_ylabel(names[1])
    figure.colorbar(points, ax=axis, label=metric)
