"""The pictures of a run, for a talk or a paper: fitness, each robot's fitness, predictions,
trajectories on the arena, and an animation of the post-evaluation.

Every picture is written as PNG (for a quick look) and PDF (vector, for a paper), and titled with
the scenario and the run. The report (:mod:`reporting.report`) decides which pictures
a run gets; this module only draws, through matplotlib's object-oriented API (no pyplot, no
display).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from minimize_surprise.figures import FORMATS as FIGURE_FORMATS
from minimize_surprise.figures import save_figure
from minimize_surprise.safety import SAFETY_DOMINATES
from runfiles.schema import write_atomic, writing
from simulator.render import draw_arena, draw_boxes, draw_robot, robot_colours
from simulator.scenarios import WorldConfig

__all__ = [
    "ANIMATION",
    "FORMATS",
    "Arena",
    "animate_post_evaluation",
    "baseline_picture",
    "figure",
    "fitness_picture",
    "predictions_picture",
    "robot_fitness_picture",
    "save",
    "trajectories_picture",
]

#: The formats every picture is written in: a raster to look at, a vector one to print (the
#: project's, :data:`minimize_surprise.figures.FORMATS`; the PNGs at its resolution, ``DPI``).
FORMATS: Final = FIGURE_FORMATS
#: The animation's file name in ``plots/``.
ANIMATION: Final = "post_evaluation.gif"
#: At most this many points of a trajectory are drawn (a 100 Hz post-evaluation has 10,000):
#: the eye sees no difference, the PDF stays small.
_MAX_POINTS: Final = 2_500
#: Up to this many robots get a panel each in the per-robot picture; more share a band.
_MAX_PANELS: Final = 20
#: The animation: at most this long, at this many frames a second, with this much trail.
_ANIMATION_SECONDS: Final = 20.0
_ANIMATION_FPS: Final = 10
_TRAIL_SECONDS: Final = 5.0


@dataclass(frozen=True)
class Arena:
    """What the pictures need of a simulated run's world: its configuration and the boxes."""

    config: WorldConfig
    #: the boxes when the post-evaluation began and ended, (K, 2) each, or None without boxes
    boxes_start: np.ndarray | None = None
    boxes_end: np.ndarray | None = None
    #: the boxes during the post-evaluation, (frames, K, 2), a frame every ``box_every`` steps
    box_track: np.ndarray | None = None
    box_every: int = 1


def figure(width: float, height: float, *, constrained: bool = True) -> Any:
    """A matplotlib figure of ``width`` x ``height`` inches on the Agg canvas (no display)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    # Constrained layout keeps titles, labels and legends inside the figure whatever their size.
    fig = Figure(figsize=(width, height), layout="constrained" if constrained else None)
    FigureCanvasAgg(fig)
    return fig


def save(fig: Any, directory: Path, name: str) -> list[Path]:
    """Write ``fig`` as ``directory/name`` in every format of the run's plots."""
    # The figure's size as laid out (constrained layout, or axes placed by hand): no cropping.
    # A file that cannot be written is a FileWriteError naming it.
    return save_figure(fig, directory / name, formats=FORMATS, tight=False, write=write_atomic)


# -- fitness ---------------------------------------------------------------------------------


