"""Pictures of a simulated world: arena, carpet edge, walls, light, robots, boxes, trajectories.

matplotlib is an optional extra (``minimize-surprise[master]``); it is imported only when a picture
is drawn, through its object-oriented API and the Agg canvas, so drawing never touches pyplot's
global state or needs a display.

Command line: ``python -m sim_stub.render SCENARIO OUT.png [--seed S] [--steps K]`` draws a
scenario after K steps of a seeded random walk, with the trajectories.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sim_stub.world import World

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_CARPET = "#9c8f7a"
_BEYOND = "#e6e6e6"
_WALL = "#7f7f7f"
_BOX = "#c8a165"
_BOX_EDGE = "#7a5c2e"


def _matplotlib() -> Any:
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError(
            "drawing needs matplotlib: pip install 'minimize-surprise[master]'"
        ) from exc
    from matplotlib import patches
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PatchCollection
    from matplotlib.figure import Figure

    return Figure, FigureCanvasAgg, patches, PatchCollection


def render_world(
    world: World,
    path: str | Path | None = None,
    *,
    trajectories: np.ndarray | None = None,
    title: str | None = None,
    size: float = 6.0,
    dpi: int = 120,
) -> Figure:
    """Draw ``world`` as it is now and return the figure; write a PNG to ``path`` if given.

    ``trajectories``: poses of shape (T + 1, N, 3) (e.g. :meth:`World.recorded_poses`) drawn as
    one line per robot. The light gradient is drawn when the world has a lamp.
    """
    figure_cls, canvas_cls, patches, collection_cls = _matplotlib()
    cfg = world.config
    half = cfg.arena_side / 2
    wall = cfg.wall_half
    fig = figure_cls(figsize=(size, size), dpi=dpi)
    canvas_cls(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_aspect("equal")
    lim = wall + 0.03
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.add_patch(patches.Rectangle((-wall, -wall), 2 * wall, 2 * wall, color=_BEYOND, zorder=0))
    if cfg.light:
        grid = np.linspace(-wall, wall, 200)
        gx, gy = np.meshgrid(grid, grid)
        image = ax.imshow(
            world.light_at(gx, gy),
            extent=(-wall, wall, -wall, wall),
            origin="lower",
            cmap="inferno",
            vmin=0.0,
            vmax=1.0,
            alpha=0.85,
            zorder=1,
        )
        fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04, label="light")
    else:
        ax.add_patch(patches.Rectangle((-half, -half), 2 * half, 2 * half, color=_CARPET, zorder=1))
    # The carpet's edge, which the ground sensors see, and the walls beyond it.
    ax.add_patch(
        patches.Rectangle(
            (-half, -half), 2 * half, 2 * half, fill=False, ec="white", lw=1.5, ls="--", zorder=2
        )
    )
    ax.add_patch(
        patches.Rectangle(
            (-wall, -wall),
            2 * wall,
            2 * wall,
            fill=False,
            ec=_WALL,
            # Thick walls are the ones the IR sensors see.
            lw=5 if cfg.walls_visible_to_ir else 2,
            zorder=2,
        )
    )
    boxes = world.box_positions
    if len(boxes):
        s = cfg.box_size
        squares = [patches.Rectangle((bx - s / 2, by - s / 2), s, s) for bx, by in boxes]
        ax.add_collection(
            collection_cls(squares, facecolor=_BOX, edgecolor=_BOX_EDGE, lw=0.4, zorder=3)
        )
    colours = [f"C{i % 10}" for i in range(world.n_robots)]
    if trajectories is not None and len(trajectories):
        traj = np.asarray(trajectories)
        for i in range(traj.shape[1]):
            ax.plot(traj[:, i, 0], traj[:, i, 1], color=colours[i], lw=1.0, alpha=0.8, zorder=4)
    _draw_robots(ax, world, patches, colours)
    ax.set_title(title or f"{world.n_robots} robots, t = {world.time:.1f} s")
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, format="png")
    return fig


def _draw_robots(ax: Any, world: World, patches: Any, colours: list[str]) -> None:
    cfg = world.config
    r = cfg.robot_radius
    for i, (x, y, th) in enumerate(world.poses):
        c, s = math.cos(th), math.sin(th)
        cx, cy = x + cfg.body_offset * c, y + cfg.body_offset * s
        ax.add_patch(
            patches.Circle((cx, cy), r, fc=colours[i], ec="black", lw=0.8, alpha=0.9, zorder=5)
        )
        if cfg.has_blade:
            hw = cfg.blade_width / 2
            bx, by = x + cfg.blade_x * c, y + cfg.blade_x * s
            ax.plot(
                [bx - hw * s, bx + hw * s],
                [by + hw * c, by - hw * c],
                color="black",
                lw=3,
                solid_capstyle="round",
                zorder=6,
            )
        # Heading: an arrow from the wheel axis to the front of the body.
        ax.annotate(
            "",
            xy=(x + 0.075 * c, y + 0.075 * s),
            xytext=(x, y),
            arrowprops={"arrowstyle": "-|>", "color": "white", "lw": 1.5},
            zorder=7,
        )
        ax.text(
            cx - 0.02 * c,
            cy - 0.02 * s,
            str(i),
            fontsize=7,
            ha="center",
            va="center",
            color="white",
            zorder=8,
        )


def _random_walk(world: World, steps: int, seed: int) -> np.ndarray:
    # Commands held for 2 s each, biased forward so that robots travel and push boxes.
    rng = np.random.default_rng(seed)
    world.start_recording()
    for k in range(steps):
        if k % 20 == 0:
            cmd = rng.uniform(-0.4, 1.0, size=(world.n_robots, 2))
        world.set_commands(cmd)
        world.step()
    return world.stop_recording()


def main(argv: list[str] | None = None) -> None:
    """Draw a named scenario to a PNG (see the module docstring)."""
    from sim_stub.scenarios import SCENARIOS, scenario_config

    parser = argparse.ArgumentParser(prog="python -m sim_stub.render", description=__doc__)
    parser.add_argument("scenario", choices=SCENARIOS)
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=300, help="steps of random walk to draw")
    args = parser.parse_args(argv)
    world = World(scenario_config(args.scenario), seed=args.seed)
    trajectories = _random_walk(world, args.steps, args.seed) if args.steps > 0 else None
    render_world(
        world,
        args.out,
        trajectories=trajectories,
        title=f"{args.scenario}: {world.n_robots} robots, {len(world.box_positions)} boxes, "
        f"seed {args.seed}, t = {world.time:.1f} s",
    )


if __name__ == "__main__":
    main()
