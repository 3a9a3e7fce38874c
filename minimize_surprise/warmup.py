"""Run the control step once before it is needed, so that what its first call costs is paid at
start-up, not at the first step of the first evaluation.

Where numba is installed (the laptop's simulated agents; a robot only if its lab adds numba to
the ``robot`` extra) a kernel not compiled yet takes seconds on its first call, and paid at the
first step that delay made a swarm's first round miss its deadline. A robot's Pi as installed
has no numba: the kernels run as Python over numpy and the warm-up takes milliseconds
(docs/robot-agent.md). The agent calls :func:`warm_up_control` at start-up, before it joins the
master. The sizes do not matter: a kernel is compiled for the types of its arguments, which every
network, safety layer and score shares.
"""

from __future__ import annotations

import time

import numpy as np

from minimize_surprise.fitness import SurpriseScore
from minimize_surprise.network import GenomeLayout, NetworkPair, NetworkSpec
from minimize_surprise.safety import SafetyConfig, SafetyLayer

__all__ = ["warm_up_control"]


def warm_up_control(sensors: tuple[str, ...]) -> float:
    """Run one control step of a robot with ``sensors`` (the network pair, the surprise score
    and the safety layer in both profiles) on zeros; the seconds it took."""
    began = time.monotonic()
    spec = NetworkSpec(sensors=sensors, actor_hidden=2, predictor_hidden=2)
    network = NetworkPair(spec, np.zeros(GenomeLayout(spec).size))
    values = np.zeros(len(sensors))
    score = SurpriseScore()
    score.expect(network.step(values)[1])
    score.observe(values)
    for profile in ("stop", "escape"):
        layer = SafetyLayer(sensors, SafetyConfig(profile=profile))
        layer.step(layer.initial_state(), values, (1.0, 1.0))
    return time.monotonic() - began
