"""MAP-Elites in the grid world: an archive of the best genome per cell of pattern measures.

Quality diversity through pyribs (``ribs``): a :class:`ribs.archives.GridArchive` over the
measures the configuration names (each a pattern's fraction of agents, ``GridMeasure``), a
:class:`ribs.emitters.GaussianEmitter` and a :class:`ribs.schedulers.Scheduler` asked and told
once per batch. The objective is the GA's fitness (the swarm's prediction accuracy, the worst of
``repetitions`` runs by default); the measures and the class are read on the final grid of the
run that stands for that fitness, as a GA run classifies its best genome. A batch of
``population`` candidates is one compiled call on shared start configurations, like a
generation; ``generations`` batches are the budget.

Every random draw comes from the run's seed and the batch: the starts and noise of batch b are
those of generation b of a GA run with the seed (:func:`gridworld.evolve.generation_starts`), the
first batch is ``population`` uniform random genomes (``default_rng([seed, 3])``), and the
archive's and the emitter's generators of batch b are seeded from ``[seed, 5, b]`` and
``[seed, 4, b]``. The archive is built afresh from its elites at every batch, so a run's state
between batches is its elites alone: the checkpoint (``checkpoint.json`` naming an
``archive-<batch>.npz``) holds them, and a resumed run ends with the same archive, bit for bit.

Files of a run directory: ``config.json``; ``checkpoint.json`` and its ``archive-<batch>.npz``;
``qd_progress.csv`` (per batch: evaluations, elites, coverage, QD score, best and batch mean
fitness, elites per class); once finished ``archive.csv`` (per elite: cell, measures, fitness,
class, quality, the nine scores, the evaluation that found it, the genes), the plots
(``archive_heatmap``, ``qd_progress``), ``elites.json`` and ``elites/<class>/`` (the best elite
of each class, post-evaluated), ``best_genome.json`` and ``final_grid.json`` (the best elite's
post-evaluation) and ``summary.json``.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from gridworld.config import GridRunConfig
from gridworld.evolve import (
    GenerationReport,
    evaluator_of,
    generation_noise_key,
    generation_starts,
    open_run,
    write_best,
    write_csv,
    write_final_grid,
)
from gridworld.patterns import PATTERNS, classify
from gridworld.world import Poses, Torus, draw_starts
from minimize_surprise.config import to_builtins
from minimize_surprise.errors import ConfigError
from minimize_surprise.files import write_atomic, write_json
from minimize_surprise.genetic import reduce_repetitions

__all__ = ["CHECKPOINT_VERSION", "Elites", "run_map_elites"]

#: Version of a MAP-Elites run's checkpoint.json; bump when its shape changes.
CHECKPOINT_VERSION = 1

#: Columns of qd_progress.csv before the elites per class.
PROGRESS_COLUMNS = (
    "batch",
    "evaluations",
    "elites",
    "coverage",
    "qd_score",
    "best_fitness",
    "mean_fitness",
    "classes",
)


@dataclass(frozen=True)
class Elites:
    """An archive's content, in the archive's order: ``genomes`` (E, G), ``fitness`` (E,),
    ``measures`` (E, M), ``pattern`` (E,) index into :data:`~gridworld.patterns.PATTERNS`,
    ``quality`` (E,), ``scores`` (E, 9) in PATTERNS order, ``evaluation`` (E,) the 0-based
    number of the evaluation that found the elite, ``cell`` (E,) the archive's cell index."""

    genomes: np.ndarray
    fitness: np.ndarray
    measures: np.ndarray
    pattern: np.ndarray
    quality: np.ndarray
    scores: np.ndarray
    evaluation: np.ndarray
    cell: np.ndarray

    def __len__(self) -> int:
        return int(self.fitness.shape[0])

    @classmethod
    def empty(cls, genes: int, measures: int) -> Elites:
        """No elite yet."""
        return cls(
            genomes=np.zeros((0, genes)), fitness=np.zeros(0), measures=np.zeros((0, measures)),
            pattern=np.zeros(0, np.int32), quality=np.zeros(0), scores=np.zeros((0, 9)),
            evaluation=np.zeros(0, np.int64), cell=np.zeros(0, np.int64),
        )  # fmt: skip

    def to_npz(self) -> bytes:
        """The arrays as an uncompressed ``.npz`` file's bytes (float64 kept exactly)."""
        buffer = io.BytesIO()
        np.savez(buffer, **{f.name: getattr(self, f.name) for f in fields(self)})
        return buffer.getvalue()

    @classmethod
    def from_npz(cls, path: Path) -> Elites:
        """Read what :meth:`to_npz` wrote."""
        with np.load(path) as data:
            return cls(**{f.name: data[f.name] for f in fields(cls)})

    def best_of(self, pattern: int) -> int | None:
        """The index of the fittest elite of class ``pattern`` (the first of equals), or None."""
        where = np.flatnonzero(self.pattern == pattern)
        if not where.size:
            return None
        return int(where[np.argmax(self.fitness[where])])


