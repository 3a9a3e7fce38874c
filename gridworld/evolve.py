"""One evolution run in the grid world, with a checkpoint after every generation.

Every random draw comes from the run's seed: the GA's generator, the start configurations of
generation g (shared by all genomes of that generation, as in the authors' code), the noise flips
of generation g, and the novelty archive's draws. Starts and noise are pure functions of (seed, g),
so a resumed run needs only the GA's and the archive's states to continue bit for bit.

A run directory holds ``config.json`` (configuration and seed), ``checkpoint.json`` (written
atomically after each generation), ``generations.csv`` (per generation: best and mean fitness,
the best genome's index and its standing repetition's mean prediction per sensor), and once
finished ``best_genome.json``, ``final_grid.json`` (start and final poses of the classified run),
``summary.json`` and the plots. Novelty runs also write ``individuals.csv``: every individual's
novelty, behaviour vector, pattern and quality.
"""

from __future__ import annotations

import csv
import io
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gridworld.config import GridRunConfig, decode_run_config
from gridworld.evaluate import GridEvaluator
from gridworld.patterns import classify
from gridworld.world import Poses, Torus, draw_starts
from minimize_surprise.config import to_builtins
from minimize_surprise.files import write_atomic, write_json
from minimize_surprise.genetic import GeneticAlgorithm
from minimize_surprise.gridnet import GridNetSpec
from minimize_surprise.novelty import NoveltyArchive

__all__ = [
    "GenerationReport",
    "RunFinished",
    "evaluator_of",
    "generation_noise_key",
    "generation_starts",
    "load_best",
    "open_run",
    "run_evolution",
    "write_best",
    "write_csv",
    "write_final_grid",
]

#: Version of checkpoint.json; bump when its shape changes.
CHECKPOINT_VERSION = 1


def open_run(
    out: Path, config: GridRunConfig | None, seed: int | None
) -> tuple[GridRunConfig, int]:
    """The configuration and seed of the run in ``out``: those it stored, for a run to continue
    (a finished one raises :class:`RunFinished`), else ``config`` and ``seed``, stored there for
    a new run (a ``ValueError`` without them)."""
    out.mkdir(parents=True, exist_ok=True)
    stored = out / "config.json"
    if stored.exists():
        data = json.loads(stored.read_text(encoding="utf-8"))
        if (out / "summary.json").exists():
            raise RunFinished(json.loads((out / "summary.json").read_text(encoding="utf-8")))
        return decode_run_config(data["config"], file=stored), int(data["seed"])
    if config is None or seed is None:
        raise ValueError(f"{out} holds no run: a configuration and a seed are needed")
    write_json(stored, {"config": to_builtins(config), "seed": seed})
    return config, int(seed)


class RunFinished(Exception):
    """The run directory holds a finished run; ``summary`` is its summary."""

    def __init__(self, summary: dict[str, Any]) -> None:
        super().__init__("the run is finished")
        self.summary = summary


@dataclass(frozen=True)
class GenerationReport:
    """Progress after a generation: ``generation`` done of ``total``, best and mean fitness."""

    generation: int
    total: int
    best_fitness: float
    mean_fitness: float
    elapsed_s: float


def write_best(run_dir: Path, genome: Any, spec: GridNetSpec, fitness: float, **extra: Any) -> None:
    """Write a run's best genome and its network spec to ``best_genome.json`` (with ``extra``
    keys, e.g. the generation that found it)."""
    write_json(run_dir / "best_genome.json", {
        "genome": np.asarray(genome).tolist(), "sensors": spec.sensors,
        "predefined": spec.predefined, "actor_only": spec.actor_only, "fitness": fitness, **extra,
    })  # fmt: skip


def write_final_grid(
    run_dir: Path, width: int, height: int, repetition: int, start: list, final: list
) -> None:
    """Write the start and final poses (``Poses.to_rows``) of a run's recorded repetition to
    ``final_grid.json``."""
    write_json(run_dir / "final_grid.json", {
        "width": width, "height": height, "repetition": repetition,
        "start": start, "final": final,
    })  # fmt: skip


def load_best(run_dir: Path) -> tuple[np.ndarray, GridNetSpec, dict[str, Any]]:
    """The best genome, its network spec and the final grid that :func:`write_best` and
    :func:`write_final_grid` wrote; raises OSError, ValueError or KeyError for a run directory
    that does not hold them."""
    data = json.loads((run_dir / "best_genome.json").read_text(encoding="utf-8"))
    grid = json.loads((run_dir / "final_grid.json").read_text(encoding="utf-8"))
    spec = GridNetSpec(int(data["sensors"]), data.get("predefined"),
                       bool(data.get("actor_only", False)))  # fmt: skip
    return np.array(data["genome"], dtype=np.float64), spec, grid


