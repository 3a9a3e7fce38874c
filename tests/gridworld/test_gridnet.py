"""The grid networks' genome layout, gene by gene, and the kernels' arithmetic against the
plain-loop reference of the authors' propagation."""

from __future__ import annotations

import math
from functools import partial

import numpy as np
import pytest

from gridworld import simd
from gridworld.kernels import (
    actor_decision,
    actor_decisions,
    prefix_sums,
    tanh_fast,
)
from gridworld.predictor import (
    LANE_ALIGN,
    OUTPUT_MARGIN,
    Predictor,
    input_sums,
    predict,
    predict_outputs,
)
from gridworld.simd import GROUP, TERMS, UNITS, step_lanes
from minimize_surprise.errors import GenomeError
from minimize_surprise.gridnet import (
    GridGenomeLayout,
    GridNetSpec,
    activation,
    actor_reference,
    c_activation,
    c_negative,
    grid_networks,
    predefined_names,
    predictor_reference,
)
from minimize_surprise.jit import kernel


def test_sizes_of_the_codes_networks():
    assert GridGenomeLayout(GridNetSpec(14)).size == 166 + 450
    assert GridGenomeLayout(GridNetSpec(6)).size == (14 + 28 + 8) + (14 + 6 * 8 + 36)
    assert GridGenomeLayout(GridNetSpec(8)).size == (18 + 54 + 12) + (18 + 8 * 10 + 64)
    man = GridNetSpec(14, "line-partial")
    assert man.outputs == (1, 2, 4, 5, 6, 7, 9, 10, 12, 13)
    assert man.predictor_hidden == 12
    assert GridGenomeLayout(man).size == 166 + 30 + 12 * 16 + 10 * 12
    assert GridGenomeLayout(GridNetSpec(14, "line")).size == 166
    assert GridGenomeLayout(GridNetSpec(14, actor_only=True)).size == 166


def test_every_gene_has_one_place_in_code_order():
    # a genome numbered 0, 1, 2, ...: each block is the used prefix of the code's layer array
    spec = GridNetSpec(14)
    layout = GridGenomeLayout(spec)
    w = layout.unpack(np.arange(layout.size, dtype=float))
    seen = np.concatenate([block.ravel() for block in w.values()])
    np.testing.assert_array_equal(np.sort(seen), np.arange(layout.size))
    start = 0
    for i in range(15):  # layer 0: 2i weight, 2i + 1 threshold
        assert w["actor.input"][i, 0] == start + 2 * i
        assert w["actor.input"][i, 1] == start + 2 * i + 1
    start += 30
    for j in range(8):  # layer 1: 15 j + i
        for i in range(15):
            assert w["actor.hidden"][j, i] == start + 15 * j + i
    start += 120
    for k in range(2):  # layer 2: 8 k + j
        for j in range(8):
            assert w["actor.output"][k, j] == start + 8 * k + j
    start += 16
    for i in range(15):
        assert w["predictor.input"][i, 0] == start + 2 * i
    start += 30
    for j in range(14):  # 16 j + i, self-loop at 16 j + 15
        for i in range(16):
            assert w["predictor.hidden"][j, i] == start + 16 * j + i
    start += 224
    for k in range(14):
        for j in range(14):
            assert w["predictor.output"][k, j] == start + 14 * k + j