def fitness_picture(
    directory: Path,
    rows: Sequence[dict[str, Any]],
    title: str,
    *,
    post_fitness: float | None = None,
    post_steps: int | None = None,
) -> list[Path]:
    """``fitness``: every evaluation's fitness by kind and the best so far, the post-evaluation's
    fitness beside the best at the end, and below it the share of steps the safety layer drove."""
    shares = [r.get("safety_share") for r in rows]
    has_share = any(s is not None for s in shares)
    fig = figure(9, 6.5 if has_share else 4.8)
    if has_share:
        top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    else:
        top, bottom = fig.subplots(1, 1), None
    styles = (
        ("initial", "s", "initial genome", "C2"),
        ("offspring", ".", "offspring", "C0"),
        ("reevaluation", "x", "re-evaluation of the best", "C1"),
    )
    for kind, marker, label, colour in styles:
        pts = [(r["evaluation"], r["fitness"]) for r in rows if r["kind"] == kind]
        if pts:
            px, py = zip(*pts, strict=True)
            top.scatter(px, py, s=10, marker=marker, color=colour, alpha=0.6, label=label)
    x = [r["evaluation"] for r in rows]
    top.step(
        x,
        [r["best_fitness"] for r in rows],
        where="post",
        color="black",
        lw=1.5,
        label="best fitness",
    )
    if post_fitness is not None and x:
        # Beside the best at the end: what the best genome scored when run once more, longer.
        end = x[-1] + max(1.0, 0.03 * len(x))
        label = "post-evaluation of the best"
        if post_steps:
            label += f" ({post_steps} steps)"
        top.plot([end], [post_fitness], marker="*", ms=14, color="C3", ls="none", label=label)
        top.annotate(
            f"{post_fitness:.3f}",
            (end, post_fitness),
            textcoords="offset points",
            xytext=(0, 9),
            ha="center",
            color="C3",
        )
        top.annotate(
            f"{rows[-1]['best_fitness']:.3f}",
            (x[-1], rows[-1]["best_fitness"]),
            textcoords="offset points",
            xytext=(-4, 6),
            ha="right",
        )
    top.set_ylabel("fitness (1 - mean prediction error)")
    top.set_title(title)
    top.grid(alpha=0.3)
    top.legend(loc="lower right", fontsize="small", framealpha=0.9)
    if bottom is not None:
        xs = [r["evaluation"] for r, s in zip(rows, shares, strict=True) if s is not None]
        ys = [100 * s for s in shares if s is not None]
        bottom.fill_between(xs, ys, step="post", color="C7", alpha=0.5, lw=0)
        bottom.step(xs, ys, where="post", color="C7", lw=0.8)
        bottom.axhline(100 * SAFETY_DOMINATES, color="C3", ls="--", lw=1)
        bottom.text(
            xs[0] if xs else 0,
            100 * SAFETY_DOMINATES + 3,
            "above: safety layer dominates",
            color="C3",
            fontsize="small",
            va="bottom",
        )
        bottom.set_ylim(0, 105)
        bottom.set_ylabel("safety drove\n(% of steps)")
        bottom.grid(alpha=0.3)
        bottom.set_xlabel("evaluation")
    else:
        top.set_xlabel("evaluation")
    return save(fig, directory, "fitness")


def robot_fitness_picture(
    directory: Path, rows: Sequence[dict[str, Any]], robots: Sequence[str], title: str
) -> list[Path]:
    """``robot_fitness``: each robot's fitness over the run, one small panel per robot against
    the swarm's (grey); with more than twenty robots, the swarm's spread as bands instead."""
    x = np.array([r["evaluation"] for r in rows])
    swarm = np.array([r["fitness"] for r in rows])
    # NaN where a robot was not in the row's swarm (it left, or joined later): a gap in its line.
    each = np.array(
        [[r["robots"].get(robot, np.nan) for robot in robots] for r in rows], dtype=float
    ).reshape(len(rows), -1)
    colours = robot_colours(len(robots))
    if len(robots) <= _MAX_PANELS:
        cols = min(5, len(robots))
        rows_n = math.ceil(len(robots) / cols)
        fig = figure(2.4 * cols + 0.8, 2.0 * rows_n + 1.0)
        axes = np.atleast_1d(fig.subplots(rows_n, cols, sharex=True, sharey=True, squeeze=False))
        for k, ax in enumerate(axes.flat):
            if k >= len(robots):
                ax.set_visible(False)
                continue
            ax.plot(x, swarm, color="0.7", lw=0.8, label="swarm (mean)")
            ax.plot(x, each[:, k], color=colours[k], lw=0.9, label="this robot")
            ax.set_title(robots[k], fontsize="medium", color=colours[k])
            ax.grid(alpha=0.3)
            if k % cols == 0:
                ax.set_ylabel("fitness")
            if k >= len(robots) - cols:
                ax.set_xlabel("evaluation")
        axes.flat[0].legend(fontsize="x-small", loc="lower right")
        fig.suptitle(f"{title}\neach robot's fitness, against the swarm's (grey)")
    else:
        fig = figure(9, 4.8)
        ax = fig.subplots()
        low, q1, median, q3, high = np.nanpercentile(each, [0, 25, 50, 75, 100], axis=1)
        ax.fill_between(x, low, high, color="C0", alpha=0.2, lw=0, label="all robots (min-max)")
        ax.fill_between(x, q1, q3, color="C0", alpha=0.4, lw=0, label="middle half of robots")
        ax.plot(x, median, color="C0", lw=1, label="median robot")
        ax.plot(x, swarm, color="black", lw=0.8, label="swarm (mean)")
        ax.set(xlabel="evaluation", ylabel="fitness")
        ax.set_title(f"{title}\nthe {len(robots)} robots' fitness")
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize="small")
    return save(fig, directory, "robot_fitness")


