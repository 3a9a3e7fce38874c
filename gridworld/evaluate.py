"""Evaluating genomes in the grid world: the Python face of :mod:`gridworld.runs`.

:class:`GridEvaluator` holds a world (torus, agents, sensor model, steps, noise) and a network
layout, and evaluates a batch of genomes on shared start configurations in one compiled call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gridworld.kernels import Noise, build_torus
from gridworld.runs import BatchOutcome, evaluate_batch
from gridworld.world import WINDOW_MAX_SIDE, Torus, window_table
from minimize_surprise.gridnet import GridGenomeLayout, GridNetSpec, grid_networks

__all__ = ["Evaluation", "GridEvaluator", "noise_threshold"]


def noise_threshold(probability: float) -> int:
    """The 32-bit threshold below which a reading is flipped (0 switches noise off)."""
    if not 0.0 <= probability <= 1.0:
        raise ValueError(f"noise must be a probability in [0, 1], got {probability}")
    return min(round(probability * 4294967296.0), 4294967296)


@dataclass(frozen=True)
class Evaluation:
    """What evaluating G genomes on R start configurations gives.

    ``fitness`` (G, R) per run; ``predictions`` (G, R, S) mean scored prediction per sensor;
    ``final`` (G, R, N, 2) poses after the last step (cell, heading); ``behaviour`` (G, R, S)
    mean true sensor value over agents in the final configuration; ``trace`` the recorded run's
    poses ((T + 1, N, 2)) or None.
    """

    fitness: np.ndarray
    predictions: np.ndarray
    final: np.ndarray
    behaviour: np.ndarray
    trace: np.ndarray | None = None


class GridEvaluator:
    """Runs genomes of ``spec`` in a ``torus`` with ``steps`` steps per run and sensor ``noise``.

    ``exact`` uses the code's exp-based tanh in the predictor too (slower; see
    :mod:`gridworld.runs`).
    """

    def __init__(
        self,
        torus: Torus,
        spec: GridNetSpec,
        steps: int,
        noise: float = 0.0,
        exact: bool = False,
    ) -> None:
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        self.torus = torus
        self.spec = spec
        self.layout = GridGenomeLayout(spec)
        self.steps = steps
        self.noise = noise
        self.exact = exact
        self._threshold = noise_threshold(noise)
        self.neighbours = torus.neighbours(spec.sensors)
        sides = (torus.width, torus.height)
        if all(5 <= side <= WINDOW_MAX_SIDE for side in sides):
            self.window = window_table(spec.sensors)
        else:  # sensors are looked up cell by cell
            self.window = np.zeros((0, 3, 32), dtype=np.uint16)
        self._compiled_torus = build_torus(self.neighbours, self.window, torus.width)

    def evaluate(
        self,
        genomes: np.ndarray,
        starts: np.ndarray,
        noise_key: int = 0,
        trace: tuple[int, int] | None = None,
    ) -> Evaluation:
        """Run every genome (rows of ``genomes``) from every start in ``starts`` ((R, N, 2)).

        ``noise_key`` selects the noise flips (the same key gives every genome the same flips);
        ``trace = (genome, run)`` records that run's poses at every step.
        """
        nets = grid_networks(self.layout, genomes)
        starts = np.ascontiguousarray(starts, dtype=np.int32)
        if starts.ndim != 3 or starts.shape[2] != 2:
            raise ValueError(f"starts must have shape (runs, agents, 2), got {starts.shape}")
        if starts.size and (starts[:, :, 0].min() < 0 or starts[:, :, 0].max() >= self.torus.cells):
            raise ValueError("a start cell lies outside the grid")
        for rep in range(starts.shape[0]):
            if np.unique(starts[rep, :, 0]).size != starts.shape[1]:
                raise ValueError(f"start configuration {rep} puts two agents on one cell")
        g, reps, n = nets.genomes, starts.shape[0], starts.shape[1]
        s = self.spec.sensors
        fitness = np.empty((g, reps))
        predictions = np.empty((g, reps, s))
        final = np.empty((g, reps, n, 2), dtype=np.int32)
        behaviour = np.empty((g, reps, s))
        record = np.zeros((self.steps + 1, n, 2), dtype=np.int32)
        trace_run = -1 if trace is None else trace[0] * reps + trace[1]
        noise = Noise(self._threshold, int(noise_key) & 0xFFFFFFFF)
        out = BatchOutcome(fitness, predictions, final, behaviour, record, trace_run)
        evaluate_batch(self._compiled_torus, starts, self.steps, nets, noise, self.exact, out)
        return Evaluation(fitness, predictions, final, behaviour, record if trace else None)