def test_each_gene_reaches_the_kernel_arrays_where_the_reference_reads_it():
    spec = GridNetSpec(14)
    layout = GridGenomeLayout(spec)
    rng = np.random.default_rng(0)
    base = rng.uniform(-1, 1, layout.size)
    ref = grid_networks(layout, base)
    for gene in range(layout.size):
        genome = base.copy()
        genome[gene] += 0.25
        nets = grid_networks(layout, genome)
        changed = [
            name
            for name in ("a_u", "a_hidden", "a_out", "p_u", "p_hidden", "p_self", "p_out")
            if not np.array_equal(getattr(nets, name), getattr(ref, name))
        ]
        block = next(n for n, (s, shape) in layout.blocks.items()
                     if s <= gene < s + math.prod(shape))  # fmt: skip
        expected = {
            "actor.input": "a_u", "actor.hidden": "a_hidden", "actor.output": "a_out",
            "predictor.input": "p_u", "predictor.output": "p_out",
        }  # fmt: skip
        if block == "predictor.hidden":
            s, _ = layout.blocks[block]
            expected_name = "p_self" if (gene - s) % 16 == 15 else "p_hidden"
        else:
            expected_name = expected[block]
        assert changed == [expected_name], (gene, block, changed)


@pytest.mark.parametrize("sensors", [14, 6, 8])
@pytest.mark.parametrize("bits", [0, 5, 11])
def test_actor_kernel_matches_the_reference_on_every_input(sensors, bits):
    spec = GridNetSpec(sensors)
    layout = GridGenomeLayout(spec)
    rng = np.random.default_rng(sensors)
    genomes = rng.uniform(-1, 1, (2, layout.size))
    # the second genome's hidden units come in nearly equal pairs of opposite output weights:
    # its outputs lie near zero, where the kernel decides with the code's tanh
    w = layout.unpack(genomes[1])
    w["actor.hidden"][1::2] = w["actor.hidden"][0::2] * (1 + 1e-6)
    w["actor.output"][:, 1::2] = -w["actor.output"][:, 0::2]
    nets = grid_networks(layout, genomes)
    keys = range(1 << (sensors + 1)) if sensors < 14 else rng.integers(0, 1 << 15, 300)
    scratch = np.zeros(spec.actor_hidden, dtype=np.float32)
    bits = min(bits, sensors + 1)
    for g in range(2):
        prefix = np.zeros((spec.actor_hidden, 1 << bits), dtype=np.float32)
        prefix_sums(nets.a_u, nets.a_hidden, g, bits, prefix)
        for key in keys:
            inputs = [(int(key) >> i) & 1 for i in range(sensors + 1)]
            a0, turn = actor_reference(layout, genomes[g], inputs)
            m = actor_decision(nets.a_u, nets.a_hidden, nets.a_out, g, int(key), sensors + 1,
                               prefix, bits, scratch)  # fmt: skip
            assert (m & 1, 1 if m >> 1 else -1) == (a0, turn), (g, key)


@pytest.mark.parametrize("sensors", [14, 6, 8])
def test_actor_decisions_for_every_input_at_once_are_the_decisions_one_by_one(sensors):
    spec = GridNetSpec(sensors)
    layout = GridGenomeLayout(spec)
    rng = np.random.default_rng(sensors + 1)
    genomes = rng.uniform(-1, 1, (2, layout.size))
    w = layout.unpack(genomes[1])  # outputs near zero, as above
    w["actor.hidden"][1::2] = w["actor.hidden"][0::2] * (1 + 1e-6)
    w["actor.output"][:, 1::2] = -w["actor.output"][:, 0::2]
    genomes = np.vstack([genomes, genomes[:1]])
    nets = grid_networks(layout, genomes)
    nets.a_out[2, :, 0] = np.inf  # a float32 overflow: sums of inf and -inf are NaN
    nets.a_out[2, :, 1] = -np.inf
    patterns = 1 << (sensors + 1)
    bits = min(11, sensors + 1)  # the lookups continue over the remaining inputs
    memo = np.full(patterns, -1, dtype=np.int8)
    sums = np.empty((spec.actor_hidden, patterns), dtype=np.float32)
    z = np.empty((2, patterns), dtype=np.float32)
    scratch = np.zeros(spec.actor_hidden, dtype=np.float32)
    for g in range(3):
        prefix = np.zeros((spec.actor_hidden, 1 << bits), dtype=np.float32)
        prefix_sums(nets.a_u, nets.a_hidden, g, bits, prefix)
        actor_decisions(nets.a_u, nets.a_hidden, nets.a_out, g, sums, z, memo)
        one_by_one = [
            actor_decision(
                nets.a_u, nets.a_hidden, nets.a_out, g, key, sensors + 1, prefix, bits, scratch
            )
            for key in range(patterns)
        ]
        assert memo.tolist() == one_by_one, g


