"""The grid world's genetic algorithm as ask/tell (paper Sec. III-B, the authors' C code).

A population of ``population`` genomes, drawn uniformly from [-initial_range, initial_range].
Each generation :meth:`GeneticAlgorithm.ask` gives the population to evaluate and
:meth:`GeneticAlgorithm.tell` takes its fitness: one value per genome, or one per genome and
repetition, reduced by ``fitness_of`` (``min``, the code's choice; ``mean``; ``max``). The best
genome is the first with the largest fitness. The next generation replaces the whole population
(generational, "age-based"): with ``elitism`` the best genome keeps its slot unmutated; every other
slot gets a copy of a parent chosen by roulette wheel (fitness-proportionate, the elite included:
draw r uniform in [0, 1) and take the first genome whose cumulative share of the total fitness
reaches r), each gene of which is mutated with probability ``mutation_probability`` by adding a
uniform number from [-mutation_range, mutation_range]. No crossover. Fitness must not be
negative; when it is 0 for every genome, parents are chosen uniformly (the code divides by 0).

The optimizer knows nothing about how genomes are evaluated. :meth:`GeneticAlgorithm.state` is
plain JSON-safe data; :meth:`GeneticAlgorithm.from_state` resumes bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from minimize_surprise.errors import GenomeError
from minimize_surprise.evolution import EvolutionStateError

__all__ = ["GenerationOutcome", "GeneticAlgorithm", "GeneticConfig", "reduce_repetitions"]

FitnessOf = Literal["min", "mean", "max"]

#: Version of the plain-data state; bump when its shape changes.
STATE_VERSION = 1


@dataclass(frozen=True)
class GeneticConfig:
    """Parameters of :class:`GeneticAlgorithm` (defaults: the paper's Table I)."""

    population: int = 50
    generations: int = 100
    mutation_probability: float = 0.1
    mutation_range: float = 0.4
    initial_range: float = 0.5
    elitism: int = 1
    fitness_of: FitnessOf = "min"

    def __post_init__(self) -> None:
        if self.population < 1:
            raise ValueError(f"population must be at least 1, got {self.population}")
        if self.generations < 1:
            raise ValueError(f"generations must be at least 1, got {self.generations}")
        if not 0.0 <= self.mutation_probability <= 1.0:
            raise ValueError("mutation_probability must lie in [0, 1]")
        if self.mutation_range < 0 or self.initial_range < 0:
            raise ValueError("mutation_range and initial_range must not be negative")
        if self.elitism not in (0, 1):
            raise ValueError(f"elitism must be 0 or 1, got {self.elitism}")
        if self.fitness_of not in ("min", "mean", "max"):
            raise ValueError(f"fitness_of must be min, mean or max, got {self.fitness_of!r}")


def reduce_repetitions(fitness: np.ndarray, how: FitnessOf) -> tuple[np.ndarray, np.ndarray]:
    """Per-genome fitness from a (genomes, repetitions) matrix and the repetition that stands for
    each genome: the first worst for ``min``, the first best for ``max``, the last for ``mean``
    (the run the code keeps and logs)."""
    fitness = np.asarray(fitness, dtype=np.float64)
    if fitness.ndim != 2 or fitness.shape[1] < 1:
        raise ValueError(f"expected a (genomes, repetitions) matrix, got shape {fitness.shape}")
    if how == "min":
        return fitness.min(axis=1), fitness.argmin(axis=1)
    if how == "max":
        return fitness.max(axis=1), fitness.argmax(axis=1)
    if how == "mean":
        return fitness.mean(axis=1), np.full(fitness.shape[0], fitness.shape[1] - 1)
    raise ValueError(f"fitness_of must be min, mean or max, got {how!r}")


@dataclass(frozen=True)
class GenerationOutcome:
    """What one told generation gave: ``fitness`` per genome, the first best's index and value,
    the mean, and (for a (genomes, repetitions) tell) each genome's standing repetition."""

    generation: int
    fitness: np.ndarray
    best_index: int
    best_fitness: float
    mean_fitness: float
    best_genome: np.ndarray
    repetition: np.ndarray | None


class GeneticAlgorithm:
    """The generational GA of the module docstring for genomes of ``genome_size`` genes.

    ``seed`` seeds its only random generator; ``initial`` replaces the random first population.
    """

    def __init__(
        self,
        config: GeneticConfig,
        genome_size: int,
        seed: int,
        initial: np.ndarray | None = None,
    ) -> None:
        if genome_size < 1:
            raise ValueError(f"genome_size must be at least 1, got {genome_size}")
        self.config = config
        self.genome_size = genome_size
        self.rng = np.random.default_rng(seed)
        self.generation = 0
        if initial is None:
            r = config.initial_range
            self.population = self.rng.uniform(-r, r, (config.population, genome_size))
        else:
            initial = np.array(initial, dtype=np.float64)
            if initial.shape != (config.population, genome_size) or not np.all(
                np.isfinite(initial)
            ):
                raise GenomeError(
                    f"initial population must be {config.population} x {genome_size} finite values"
                )
            self.population = initial

    @property
    def done(self) -> bool:
        """True once every configured generation has been told."""
        return self.generation >= self.config.generations

    def ask(self) -> np.ndarray:
        """The generation to evaluate, (population, genome_size); the same until told. Do not
        modify it."""
        return self.population

    def tell(self, fitness: np.ndarray) -> GenerationOutcome:
        """Count the current generation with ``fitness`` ((population,) or (population,
        repetitions), reduced by ``fitness_of``) and breed the next one."""
        if self.done:
            raise EvolutionStateError("every generation has been told already")
        fitness = np.asarray(fitness, dtype=np.float64)
        repetition = None
        if fitness.ndim == 2:
            if fitness.shape[0] != self.config.population:
                raise ValueError(f"fitness has {fitness.shape[0]} rows, expected the population")
            fitness, repetition = reduce_repetitions(fitness, self.config.fitness_of)
        if fitness.shape != (self.config.population,):
            raise ValueError(
                f"fitness has shape {fitness.shape}, expected ({self.config.population},)"
            )
        if not np.all(np.isfinite(fitness)) or np.any(fitness < 0):
            raise ValueError("fitness must be finite and not negative (roulette-wheel selection)")
        best = int(np.argmax(fitness))  # the first of the largest, as the code takes it
        outcome = GenerationOutcome(
            self.generation, fitness, best, float(fitness[best]), float(fitness.mean()),
            self.population[best].copy(), repetition,
        )  # fmt: skip
        self.population = self._breed(fitness, best)
        self.generation += 1
        return outcome

    def select(self, fitness: np.ndarray, draws: np.ndarray) -> np.ndarray:
        """Roulette-wheel parents for uniform ``draws`` in [0, 1): for each, the first genome
        whose cumulative share of the total fitness reaches it."""
        total = fitness.sum()
        if total <= 0.0:
            return np.minimum((draws * fitness.size).astype(np.intp), fitness.size - 1)
        shares = np.cumsum(fitness) / total
        return np.minimum(np.searchsorted(shares, draws, side="left"), fitness.size - 1)

    def _breed(self, fitness: np.ndarray, best: int) -> np.ndarray:
        cfg = self.config
        p, size = cfg.population, self.genome_size
        parents = self.select(fitness, self.rng.random(p))
        mask = self.rng.random((p, size)) < cfg.mutation_probability
        delta = self.rng.uniform(-cfg.mutation_range, cfg.mutation_range, (p, size))
        children = self.population[parents] + np.where(mask, delta, 0.0)
        if cfg.elitism:
            children[best] = self.population[best]
        return children

    def state(self) -> dict[str, Any]:
        """Everything needed to continue bit for bit, as JSON-safe plain data."""
        return {
            "version": STATE_VERSION,
            "genome_size": self.genome_size,
            "generation": self.generation,
            "population": self.population.tolist(),
            "rng": self.rng.bit_generator.state,
        }

    @classmethod
    def from_state(cls, config: GeneticConfig, state: dict[str, Any]) -> GeneticAlgorithm:
        """Rebuild an optimizer from :meth:`state` (the configuration is not part of it)."""
        try:
            if state["version"] != STATE_VERSION:
                raise EvolutionStateError(f"state version {state['version']} is not supported")
            population = np.array(state["population"], dtype=np.float64)
            self = cls(config, int(state["genome_size"]), seed=0, initial=population)
            self.rng.bit_generator.state = state["rng"]
            self.generation = int(state["generation"])
        except (KeyError, TypeError, ValueError, GenomeError) as exc:
            raise EvolutionStateError(f"cannot restore the GA state: {exc!r}") from None
        return self
