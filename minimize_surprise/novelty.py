"""Novelty search's novelty score and archive (paper Sec. IV-C, after Lehman and Stanley).

An individual's novelty is the mean Euclidean distance from its behaviour vector to its k nearest
neighbours (k = 10) among the current population (itself excluded) and the archive; with fewer
than k others, all of them count. After a generation is scored, each of its individuals joins the
archive with probability ``add_probability`` (0.02); the archive has no size limit. The paper
leaves the neighbour pool and the exclusion of the individual itself open: these are our choices
(docs/gridworld.md). :meth:`NoveltyArchive.state` is JSON-safe; :meth:`from_state` resumes it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["NoveltyArchive", "knn_novelty"]


def knn_novelty(behaviours: np.ndarray, archive: np.ndarray, k: int) -> np.ndarray:
    """Novelty of each row of ``behaviours`` ((P, D)): mean distance to its ``k`` nearest among
    the other rows and the rows of ``archive`` ((A, D)); 0 when there are no others."""
    behaviours = np.asarray(behaviours, dtype=np.float64)
    archive = np.asarray(archive, dtype=np.float64).reshape(-1, behaviours.shape[1])
    pool = np.concatenate([behaviours, archive])
    diff = behaviours[:, None, :] - pool[None, :, :]
    dist = np.sqrt(np.einsum("pqd,pqd->pq", diff, diff))
    p = behaviours.shape[0]
    dist[np.arange(p), np.arange(p)] = np.inf  # an individual is not its own neighbour
    others = pool.shape[0] - 1
    kk = min(k, others)
    if kk <= 0:
        return np.zeros(p)
    nearest = np.partition(dist, kk - 1, axis=1)[:, :kk]
    return nearest.mean(axis=1)


class NoveltyArchive:
    """The archive of past behaviours, with its own seeded random generator."""

    def __init__(
        self, dimensions: int, seed: int, k: int = 10, add_probability: float = 0.02
    ) -> None:
        if k < 1:
            raise ValueError(f"k must be at least 1, got {k}")
        if not 0.0 <= add_probability <= 1.0:
            raise ValueError("add_probability must lie in [0, 1]")
        self.dimensions = dimensions
        self.k = k
        self.add_probability = add_probability
        self.rng = np.random.default_rng(seed)
        self.behaviours = np.empty((0, dimensions))

    def score(self, behaviours: np.ndarray) -> np.ndarray:
        """Novelty of a generation's behaviours ((P, D)), then each joins the archive with
        ``add_probability``."""
        behaviours = np.asarray(behaviours, dtype=np.float64)
        if behaviours.ndim != 2 or behaviours.shape[1] != self.dimensions:
            raise ValueError(f"behaviours must have shape (P, {self.dimensions})")
        novelty = knn_novelty(behaviours, self.behaviours, self.k)
        added = self.rng.random(behaviours.shape[0]) < self.add_probability
        self.behaviours = np.concatenate([self.behaviours, behaviours[added]])
        return novelty

    def state(self) -> dict[str, Any]:
        """JSON-safe state: the archive and the random generator."""
        return {
            "dimensions": self.dimensions,
            "k": self.k,
            "add_probability": self.add_probability,
            "behaviours": self.behaviours.tolist(),
            "rng": self.rng.bit_generator.state,
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> NoveltyArchive:
        """Rebuild an archive from :meth:`state`."""
        self = cls(int(state["dimensions"]), 0, int(state["k"]), float(state["add_probability"]))
        self.behaviours = np.array(state["behaviours"], dtype=np.float64).reshape(
            -1, self.dimensions
        )
        self.rng.bit_generator.state = state["rng"]
        return self