def test_prefix_sums_are_the_sums_in_input_order():
    spec = GridNetSpec(14)
    layout = GridGenomeLayout(spec)
    nets = grid_networks(layout, np.random.default_rng(3).uniform(-1, 1, (1, layout.size)))
    prefix = np.zeros((spec.predictor_hidden, 1 << 6), dtype=np.float32)
    prefix_sums(nets.p_u, nets.p_hidden, 0, 6, prefix)
    for k in range(1 << 6):
        for j in range(spec.predictor_hidden):
            total = np.float32(0.0)
            for i in range(6):
                total += nets.p_u[0, (k >> i) & 1, i] * nets.p_hidden[0, j, i]
            assert prefix[j, k] == total  # bit for bit


def _sensors_of(outputs):
    # The tests' predictors: output q predicts sensor 2 q (of 14).
    return (2 * np.arange(outputs)) % 14


def _predictor(out, table=None, self_loop=None, exact=False):
    # A Predictor for output weights out ((O, H)), fixed prediction 1 for sensor 13.
    o, hp = out.shape
    outputs = _sensors_of(o)
    weights = np.zeros((UNITS, UNITS), np.float32)
    margin = np.full(UNITS, -1.0, np.float32)
    for q in range(o):
        weights[:hp, outputs[q]] = out[q]
        margin[outputs[q]] = OUTPUT_MARGIN * np.abs(out[q]).sum(dtype=np.float32) + np.float32(1e-9)
    keep = np.uint32(sum(1 << int(k) for k in outputs))
    table = np.zeros((1, UNITS), np.float32) if table is None else table
    self_loop = np.zeros(UNITS, np.float32) if self_loop is None else self_loop
    return Predictor(table, self_loop, weights, margin, keep, np.uint32(1 << 13), exact)


def _codes_bits(out, hidden, lane):
    # The lane's predictions from the code's sums: terms in order from 0, the code's sign.
    bits = 1 << 13
    for q, k in enumerate(_sensors_of(out.shape[0])):
        z = np.float32(0.0)
        for j in range(out.shape[1]):
            z = np.float32(z + hidden[lane, j] * out[q, j])
        bits = (bits & ~(1 << int(k))) | (0 if c_negative(z) else 1 << int(k))
    return bits


def test_estimated_outputs_read_as_the_codes_sums_even_next_to_zero():
    rng = np.random.default_rng(6)
    lanes, o = 64, 7
    out = rng.uniform(-1, 1, (o, TERMS)).astype(np.float32)
    hidden = np.zeros((lanes, UNITS), np.float32)
    hidden[:, :TERMS] = rng.uniform(-1, 1, (lanes, TERMS))
    hidden[0] = 0.0  # every sum exactly 0: read as 1
    hidden[1] = 0.0
    hidden[1, 0] = -1e-17  # output sums within 1e-10 below 0, where the code's tanh decides
    hidden[2] = 0.0
    hidden[2, 0] = -1e-3
    hidden[2, 1] = 1e-3 * out[0, 0] / out[0, 1]  # output 0 cancels up to float32 rounding
    hidden[3] = hidden[4] * np.float32(1e-7)  # small, but far from zero for its weights
    for a in range(5, lanes):  # an output that cancels: its estimate's sign is a coin's toss
        q = a % o
        hidden[a, : TERMS - 1] *= np.float32(0.05)
        partial = np.dot(hidden[a, : TERMS - 1], out[q, : TERMS - 1])
        hidden[a, TERMS - 1] = -partial / out[q, TERMS - 1]
    assert np.abs(hidden).max() <= 1.0
    hidden[lanes - 1, 3] = np.nan  # NaN sums: the code's rule reads them as not negative
    predictor = _predictor(out)
    pmask = np.zeros(lanes, dtype=np.uint32)
    predict_outputs(predictor, hidden, pmask)
    for a in range(lanes):
        assert pmask[a] == _codes_bits(out, hidden, a), a
    assert pmask[0] == int(predictor.keep) | 1 << 13