def _ribs():
    # pyribs comes with the `qd` extra; the rest of the grid world runs without it.
    try:
        from ribs.emitters import GaussianEmitter
        from ribs.schedulers import Scheduler
    except ImportError as exc:
        raise ConfigError(
            f"MAP-Elites needs pyribs ({exc}): pip install '.[qd]'", key="optimizer"
        ) from None
    return GaussianEmitter, Scheduler


def _seed(*key: int) -> int:
    return int(np.random.default_rng(list(key)).integers(0, 2**63))


def _archive(config: GridRunConfig, genes: int, elites: Elites, seed: int, batch: int):
    from ribs.archives import GridArchive

    measures = config.archive_measures()
    archive = GridArchive(
        solution_dim=genes,
        dims=[m.bins for m in measures],
        ranges=[m.range for m in measures],
        seed=_seed(seed, 5, batch),
        extra_fields={
            "pattern": ((), np.int32),
            "quality": ((), np.float64),
            "scores": ((len(PATTERNS),), np.float64),
            "evaluation": ((), np.int64),
        },
    )
    if len(elites):
        archive.add(
            solution=elites.genomes, objective=elites.fitness, measures=elites.measures,
            pattern=elites.pattern, quality=elites.quality, scores=elites.scores,
            evaluation=elites.evaluation,
        )  # fmt: skip
        assert len(archive) == len(elites), "every elite has a cell of its own"
    return archive


def _elites_of(archive) -> Elites:
    data = archive.data()
    return Elites(
        genomes=data["solution"], fitness=data["objective"], measures=data["measures"],
        pattern=data["pattern"], quality=data["quality"], scores=data["scores"],
        evaluation=data["evaluation"], cell=data["index"],
    )  # fmt: skip


def _progress_row(
    batch: int, evaluations: int, archive, elites: Elites, batch_fitness: np.ndarray
) -> list:
    per_class = np.bincount(elites.pattern, minlength=len(PATTERNS))
    stats = archive.stats
    return [
        batch,
        evaluations,
        len(elites),
        float(stats.coverage),
        float(stats.qd_score),
        float(elites.fitness.max()),
        float(batch_fitness.mean()),
        int(np.count_nonzero(per_class)),
        *per_class.tolist(),
    ]


