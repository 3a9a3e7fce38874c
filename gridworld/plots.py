"""Pictures of one grid-world run: fitness over generations, a grid with headings, an animation.

matplotlib (the ``master`` extra) is imported inside each function, so the rest of the package
works without it. Each picture is written as PNG and PDF (the animation as GIF).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from gridworld.world import Poses
from minimize_surprise.figures import save_figure

__all__ = ["animate", "draw_grid", "plot_fitness", "plot_grid"]

#: Resolution of a run's PNGs: these pictures are looked at on a screen, not printed.
_DPI = 120


def _save(fig, stem: Path) -> list[Path]:
    return save_figure(fig, stem, dpi=_DPI)


def plot_fitness(
    generations_csv: str | Path, stem: str | Path, novelty: bool = False
) -> list[Path]:
    """Best and mean fitness (novelty) per generation from a run's ``generations.csv``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with Path(generations_csv).open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    gen = [int(r["generation"]) for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(gen, [float(r["best_fitness"]) for r in rows], label="best")
    ax.plot(gen, [float(r["mean_fitness"]) for r in rows], label="mean")
    ax.set_xlabel("generation")
    ax.set_ylabel("novelty" if novelty else "fitness")
    ax.legend()
    ax.grid(alpha=0.3)
    paths = _save(fig, Path(stem))
    plt.close(fig)
    return paths


def draw_grid(ax, width: int, height: int, poses: Poses, title: str | None = None) -> None:
    """Draw agents as triangles pointing along their headings on ``ax``."""
    from matplotlib.patches import Polygon

    ax.clear()
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(-0.5, height - 0.5)
    ax.set_aspect("equal")
    ax.set_xticks(np.arange(-0.5, width, 1), minor=True)
    ax.set_yticks(np.arange(-0.5, height, 1), minor=True)
    ax.grid(which="minor", color="0.85", linewidth=0.5)
    ax.tick_params(which="both", length=0, labelbottom=False, labelleft=False)
    hx, hy = poses.vectors()
    for x, y, dx, dy in zip(poses.x, poses.y, hx, hy, strict=True):
        tip = (x + 0.4 * dx, y + 0.4 * dy)
        side = (-dy, dx)
        base1 = (x - 0.3 * dx + 0.3 * side[0], y - 0.3 * dy + 0.3 * side[1])
        base2 = (x - 0.3 * dx - 0.3 * side[0], y - 0.3 * dy - 0.3 * side[1])
        ax.add_patch(Polygon([tip, base1, base2], closed=True, color="0.15"))
    if title:
        ax.set_title(title)


def plot_grid(
    width: int, height: int, poses: Poses, stem: str | Path, title: str | None = None
) -> list[Path]:
    """A grid with headings as PNG and PDF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    size = max(3.0, 0.3 * max(width, height))
    fig, ax = plt.subplots(figsize=(size, size * height / width))
    draw_grid(ax, width, height, poses, title)
    paths = _save(fig, Path(stem))
    plt.close(fig)
    return paths


def animate(
    width: int, height: int, trace: np.ndarray, path: str | Path, every: int = 5, fps: int = 10
) -> Path:
    """A GIF of a run from its recorded poses (``trace``: (T + 1, N, 2) cell and heading), one
    frame every ``every`` steps and the last."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    from gridworld.world import Torus

    torus = Torus(width, height)
    frames = list(range(0, trace.shape[0], max(1, every)))
    if frames[-1] != trace.shape[0] - 1:
        frames.append(trace.shape[0] - 1)
    size = max(3.0, 0.3 * max(width, height))
    fig, ax = plt.subplots(figsize=(size, size * height / width))

    def frame(t: int):
        draw_grid(ax, width, height, Poses.from_cells(torus, trace[t]), f"step {t}")
        return []

    anim = FuncAnimation(fig, frame, frames=frames, blit=False)
    path = Path(path)
    anim.save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path