def test_the_vector_code_refuses_lanes_of_the_wrong_shape():
    predictor = _predictor(np.ones((3, TERMS), np.float32))
    with pytest.raises(ValueError, match="multiple of 16"):
        predict_outputs(predictor, np.zeros((20, UNITS), np.float32), np.zeros(20, np.uint32))
    with pytest.raises(ValueError, match="multiple of 16"):
        predict_outputs(predictor, np.zeros((16, 14), np.float32), np.zeros(16, np.uint32))
    with pytest.raises(ValueError, match="bit mask per lane"):
        predict(predictor, np.zeros(16, np.int32), np.zeros((16, UNITS), np.float32),
                np.zeros(8, np.uint32))  # fmt: skip


@pytest.mark.parametrize("hp", [14, 6])
def test_the_vector_step_is_the_scalar_units_bit_for_bit(hp):
    rng = np.random.default_rng(hp)
    lanes = 3 * LANE_ALIGN
    table = np.zeros((1 << 6, UNITS), np.float32)
    table[:, :hp] = rng.normal(0, 2, (1 << 6, hp))
    table[5, :hp] = 40.0  # beyond the tanh's clamp
    self_loop = np.zeros(UNITS, np.float32)
    self_loop[:hp] = rng.uniform(-1, 1, hp)
    out = rng.uniform(-1, 1, (5, hp)).astype(np.float32)
    hidden = np.zeros((lanes, UNITS), np.float32)
    hidden[:, :hp] = rng.uniform(-1, 1, (lanes, hp))
    pkey = rng.integers(0, 1 << 6, lanes).astype(np.int32)
    for exact in (False, True):
        predictor = _predictor(out, table=table, self_loop=self_loop, exact=exact)
        states, pmask = hidden.copy(), np.zeros(lanes, np.uint32)
        for _ in range(3):  # the self-loops read the states the step before wrote
            before = states.copy()
            predict(predictor, pkey, states, pmask)
            unit = c_activation if exact else tanh_fast
            for a in range(lanes):
                for j in range(UNITS):
                    x = np.float32(table[pkey[a], j] + np.float32(before[a, j] * self_loop[j]))
                    assert states[a, j].tobytes() == np.float32(unit(x)).tobytes(), (a, j)
                assert pmask[a] == _codes_bits(out, states, a), a


@kernel
def _step_group(table, pkey, hidden, self_loop, weights, margin, pmask, keep, first):
    # step_lanes is a compiled intrinsic: only a kernel can call it
    return step_lanes(table, pkey, hidden, 0, self_loop, weights, margin, pmask, keep, first)


def test_the_plain_python_lanes_read_as_the_vector_code():
    # without numba the group's step is plain Python; its sums are the code's
    rng = np.random.default_rng(2)
    table = rng.normal(0, 1, (16, UNITS)).astype(np.float32)
    table[:, TERMS:] = 0.0
    self_loop = rng.uniform(-1, 1, UNITS).astype(np.float32)
    weights = rng.uniform(-1, 1, (UNITS, UNITS)).astype(np.float32)
    weights[TERMS:] = 0.0
    margin = np.full(UNITS, 1e-5, np.float32)
    pkey = rng.integers(0, 16, GROUP).astype(np.int32)
    hidden = rng.uniform(-1, 1, (GROUP, UNITS)).astype(np.float32)
    results = []
    keep, first = np.uint32(0x3FF), np.uint32(1 << 12)
    for step in (_step_group, partial(simd._step_lanes_py, a=0)):
        states, pmask = hidden.copy(), np.zeros(GROUP, np.uint32)
        unsure = step(table, pkey, states, self_loop=self_loop, weights=weights, margin=margin,
                      pmask=pmask, keep=keep, first=first)  # fmt: skip
        results.append((states, pmask, unsure))
    (h0, p0, u0), (h1, p1, u1) = results
    assert h0.tobytes() == h1.tobytes()
    sure = [lane for lane in range(GROUP) if not (u0 | u1) >> lane & 1]
    assert sure and np.array_equal(p0[sure], p1[sure])
    assert all(int(p) & ~0x3FF == 1 << 12 for p in p0)  # only the kept sensors over the first


@pytest.mark.parametrize("bits", [8, 15])  # levels only; levels, then rows continued
def test_input_sums_by_pattern_are_the_sums_by_unit(bits):
    spec = GridNetSpec(14)
    nets = grid_networks(GridGenomeLayout(spec), np.random.default_rng(4).uniform(-1, 1, (2, 616)))
    by_unit = np.zeros((spec.predictor_hidden, 1 << bits), dtype=np.float32)
    prefix_sums(nets.p_u, nets.p_hidden, 1, bits, by_unit)
    by_pattern = np.full((1 << bits, UNITS), np.nan, dtype=np.float32)
    input_sums(nets.p_u, nets.p_hidden, 1, bits, by_pattern)
    assert by_pattern[:, : spec.predictor_hidden].tobytes() == by_unit.T.copy().tobytes()
    assert not by_pattern[:, spec.predictor_hidden :].any()


def test_predictor_reference_keeps_fixed_sensors():
    spec = GridNetSpec(14, "line-partial")
    layout = GridGenomeLayout(spec)
    genome = np.random.default_rng(1).uniform(-1, 1, layout.size)
    predictions, hidden = predictor_reference(layout, genome, [0] * 15, [0.0] * 12)
    assert [predictions[k] for k in (0, 3, 8, 11)] == [1, 1, 1, 1]
    assert len(hidden) == 12
    assert list(GridNetSpec(14, "pair").fixed) == [1] + [0] * 13
    assert list(GridNetSpec(8, "line").fixed) == [1, 0, 0, 0, 0, 1, 0, 0]
    assert list(GridNetSpec(14, "aggregation").fixed) == [1] * 14
    assert GridNetSpec(14, "aggregation").outputs == ()


def test_the_codes_tanh_and_its_sign():
    assert activation(0.0) == 0.0
    assert activation(0.5) == pytest.approx(math.tanh(0.5), abs=1e-7)
    assert not c_negative(np.float32(0.0))
    assert c_negative(np.float32(-1e-3))
    # exp(2e-17) rounds to 1 in double: the code's tanh gives 0, which is not negative
    assert not c_negative(np.float32(-1e-17))
    xs = np.linspace(-12, 12, 4001, dtype=np.float32)
    assert max(abs(float(tanh_fast(x)) - math.tanh(float(x))) for x in xs) < 3e-7


def test_bad_specs_and_genomes_are_refused():
    with pytest.raises(ValueError, match="one of 14, 6, 8"):
        GridNetSpec(7)
    with pytest.raises(ValueError, match="unknown predefined"):
        GridNetSpec(14, "circle")
    with pytest.raises(ValueError, match="nothing is left"):
        GridNetSpec(6, "square-partial")
    with pytest.raises(ValueError, match="nothing is left"):
        GridNetSpec(14, "aggregation-partial")
    assert "line-partial" in predefined_names()
    layout = GridGenomeLayout(GridNetSpec(14))
    with pytest.raises(GenomeError, match="shape"):
        layout.unpack(np.zeros(5))
    with pytest.raises(GenomeError, match="non-finite"):
        layout.unpack(np.full(layout.size, np.nan))
