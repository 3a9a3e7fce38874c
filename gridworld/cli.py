"""``surprise-grid``: evolve, replay and classify in the grid world.

Subcommands::

    surprise-grid evolve --size L [--seed S] [--sensors 14|6|8] [--predefined NAME] [--novelty]
                         [--noise P] [--population N] [--generations N] [--agents N]
                         [--repetitions N] [--steps N] [--out DIR]
                         [--optimizer ga|map-elites] [--measure NAME[:BINS|:LOW:HIGH:BINS]]...
                         [--sigma S]
        one run (the GA, or MAP-Elites over pattern measures: then the population is the batch
        and the generations the batches); on a DIR holding an unfinished run it continues it
        bit for bit
    surprise-grid replay DIR [--every K]
        run the best genome again: final grid with headings and an animated GIF
    surprise-grid classify GRID
        pattern scores of a grid file (final_grid.json, or JSON with width, height, poses)

Exit status: 0 done (or the run was already finished); 2 bad input (one message naming it);
130 interrupted (the run resumes from its last checkpoint).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from minimize_surprise.errors import ConfigError

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="surprise-grid", description="Minimize surprise on a torus grid (paper Sec. III-IV)."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    ev = sub.add_parser("evolve", help="one evolution run (resumes an unfinished one)")
    ev.add_argument("--size", type=int, help="torus side L (default 15)")
    ev.add_argument("--height", type=int, help="torus height for a rectangle (default L)")
    ev.add_argument("--seed", type=int, help="random seed (default 0)")
    ev.add_argument("--sensors", type=int, choices=(14, 6, 8),
                    help="sensor model: cells each agent senses (default 14)")  # fmt: skip
    ev.add_argument("--predefined", help="fixed predictions, e.g. line or line-partial")
    ev.add_argument("--novelty", action="store_true", help="novelty search (actor only)")
    ev.add_argument("--noise", type=float, help="probability of flipping a sensor reading")
    ev.add_argument("--population", type=int, help="genomes per generation (default 50)")
    ev.add_argument("--generations", type=int, help="generations (default 100)")
    ev.add_argument("--agents", type=int, help="agents N on the torus (default 100)")
    ev.add_argument("--repetitions", type=int,
                    help="runs per genome, from different starts (default 10)")  # fmt: skip
    ev.add_argument("--steps", type=int, help="steps T per run (default 500)")
    ev.add_argument("--mutation-rate", type=float, dest="mutation_rate",
                    help="probability of mutating each gene (default 0.1)")  # fmt: skip
    ev.add_argument("--fitness-of", choices=("min", "mean", "max"), dest="fitness_of",
                    help="a genome's fitness from its runs (default min)")  # fmt: skip
    ev.add_argument("--optimizer", choices=("ga", "map-elites"),
                    help="the genetic algorithm (default) or MAP-Elites")  # fmt: skip
    ev.add_argument("--measure", action="append", dest="measure", metavar="NAME[:BINS]",
                    help="map-elites: an archive axis, a pattern code (LN, PR, ...) with its "
                    "bins, or NAME:LOW:HIGH:BINS; repeat for more axes (default LN and PR, "
                    "10 bins over [0, 1])")  # fmt: skip
    ev.add_argument("--sigma", type=float,
                    help="map-elites: noise added to every gene (default 0.07)")  # fmt: skip
    ev.add_argument("--out", type=Path, help="run directory (default runs/grid-<time>)")
    ev.set_defaults(handler=_evolve)
    rp = sub.add_parser("replay", help="run the best genome again and animate it")
    rp.add_argument("dir", type=Path, metavar="DIR", help="a grid run's directory")
    rp.add_argument("--every", type=int, default=5, help="steps per animation frame")
    rp.set_defaults(handler=_replay)
    cl = sub.add_parser("classify", help="pattern scores of a grid file")
    cl.add_argument(
        "grid", type=Path, metavar="GRID",
        help="final_grid.json, or {width, height, final: [[x, y, hx, hy], ...]}",
    )  # fmt: skip
    cl.set_defaults(handler=_classify)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``surprise-grid``."""
    args = _parser().parse_args(argv)
    try:
        return args.handler(args)
    except ConfigError as exc:
        print(f"surprise-grid: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("surprise-grid: interrupted; evolve --out DIR continues the run", file=sys.stderr)
        return 130


class _Progress:
    """A rich progress bar on a terminal, one plain line per generation otherwise."""

    def __init__(self, total: int, done: int, stream=None) -> None:
        self.stream = stream or sys.stderr
        self.live = self.stream.isatty()
        self.total, self.done = total, done
        self._bar: Any = None

    def __enter__(self) -> _Progress:
        if self.live:
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self._bar = Progress(
                TextColumn("generation {task.completed}/{task.total}"),
                BarColumn(),
                TextColumn("{task.fields[best]}"),
                TimeRemainingColumn(),
                console=Console(file=self.stream),
            )
            self._bar.start()
            self._task = self._bar.add_task("evolve", total=self.total, completed=self.done,
                                            best="")  # fmt: skip
        return self

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.stop()

    def __call__(self, report) -> None:
        text = f"best {report.best_fitness:.4f} mean {report.mean_fitness:.4f}"
        if self._bar is not None:
            self._bar.update(self._task, completed=report.generation, best=text)
        else:
            print(
                f"generation {report.generation}/{report.total} {text} "
                f"elapsed {report.elapsed_s:.1f} s",
                file=self.stream,
                flush=True,
            )


def _measure(text: str) -> dict[str, Any]:
    # NAME, NAME:BINS or NAME:LOW:HIGH:BINS; the configuration checks the values.
    parts = text.split(":")
    try:
        if len(parts) == 1:
            return {"name": parts[0]}
        if len(parts) == 2:
            return {"name": parts[0], "bins": int(parts[1])}
        if len(parts) == 4:
            return {"name": parts[0], "range": [float(parts[1]), float(parts[2])],
                    "bins": int(parts[3])}  # fmt: skip
    except ValueError:
        pass
    raise ConfigError(f"{text!r}: expected NAME, NAME:BINS or NAME:LOW:HIGH:BINS", key="--measure")


def _evolve(args: argparse.Namespace) -> int:
    from gridworld.config import decode_run_config
    from gridworld.evolve import RunFinished, run_evolution
    from gridworld.qd import run_map_elites

    out = args.out or Path("runs") / time.strftime("grid-%Y%m%d-%H%M%S")
    options = {
        key: getattr(args, key)
        for key in (
            "size",
            "height",
            "sensors",
            "predefined",
            "noise",
            "population",
            "generations",
            "agents",
            "repetitions",
            "steps",
            "mutation_rate",
            "fitness_of",
            "optimizer",
            "sigma",
        )
        if getattr(args, key) is not None
    }
    if args.novelty:
        options["novelty"] = True
    if args.measure:
        options["measures"] = [_measure(text) for text in args.measure]
    resuming = (out / "config.json").exists()
    if resuming:
        if options:
            print(f"surprise-grid: {out} holds a run: continuing it with its own configuration "
                  f"(ignoring {', '.join(sorted(options))})", file=sys.stderr)  # fmt: skip
        config, seed = None, None
        stored = json.loads((out / "config.json").read_text(encoding="utf-8"))
        total = int(stored["config"].get("generations", 100))
        done = 0
        qd = stored["config"].get("optimizer", "ga") == "map-elites"
        if (out / "checkpoint.json").exists():
            ck = json.loads((out / "checkpoint.json").read_text())
            done = int(ck["batch"] if qd else ck["ga"]["generation"])
    else:
        config = decode_run_config(options, file="<command line>")
        seed = args.seed if args.seed is not None else 0
        total, done = config.generations, 0
        qd = config.optimizer == "map-elites"
    run = run_map_elites if qd else run_evolution
    try:
        with _Progress(total, done) as progress:
            summary = run(config, seed, out, progress=progress)
    except RunFinished as finished:
        print(f"{out}: the run is finished (best fitness {finished.summary['best_fitness']}, "
              f"{finished.summary['pattern']})")  # fmt: skip
        return 0
    _print_summary(out, summary)
    return 0


def _print_summary(out: Path, summary: dict[str, Any]) -> None:
    from gridworld.patterns import PATTERN_NAMES

    best = summary.get("best_fitness")
    best_text = "-" if best is None else f"{best:.4f}"
    print(f"run directory: {out}")
    print(f"best fitness: {best_text}")
    print(f"pattern: {summary['pattern']} ({PATTERN_NAMES[summary['pattern']]}), "
          f"quality {summary['quality']:.0%}")  # fmt: skip
    if "patterns_found" in summary:
        print(f"archive: {summary['elites']} elites of {summary['cells']} cells, QD score "
              f"{summary['qd_score']:.3f}; classes {' '.join(summary['patterns_found'])}; "
              f"post-evaluated {' '.join(summary['post_patterns_found'])}")  # fmt: skip


def _replay(args: argparse.Namespace) -> int:
    import numpy as np

    from gridworld.evaluate import GridEvaluator
    from gridworld.patterns import classify
    from gridworld.plots import animate, plot_grid
    from gridworld.world import Poses, Torus
    from minimize_surprise.gridnet import GridNetSpec

    run = args.dir
    try:
        genome_data = json.loads((run / "best_genome.json").read_text(encoding="utf-8"))
        grid = json.loads((run / "final_grid.json").read_text(encoding="utf-8"))
        config = json.loads((run / "config.json").read_text(encoding="utf-8"))["config"]
    except (OSError, ValueError, KeyError) as exc:
        raise ConfigError(f"not a finished grid run: {exc}", file=str(run)) from None
    spec = GridNetSpec(int(genome_data["sensors"]), genome_data.get("predefined"),
                       bool(genome_data.get("actor_only", False)))  # fmt: skip
    width, height = int(grid["width"]), int(grid["height"])
    torus = Torus(width, height)
    evaluator = GridEvaluator(torus, spec, int(config.get("steps", 500)))
    start = Poses.from_rows(grid["start"]).to_cells(torus)
    result = evaluator.evaluate(np.array(genome_data["genome"])[None, :], start[None], trace=(0, 0))
    final = Poses.from_cells(torus, result.final[0, 0])
    c = classify(width, height, final)
    plot_grid(width, height, final, run / "replay_final", title=f"{c.pattern} ({c.quality:.0%})")
    assert result.trace is not None
    gif = animate(width, height, result.trace, run / "replay.gif", every=args.every)
    print(f"fitness of the replay: {result.fitness[0, 0]:.4f}")
    print(f"pattern: {c.pattern}, quality {c.quality:.0%}")
    print(f"wrote {run / 'replay_final.png'}, {gif}")
    return 0


def _classify(args: argparse.Namespace) -> int:
    from gridworld.patterns import classify
    from gridworld.world import Poses

    try:
        data = json.loads(args.grid.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"cannot read the grid: {exc}", file=str(args.grid)) from None
    for key in ("width", "height"):
        if not isinstance(data.get(key), int) or data[key] < 1:
            raise ConfigError("expected a positive integer", file=str(args.grid), key=key)
    rows = data.get("final", data.get("poses"))
    if not isinstance(rows, list):
        raise ConfigError("expected a list of [x, y, hx, hy]", file=str(args.grid), key="final")
    try:
        c = classify(data["width"], data["height"], Poses.from_rows(rows))
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(exc), file=str(args.grid), key="final") from None
    print(json.dumps({"pattern": c.pattern, "quality": c.quality, "scores": c.scores}, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
