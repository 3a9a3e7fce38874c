"""What it means when the safety layer drove most of a run's steps: a note or a warning.

Above :data:`~minimize_surprise.safety.SAFETY_DOMINATES` of the steps, what a run shows is mostly
the safety layer's doing. Whether a person should act on that depends on why it drove
(docs/runs.md, the notes and warnings of a report):

- robots held against a neighbour or a wall (front or rear obstacles), turned away again and
  again (escape manoeuvres) or cut short reversing (the backward limit) are what the evolved
  networks do in this arena (held, they stand still, as the paper's *stopped* robots do); it is a
  result, said as a **note**;
- the ground rule on most steps is either: robots driving to the edge of the arena and held
  there (an outcome, like a wall) or a floor the thresholds take for the edge everywhere (a
  fault). The first steps tell them apart: robots start on the floor, away from its edge, so
  a floor mistaken for the edge stops them at once, while an evolved approach to the edge takes
  time. When the caller knows the share of robots the ground rule held in their first steps
  (:data:`START_STEPS`) and it is at most half, it is a note; else a warning;
- the force limit, stale readings and failing sensors are faults of the set-up: a **warning**,
  naming what to check.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from itertools import islice
from typing import Final, NamedTuple

from minimize_surprise.safety import (
    REASON_BACKWARD_LIMIT,
    REASON_ESCAPE,
    REASON_EXPERIMENTER,
    REASON_FORCE,
    REASON_FRONT,
    REASON_GROUND,
    REASON_REAR,
    REASON_SENSOR,
    REASON_STALE,
    SAFETY_DOMINATES,
    intervention_reasons,
)

__all__ = ["ACTIONABLE_REASONS", "START_STEPS", "Dominance", "dominance", "ground_at_start"]

#: The first steps of a robot's trace in which the ground rule holding it means a wrong floor.
START_STEPS: Final = 5

#: What to check, per actionable reason.
_CHECK: Final[dict[str, str]] = {
    REASON_GROUND: "the ground rule tripped: check safety.ground_threshold and "
    "safety.ground_boundary against this floor (on a floor as light as the edge marking every "
    "step looks like the edge)",
    REASON_FORCE: "the pushing force rule: safety.force_threshold below what the boxes need",
    REASON_STALE: "stale sensor readings: the sensors do not keep up with the step period",
    REASON_SENSOR: "sensor values that are not numbers: a sensor is failing",
}
#: Reasons whose dominance is a fault of the set-up, for a person to act on.
ACTIONABLE_REASONS: Final = frozenset(_CHECK)

#: What the behaviour is, per reason that is the evolved networks' doing.
_OUTCOME: Final[dict[str, str]] = {
    REASON_FRONT: "mostly against a neighbour or a wall ahead: the robots press on and the layer "
    "holds them, standing still as the paper's stopped robots do (the stop profile's aggregates "
    "look like this)",
    REASON_REAR: "mostly against a neighbour or a wall behind: the robots reverse into it and the "
    "layer holds them, standing still as the paper's stopped robots do",
    REASON_ESCAPE: "mostly in escape manoeuvres: the networks keep driving into obstacles or the "
    "boundary and the layer turns them away",
    REASON_BACKWARD_LIMIT: "mostly at the backward limit: the networks reverse for long "
    "stretches and the layer cuts them short",
    # Each is one step (the manoeuvre's others count as escape); only a test would get here.
    REASON_EXPERIMENTER: "mostly starting escapes the experimenter asked for "
    "(surprise-master escape)",
}


#: The ground rule, when the robots met the edge only after they had set off.
_AT_THE_EDGE: Final = (
    "mostly at the edge of the arena: the robots drive to the boundary and the layer holds them "
    "there, standing still as the paper's stopped robots do (the ground rule; it held few of "
    "them in their first steps, so the floor is not mistaken for the edge)"
)


def ground_at_start(reasons: Iterable[Iterable[str]]) -> float | None:
    """The share of robots whose safety layer applied the ground rule in one of their first
    :data:`START_STEPS` steps, from each robot's per-step reasons; None without robots."""
    held = [REASON_GROUND in islice(steps, START_STEPS) for steps in reasons]
    return sum(held) / len(held) if held else None


class Dominance(NamedTuple):
    """The layer drove most of the steps: ``text``, one sentence, and whether a person should
    act on it (``actionable``: a warning) or it describes the behaviour (a note)."""

    text: str
    actionable: bool


def dominance(
    share: float, counts: Iterable[Mapping[str, int]], *, at_start: float | None = None
) -> Dominance | None:
    """None unless the layer drove more than ``SAFETY_DOMINATES`` of the steps; otherwise what
    that means, from the commonest reason over every robot's ``counts`` of interventions per
    reason. Without counts the reason is unknown, and that is worth a look: a warning.
    ``at_start``: the share of robots the ground rule held in their first steps
    (:func:`ground_at_start`), which tells an arena's edge from a wrong floor."""
    if share <= SAFETY_DOMINATES:
        return None
    reasons = intervention_reasons(counts)
    reason = max(reasons, key=lambda r: reasons[r]) if reasons else None
    outcome = _OUTCOME.get(reason) if reason is not None else None
    if reason == REASON_GROUND and at_start is not None and at_start <= 0.5:
        outcome = _AT_THE_EDGE
    if outcome is not None:
        return Dominance(
            f"the safety layer drove {100 * share:.0f} % of the steps, {outcome}; an outcome of "
            "the evolution, not a fault",
            actionable=False,
        )
    text = (
        f"the safety layer overrode {100 * share:.0f} % of the steps: what the robots did is "
        "mostly the safety layer's doing, not the networks' commands"
    )
    if reason in _CHECK:
        text += f"; mostly {_CHECK[reason]}"
    return Dominance(text, actionable=True)
