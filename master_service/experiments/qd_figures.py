"""A MAP-Elites run's figures: the archive's heat map and its coverage and QD score over the
evaluations (docs/quality-diversity.md). matplotlib only when drawn."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from minimize_surprise.figures import save_figure
from minimize_surprise.optimizer import OptimizerConfig

__all__ = ["draw_heatmap", "draw_progress"]


def draw_heatmap(path: Path, archive: Any, optimizer: OptimizerConfig) -> list[Path]:
    """The best fitness of every cell over the grid's first two measures (one measure: a row of
    cells; more than two: the best over the others), the paper's thresholds drawn where they
    cut an axis; the files written."""
    measures = optimizer.measures
    grid = np.full([m.bins for m in measures], np.nan)
    if archive.stats.num_elites:
        data = archive.data()
        cells = archive.int_to_grid_index(data["index"])
        for cell, fitness in zip(cells, data["objective"], strict=True):
            key = tuple(int(c) for c in cell)
            if not fitness <= grid[key]:  # NaN (empty) or lower: this one
                grid[key] = fitness
    while grid.ndim > 2:
        grid = np.nanmax(grid, axis=-1) if np.isfinite(grid).any() else grid[..., 0]
    if grid.ndim == 1:
        grid = grid[:, None]
    x = measures[0]
    y = measures[1] if len(measures) > 1 else None
    fig = _figure(6.4, 4.8)
    ax = fig.subplots()
    low, high = y.range if y is not None else (0.0, 1.0)
    extent = (x.range[0], x.range[1], low, high)
    image = ax.imshow(
        grid.T, origin="lower", aspect="auto", extent=extent, vmin=0.0, vmax=1.0, cmap="viridis"
    )
    fig.colorbar(image, ax=ax, label="fitness (prediction accuracy)")
    thresholds = {"rotation": (5.0, 55.0), "mean_cluster_size": (1.43,), "box_displacement": (0.1,)}
    for value in thresholds.get(x.name, ()):
        ax.axvline(value, color="white", lw=0.8, ls="--")
    if y is not None:
        for value in thresholds.get(y.name, ()):
            ax.axhline(value, color="white", lw=0.8, ls="--")
    ax.set_xlabel(x.name)
    ax.set_ylabel(y.name if y is not None else "")
    ax.set_title(f"MAP-Elites archive: {archive.stats.num_elites} of {grid.size} cells")
    return save_figure(fig, path, formats=("png",))


def draw_progress(path: Path, progress: list[list[Any]]) -> list[Path]:
    """Coverage and QD score against the evaluations; the files written."""
    rows = np.array([row[:3] for row in progress], dtype=float).reshape(-1, 3)
    fig = _figure(6.4, 3.6)
    left = fig.subplots()
    left.plot(rows[:, 0], rows[:, 1], color="tab:blue")
    left.set_xlabel("evaluations")
    left.set_ylabel("coverage", color="tab:blue")
    right = left.twinx()
    right.plot(rows[:, 0], rows[:, 2], color="tab:orange")
    right.set_ylabel("QD score", color="tab:orange")
    return save_figure(fig, path, formats=("png",))


def _figure(width: float, height: float) -> Any:
    # On the Agg canvas, no display, laid out to keep labels inside (as the run's pictures).
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig
