"""The network pair: genome layout, exact forward pass, batching, predefined predictions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from minimize_surprise.config import ExperimentConfig, decode
from minimize_surprise.errors import GenomeError
from minimize_surprise.network import GenomeLayout, NetworkPair, NetworkSpec, spec_from_config

SENSORS = ("ir.f0", "ir.f2", "ir.b0", "ground.0")


def spec(**kw) -> NetworkSpec:
    args = {"sensors": SENSORS, "actor_hidden": 3, "predictor_hidden": 5}
    args.update(kw)
    return NetworkSpec(**args)


def reference_run(spec: NetworkSpec, genome: np.ndarray, sensor_seq: np.ndarray):
    """The documented layout, read gene by gene with plain loops: the executable specification."""
    r, m, ha, hp = len(spec.sensors), 2, spec.actor_hidden, spec.predictor_hidden
    free = [i for i, n in enumerate(spec.sensors) if n not in spec.predefined]
    genes = iter(genome.tolist())
    a_hidden = [[next(genes) for _ in range(r + m + 1)] for _ in range(ha)]
    a_out = [[next(genes) for _ in range(ha + 1)] for _ in range(m)]
    if free:
        p_hidden = [[next(genes) for _ in range(r + m + 1)] for _ in range(hp)]
        p_self = [next(genes) for _ in range(hp)]
        h = [next(genes) for _ in range(hp)]
        p_out = [[next(genes) for _ in range(hp + 1)] for _ in range(len(free))]
    assert next(genes, None) is None, "genome longer than the documented layout"
    sig = lambda x: 1.0 / (1.0 + math.exp(-x))  # noqa: E731
    prev = [spec.initial_action] * m
    out = []
    for s in sensor_seq.tolist():
        x = s + prev + [1.0]
        hid = [math.tanh(sum(w * v for w, v in zip(row, x, strict=True))) for row in a_hidden]
        act = [
            math.tanh(sum(w * v for w, v in zip(row, [*hid, 1.0], strict=True))) for row in a_out
        ]
        pred = [spec.predefined.get(n, 0.0) for n in spec.sensors]
        if free:
            x = s + act + [1.0]
            h = [
                sig(sum(w * v for w, v in zip(row, x, strict=True)) + p_self[j] * h[j])
                for j, row in enumerate(p_hidden)
            ]
            for k, i in enumerate(free):
                pred[i] = sig(sum(w * v for w, v in zip(p_out[k], [*h, 1.0], strict=True)))
        prev = act
        out.append((act, pred))
    return out


def test_layout_size_follows_the_documented_blocks():
    layout = GenomeLayout(spec())
    r, ha, hp = 4, 3, 5
    assert layout.size == ha * (r + 3) + 2 * (ha + 1) + hp * (r + 3) + hp + hp + r * (hp + 1)
    starts = sorted(start for start, _ in layout.blocks.values())
    ends = sorted(start + int(np.prod(shape)) for start, shape in layout.blocks.values())
    assert starts[0] == 0 and ends[-1] == layout.size and starts[1:] == ends[:-1]


@pytest.mark.parametrize(
    "predefined", [{}, {"ground.0": 0.4}, {s: 0.1 for s in SENSORS}], ids=["free", "one", "all"]
)
def test_forward_pass_matches_the_reference_gene_by_gene(predefined):
    sp = spec(predefined=predefined, initial_action=0.5)
    rng = np.random.default_rng(3)
    genome = rng.uniform(-2, 2, GenomeLayout(sp).size)
    seq = rng.random((6, len(SENSORS)))
    net = NetworkPair(sp, genome)
    for s, (act, pred) in zip(seq, reference_run(sp, genome, seq), strict=True):
        a, p = net.step(s)
        np.testing.assert_allclose(a, act, rtol=0, atol=1e-12)
        np.testing.assert_allclose(p, pred, rtol=0, atol=1e-12)


def test_all_predefined_drops_the_predictor():
    sp = spec(predefined={s: 0.3 for s in SENSORS})
    layout = GenomeLayout(sp)
    assert not layout.has_predictor
    assert set(layout.blocks) == {"actor.hidden", "actor.output"}
    _, p = NetworkPair(sp, np.zeros(layout.size)).step(np.full(4, 0.9))
    assert p.tolist() == [0.3] * 4


def test_batch_equals_independent_single_robots():
    sp = spec()
    rng = np.random.default_rng(7)
    genome = rng.uniform(-1, 1, GenomeLayout(sp).size)
    seq = rng.random((5, 3, len(SENSORS)))  # steps x robots x sensors
    batch = NetworkPair(sp, genome, robots=3)
    singles = [NetworkPair(sp, genome) for _ in range(3)]
    for s in seq:
        a, p = batch.step(s)
        for i, net in enumerate(singles):
            ai, pi = net.step(s[i])
            # BLAS may order a batched product's sums differently: equal up to rounding.
            np.testing.assert_allclose(a[i], ai, rtol=0, atol=1e-14)
            np.testing.assert_allclose(p[i], pi, rtol=0, atol=1e-14)


@pytest.mark.parametrize(
    "predefined", [{}, {"ground.0": 0.4}, {s: 0.1 for s in SENSORS}], ids=["free", "one", "all"]
)
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "interpreted"])
@pytest.mark.parametrize("genomes", [1, 2], ids=["shared", "per-lane"])
def test_robots_as_lanes_compute_the_same_bits_as_one_robot_at_a_time(
    predefined, compiled, genomes
):
    # The simulator's engine steps swarms' networks with robots as lanes (network_step_lanes),
    # one genome shared by every lane or a genome per run; a robot's agent steps its own alone
    # (network_step): every action, prediction, hidden state and next input must be the same to
    # the last bit, over steps.
    from minimize_surprise.network import (
        lane_weights,
        network_step,
        network_step_lanes,
        network_weights,
    )

    lanes_step = network_step_lanes if compiled else network_step_lanes.py_func
    one = network_step if compiled else network_step.py_func
    sp = spec(predefined=predefined, initial_action=0.5)
    rng = np.random.default_rng(11)
    layout = GenomeLayout(sp)
    weights = [network_weights(layout, rng.uniform(-3, 3, layout.size)) for _ in range(genomes)]
    robots, r, ha = 5, len(SENSORS), sp.actor_hidden
    lanes = 8 * -(-genomes * robots // 8)  # padded as the engine pads
    net = lane_weights(weights, robots, lanes)
    hp = net.p_in.shape[0]
    seq = rng.random((8, lanes, r))
    work = np.empty((r + 3 + ha, lanes))
    previous, hidden = np.full((2, lanes), 0.5), net.p_init.copy()
    acc = np.empty((max(ha, hp, r, 2), lanes))
    action, prediction = np.empty((2, lanes)), np.empty((r, lanes))
    singles = [
        (weights[i // robots], np.full(2, 0.5), weights[i // robots].p_init.copy())
        for i in range(genomes * robots)
    ]
    for s in seq:
        work[:r] = s.T
        lanes_step(*net[:7], work, previous, hidden, acc, action, prediction)
        for i, (w, prev_i, hidden_i) in enumerate(singles):
            a_i, p_i = np.empty(2), np.empty(r)
            one(*w[:7], s[i].copy(), prev_i, hidden_i, np.empty(r + 3 + ha), a_i, p_i)
            assert np.array_equal(action[:, i], a_i) and np.array_equal(prediction[:, i], p_i)
            assert np.array_equal(previous[:, i], prev_i)
            assert np.array_equal(hidden[:, i], hidden_i) and hidden_i.shape == (hp,)


def test_reset_restarts_the_evaluation():
    sp = spec()
    genome = np.random.default_rng(1).uniform(-1, 1, GenomeLayout(sp).size)
    net = NetworkPair(sp, genome)
    s = np.full(4, 0.2)
    first = net.step(s)
    net.step(np.full(4, 0.8))
    net.reset()
    again = net.step(s)
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])


@pytest.mark.parametrize("bad", [np.zeros(3), np.full(200, np.nan)], ids=["short", "nan"])
def test_genome_that_does_not_fit_is_refused(bad):
    sp = spec()
    if bad.size == 200:
        bad = np.full(GenomeLayout(sp).size, np.nan)
    with pytest.raises(GenomeError):
        NetworkPair(sp, bad)


def test_wrong_sensor_count_names_the_shapes():
    sp = spec()
    net = NetworkPair(sp, np.zeros(GenomeLayout(sp).size))
    with pytest.raises(ValueError, match=r"expected \(1, 4\)"):
        net.step(np.zeros(5))


@settings(max_examples=50, deadline=None)
@given(
    weights=st.floats(-1e3, 1e3),
    sensors=arrays(np.float64, (4,), elements=st.floats(0, 1)),
)
def test_outputs_stay_in_range_for_any_weights(weights, sensors):
    sp = spec()
    genome = np.full(GenomeLayout(sp).size, weights)
    a, p = NetworkPair(sp, genome).step(sensors)
    assert np.all(np.abs(a) <= 1) and np.all((p >= 0) & (p <= 1))


def test_spec_from_config_defaults_predictor_to_r_plus_one():
    cfg = decode({"sensors": list(SENSORS), "predefined": {"ir.b0": 0.2}}, ExperimentConfig)
    sp = spec_from_config(cfg)
    assert sp.predictor_hidden == 5 and sp.actor_hidden == 8 and sp.predefined == {"ir.b0": 0.2}