def predictions_picture(
    directory: Path, sensors: dict[str, dict[str, float]], title: str
) -> list[Path]:
    """``predictions``: per sensor, the mean prediction beside the mean reading over the
    post-evaluation (a good predictor's bars match)."""
    names = list(sensors)
    idx = np.arange(len(names))
    fig = figure(max(6.0, len(names) * 0.75), 4.8)
    ax = fig.subplots()
    ax.bar(idx - 0.2, [sensors[n]["mean_predicted"] for n in names], 0.4, label="predicted")
    ax.bar(idx + 0.2, [sensors[n]["mean_real"] for n in names], 0.4, label="sensed")
    ax.set_xticks(idx, names, rotation=45, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set(ylabel="mean normalised value")
    ax.set_title(f"{title}\npost-evaluation: mean prediction and mean reading per sensor")
    ax.grid(alpha=0.3, axis="y")
    ax.legend()
    return save(fig, directory, "predictions")


def baseline_picture(directory: Path, comparison: dict[str, Any], title: str) -> list[Path]:
    """``evolved_vs_random``: every random pair's fitness, and the evolved run's best and
    post-evaluation fitness beside the best random pair."""
    random = np.asarray(comparison["random_fitness"], dtype=float)
    fig = figure(6.5, 4.8)
    ax = fig.subplots()
    jitter = np.random.default_rng(0).uniform(-0.15, 0.15, len(random))  # only for the eye
    ax.scatter(jitter, random, s=14, color="C7", alpha=0.7, label=f"{len(random)} random pairs")
    ax.hlines(random.max(), -0.3, 0.3, color="C7", lw=2, label=f"best random {random.max():.3f}")
    ax.hlines(
        np.median(random),
        -0.3,
        0.3,
        color="C7",
        lw=1,
        ls="--",
        label=f"median random {np.median(random):.3f}",
    )
    evolved = comparison.get("evolved_best_fitness")
    if evolved is not None:
        ax.plot([1], [evolved], "*", ms=15, color="C0", label=f"evolved: best {evolved:.3f}")
    post = comparison.get("evolved_post_fitness")
    if post is not None:
        ax.plot([1.25], [post], "D", ms=8, color="C3", label=f"evolved: post-evaluation {post:.3f}")
    ax.set_xticks([0, 1.1], ["random pairs", "evolved run"])
    ax.set_xlim(-0.6, 1.7)
    ax.set_ylabel("fitness")
    ax.set_title(f"{title}\nevolved against random network pairs")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize="small", loc="best")
    return save(fig, directory, "evolved_vs_random")


# -- the arena ------------------------------------------------------------------------------------


def _thin(poses: np.ndarray) -> np.ndarray:
    step = max(1, math.ceil(len(poses) / _MAX_POINTS))
    thinned = poses[::step]
    if len(poses) and (len(poses) - 1) % step:
        thinned = np.concatenate([thinned, poses[-1:]])
    return thinned


