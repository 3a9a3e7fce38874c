"""Pictures of a simulated world: arena, carpet edge, walls, light, robots, boxes, trajectories.

matplotlib is an optional extra (``minimize-surprise[master]``); it is imported only when a picture
is drawn, through its object-oriented API and the Agg canvas, so drawing never touches pyplot's
global state or needs a display.

Command line: ``python -m simulator.render SCENARIO OUT.png [--seed S] [--steps K]`` draws a
scenario after K steps of a seeded random walk, with the trajectories.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from minimize_surprise.figures import save_figure
from simulator.scenarios import WorldConfig
from simulator.world import World

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_CARPET = "#9c8f7a"
_BEYOND = "#e6e6e6"
_WALL = "#7f7f7f"
_BOX = "#c8a165"
_BOX_EDGE = "#7a5c2e"
_BOX_OUTLINE = "#5a5a5a"


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


def robot_colours(count: int) -> list[Any]:
    """One colour per robot, all distinguishable: the ten of tab10, then tab20's, then hues."""
    from matplotlib import colormaps

    if count <= 10:
        return [colormaps["tab10"](i) for i in range(count)]
    if count <= 20:
        return [colormaps["tab20"](i) for i in range(count)]
    return [colormaps["hsv"](i / count) for i in range(count)]


def draw_arena(ax: Any, config: WorldConfig, world: World | None = None) -> Any:
    """Draw the arena of ``config`` on ``ax``: the floor beyond the carpet, the carpet (or, with a
    lamp, its light, taken from ``world``), the carpet's edge, the walls; axes in metres.

    Returns the light's image (for a colour bar) or None.
    """
    _, _, patches, _ = _matplotlib()
    hx, hy = config.carpet_width / 2, config.carpet_height / 2
    wx, wy = config.wall_hx, config.wall_hy
    ax.set_aspect("equal")
    ax.set_xlim(-wx - 0.03, wx + 0.03)
    ax.set_ylim(-wy - 0.03, wy + 0.03)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.add_patch(patches.Rectangle((-wx, -wy), 2 * wx, 2 * wy, color=_BEYOND, zorder=0))
    image = None
    if config.light:
        if world is None:
            world = World(config)
        gx, gy = np.meshgrid(np.linspace(-wx, wx, 200), np.linspace(-wy, wy, 200))
        image = ax.imshow(
            world.light_at(gx, gy),
            extent=(-wx, wx, -wy, wy),
            origin="lower",
            cmap="inferno",
            vmin=0.0,
            vmax=1.0,
            alpha=0.85,
            zorder=1,
        )
    else:
        ax.add_patch(patches.Rectangle((-hx, -hy), 2 * hx, 2 * hy, color=_CARPET, zorder=1))
    # The carpet's edge, which the ground sensors see, and the walls beyond it.
    ax.add_patch(
        patches.Rectangle(
            (-hx, -hy), 2 * hx, 2 * hy, fill=False, ec="white", lw=1.5, ls="--", zorder=2
        )
    )
    ax.add_patch(
        patches.Rectangle(
            (-wx, -wy),
            2 * wx,
            2 * wy,
            fill=False,
            ec=_WALL,
            # Thick walls are the ones the IR sensors see.
            lw=5 if config.walls_visible_to_ir else 2,
            zorder=2,
        )
    )
    return image


def draw_boxes(
    ax: Any, positions: np.ndarray, size: float, *, filled: bool = True, zorder: float = 3
) -> Any:
    """Draw boxes of side ``size`` at ``positions`` (K, 2): filled, or as outlines (where the
    boxes were). Returns the collection (remove it to redraw)."""
    _, _, patches, collection_cls = _matplotlib()
    squares = [patches.Rectangle((x - size / 2, y - size / 2), size, size) for x, y in positions]
    if filled:
        style = {"facecolor": _BOX, "edgecolor": _BOX_EDGE, "lw": 0.4}
    else:
        style = {"facecolor": "none", "edgecolor": _BOX_OUTLINE, "lw": 0.6}
    return ax.add_collection(collection_cls(squares, zorder=zorder, **style))


