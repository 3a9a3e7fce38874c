"""Configuration of a grid-world run, decoded strictly: a bad key is a ConfigError naming it.

Defaults are the paper's (Table I): a 15 x 15 torus, 100 agents, 14 sensors, population 50,
100 generations, 10 repetitions of 500 steps scored by their minimum, mutation 0.1 of +-0.4.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from surprise.config import Probability, Strict, decode
from surprise.genetic import GeneticConfig
from surprise.gridnet import GridNetSpec

__all__ = ["GridRunConfig", "GridWorldParams", "PositiveInt", "decode_run_config"]

PositiveInt = Annotated[int, msgspec.Meta(ge=1)]


class GridWorldParams(Strict):
    """The world and the scoring every grid task shares: the torus, the agents, their sensors
    and fixed predictions, sensor noise, and how a genome is scored.

    ``size`` is the torus side (``height`` makes it a rectangle: size wide, height tall);
    ``predefined`` names fixed predictions (``surprise.gridnet``: e.g. ``line``,
    ``line-partial``); ``noise`` is the probability of flipping each sensor reading; a genome's
    fitness is ``fitness_of`` its ``repetitions`` runs of ``steps`` steps; random genomes are
    drawn uniformly from +-``initial_range``.
    """

    size: PositiveInt = 15
    height: PositiveInt | None = None
    agents: PositiveInt = 100
    sensors: Literal[14, 6, 8] = 14
    predefined: str | None = None
    noise: Probability = 0.0
    repetitions: PositiveInt = 10
    steps: PositiveInt = 500
    initial_range: Annotated[float, msgspec.Meta(ge=0.0)] = 0.5
    fitness_of: Literal["min", "mean", "max"] = "min"

    def __post_init__(self) -> None:
        if self.agents > self.size * self.grid_height:
            raise ValueError(
                f"`agents`: {self.agents} agents do not fit on {self.size} x {self.grid_height}"
            )
        try:
            GridNetSpec(self.sensors, self.predefined)
        except ValueError as exc:
            raise ValueError(f"`predefined`: {exc}") from None

    @property
    def grid_height(self) -> int:
        """The torus height (``height`` or ``size``)."""
        return self.height or self.size


class GridRunConfig(GridWorldParams):
    """One evolution run in the grid world: the world's parameters and the GA's.

    ``novelty`` evolves the actor alone by novelty search (no elitism; ``novelty_k`` nearest
    neighbours, archive probability ``archive_probability``).
    """

    population: PositiveInt = 50
    generations: PositiveInt = 100
    mutation_rate: Probability = 0.1
    mutation_range: Annotated[float, msgspec.Meta(ge=0.0)] = 0.4
    novelty: bool = False
    novelty_k: PositiveInt = 10
    archive_probability: Probability = 0.02

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.novelty and self.predefined is not None:
            raise ValueError("`predefined`: novelty search evolves the actor alone")

    def net_spec(self) -> GridNetSpec:
        """The network shape this run evolves."""
        return GridNetSpec(self.sensors, self.predefined, actor_only=self.novelty)

    def genetic(self) -> GeneticConfig:
        """The GA's parameters."""
        return GeneticConfig(
            population=self.population,
            generations=self.generations,
            mutation_probability=self.mutation_rate,
            mutation_range=self.mutation_range,
            initial_range=self.initial_range,
            elitism=0 if self.novelty else 1,
            fitness_of=self.fitness_of,
        )


def decode_run_config(data: Any, *, file: str | Path | None = None) -> GridRunConfig:
    """Decode plain data into :class:`GridRunConfig` (ConfigError naming file and key)."""
    return decode(data, GridRunConfig, file=file)
