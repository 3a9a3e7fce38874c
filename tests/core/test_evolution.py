"""(1+1) online evolution as ask/tell: selection, re-evaluation, failures, checkpoint/restore."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minimize_surprise.config import EvolutionConfig
from minimize_surprise.errors import GenomeError
from minimize_surprise.evolution import EvolutionStateError, OnePlusOne

CFG = EvolutionConfig(evaluations=50)


def test_first_candidate_is_the_initial_genome_within_range():
    evo = OnePlusOne(EvolutionConfig(initial_range=0.5), 1000, seed=0)
    c = evo.ask()
    assert c.kind == "initial" and np.all(np.abs(c.genome) <= 0.5)
    assert np.abs(c.genome).max() > 0.45  # uniform over the range, not a narrower one


def test_reevaluation_share_is_close_to_the_configured_probability():
    evo = OnePlusOne(EvolutionConfig(evaluations=10**6), 20, seed=42)
    kinds = []
    rng = np.random.default_rng(0)
    for _ in range(5001):
        kinds.append(evo.ask().kind)
        evo.tell(rng.random())
    share = kinds[1:].count("reevaluation") / 5000
    assert abs(share - 0.2) < 0.02  # 3.5 standard deviations of a binomial share


@pytest.mark.parametrize("p, expected", [(0.0, {"offspring"}), (1.0, {"reevaluation"})])
def test_reevaluation_probability_comes_from_configuration(p, expected):
    evo = OnePlusOne(EvolutionConfig(reevaluation_probability=p), 5, seed=1)
    evo.ask()
    evo.tell(0.5)
    kinds = set()
    for _ in range(50):
        kinds.add(evo.ask().kind)
        evo.tell(0.5)
    assert kinds == expected


def test_moving_average_on_reevaluation_is_exact_and_best_stays():
    evo = OnePlusOne(EvolutionConfig(reevaluation_probability=1.0), 5, seed=1)
    best = evo.ask().genome
    evo.tell(0.5)
    expected = 0.5
    for f in (0.1, 0.9, 0.3):
        assert evo.ask().kind == "reevaluation"
        outcome = evo.tell(f)
        expected = 0.2 * f + 0.8 * expected
        assert outcome.best_fitness == expected and outcome.accepted
        assert evo.best is best


def test_mutation_rate_and_range():
    cfg = EvolutionConfig(reevaluation_probability=0.0, mutation_probability=0.1,
                          mutation_range=0.4)  # fmt: skip
    evo = OnePlusOne(cfg, 20000, seed=2)
    parent = evo.ask().genome
    evo.tell(0.5)
    delta = evo.ask().genome - parent
    changed = delta != 0
    assert abs(changed.mean() - 0.1) < 0.01
    assert np.abs(delta).max() <= 0.4 and np.abs(delta[changed]).max() > 0.39


def test_offspring_replaces_best_when_at_least_as_good():
    evo = OnePlusOne(EvolutionConfig(reevaluation_probability=0.0), 5, seed=3)
    evo.ask()
    evo.tell(0.5)
    worse = evo.ask().genome
    assert not evo.tell(0.49).accepted and evo.best_fitness == 0.5
    assert worse is not evo.best
    equal = evo.ask().genome
    assert evo.tell(0.5).accepted and evo.best is equal


def test_the_best_remembers_the_evaluation_that_found_it():
    # The number best_genome.json gives: the evaluation whose candidate is the best genome, not
    # how many have been counted, and not a later re-evaluation of it.
    evo = OnePlusOne(EvolutionConfig(reevaluation_probability=0.5), 5, seed=6)
    found = None
    for fitness in np.linspace(0.1, 0.9, 30):
        candidate = evo.ask()
        outcome = evo.tell(fitness if candidate.kind != "offspring" else 1 - fitness)
        if outcome.accepted and candidate.kind != "reevaluation":
            found = outcome.evaluation
        assert evo.best_evaluation == found
    assert found is not None and found < evo.evaluations  # re-evaluations and rejects since
    restored = OnePlusOne.from_state(CFG, json.loads(json.dumps(evo.state())))
    assert restored.best_evaluation == found
    older = {key: value for key, value in evo.state().items() if key != "best_evaluation"}
    assert OnePlusOne.from_state(CFG, older).best_evaluation == evo.evaluations  # as it said


def test_failed_round_repeats_the_candidate_and_counts_nothing():
    evo = OnePlusOne(CFG, 5, seed=4)
    evo.ask()
    evo.tell(0.4)
    c = evo.ask()
    evo.tell_failed()
    evo.tell_failed()
    again = evo.ask()
    assert again.genome is c.genome and again.kind == c.kind
    assert evo.evaluations == 1 and evo.failed_rounds == 2
    assert evo.tell(0.6).evaluation == 2


def test_out_of_order_use_is_an_error():
    evo = OnePlusOne(CFG, 5, seed=4)
    with pytest.raises(EvolutionStateError):
        evo.tell(0.5)
    with pytest.raises(EvolutionStateError):
        evo.tell_failed()
    evo.ask()
    with pytest.raises(ValueError):
        evo.tell(float("nan"))


def test_initial_genome_can_be_given():
    evo = OnePlusOne(CFG, 3, seed=0, initial=np.array([1.0, 2.0, 3.0]))
    assert evo.ask().genome.tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(GenomeError):
        OnePlusOne(CFG, 3, seed=0, initial=np.zeros(2))


def test_done_after_the_configured_evaluations():
    evo = OnePlusOne(EvolutionConfig(evaluations=3), 2, seed=0)
    for _ in range(3):
        assert not evo.done
        evo.ask()
        evo.tell(0.5)
    assert evo.done


@settings(max_examples=40, deadline=None)
@given(
    script=st.lists(st.one_of(st.floats(0, 1), st.just("fail")), min_size=1, max_size=40),
    cut=st.integers(0, 40),
    seed=st.integers(0, 2**32 - 1),
)
def test_checkpoint_then_restore_gives_the_same_next_asks(script, cut, seed):
    """A run checkpointed after any step (through JSON) continues bit for bit."""
    cut = min(cut, len(script))

    def play(evo, steps):
        log = []
        for step in steps:
            c = evo.ask()
            log.append((c.kind, c.genome.tobytes()))
            if step == "fail":
                evo.tell_failed()
            else:
                log.append(evo.tell(step))
        return log

    straight = OnePlusOne(CFG, 12, seed=seed)
    expected = play(straight, script)

    first = OnePlusOne(CFG, 12, seed=seed)
    head = play(first, script[:cut])
    restored = OnePlusOne.from_state(CFG, json.loads(json.dumps(first.state())))
    assert head + play(restored, script[cut:]) == expected
    assert restored.state() == straight.state()


def test_restore_rejects_a_broken_state():
    with pytest.raises(EvolutionStateError):
        OnePlusOne.from_state(CFG, {"version": 1})
    with pytest.raises(EvolutionStateError):
        OnePlusOne.from_state(CFG, {**OnePlusOne(CFG, 2, seed=0).state(), "version": 99})