def draw_robot(
    ax: Any,
    config: WorldConfig,
    pose: Sequence[float],
    colour: Any,
    *,
    label: str | None = None,
    zorder: float = 5,
) -> list[Any]:
    """Draw one robot to scale at ``pose`` (x, y, heading): its body, its blade if it has one,
    an arrow for its heading and ``label`` on it. Returns the artists (remove them to redraw)."""
    _, _, patches, _ = _matplotlib()
    x, y, th = (float(v) for v in pose)
    c, s = math.cos(th), math.sin(th)
    cx, cy = x + config.body_offset * c, y + config.body_offset * s
    artists = [
        ax.add_patch(
            patches.Circle(
                (cx, cy),
                config.robot_radius,
                fc=colour,
                ec="black",
                lw=0.8,
                alpha=0.9,
                zorder=zorder,
            )
        )
    ]
    if config.has_blade:
        hw = config.blade_width / 2
        bx, by = x + config.blade_x * c, y + config.blade_x * s
        artists += ax.plot(
            [bx - hw * s, bx + hw * s],
            [by + hw * c, by - hw * c],
            color="black",
            lw=3,
            solid_capstyle="round",
            zorder=zorder + 1,
        )
    # Heading: an arrow from the wheel axis to the front of the body.
    artists.append(
        ax.annotate(
            "",
            xy=(x + 0.075 * c, y + 0.075 * s),
            xytext=(x, y),
            arrowprops={"arrowstyle": "-|>", "color": "white", "lw": 1.5},
            zorder=zorder + 2,
        )
    )
    if label is not None:
        artists.append(
            ax.text(
                # Behind the wheel axis, where the heading arrow does not cover it.
                x - 0.017 * c,
                y - 0.017 * s,
                label,
                fontsize=7,
                ha="center",
                va="center",
                color="white",
                zorder=zorder + 3,
            )
        )
    return artists


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
    figure_cls, canvas_cls, _, _ = _matplotlib()
    cfg = world.config
    fig = figure_cls(figsize=(size, size), dpi=dpi)
    canvas_cls(fig)
    ax = fig.add_subplot(1, 1, 1)
    image = draw_arena(ax, cfg, world)
    if image is not None:
        fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04, label="light")
    if len(world.box_positions):
        draw_boxes(ax, world.box_positions, cfg.box_size)
    colours = robot_colours(world.n_robots)
    if trajectories is not None and len(trajectories):
        traj = np.asarray(trajectories)
        for i in range(traj.shape[1]):
            ax.plot(traj[:, i, 0], traj[:, i, 1], color=colours[i], lw=1.0, alpha=0.8, zorder=4)
    for i, pose in enumerate(world.poses):
        draw_robot(ax, cfg, pose, colours[i], label=str(i))
    ax.set_title(title or f"{world.n_robots} robots, t = {world.time:.1f} s")
    fig.tight_layout()
    if path is not None:
        # The figure's own size and dpi, laid out above: no cropping.
        save_figure(fig, path, formats=("png",), dpi=None, tight=False, suffix=False)
    return fig


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
    from simulator.arenas import load_arena
    from simulator.scenarios import SCENARIOS, scenario_config

    parser = argparse.ArgumentParser(prog="python -m simulator.render", description=__doc__)
    parser.add_argument("scenario", choices=SCENARIOS)
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=300, help="steps of random walk to draw")
    parser.add_argument("--arena", help="the scenario's robots in this arena (name or file)")
    args = parser.parse_args(argv)
    arena = None if args.arena is None else load_arena(args.arena)
    world = World(scenario_config(args.scenario, arena=arena), seed=args.seed)
    trajectories = _random_walk(world, args.steps, args.seed) if args.steps > 0 else None
    render_world(
        world,
        args.out,
        trajectories=trajectories,
        title=f"{args.scenario}{'' if arena is None else ' in ' + arena.name}: "
        f"{world.n_robots} robots, {len(world.box_positions)} boxes, "
        f"seed {args.seed}, t = {world.time:.1f} s",
    )


if __name__ == "__main__":
    main()