def _legend_handles(
    arena: Arena, colours: Sequence[Any], robots: Sequence[str], *, moving: bool = False
) -> list[Any]:
    """The legend of an arena picture; ``moving``: of the animation (robots where they are now,
    boxes where they are now)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles: list[Any] = [
        Line2D([], [], color=colours[k], lw=2, label=robot) for k, robot in enumerate(robots)
    ]
    if not moving:
        handles.append(
            Line2D([], [], marker="o", ls="none", mfc="white", mec="black", ms=7, label="start")
        )
    handles += [
        Line2D(
            [],
            [],
            marker="o",
            ls="none",
            mfc="0.5",
            mec="black",
            ms=11,
            label="robot (arrow: heading)" if moving else "end (arrow: heading)",
        ),
        Line2D([], [], color="white", ls="--", lw=1.5, label="carpet edge"),
        Line2D([], [], color="#7f7f7f", lw=3, label="wall"),
    ]
    if moving and arena.box_track is not None and arena.box_track.shape[1]:
        handles.append(Patch(fc="#c8a165", ec="#7a5c2e", label="box"))
    elif arena.boxes_start is not None and len(arena.boxes_start):
        handles += [
            Patch(fc="none", ec="#5a5a5a", label="box before"),
            Patch(fc="#c8a165", ec="#7a5c2e", label="box after"),
        ]
    if arena.config.light:
        handles.append(
            Line2D(
                [],
                [],
                marker="*",
                ls="none",
                color="gold",
                mec="black",
                ms=12,
                label="under the lamp",
            )
        )
    return handles


def _styled_legend(fig: Any, ax: Any, handles: list[Any]) -> None:
    legend = ax.legend(
        handles=handles,
        loc="upper left",
        bbox_to_anchor=(1.02, 1.0),
        fontsize="small",
        frameon=False,
        borderaxespad=0,
    )
    # The carpet edge is white on the carpet; on the legend's white it needs an outline.
    for handle in legend.legend_handles:
        if getattr(handle, "get_color", lambda: None)() == "white":
            handle.set_path_effects(_outline())


def _outline() -> list[Any]:
    from matplotlib import patheffects

    return [patheffects.withStroke(linewidth=3, foreground="0.4")]


def trajectories_picture(
    directory: Path,
    poses: dict[str, np.ndarray],
    arena: Arena | None,
    title: str,
) -> list[Path]:
    """``trajectories``: each robot's path over the post-evaluation on the arena, drawn to
    scale in metres: where it started (hollow circle), where it ended (its body, the arrow its
    heading), the boxes before (outline) and after (filled), the carpet's edge, walls, light.
    Without an ``arena`` (poses from elsewhere than the simulator) the paths alone."""
    if arena is None:
        return _bare_trajectories(directory, poses, title)
    robots = list(poses)
    colours = robot_colours(len(robots))
    fig = figure(9.5, 7.2, constrained=False)
    ax = fig.add_axes((0.08, 0.08, 0.62, 0.8))
    image = draw_arena(ax, arena.config)
    if arena.config.light:
        ax.plot([0], [0], "*", color="gold", mec="black", ms=14, zorder=8)
        cax = fig.add_axes((0.72, 0.08, 0.02, 0.3))
        fig.colorbar(image, cax=cax, label="light")
    size = arena.config.box_size
    if arena.boxes_start is not None and len(arena.boxes_start):
        draw_boxes(ax, arena.boxes_start, size, filled=False, zorder=3)
        end = arena.boxes_end if arena.boxes_end is not None else arena.boxes_start
        draw_boxes(ax, end, size, filled=True, zorder=3.5)
    for k, robot in enumerate(robots):
        path = _thin(poses[robot])
        ax.plot(path[:, 0], path[:, 1], color=colours[k], lw=1.1, alpha=0.85, zorder=4)
        # On top: a robot that barely moved still shows where it started.
        ax.plot(path[0, 0], path[0, 1], "o", mfc="white", mec=colours[k], mew=1.8, ms=7, zorder=11)
        draw_robot(ax, arena.config, path[-1], colours[k], label=str(k), zorder=7)
    _styled_legend(fig, ax, _legend_handles(arena, colours, robots))
    ax.set_title(title)
    return save(fig, directory, "trajectories")


def _bare_trajectories(directory: Path, poses: dict[str, np.ndarray], title: str) -> list[Path]:
    from matplotlib.lines import Line2D

    robots = list(poses)
    colours = robot_colours(len(robots))
    fig = figure(8, 6.5)
    ax = fig.subplots()
    for k, robot in enumerate(robots):
        path = _thin(poses[robot])
        ax.plot(path[:, 0], path[:, 1], color=colours[k], lw=1.1, label=robot)
        ax.plot(path[0, 0], path[0, 1], "o", mfc="white", mec=colours[k], mew=1.8, ms=7)
        ax.plot(path[-1, 0], path[-1, 1], "o", color=colours[k], mec="black", ms=8)
    handles, _ = ax.get_legend_handles_labels()
    handles += [
        Line2D([], [], marker="o", ls="none", mfc="white", mec="black", ms=7, label="start"),
        Line2D([], [], marker="o", ls="none", mfc="0.5", mec="black", ms=8, label="end"),
    ]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
    ax.set(xlabel="x (m)", ylabel="y (m)", aspect="equal", title=title)
    ax.grid(alpha=0.3)
    return save(fig, directory, "trajectories")


def animate_post_evaluation(
    path: Path,
    poses: dict[str, np.ndarray],
    arena: Arena,
    title: str,
    dt: float,
) -> Path:
    """Write a GIF of the post-evaluation to ``path``: the robots driving on the arena with a
    trail of their last seconds and the boxes where they were at that moment, at most
    twenty seconds long (faster than real time when the post-evaluation is longer)."""
    from matplotlib.animation import PillowWriter

    robots = list(poses)
    steps = min(len(p) for p in poses.values())
    frames = min(steps, int(_ANIMATION_SECONDS * _ANIMATION_FPS))
    stride = max(1, math.ceil(steps / frames))
    speed = stride * _ANIMATION_FPS * dt  # simulated seconds per second of animation
    trail = max(1, round(_TRAIL_SECONDS / dt))
    colours = robot_colours(len(robots))
    fig = figure(7.6, 6.4, constrained=False)
    ax = fig.add_axes((0.09, 0.08, 0.62, 0.8))
    image = draw_arena(ax, arena.config)
    if arena.config.light:
        ax.plot([0], [0], "*", color="gold", mec="black", ms=14, zorder=8)
        fig.colorbar(image, cax=fig.add_axes((0.73, 0.08, 0.02, 0.3)), label="light")
    _styled_legend(fig, ax, _legend_handles(arena, colours, robots, moving=True))
    heading = ax.set_title("")
    dynamic: list[Any] = []
    writer = PillowWriter(fps=_ANIMATION_FPS)
    with writing(path), writer.saving(fig, str(path), dpi=80):
        for t in range(0, steps, stride):
            for artist in dynamic:
                artist.remove()
            dynamic = []
            if arena.box_track is not None and len(arena.box_track):
                frame = min(len(arena.box_track) - 1, t // max(1, arena.box_every))
                dynamic.append(draw_boxes(ax, arena.box_track[frame], arena.config.box_size))
            for k, robot in enumerate(robots):
                seen = poses[robot][max(0, t - trail) : t + 1]
                dynamic += ax.plot(seen[:, 0], seen[:, 1], color=colours[k], lw=1.2, zorder=4)
                dynamic += draw_robot(
                    ax, arena.config, poses[robot][t], colours[k], label=str(k), zorder=6
                )
            heading.set_text(f"{title}\nt = {t * dt:5.1f} s ({speed:g}x real time)")
            writer.grab_frame()
    return path
