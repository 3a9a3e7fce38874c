"""The generational GA: roulette-wheel proportions, elitism, reduction over repetitions, and a
bit-exact resume from its plain-data state; novelty's kNN score and archive."""

from __future__ import annotations

import json

import numpy as np
import pytest

from minimize_surprise.evolution import EvolutionStateError
from minimize_surprise.genetic import GeneticAlgorithm, GeneticConfig, reduce_repetitions
from minimize_surprise.novelty import NoveltyArchive, knn_novelty


def test_roulette_wheel_picks_in_proportion_to_fitness():
    ga = GeneticAlgorithm(GeneticConfig(population=4), 3, seed=0)
    fitness = np.array([0.1, 0.2, 0.3, 0.4])
    parents = ga.select(fitness, np.random.default_rng(1).random(200_000))
    shares = np.bincount(parents, minlength=4) / parents.size
    np.testing.assert_allclose(shares, fitness / fitness.sum(), atol=0.005)
    # the first genome whose cumulative share reaches the draw
    assert list(ga.select(fitness, np.array([0.0, 0.1, 0.1000001, 0.3, 1.0]))) == [0, 0, 1, 1, 3]
    # all zero: uniform
    zero = ga.select(np.zeros(4), np.random.default_rng(2).random(40_000))
    np.testing.assert_allclose(np.bincount(zero) / zero.size, 0.25, atol=0.01)


def test_elite_keeps_its_slot_unmutated_and_the_others_mutate_at_the_rate():
    config = GeneticConfig(population=20, generations=3, mutation_probability=0.1)
    ga = GeneticAlgorithm(config, 500, seed=3)
    before = ga.ask().copy()
    fitness = np.linspace(0.1, 0.5, 20)
    fitness[7] = 0.9
    fitness[12] = 0.9  # a tie: the first is the best
    outcome = ga.tell(fitness)
    assert outcome.best_index == 7 and outcome.best_fitness == 0.9
    after = ga.ask()
    np.testing.assert_array_equal(after[7], before[7])
    others = np.delete(np.arange(20), 7)
    # each child differs from some parent in about 10 % of its genes, by at most 0.4
    changed = []
    for i in others:
        diffs = np.abs(after[i] - before).sum(axis=1)
        parent = int(np.argmin(diffs))
        delta = after[i] - before[parent]
        assert np.abs(delta).max() <= 0.4
        changed.append(np.mean(delta != 0))
    assert 0.08 < np.mean(changed) < 0.12
    novelty = GeneticAlgorithm(GeneticConfig(population=20, elitism=0), 500, seed=3)
    best = novelty.ask()[7].copy()
    novelty.tell(fitness)
    assert not np.array_equal(novelty.ask()[7], best)


def test_fitness_of_a_genome_is_the_minimum_over_its_repetitions():
    runs = np.array([[0.5, 0.3, 0.3, 0.9], [0.2, 0.8, 0.7, 0.1]])
    values, reps = reduce_repetitions(runs, "min")
    assert list(values) == [0.3, 0.1] and list(reps) == [1, 3]
    values, reps = reduce_repetitions(runs, "max")
    assert list(values) == [0.9, 0.8] and list(reps) == [3, 1]
    values, reps = reduce_repetitions(runs, "mean")
    np.testing.assert_allclose(values, [0.5, 0.45])
    assert list(reps) == [3, 3]
    ga = GeneticAlgorithm(GeneticConfig(population=2), 4, seed=0)
    outcome = ga.tell(runs)
    assert outcome.best_index == 0 and outcome.best_fitness == 0.3
    assert list(outcome.repetition) == [1, 3]


def test_resume_from_state_is_bit_for_bit():
    config = GeneticConfig(population=8, generations=6)
    rng = np.random.default_rng(9)
    scores = rng.random((6, 8, 3))
    whole = GeneticAlgorithm(config, 30, seed=5)
    populations = []
    for g in range(6):
        populations.append(whole.ask().copy())
        whole.tell(scores[g])
    part = GeneticAlgorithm(config, 30, seed=5)
    for g in range(3):
        part.tell(scores[g])
    state = json.loads(json.dumps(part.state()))
    resumed = GeneticAlgorithm.from_state(config, state)
    for g in range(3, 6):
        np.testing.assert_array_equal(resumed.ask(), populations[g])
        resumed.tell(scores[g])
    assert resumed.done
    with pytest.raises(EvolutionStateError):
        resumed.tell(scores[0])
    with pytest.raises(EvolutionStateError):
        GeneticAlgorithm.from_state(config, {"version": 99})


def test_bad_fitness_is_refused():
    ga = GeneticAlgorithm(GeneticConfig(population=3), 2, seed=0)
    with pytest.raises(ValueError, match="not negative"):
        ga.tell(np.array([0.1, -0.2, 0.3]))
    with pytest.raises(ValueError, match="shape"):
        ga.tell(np.array([0.1, 0.2]))
    with pytest.raises(ValueError, match="elitism"):
        GeneticConfig(elitism=2)


def test_knn_novelty_by_hand():
    behaviours = np.array([[0.0], [1.0], [3.0]])
    archive = np.array([[10.0]])
    # k = 2 among the others (population + archive, itself excluded)
    np.testing.assert_allclose(knn_novelty(behaviours, archive, 2), [2.0, 1.5, 2.5])
    # k larger than the pool: all others count
    np.testing.assert_allclose(knn_novelty(behaviours, archive, 10), [14 / 3, 4.0, 4.0])
    assert list(knn_novelty(np.array([[1.0, 2.0]]), np.empty((0, 2)), 10)) == [0.0]
    # Euclidean in several dimensions
    assert knn_novelty(np.array([[0.0, 0.0], [3.0, 4.0]]), np.empty((0, 2)), 1)[0] == 5.0


def test_archive_adds_with_its_probability_and_resumes():
    archive = NoveltyArchive(2, seed=1, k=3, add_probability=0.02)
    rng = np.random.default_rng(0)
    for _ in range(100):
        archive.score(rng.random((50, 2)))
    assert 70 < archive.behaviours.shape[0] < 130  # 5000 x 0.02 = 100
    copy = NoveltyArchive.from_state(json.loads(json.dumps(archive.state())))
    batch = rng.random((50, 2))
    np.testing.assert_array_equal(archive.score(batch), copy.score(batch))
    np.testing.assert_array_equal(archive.behaviours, copy.behaviours)
    with pytest.raises(ValueError, match="shape"):
        archive.score(np.zeros((3, 5)))
