"""(1+1) online evolution with re-evaluation, as ask/tell (paper Sec. V-A; docs/method.md).

The first candidate is the initial genome. After it, with probability ``reevaluation_probability``
the current best is evaluated again and its fitness becomes ``F = w f + (1 - w) F`` (it stays the
best whatever the result); otherwise an offspring is evaluated: every gene mutated with probability
``mutation_probability`` by adding uniform ``[-mutation_range, mutation_range]``. The offspring
replaces the best when ``f >= F`` (ties favour the newcomer, which lets neutral drift happen).

The optimizer knows nothing about how a candidate is evaluated. A failed round
(:meth:`OnePlusOne.tell_failed`) counts nothing and the next :meth:`OnePlusOne.ask` returns the same
candidate. :meth:`OnePlusOne.state` is plain data (JSON-safe); :meth:`OnePlusOne.from_state` resumes
bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from minimize_surprise.config import EvolutionConfig
from minimize_surprise.errors import GenomeError, SurpriseError

Kind = Literal["initial", "offspring", "reevaluation"]

#: Version of the plain-data state; bump when its shape changes.
STATE_VERSION = 1


class EvolutionStateError(SurpriseError, RuntimeError):
    """The optimizer was used out of order (tell without ask) or a state cannot be restored."""


@dataclass(frozen=True)
class Candidate:
    """A genome to evaluate; ``kind`` says why it was chosen. ``genome`` must not be modified."""

    genome: np.ndarray
    kind: Kind


@dataclass(frozen=True)
class Outcome:
    """What one counted evaluation changed: ``accepted`` is True when the candidate is the best
    afterwards (always for the initial genome and a re-evaluation)."""

    evaluation: int
    kind: Kind
    fitness: float
    accepted: bool
    best_fitness: float


def random_genome(rng: np.random.Generator, size: int, half_range: float) -> np.ndarray:
    """A genome drawn uniformly from [-half_range, half_range], as the first one of a run (the
    paper: 0.5); the random pairs of a baseline are drawn the same way."""
    return rng.uniform(-half_range, half_range, size)


class OnePlusOne:
    """The (1+1) online evolution of paper Sec. V-A (docs/method.md, "Online (1+1) evolution").

    ``genome_size`` is the length of a genome; ``seed`` seeds the only random generator used.
    ``initial`` replaces the random initial genome (e.g. to continue from a known genome).
    """

    def __init__(
        self,
        config: EvolutionConfig,
        genome_size: int,
        seed: int,
        initial: np.ndarray | None = None,
    ) -> None:
        self.config = config
        self.genome_size = genome_size
        self.rng = np.random.default_rng(seed)
        self.best: np.ndarray | None = None
        self.best_fitness: float | None = None
        #: The counted evaluation (1-based, as ``evaluations.csv`` numbers them) whose candidate
        #: is the current best genome: re-evaluations change its fitness, not this.
        self.best_evaluation: int | None = None
        self.evaluations = 0
        self.failed_rounds = 0
        self._pending: Candidate | None = None
        if initial is not None:
            initial = np.array(initial, dtype=np.float64)
            if initial.shape != (genome_size,) or not np.all(np.isfinite(initial)):
                raise GenomeError(f"initial genome must be {genome_size} finite values")
            self._pending = Candidate(initial, "initial")

    @property
    def done(self) -> bool:
        """True once the configured number of evaluations has been counted (never for an
        endless run, ``evaluations: null``)."""
        total = self.config.evaluations
        return total is not None and self.evaluations >= total

    def ask(self) -> Candidate:
        """The next candidate; the same one again until it is told a fitness."""
        if self._pending is None:
            self._pending = self._draw()
        return self._pending

    def _draw(self) -> Candidate:
        cfg = self.config
        if self.best is None:
            genome = random_genome(self.rng, self.genome_size, cfg.initial_range)
            if cfg.first_genome == "mutant":  # the authors' code evaluates a mutant of it first
                genome = self._mutant(genome)
            return Candidate(genome, "initial")
        if self.rng.random() < cfg.reevaluation_probability:
            return Candidate(self.best, "reevaluation")
        return Candidate(self._mutant(self.best), "offspring")

    def _mutant(self, genome: np.ndarray) -> np.ndarray:
        cfg = self.config
        mask = self.rng.random(self.genome_size) < cfg.mutation_probability
        delta = self.rng.uniform(-cfg.mutation_range, cfg.mutation_range, self.genome_size)
        return genome + np.where(mask, delta, 0.0)

    def tell(self, fitness: float) -> Outcome:
        """Count an evaluation of the pending candidate with swarm fitness ``fitness``."""
        candidate = self._pending
        if candidate is None:
            raise EvolutionStateError("tell() without a pending candidate: call ask() first")
        fitness = float(fitness)
        if not np.isfinite(fitness):
            raise ValueError(f"fitness must be finite, got {fitness}")
        w = self.config.reevaluation_weight
        if candidate.kind == "initial" or self.best_fitness is None:
            self.best, self.best_fitness, accepted = candidate.genome, fitness, True
            self.best_evaluation = self.evaluations + 1
        elif candidate.kind == "reevaluation":
            self.best_fitness = w * fitness + (1.0 - w) * self.best_fitness
            accepted = True
        else:
            accepted = fitness >= self.best_fitness
            if accepted:
                self.best, self.best_fitness = candidate.genome, fitness
                self.best_evaluation = self.evaluations + 1
        self._pending = None
        self.evaluations += 1
        return Outcome(self.evaluations, candidate.kind, fitness, accepted, self.best_fitness)

    def tell_failed(self) -> None:
        """The pending candidate's round was lost: nothing counts, :meth:`ask` repeats it."""
        if self._pending is None:
            raise EvolutionStateError("tell_failed() without a pending candidate")
        self.failed_rounds += 1

    def state(self) -> dict[str, Any]:
        """Everything needed to continue bit for bit, as JSON-safe plain data."""
        pending = self._pending
        return {
            "version": STATE_VERSION,
            "genome_size": self.genome_size,
            "best": None if self.best is None else self.best.tolist(),
            "best_fitness": self.best_fitness,
            "best_evaluation": self.best_evaluation,
            "evaluations": self.evaluations,
            "failed_rounds": self.failed_rounds,
            "pending": None
            if pending is None
            else {"genome": pending.genome.tolist(), "kind": pending.kind},
            "rng": self.rng.bit_generator.state,
        }

    @classmethod
    def from_state(cls, config: EvolutionConfig, state: dict[str, Any]) -> OnePlusOne:
        """Rebuild an optimizer from :meth:`state` (the configuration is not part of the state)."""
        try:
            if state["version"] != STATE_VERSION:
                raise EvolutionStateError(f"state version {state['version']} is not supported")
            self = cls(config, int(state["genome_size"]), seed=0)
            self.rng.bit_generator.state = state["rng"]
            if state["best"] is not None:
                self.best = np.array(state["best"], dtype=np.float64)
            self.best_fitness = state["best_fitness"]
            self.evaluations = int(state["evaluations"])
            self.best_evaluation = _best_evaluation(state, self.best is not None)
            self.failed_rounds = int(state["failed_rounds"])
            pending = state["pending"]
            if pending is not None:
                self._pending = Candidate(np.array(pending["genome"], np.float64), pending["kind"])
        except (KeyError, TypeError, ValueError) as exc:
            raise EvolutionStateError(f"cannot restore the evolution state: {exc!r}") from None
        return self


def _best_evaluation(state: dict[str, Any], has_best: bool) -> int | None:
    # A checkpoint written before the field existed: the count of evaluations then, which is
    # what best_genome.json said at the time (the number that found the best is not kept).
    found = state.get("best_evaluation")
    if found is None and has_best:
        return int(state["evaluations"])
    return None if found is None else int(found)