def run_map_elites(
    config: GridRunConfig | None,
    seed: int | None,
    out: str | Path,
    *,
    progress: Callable[[GenerationReport], None] | None = None,
    plots: bool = True,
    checkpoint_seconds: float = 10.0,
) -> dict[str, Any]:
    """Run (or continue) a MAP-Elites run in ``out`` and return its summary.

    A new run needs ``config`` (``optimizer: map-elites``) and ``seed``; a directory holding an
    unfinished run continues from its checkpoint with the stored configuration and seed, a
    finished one raises :class:`~gridworld.evolve.RunFinished`. The checkpoint is written when
    ``checkpoint_seconds`` have passed since the last one (0: after every batch) and at the end.
    """
    out = Path(out)
    config, seed = open_run(out, config, seed)
    checkpoint_file = out / "checkpoint.json"
    if config.optimizer != "map-elites":
        raise ValueError(f"{out}: the run's optimizer is {config.optimizer}, not map-elites")
    seed = int(seed)
    evaluator = evaluator_of(config)
    genes = evaluator.layout.size
    measures = config.archive_measures()
    columns = [*PROGRESS_COLUMNS, *(f"elites_{p}" for p in PATTERNS)]
    if checkpoint_file.exists():
        ck = json.loads(checkpoint_file.read_text(encoding="utf-8"))
        if ck.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"{checkpoint_file}: checkpoint version {ck.get('version')} unknown")
        elites = Elites.from_npz(out / ck["archive"])
        batch, rows, elapsed = int(ck["batch"]), ck["rows"], float(ck["elapsed_s"])
    else:
        elites, batch, rows, elapsed = Elites.empty(genes, len(measures)), 0, [], 0.0
    initial = np.random.default_rng([seed, 3]).uniform(
        -config.initial_range, config.initial_range, (config.population, genes)
    )
    measure_index = [PATTERNS.index(m.name) for m in measures]
    last_checkpoint = time.monotonic()

    def checkpoint() -> None:
        # The elites first, then the file naming them: a kill in between leaves the last
        # checkpoint whole, and the one before (or a stray one) is removed only after.
        name = f"archive-{batch}.npz"
        write_atomic(out / name, elites.to_npz())
        write_json(checkpoint_file, {
            "version": CHECKPOINT_VERSION, "batch": batch, "archive": name, "rows": rows,
            "elapsed_s": elapsed,
        })  # fmt: skip
        write_csv(out / "qd_progress.csv", columns, rows)
        for old in out.glob("archive-*.npz"):
            if old.name != name:
                old.unlink(missing_ok=True)

    GaussianEmitter, Scheduler = _ribs()
    while batch < config.generations:
        started = time.perf_counter()
        archive = _archive(config, genes, elites, seed, batch)
        emitter = GaussianEmitter(
            archive, sigma=config.sigma, initial_solutions=initial,
            batch_size=config.population, seed=_seed(seed, 4, batch),
        )  # fmt: skip
        scheduler = Scheduler(archive, [emitter])
        genomes = scheduler.ask()
        starts = generation_starts(config, seed, batch)
        result = evaluator.evaluate(genomes, starts, generation_noise_key(seed, batch))
        fitness, reps = reduce_repetitions(result.fitness, config.fitness_of)
        scores = np.empty((genomes.shape[0], len(PATTERNS)))
        pattern = np.empty(genomes.shape[0], np.int32)
        quality = np.empty(genomes.shape[0])
        for i in range(genomes.shape[0]):
            poses = Poses.from_cells(evaluator.torus, result.final[i, int(reps[i])])
            c = classify(config.size, config.grid_height, poses)
            scores[i] = [c.scores[p] for p in PATTERNS]
            pattern[i], quality[i] = PATTERNS.index(c.pattern), c.quality
        done = batch * config.population
        scheduler.tell(
            fitness, scores[:, measure_index], pattern=pattern, quality=quality, scores=scores,
            evaluation=np.arange(done, done + genomes.shape[0], dtype=np.int64),
        )  # fmt: skip
        elites = _elites_of(archive)
        batch += 1
        rows.append(_progress_row(batch, done + genomes.shape[0], archive, elites, fitness))
        elapsed += time.perf_counter() - started
        if time.monotonic() - last_checkpoint >= checkpoint_seconds:
            checkpoint()
            last_checkpoint = time.monotonic()
        if progress is not None:
            progress(GenerationReport(batch, config.generations, float(elites.fitness.max()),
                                      float(fitness.mean()), elapsed))  # fmt: skip
    checkpoint()
    return _finish(out, config, seed, elites, rows, elapsed, plots)


def _post_evaluate(config: GridRunConfig, seed: int, elites: Elites) -> dict[str, dict[str, Any]]:
    """The best elite of each class run again from fresh starts (``[seed, 6]``; noise
    ``[seed, 7]``), all in one call; per class code: its index, fitness, pattern, ...."""
    chosen = [(code, elites.best_of(k)) for k, code in enumerate(PATTERNS)]
    present = [(code, i) for code, i in chosen if i is not None]
    evaluator = evaluator_of(config)
    torus = Torus(config.size, config.grid_height)
    starts = draw_starts(np.random.default_rng([seed, 6]), torus, config.agents,
                         config.repetitions)  # fmt: skip
    noise_key = int(np.random.default_rng([seed, 7]).integers(0, 2**32))
    genomes = elites.genomes[[i for _, i in present]]
    result = evaluator.evaluate(genomes, starts, noise_key)
    fitness, reps = reduce_repetitions(result.fitness, config.fitness_of)
    post: dict[str, dict[str, Any]] = {}
    for row, (code, i) in enumerate(present):
        rep = int(reps[row])
        final = Poses.from_cells(torus, result.final[row, rep])
        c = classify(config.size, config.grid_height, final)
        post[code] = {
            "index": i,
            "archive_fitness": float(elites.fitness[i]),
            "archive_quality": float(elites.quality[i]),
            "measures": elites.measures[i].tolist(),
            "evaluation": int(elites.evaluation[i]),
            "fitness": float(fitness[row]),
            "run_fitness": result.fitness[row].tolist(),
            "pattern": c.pattern,
            "quality": c.quality,
            "scores": c.scores,
            "repetition": rep,
            "start": Poses.from_cells(torus, starts[rep]).to_rows(),
            "final": final.to_rows(),
            "predictions": result.predictions[row, rep].tolist(),
        }
    return post


def _write_elite(directory: Path, config: GridRunConfig, seed: int, elites: Elites,
                 entry: dict[str, Any]) -> None:  # fmt: skip
    directory.mkdir(parents=True, exist_ok=True)
    i = entry["index"]
    write_json(directory / "config.json", {"config": to_builtins(config), "seed": seed})
    write_best(directory, elites.genomes[i], config.net_spec(), entry["fitness"],
               archive_fitness=entry["archive_fitness"], evaluation=entry["evaluation"],
               measures=entry["measures"])  # fmt: skip
    write_final_grid(directory, config.size, config.grid_height, entry["repetition"],
                     entry["start"], entry["final"])  # fmt: skip


