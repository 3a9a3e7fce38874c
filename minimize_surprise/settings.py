"""What a named setting gives an experiment: step, lengths, first genome (docs/simulation.md).

``paper`` is the authors' Webots simulation (the paper's Sec. V results), ``lab`` the real
robots. An experiment names its setting (default ``lab``); every field below that the experiment
file leaves out is taken from it, so ``surprise-master sim --setting paper`` runs the paper's
experiment and a lab's real-robot run keeps the real robots' numbers. The world and the safety
layer of a setting are the simulator's business (``simulator.settings``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["SETTINGS", "ExperimentDefaults", "Setting", "experiment_defaults"]

Setting = Literal["paper", "lab"]
#: The settings' names.
SETTINGS: tuple[str, ...] = ("paper", "lab")


@dataclass(frozen=True)
class ExperimentDefaults:
    """The experiment-level numbers of a setting (see :func:`experiment_defaults`)."""

    #: seconds per control step
    step_period: float
    #: steps of an evaluation and of the post-evaluation of the best genome
    evaluation_steps: int
    post_evaluation_steps: int
    #: evaluations of a run
    evaluations: int
    #: the first genome is uniform in [-initial_range, initial_range]
    initial_range: float
    #: the first genome evaluated: the random one, or a mutant of it (the authors' code)
    first_genome: Literal["random", "mutant"]
    #: a(-1), the previous action the actor sees at the first step of every evaluation
    initial_action: float
    #: hidden neurons of the actor for a given number of sensors
    actor_hidden: dict[int, int]
    #: the actor's hidden size for a sensor count not listed
    actor_hidden_default: int

    def actor_hidden_for(self, sensors: int) -> int:
        """The actor's hidden size for ``sensors`` sensors."""
        return self.actor_hidden.get(sensors, self.actor_hidden_default)


_DEFAULTS: dict[str, ExperimentDefaults] = {
    # The authors' Webots code: 10 ms steps, 1000-step evaluations, a 10,000-step post-evaluation,
    # 1000 evaluations; genes uniform in [-1, 1), the first genome sent a mutant of a random one;
    # a(-1) all ones; actors of 7 hidden neurons for 9 or 10 sensors, 8 for 12.
    "paper": ExperimentDefaults(
        step_period=0.01,
        evaluation_steps=1000,
        post_evaluation_steps=10_000,
        evaluations=1000,
        initial_range=1.0,
        first_genome="mutant",
        initial_action=1.0,
        actor_hidden={9: 7, 10: 7, 12: 8},
        actor_hidden_default=8,
    ),
    # The real robots at 10 Hz: 100-step evaluations, a 1000-step post-evaluation; the paper's
    # text for the first genome ([-0.5, 0.5]); a(-1) zero; actors of 8 hidden neurons (ours).
    "lab": ExperimentDefaults(
        step_period=0.1,
        evaluation_steps=100,
        post_evaluation_steps=1000,
        evaluations=1000,
        initial_range=0.5,
        first_genome="random",
        initial_action=0.0,
        actor_hidden={},
        actor_hidden_default=8,
    ),
}


def experiment_defaults(setting: str) -> ExperimentDefaults:
    """The experiment-level numbers of ``setting`` (``KeyError`` for an unknown name)."""
    return _DEFAULTS[setting]
