"""Configuration of a grid-world run, decoded strictly: a bad key is a ConfigError naming it.

Defaults are the paper's (Table I): a 15 x 15 torus, 100 agents, 14 sensors, population 50,
100 generations, 10 repetitions of 500 steps scored by their minimum, mutation 0.1 of +-0.4.
``optimizer: map-elites`` runs quality diversity instead of the GA (:mod:`gridworld.qd`): an
archive over pattern measures (:class:`GridMeasure`), a batch of ``population`` candidates per
"generation".
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from minimize_surprise.config import Probability, Strict, decode
from minimize_surprise.genetic import GeneticConfig
from minimize_surprise.gridnet import GridNetSpec

__all__ = [
    "DEFAULT_MEASURES",
    "MAX_ARCHIVE_CELLS",
    "MEASURE_NAMES",
    "GridMeasure",
    "GridRunConfig",
    "GridWorldParams",
    "PositiveInt",
    "decode_run_config",
]

PositiveInt = Annotated[int, msgspec.Meta(ge=1)]

#: The measures a MAP-Elites archive can span: the nine patterns' fractions
#: (:data:`gridworld.patterns.PATTERNS`, in that order; config sits below patterns, so it
#: repeats the codes and a test keeps the two equal).
MEASURE_NAMES: tuple[str, ...] = ("CL", "AG", "LG", "LN", "PR", "TL", "SQ", "SW", "RD")

#: The most cells an archive may have: each holds a genome (616 float64 with 14 sensors), so
#: 100,000 cells are some 500 MB, about what a study's worker can spare.
MAX_ARCHIVE_CELLS = 100_000


class GridMeasure(Strict, frozen=True):
    """One axis of a MAP-Elites archive: a pattern's fraction (``name``, a code of
    :data:`MEASURE_NAMES`) over ``range`` (within [0, 1]) cut into ``bins`` equal cells."""

    #: the pattern whose fraction of agents is the measure: CL, AG, LG, LN, PR, TL, SQ, SW or RD
    name: str
    #: the measure's low and high end, within [0, 1] (a fraction of the agents); values outside
    #: fall into the first or last bin
    range: tuple[float, float] = (0.0, 1.0)
    #: cells along this axis
    bins: PositiveInt = 10

    def __post_init__(self) -> None:
        if self.name not in MEASURE_NAMES:
            raise ValueError(
                f"`name`: unknown pattern {self.name!r}; expected one of {', '.join(MEASURE_NAMES)}"
            )
        lo, hi = self.range
        if not (0.0 <= lo < hi <= 1.0):
            raise ValueError(
                f"`range`: [{lo}, {hi}] must be a non-empty interval [low, high] within [0, 1] "
                "(a fraction of the agents)"
            )


#: The measures of a MAP-Elites run that names none: the fractions of agents in lines and in
#: pairs, ten bins each (docs/gridworld.md, "MAP-Elites").
DEFAULT_MEASURES: tuple[GridMeasure, ...] = (
    GridMeasure(name="LN", range=(0.0, 1.0), bins=10),
    GridMeasure(name="PR", range=(0.0, 1.0), bins=10),
)


class GridWorldParams(Strict, frozen=True):
    """The world and the scoring every grid task shares: the torus, the agents, their sensors
    and fixed predictions, sensor noise, and how a genome is scored.

    ``size`` is the torus side (``height`` makes it a rectangle: size wide, height tall);
    ``predefined`` names fixed predictions (``minimize_surprise.gridnet``: e.g. ``line``,
    ``line-partial``); ``noise`` is the probability of flipping each sensor reading; a genome's
    fitness is ``fitness_of`` its ``repetitions`` runs of ``steps`` steps; random genomes are
    drawn uniformly from +-``initial_range``.
    """

    #: the torus side L (its width)
    size: PositiveInt = 15
    #: the torus height for a rectangle (default: L)
    height: PositiveInt | None = None
    #: agents N, one per cell
    agents: PositiveInt = 100
    #: the sensor model: how many cells around an agent it senses (14, 6 or 8)
    sensors: Literal[14, 6, 8] = 14
    #: fixed predictions (e.g. `line`, `line-partial`; docs/gridworld.md), or none
    predefined: str | None = None
    #: the probability of flipping each sensor reading (the networks and the fitness see it;
    #: moves are blocked by true occupancy)
    noise: Probability = 0.0
    #: runs per genome, each from its own start configuration
    repetitions: PositiveInt = 10
    #: steps T per run
    steps: PositiveInt = 500
    #: genes of a random or initial genome are uniform in +- this
    initial_range: Annotated[float, msgspec.Meta(ge=0.0)] = 0.5
    #: a genome's fitness from its runs: the worst (the paper), the mean or the best
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


class GridRunConfig(GridWorldParams, frozen=True):
    """One evolution run in the grid world: the world's parameters and the GA's.

    ``novelty`` evolves the actor alone by novelty search (no elitism; ``novelty_k`` nearest
    neighbours, archive probability ``archive_probability``). ``optimizer: map-elites`` fills an
    archive over ``measures`` instead (:mod:`gridworld.qd`): ``generations`` batches of
    ``population`` candidates, each a copy of a random elite with Gaussian noise of ``sigma``
    added to every gene.
    """

    #: genomes per generation
    population: PositiveInt = 50
    #: generations of the run
    generations: PositiveInt = 100
    #: the probability of mutating each gene
    mutation_rate: Probability = 0.1
    #: a mutation adds a uniform value in +- this
    mutation_range: Annotated[float, msgspec.Meta(ge=0.0)] = 0.4
    #: novelty search: the actor alone, selected on novelty, no elitism
    novelty: bool = False
    #: nearest neighbours in behaviour space whose mean distance is an individual's novelty
    novelty_k: PositiveInt = 10
    #: the probability that an evaluated individual joins the novelty archive
    archive_probability: Probability = 0.02
    #: `ga` (the paper's genetic algorithm) or `map-elites` (quality diversity: an archive of the
    #: best genome per cell of `measures`; `population` is then the batch size and `generations`
    #: the number of batches)
    optimizer: Literal["ga", "map-elites"] = "ga"
    #: map-elites: the archive's axes, each `{name: <pattern code>, range: [low, high], bins: N}`
    #: (default: LN and PR over [0, 1] in 10 bins each)
    measures: tuple[GridMeasure, ...] | None = None
    #: map-elites: the standard deviation of the Gaussian noise added to every gene of an elite
    #: to make a candidate
    sigma: Annotated[float, msgspec.Meta(gt=0.0)] = 0.07

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.novelty and self.predefined is not None:
            raise ValueError("`predefined`: novelty search evolves the actor alone")
        if self.optimizer == "ga":
            if self.measures is not None:
                raise ValueError("`measures`: only for `optimizer: map-elites`")
            return
        if self.novelty:
            raise ValueError("`optimizer`: novelty search is a run of the genetic algorithm")
        measures = self.archive_measures()
        if not measures:
            raise ValueError("`measures`: name at least one pattern")
        names = [m.name for m in measures]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise ValueError(f"`measures[{i}].name`: {name} is already an axis")
        cells = 1
        for m in measures:
            cells *= m.bins
        if cells > MAX_ARCHIVE_CELLS:
            raise ValueError(
                f"`measures`: {cells} cells in all, at most {MAX_ARCHIVE_CELLS} (fewer bins)"
            )

    def archive_measures(self) -> tuple[GridMeasure, ...]:
        """The archive's axes of a MAP-Elites run (``measures`` or :data:`DEFAULT_MEASURES`)."""
        return DEFAULT_MEASURES if self.measures is None else self.measures

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