def _archive_rows(config: GridRunConfig, elites: Elites) -> tuple[list[str], list[list[Any]]]:
    names = [m.name for m in config.archive_measures()]
    header = ["cell", *(f"measure_{n}" for n in names), "fitness", "pattern", "quality",
              "evaluation", *(f"score_{p}" for p in PATTERNS),
              *(f"gene_{k}" for k in range(elites.genomes.shape[1]))]  # fmt: skip
    order = np.argsort(elites.cell, kind="stable")
    rows = [
        [int(elites.cell[i]), *elites.measures[i].tolist(), float(elites.fitness[i]),
         PATTERNS[int(elites.pattern[i])], float(elites.quality[i]), int(elites.evaluation[i]),
         *elites.scores[i].tolist(), *elites.genomes[i].tolist()]
        for i in order
    ]  # fmt: skip
    return header, rows


def _finish(
    out: Path,
    config: GridRunConfig,
    seed: int,
    elites: Elites,
    rows: list[list[Any]],
    elapsed: float,
    plots: bool,
) -> dict[str, Any]:
    header, table = _archive_rows(config, elites)
    write_csv(out / "archive.csv", header, table)
    post = _post_evaluate(config, seed, elites)
    for code, entry in post.items():
        _write_elite(out / "elites" / code, config, seed, elites, entry)
    best = int(np.argmax(elites.fitness))
    best_code = PATTERNS[int(elites.pattern[best])]
    top = post[best_code]  # the fittest elite is the fittest of its class
    write_best(out, elites.genomes[best], config.net_spec(), float(elites.fitness[best]),
               evaluation=int(elites.evaluation[best]), post_fitness=top["fitness"])  # fmt: skip
    write_final_grid(out, config.size, config.grid_height, top["repetition"], top["start"],
                     top["final"])  # fmt: skip
    elites_file = {
        code: {k: v for k, v in entry.items() if k not in ("start", "final")}
        for code, entry in post.items()
    }
    write_json(out / "elites.json", elites_file)
    counts = np.bincount(elites.pattern, minlength=len(PATTERNS))
    last = rows[-1]
    summary: dict[str, Any] = {
        "kind": "grid-qd",
        "seed": seed,
        "size": config.size,
        "height": config.grid_height,
        "agents": config.agents,
        "generations": config.generations,
        "evaluations": int(last[1]),
        "cells": int(np.prod([m.bins for m in config.archive_measures()])),
        "measures": [to_builtins(m) for m in config.archive_measures()],
        "elites": len(elites),
        "coverage": float(last[3]),
        "qd_score": float(last[4]),
        "best_fitness": float(elites.fitness[best]),
        "fitness": float(elites.fitness[best]),
        "pattern": best_code,
        "quality": float(elites.quality[best]),
        "scores": dict(zip(PATTERNS, elites.scores[best].tolist(), strict=True)),
        "mean_predictions": top["predictions"],
        "patterns_found": [p for p, n in zip(PATTERNS, counts, strict=True) if n],
        "pattern_count": int(np.count_nonzero(counts)),
        "elites_per_pattern": {p: int(n) for p, n in zip(PATTERNS, counts, strict=True) if n},
        "post_evaluation": {
            code: {"fitness": e["fitness"], "pattern": e["pattern"], "quality": e["quality"]}
            for code, e in post.items()
        },
        "post_patterns_found": [p for p in PATTERNS if p in {e["pattern"] for e in post.values()}],
        "archive_file": "archive.csv",
        "generations_file": None,
        "progress_file": "qd_progress.csv",
        "seconds": elapsed,
    }
    if plots:
        from gridworld.plots import plot_grid
        from gridworld.qd_plots import plot_archive, plot_progress

        plot_archive(out / "archive.csv", config.archive_measures(), out / "archive_heatmap")
        plot_progress(out / "qd_progress.csv", out / "qd_progress")
        for code, entry in post.items():
            title = (f"{code} elite, post-evaluated: {entry['pattern']} "
                     f"({entry['quality']:.0%}), fitness {entry['fitness']:.3f}")  # fmt: skip
            plot_grid(config.size, config.grid_height, Poses.from_rows(entry["final"]),
                      out / "elites" / code / "final_grid", title=title)  # fmt: skip
        plot_grid(config.size, config.grid_height, Poses.from_rows(top["final"]),
                  out / "final_grid", title=f"{top['pattern']} ({top['quality']:.0%})")  # fmt: skip
    write_json(out / "summary.json", summary)
    return summary
