"""The surprise fitness: t-1 predictions against t readings, mean over steps, sensors, robots."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from minimize_surprise.fitness import SurpriseScore, surprise_fitness, swarm_fitness


def test_prediction_is_scored_against_the_next_reading():
    sensors = np.array([[0.0, 0.0], [1.0, 0.5], [0.2, 0.2]])
    predictions = np.array([[1.0, 0.5], [0.0, 0.0], [9.0, 9.0]])  # last row never scored
    # step 1: |1-1|, |.5-.5| -> 1.0 ; step 2: |0-.2|, |0-.2| -> 0.8
    assert surprise_fitness(predictions, sensors) == pytest.approx(0.9, abs=1e-15)


def test_running_score_equals_the_recorded_fitness():
    rng = np.random.default_rng(5)
    sensors, predictions = rng.random((50, 9)), rng.random((50, 9))
    score = SurpriseScore()
    assert score.observe(sensors[0]) is None  # nothing to score at the first step
    score.expect(predictions[0])
    for s, p in zip(sensors[1:], predictions[1:], strict=True):
        score.observe(s)
        score.expect(p)
    assert score.scored_steps == 49
    assert score.fitness == pytest.approx(surprise_fitness(predictions, sensors), abs=1e-12)


def test_batch_score_is_per_robot():
    score = SurpriseScore()
    score.observe(np.zeros((2, 3)))
    score.expect(np.array([[0.0] * 3, [0.5] * 3]))
    score.observe(np.zeros((2, 3)))
    np.testing.assert_allclose(score.fitness, [1.0, 0.5])


def test_empty_and_reset():
    score = SurpriseScore()
    assert score.fitness == 0.0
    score.expect(np.ones(2))
    score.observe(np.zeros(2))
    score.reset()
    assert score.fitness == 0.0 and score.observe(np.ones(2)) is None


def test_swarm_fitness_is_the_equal_weight_mean():
    assert swarm_fitness([0.9, 0.7, 0.8, 0.6]) == pytest.approx(0.75)
    with pytest.raises(ValueError):
        swarm_fitness([])


@settings(max_examples=100, deadline=None)
@given(
    data=arrays(np.float64, st.tuples(st.integers(2, 20), st.integers(1, 12)),
                elements=st.floats(0, 1)),
)  # fmt: skip
def test_fitness_lies_in_unit_interval_and_perfect_prediction_scores_one(data):
    assert 0.0 <= surprise_fitness(np.roll(data, 1, axis=0), data) <= 1.0
    perfect = np.vstack([data[1:], data[:1]])  # predictions[t] == sensors[t+1]
    assert surprise_fitness(perfect, data) == pytest.approx(1.0)