def evaluator_of(config: GridRunConfig, exact: bool = False) -> GridEvaluator:
    """The evaluator of a run's world and networks."""
    torus = Torus(config.size, config.grid_height)
    return GridEvaluator(torus, config.net_spec(), config.steps, config.noise, exact)


def generation_starts(config: GridRunConfig, seed: int, generation: int) -> np.ndarray:
    """The start configurations of ``generation`` of the run with ``seed``."""
    rng = np.random.default_rng([seed, 1, generation])
    torus = Torus(config.size, config.grid_height)
    return draw_starts(rng, torus, config.agents, config.repetitions)


def generation_noise_key(seed: int, generation: int) -> int:
    """The noise key of ``generation`` of the run with ``seed``."""
    return int(np.random.default_rng([seed, 2, generation]).integers(0, 2**32))


def _columns(sensors: int) -> list[str]:
    cols = ["generation", "best_fitness", "mean_fitness", "best_index", "repetition"]
    return cols + [f"prediction_{k}" for k in range(sensors)]


def write_csv(path: Path, header: list[str], rows: list[list[Any]]) -> None:
    """Replace ``path`` by a CSV file of ``header`` and ``rows``, all at once."""
    text = io.StringIO(newline="")
    writer = csv.writer(text)
    writer.writerow(header)
    writer.writerows(rows)
    write_atomic(path, text.getvalue().encode("utf-8"))


def _individual_columns(sensors: int) -> list[str]:
    cols = ["generation", "index", "novelty", "pattern", "quality"]
    return cols + [f"behaviour_{k}" for k in range(sensors)]


def run_evolution(
    config: GridRunConfig | None,
    seed: int | None,
    out: str | Path,
    *,
    progress: Callable[[GenerationReport], None] | None = None,
    plots: bool = True,
) -> dict[str, Any]:
    """Run (or continue) the evolution in ``out`` and return its summary.

    A new run needs ``config`` and ``seed``. If ``out`` holds an unfinished run it continues
    from the checkpoint with the stored configuration and seed (``config`` and ``seed`` may be
    None); a finished run raises :class:`RunFinished`.
    """
    out = Path(out)
    config, seed = open_run(out, config, seed)
    checkpoint_file = out / "checkpoint.json"
    if config.optimizer != "ga":
        raise ValueError(f"{out}: a {config.optimizer} run (gridworld.qd), not the GA's")
    evaluator = evaluator_of(config)
    spec = config.net_spec()
    sensors = spec.sensors
    genetic = config.genetic()
    if checkpoint_file.exists():
        ck = json.loads(checkpoint_file.read_text(encoding="utf-8"))
        if ck.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{checkpoint_file}: checkpoint version {ck.get('version')} unknown")
        ga = GeneticAlgorithm.from_state(genetic, ck["ga"])
        archive = NoveltyArchive.from_state(ck["archive"]) if ck["archive"] else None
        rows, last, elapsed = ck["rows"], ck["last"], float(ck["elapsed_s"])
    else:
        ga = GeneticAlgorithm(genetic, evaluator.layout.size, seed=int(seed))
        archive = (
            NoveltyArchive(sensors, int(seed) + 1, config.novelty_k, config.archive_probability)
            if config.novelty
            else None
        )
        rows, last, elapsed = [], None, 0.0
    individuals_file = out / "individuals.csv"
    if config.novelty:
        done_rows = []
        if individuals_file.exists() and ga.generation > 0:
            with individuals_file.open(encoding="utf-8") as f:
                reader = csv.reader(f)
                next(reader)
                done_rows = [row for row in reader if int(row[0]) < ga.generation]
        write_csv(individuals_file, _individual_columns(sensors), done_rows)
    while not ga.done:
        started = time.perf_counter()
        g = ga.generation
        genomes = ga.ask()
        starts = generation_starts(config, int(seed), g)
        result = evaluator.evaluate(genomes, starts, generation_noise_key(int(seed), g))
        if archive is not None:
            behaviour = result.behaviour.mean(axis=1)
            novelty = archive.score(behaviour)
            outcome = ga.tell(novelty)
            best, rep = outcome.best_index, 0
            records = []
            for i in range(genomes.shape[0]):
                # novelty individuals are classified on their first run (docs/gridworld.md)
                c = classify(
                    config.size,
                    config.grid_height,
                    Poses.from_cells(evaluator.torus, result.final[i, 0]),
                )
                records.append(
                    [g, i, float(novelty[i]), c.pattern, c.quality, *behaviour[i].tolist()]
                )
            with individuals_file.open("a", newline="", encoding="utf-8") as f:
                csv.writer(f).writerows(records)
            fitness_best = float(novelty[best])
        else:
            outcome = ga.tell(result.fitness)
            best = outcome.best_index
            rep = int(outcome.repetition[best]) if outcome.repetition is not None else 0
            fitness_best = outcome.best_fitness
        row = [g, fitness_best, outcome.mean_fitness, best, rep]
        row += result.predictions[best, rep].tolist()
        rows.append(row)
        last = {
            "generation": g,
            "best_index": best,
            "repetition": rep,
            "fitness": fitness_best,
            "run_fitness": result.fitness[best].tolist(),
            "genome": outcome.best_genome.tolist(),
            "start": Poses.from_cells(evaluator.torus, starts[rep]).to_rows(),
            "final": Poses.from_cells(evaluator.torus, result.final[best, rep]).to_rows(),
            "predictions": result.predictions[best, rep].tolist(),
        }
        elapsed += time.perf_counter() - started
        state = {
            "version": CHECKPOINT_VERSION,
            "ga": ga.state(),
            "archive": archive.state() if archive is not None else None,
            "rows": rows,
            "last": last,
            "elapsed_s": elapsed,
        }
        write_json(checkpoint_file, state)
        write_csv(out / "generations.csv", _columns(sensors), rows)
        if progress is not None:
            progress(
                GenerationReport(g + 1, genetic.generations, fitness_best, outcome.mean_fitness,
                                 elapsed)
            )  # fmt: skip
    assert last is not None
    return _finish(out, config, int(seed), last, elapsed, plots)


