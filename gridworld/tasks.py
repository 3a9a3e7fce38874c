"""The grid world's tasks for the studies: plain data in, plain data out.

``run_task(kind, params, seed, run_dir)`` runs one task of :data:`GRID_KINDS`, writes its files
into ``run_dir`` (created) and returns a JSON-safe summary (the studies layer writes it) with at
least ``kind``, ``seed``, ``size``, ``best_fitness`` and ``fitness`` (the same number; None for
novelty search, which has no predictor), ``pattern``, ``quality``, ``scores`` (pattern ->
fraction), ``mean_predictions`` (one per sensor), ``generations_file`` (relative path of the
per-generation CSV, or None) and ``seconds``. The same seed gives the same result. ``params`` are
decoded strictly per kind: an unknown or ill-typed key is a
:class:`~minimize_surprise.errors.ConfigError` naming it.

Kinds:

- ``grid-evolved``: a GA run (:class:`gridworld.config.GridRunConfig`'s keys).
- ``grid-random``: one random genome, scored as the GA scores a genome (``repetitions`` runs of
  ``steps`` steps, reduced by ``fitness_of``).
- ``grid-selected-random``: the best by that score of ``candidates`` random genomes (default
  5000), all on the same start configurations (the code with population = candidates and one
  generation).
- ``grid-qd``: a MAP-Elites run (:mod:`gridworld.qd`; ``GridRunConfig``'s keys with
  ``optimizer: map-elites``, ``measures`` the archive's axes); the summary is the archive's:
  ``patterns_found``, ``elites_per_pattern``, ``coverage``, ``qd_score``, the post-evaluation of
  each class's best elite, and ``pattern``/``best_fitness`` of the fittest elite.
- ``grid-novelty``: a novelty-search run; ``individuals.csv`` holds every individual's novelty,
  behaviour, pattern and quality, the summary its pattern counts and the quality-best one.
- ``grid-damage``: rerun an evolved genome (``genome_run``: a run directory, or ``genome`` and
  ``start``), remove the agents in the rectangle ``[xmin, xmax] x [ymin, ymax]`` of its final
  structure (``variant: remove``) or put them back at random free cells outside it
  (``reposition``), then run ``steps`` more steps; similarity S = share of the N0 agents of the
  initial run whose final pose is a final pose of the repair.
- ``grid-rerun``: rerun an evolved genome (``genome_run`` or ``genome``) on another grid from
  random starts (``repetitions`` runs, default 1).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import numpy as np

from gridworld.config import GridRunConfig, GridWorldParams, PositiveInt
from gridworld.evaluate import GridEvaluator
from gridworld.evolve import (
    RunFinished,
    load_best,
    run_evolution,
    write_best,
    write_final_grid,
)
from gridworld.patterns import classify
from gridworld.qd import run_map_elites
from gridworld.world import Poses, Torus, draw_starts
from minimize_surprise.config import Probability, Strict, decode
from minimize_surprise.errors import ConfigError
from minimize_surprise.files import write_json
from minimize_surprise.genetic import reduce_repetitions
from minimize_surprise.gridnet import GridGenomeLayout, GridNetSpec

__all__ = ["GRID_KINDS", "check_params", "run_task"]

#: The task kinds :func:`run_task` knows.
GRID_KINDS: tuple[str, ...] = (
    "grid-evolved",
    "grid-random",
    "grid-selected-random",
    "grid-novelty",
    "grid-damage",
    "grid-rerun",
    "grid-qd",
)

NonNegativeInt = Annotated[int, msgspec.Meta(ge=0)]


class RandomParams(GridWorldParams, frozen=True):
    """Parameters of ``grid-random`` and ``grid-selected-random``: the world's, and how many
    random genomes the selected one is the best of (``candidates``)."""

    #: random genomes the selected one is the best of (`grid-selected-random`; 1 for
    #: `grid-random`)
    candidates: PositiveInt = 5000


class GenomeParams(Strict, frozen=True):
    """The genome of ``grid-damage`` and ``grid-rerun``: a run directory, or the genome inline
    with its sensors and predefined predictions (and, for damage, its start poses)."""

    #: the evolved run whose best genome is used: in a study, a run below its `runs/`
    #: (`{seed}`: the run's own seed); else a directory
    genome_run: str | None = None
    #: the genome inline, instead of `genome_run`
    genome: list[float] | None = None
    #: an inline genome's sensor model
    sensors: Literal[14, 6, 8] = 14
    #: an inline genome's fixed predictions
    predefined: str | None = None
    #: an inline genome's start poses `[x, y, hx, hy]` (damage)
    start: list[list[int]] | None = None


class RerunParams(GenomeParams, frozen=True):
    """Parameters of ``grid-rerun``: the new grid and how many runs."""

    #: the new torus side L
    size: PositiveInt = 15
    #: the new torus height (default: L)
    height: PositiveInt | None = None
    #: agents N on the new grid, from random starts
    agents: PositiveInt = 100
    #: the probability of flipping each sensor reading
    noise: Probability = 0.0
    #: runs from different starts, scored by the worst
    repetitions: PositiveInt = 1
    #: steps T per run
    steps: PositiveInt = 500


class DamageParams(GenomeParams, frozen=True):
    """Parameters of ``grid-damage``: the rectangle, the variant, and the grid of the genome's
    run (taken from ``genome_run`` when given)."""

    #: `remove` the agents in the rectangle, or `reposition` them at random free cells outside
    variant: Literal["remove", "reposition"] = "remove"
    #: the rectangle's first column (not wrapping)
    xmin: NonNegativeInt = 0
    #: its last column
    xmax: NonNegativeInt = 3
    #: its first row
    ymin: NonNegativeInt = 0
    #: its last row
    ymax: NonNegativeInt = 3
    #: the torus side of an inline genome's run (from `genome_run` otherwise)
    size: PositiveInt = 15
    #: its height (default: L)
    height: PositiveInt | None = None
    #: steps of the undamaged run, and of the repair
    steps: PositiveInt = 500


def _decode(params: dict, type_, kind: str):
    return decode(params, type_, file=f"<{kind} params>")


def check_params(kind: str, params: dict | None) -> Any:
    """Decode ``params`` for ``kind`` as :func:`run_task` does, without running anything: the
    typed parameters, or a :class:`~minimize_surprise.errors.ConfigError` naming the bad key (a
    study checks every run this way before it starts one)."""
    if kind not in GRID_KINDS:
        raise ConfigError(f"unknown kind {kind!r}; expected one of {', '.join(GRID_KINDS)}")
    params = dict(params or {})
    if kind in ("grid-evolved", "grid-novelty", "grid-qd"):
        if kind == "grid-novelty":
            params.setdefault("novelty", True)
        if kind == "grid-qd":
            params.setdefault("optimizer", "map-elites")
        config = _decode(params, GridRunConfig, kind)
        if config.novelty != (kind == "grid-novelty"):
            raise ConfigError("novelty must match the kind", file=f"<{kind} params>",
                              key="novelty")  # fmt: skip
        if (config.optimizer == "map-elites") != (kind == "grid-qd"):
            raise ConfigError(
                f"optimizer {config.optimizer} does not match the kind (map-elites is grid-qd)",
                file=f"<{kind} params>", key="optimizer",
            )  # fmt: skip
        return config
    if kind in ("grid-random", "grid-selected-random"):
        return _decode(params, RandomParams, kind)
    if kind == "grid-rerun":
        return _decode(params, RerunParams, kind)
    return _decode(params, DamageParams, kind)


def run_task(kind: str, params: dict, seed: int, run_dir: str | Path) -> dict:
    """Run one task of :data:`GRID_KINDS` into ``run_dir``; see the module docstring."""
    p = check_params(kind, params)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    if kind in ("grid-evolved", "grid-novelty"):
        try:
            summary = run_evolution(p, seed, run_dir)
        except RunFinished as finished:  # deterministic: the stored result is the result
            return finished.summary
    elif kind == "grid-qd":
        try:
            summary = run_map_elites(p, seed, run_dir)
        except RunFinished as finished:
            return finished.summary
    elif kind in ("grid-random", "grid-selected-random"):
        summary = _random(kind, p, seed, run_dir)
    elif kind == "grid-rerun":
        summary = _rerun(p, seed, run_dir)
    else:
        summary = _damage(p, seed, run_dir)
    summary["kind"] = kind
    summary["seed"] = seed
    summary["seconds"] = time.perf_counter() - started
    summary.setdefault("generations_file", None)
    return summary


def _classified(
    width: int, height: int, final_cells: np.ndarray, torus: Torus
) -> tuple[Poses, dict[str, Any]]:
    poses = Poses.from_cells(torus, final_cells)
    c = classify(width, height, poses)
    return poses, {"pattern": c.pattern, "quality": c.quality, "scores": c.scores}


def _random(kind: str, p: RandomParams, seed: int, run_dir: Path) -> dict[str, Any]:
    height = p.height or p.size
    torus = Torus(p.size, height)
    spec = _spec(p.sensors, p.predefined)
    evaluator = GridEvaluator(torus, spec, p.steps, p.noise)
    layout = evaluator.layout
    rng = np.random.default_rng([seed, 10])
    count = p.candidates if kind == "grid-selected-random" else 1
    starts = draw_starts(np.random.default_rng([seed, 11]), torus, p.agents, p.repetitions)
    noise_key = int(np.random.default_rng([seed, 12]).integers(0, 2**32))
    best: tuple[float, Any, int, Any, Any] | None = None
    for begin in range(0, count, 50):  # batches bound the memory of the results
        batch = min(50, count - begin)
        genomes = rng.uniform(-p.initial_range, p.initial_range, (batch, layout.size))
        result = evaluator.evaluate(genomes, starts, noise_key)
        fitness, reps = reduce_repetitions(result.fitness, p.fitness_of)
        i = int(np.argmax(fitness))
        if best is None or fitness[i] > best[0]:
            rep = int(reps[i])
            best = (float(fitness[i]), genomes[i], rep, result.final[i, rep],
                    result.predictions[i, rep])  # fmt: skip
    assert best is not None, "at least one candidate is drawn"
    fitness_value, genome, rep, final, predictions = best
    poses, classified = _classified(p.size, height, final, torus)
    write_best(run_dir, genome, spec, fitness_value)
    write_final_grid(run_dir, p.size, height, rep,
                     Poses.from_cells(torus, starts[rep]).to_rows(), poses.to_rows())  # fmt: skip
    return {
        "size": p.size,
        "height": height,
        "candidates": count,
        "best_fitness": fitness_value,
        "fitness": fitness_value,
        **classified,
        "mean_predictions": np.asarray(predictions).tolist(),
    }


def _spec(sensors: int, predefined: str | None) -> GridNetSpec:
    try:
        return GridNetSpec(sensors, predefined)
    except ValueError as exc:
        raise ConfigError(str(exc), key="predefined") from None


def _load_genome(p: GenomeParams) -> tuple[np.ndarray, GridNetSpec, dict[str, Any] | None]:
    key_file = "<params>"
    if p.genome_run is not None:
        run = Path(p.genome_run)
        try:
            return load_best(run)
        except (OSError, ValueError, KeyError) as exc:
            raise ConfigError(f"not a finished grid run: {exc}", file=key_file,
                              key="genome_run") from None  # fmt: skip
    if p.genome is None:
        raise ConfigError("give genome_run or genome", file=key_file, key="genome")
    spec = _spec(p.sensors, p.predefined)
    genome = np.array(p.genome, dtype=np.float64)
    if genome.shape != (GridGenomeLayout(spec).size,):
        raise ConfigError(
            f"{genome.size} genes, the network needs {GridGenomeLayout(spec).size}",
            file=key_file, key="genome",
        )  # fmt: skip
    return genome, spec, None


def _rerun(p: RerunParams, seed: int, run_dir: Path) -> dict[str, Any]:
    genome, spec, _ = _load_genome(p)
    height = p.height or p.size
    torus = Torus(p.size, height)
    if p.agents > torus.cells:
        raise ConfigError(f"{p.agents} agents do not fit", file="<params>", key="agents")
    evaluator = GridEvaluator(torus, spec, p.steps, p.noise)
    starts = draw_starts(np.random.default_rng([seed, 20]), torus, p.agents, p.repetitions)
    noise_key = int(np.random.default_rng([seed, 21]).integers(0, 2**32))
    result = evaluator.evaluate(genome[None, :], starts, noise_key)
    fitness, reps = reduce_repetitions(result.fitness, "min")
    rep = int(reps[0])
    poses, classified = _classified(p.size, height, result.final[0, rep], torus)
    write_best(run_dir, genome, spec, float(fitness[0]))
    write_final_grid(run_dir, p.size, height, rep,
                     Poses.from_cells(torus, starts[rep]).to_rows(), poses.to_rows())  # fmt: skip
    return {
        "size": p.size,
        "height": height,
        "best_fitness": float(fitness[0]),
        "fitness": float(fitness[0]),
        "run_fitness": result.fitness[0].tolist(),
        **classified,
        "mean_predictions": result.predictions[0, rep].tolist(),
    }


def _damage(p: DamageParams, seed: int, run_dir: Path) -> dict[str, Any]:
    genome, spec, grid = _load_genome(p)
    if grid is not None:
        width, height = int(grid["width"]), int(grid["height"])
        start = Poses.from_rows(grid["start"])
    else:
        if p.start is None:
            raise ConfigError("an inline genome needs its start poses", file="<params>",
                              key="start")  # fmt: skip
        width, height = p.size, p.height or p.size
        try:
            start = Poses.from_rows(p.start)
        except ValueError as exc:
            raise ConfigError(str(exc), file="<params>", key="start") from None
    torus = Torus(width, height)
    evaluator = GridEvaluator(torus, spec, p.steps)
    initial = evaluator.evaluate(genome[None, :], start.to_cells(torus)[None])
    before = Poses.from_cells(torus, initial.final[0, 0])
    n0 = before.x.size
    inside = (
        (before.x >= p.xmin) & (before.x <= p.xmax) & (before.y >= p.ymin) & (before.y <= p.ymax)
    )
    kept = Poses(before.x[~inside], before.y[~inside], before.heading[~inside])
    removed = int(inside.sum())
    if p.variant == "reposition" and removed:
        # back at random free cells outside the rectangle, marked as taken as they are placed
        rng = np.random.default_rng([seed, 30])
        taken = {(int(x), int(y)) for x, y in zip(kept.x, kept.y, strict=True)}
        xs, ys, hs = list(kept.x), list(kept.y), list(kept.heading)
        free = [
            (x, y)
            for y in range(height)
            for x in range(width)
            if (x, y) not in taken and not (p.xmin <= x <= p.xmax and p.ymin <= y <= p.ymax)
        ]
        for idx in rng.choice(len(free), size=removed, replace=False):
            xs.append(free[idx][0])
            ys.append(free[idx][1])
            hs.append(int(rng.integers(0, 4)))
        damaged = Poses(np.array(xs), np.array(ys), np.array(hs))
    else:
        damaged = kept
    repair = evaluator.evaluate(genome[None, :], damaged.to_cells(torus)[None])
    after = Poses.from_cells(torus, repair.final[0, 0])
    c_initial = classify(width, height, before)
    c_start = classify(width, height, damaged)
    c_end = classify(width, height, after)
    final_set = set(map(tuple, before.to_rows()))
    similarity = sum(tuple(row) in final_set for row in after.to_rows()) / n0
    from gridworld.plots import plot_grid

    for name, poses, c in (
        ("initial", before, c_initial),
        ("damaged", damaged, c_start),
        ("repaired", after, c_end),
    ):
        title = f"{name}: {poses.x.size} agents, {c.pattern} ({c.quality:.0%})"
        plot_grid(width, height, poses, run_dir / name, title=title)
    write_json(run_dir / "damage.json", {
        "initial": before.to_rows(), "damaged": damaged.to_rows(), "repaired": after.to_rows(),
    })  # fmt: skip
    return {
        "size": width,
        "height": height,
        "variant": p.variant,
        "removed": removed,
        "initial_fitness": float(initial.fitness[0, 0]),
        "initial_pattern": c_initial.pattern,
        "initial_quality": c_initial.quality,
        "best_fitness": float(repair.fitness[0, 0]),
        "fitness": float(repair.fitness[0, 0]),
        "quality_start": c_start.quality,
        "pattern_start": c_start.pattern,
        "pattern": c_end.pattern,
        "quality": c_end.quality,
        "scores": c_end.scores,
        "similarity": similarity,
        "mean_predictions": repair.predictions[0, 0].tolist(),
    }
