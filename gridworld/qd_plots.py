"""Pictures of a MAP-Elites run (:mod:`gridworld.qd`): the archive as heat maps, and its
coverage and QD score over evaluations.

matplotlib is imported inside each function; each picture is written as PNG and PDF.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gridworld.config import GridMeasure
from gridworld.figures import PATTERN_COLOURS
from gridworld.patterns import PATTERN_NAMES, PATTERNS
from minimize_surprise.figures import save_figure

__all__ = ["plot_archive", "plot_progress"]

#: Resolution of a run's PNGs (looked at on a screen).
_DPI = 120


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _read(path: str | Path) -> list[dict[str, str]]:
    with Path(path).open(encoding="utf-8") as f:
        return list(csv.DictReader(f))


def plot_archive(
    archive_csv: str | Path, measures: Sequence[GridMeasure], stem: str | Path
) -> list[Path]:
    """Two heat maps of an archive (``archive.csv``) over its first two measures: the elites'
    fitness, and their class in the patterns' colours. With one measure the second axis has one
    cell; with more than two, each cell of the picture shows the fittest elite over the other
    measures' cells."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    plt = _pyplot()
    rows = _read(archive_csv)
    axes = list(measures[:2])
    bins = [m.bins for m in axes] + [1] * (2 - len(axes))
    fitness = np.full((bins[1], bins[0]), np.nan)
    classes = np.full((bins[1], bins[0]), np.nan)
    for row in rows:
        cell = []
        for m, n in zip(axes, bins, strict=False):
            lo, hi = m.range
            k = int((n * (float(row[f"measure_{m.name}"]) - lo) + 1e-6) / (hi - lo))
            cell.append(min(max(k, 0), n - 1))
        x, y = [*cell, 0][:2]
        value = float(row["fitness"])
        if np.isnan(fitness[y, x]) or value > fitness[y, x]:
            fitness[y, x] = value
            classes[y, x] = PATTERNS.index(row["pattern"])
    extent = [axes[0].range[0], axes[0].range[1], *(axes[1].range if len(axes) > 1 else (0, 1))]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.6))
    image = left.imshow(fitness, origin="lower", extent=extent, aspect="auto", cmap="viridis")
    fig.colorbar(image, ax=left, label="fitness")
    cmap = ListedColormap([PATTERN_COLOURS[p] for p in PATTERNS])
    right.imshow(classes, origin="lower", extent=extent, aspect="auto", cmap=cmap, vmin=-0.5,
                 vmax=len(PATTERNS) - 0.5, interpolation="nearest")  # fmt: skip
    found = sorted({row["pattern"] for row in rows}, key=PATTERNS.index)
    right.legend(
        handles=[Patch(color=PATTERN_COLOURS[p], label=f"{p} {PATTERN_NAMES[p]}") for p in found],
        fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5),
    )  # fmt: skip
    for ax, title in ((left, "fitness of the elites"), (right, "class of the elites")):
        ax.set_xlabel(f"{axes[0].name} fraction")
        ax.set_ylabel(f"{axes[1].name} fraction" if len(axes) > 1 else "")
        ax.set_title(title)
    more = f", fittest over {', '.join(m.name for m in measures[2:])}" if len(measures) > 2 else ""
    fig.suptitle(f"MAP-Elites archive: {len(rows)} elites{more}")
    fig.tight_layout()
    paths = save_figure(fig, Path(stem), dpi=_DPI)
    plt.close(fig)
    return paths


def plot_progress(progress_csv: str | Path, stem: str | Path) -> list[Path]:
    """Coverage, QD score and classes found over evaluations from ``qd_progress.csv``."""
    plt = _pyplot()
    rows = _read(progress_csv)
    evaluations = [int(r["evaluations"]) for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    for ax, key, label in (
        (axes[0], "coverage", "coverage"),
        (axes[1], "qd_score", "QD score (sum of the elites' fitness)"),
        (axes[2], "classes", "classes among the elites"),
    ):
        ax.plot(evaluations, [float(r[key]) for r in rows])
        ax.set_xlabel("evaluations")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[2].set_ylim(0, len(PATTERNS) + 0.5)
    fig.tight_layout()
    paths = save_figure(fig, Path(stem), dpi=_DPI)
    plt.close(fig)
    return paths
