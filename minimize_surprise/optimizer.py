"""The ``optimizer`` section of an experiment file: which optimizer evolves the genomes.

``one-plus-one`` (the default, and what a file without the section gets) is the paper's (1+1)
online evolution of ``evolution``. ``map-elites`` is quality diversity: MAP-Elites over a grid
of behaviour measures, each candidate evaluated from a freshly placed arena, its fitness the
swarm's prediction accuracy as for the (1+1) (docs/quality-diversity.md). The run itself lives
on the laptop (``master_service.experiments.qd_run``, which needs the ``qd`` extra); this module
is only the configuration, so that every reader of an experiment file decodes it alike.

The measures a grid may use are named in :data:`MEASURES`; the laptop's side computes each from
an evaluation's trace with the functions the paper's classification uses.
"""

from __future__ import annotations

from typing import Annotated, Final, Literal

import msgspec


# Below ``minimize_surprise.config`` (which holds this section), so its own strict base: the
# same options as ``config.Strict``.
class _Strict(msgspec.Struct, forbid_unknown_fields=True, kw_only=True, frozen=True):
    pass


PositiveInt = Annotated[int, msgspec.Meta(ge=1)]
NonNegativeFloat = Annotated[float, msgspec.Meta(ge=0.0)]

__all__ = ["DEFAULT_MEASURES", "MEASURES", "Measure", "OptimizerConfig"]

#: Measure name -> what it is (docs/quality-diversity.md has the units and the classes).
MEASURES: Final = {
    "rotation": "c_o, rad, scaled to the paper's 50 s window (motion: stopped, diverse, circling)",
    "mean_cluster_size": "robots per cluster (grouping: grouped above 1.43)",
    "distance_covered": "d_R, metres per robot over the evaluation",
    "box_displacement": "d_B, metres per box over the evaluation (pushing above 0.1)",
    "backward_share": "share of the moving steps driven backwards (reverse driving above 0.5)",
}


class Measure(_Strict, frozen=True):
    """One axis of the archive's grid: a measure, its range and its number of cells."""

    #: the measure's name: ``rotation``, ``mean_cluster_size``, ``distance_covered``,
    #: ``box_displacement`` or ``backward_share``
    name: str
    #: [low, high] of the axis; a value outside it counts in the nearest edge's cell
    range: tuple[float, float]
    #: cells along the axis
    bins: PositiveInt

    def __post_init__(self) -> None:
        if self.name not in MEASURES:
            raise ValueError(
                f"`name`: unknown measure {self.name!r}; expected one of: {', '.join(MEASURES)}"
            )
        low, high = self.range
        if not low < high:
            raise ValueError(
                f"`range`: expected [low, high] with low < high, got {list(self.range)}"
            )


#: The paper's basic-arena axes (its figure of rotation against mean cluster size), cut so that
#: the classes' thresholds fall on cell edges: c_o 5 and 55 on 5-rad cells, 1.43 on 0.43 cells.
DEFAULT_MEASURES: Final = (
    Measure(name="rotation", range=(0.0, 130.0), bins=26),
    Measure(name="mean_cluster_size", range=(1.0, 10.03), bins=21),
)


class OptimizerConfig(_Strict, frozen=True):
    """The optimizer and, for ``map-elites``, its grid, emitters and batches."""

    #: ``one-plus-one`` (the paper's, of ``evolution``) or ``map-elites`` (quality diversity)
    name: Literal["one-plus-one", "map-elites"] = "one-plus-one"
    #: map-elites: the grid's axes (one or more), each ``{name, range: [low, high], bins}``
    measures: list[Measure] = msgspec.field(default_factory=lambda: list(DEFAULT_MEASURES))
    #: map-elites: candidates of one emitter per batch (the whole batch is evaluated in one
    #: compiled call: ``emitters`` x ``batch`` swarms)
    batch: PositiveInt = 20
    #: map-elites: emitters, each with its own random numbers
    emitters: PositiveInt = 1
    #: map-elites: ``iso-line`` (Gaussian noise plus a step along the line to another elite) or
    #: ``gaussian`` (plain MAP-Elites mutation)
    emitter: Literal["iso-line", "gaussian"] = "iso-line"
    #: map-elites: the Gaussian mutation's standard deviation per gene
    sigma: NonNegativeFloat = 0.1
    #: map-elites, iso-line: the standard deviation of the step along the line between elites
    line_sigma: NonNegativeFloat = 0.2
    #: map-elites: the first batch's genomes are uniform in [-initial_range, initial_range]
    #: (``null``: the evolution's ``initial_range``)
    initial_range: Annotated[float, msgspec.Meta(ge=0.0)] | None = None

    def __post_init__(self) -> None:
        names = [m.name for m in self.measures]
        if not names:
            raise ValueError("`measures`: at least one measure is needed")
        for index, name in enumerate(names):
            if name in names[:index]:
                raise ValueError(f"`measures`: {name!r} is named twice")