def _finish(
    out: Path, config: GridRunConfig, seed: int, last: dict[str, Any], elapsed: float, plots: bool
) -> dict[str, Any]:
    final = Poses.from_rows(last["final"])
    c = classify(config.size, config.grid_height, final)
    write_best(out, last["genome"], config.net_spec(), last["fitness"],
               generation=last["generation"])  # fmt: skip
    write_final_grid(out, config.size, config.grid_height, last["repetition"], last["start"],
                     last["final"])  # fmt: skip
    summary: dict[str, Any] = {
        "kind": "grid-novelty" if config.novelty else "grid-evolved",
        "seed": seed,
        "size": config.size,
        "height": config.grid_height,
        "agents": config.agents,
        "generations": config.generations,
        "best_fitness": None if config.novelty else last["fitness"],
        "fitness": None if config.novelty else last["fitness"],
        "run_fitness": None if config.novelty else last["run_fitness"],
        "pattern": c.pattern,
        "quality": c.quality,
        "scores": c.scores,
        "mean_predictions": last["predictions"],
        "generations_file": "generations.csv",
        "seconds": elapsed,
    }
    if config.novelty:
        summary.update(_novelty_summary(out))
    if plots:
        from gridworld.plots import plot_fitness, plot_grid

        plot_fitness(out / "generations.csv", out / "fitness", novelty=config.novelty)
        plot_grid(config.size, config.grid_height, final, out / "final_grid",
                  title=f"{c.pattern} ({c.quality:.0%})")  # fmt: skip
    write_json(out / "summary.json", summary)
    return summary


def _novelty_summary(out: Path) -> dict[str, Any]:
    with (out / "individuals.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    counts: dict[str, int] = {}
    for row in rows:
        counts[row["pattern"]] = counts.get(row["pattern"], 0) + 1
    best = max(rows, key=lambda r: float(r["quality"]))
    qualities = np.array([float(r["quality"]) for r in rows])
    novelties = np.array([float(r["novelty"]) for r in rows])
    return {
        "best_novelty": float(novelties.max()),
        "individuals_file": "individuals.csv",
        "individuals": len(rows),
        "pattern_counts": counts,
        "quality_median": float(np.median(qualities)),
        "quality_best": {
            "generation": int(best["generation"]),
            "index": int(best["index"]),
            "pattern": best["pattern"],
            "quality": float(best["quality"]),
        },
    }
