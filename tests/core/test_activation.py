"""The networks' own tanh and sigmoid: accurate, and the same bits however they are run."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from minimize_surprise.activation import sigmoid, tanh
from minimize_surprise.jit import kernel


@kernel
def _tanh_lanes(xs: np.ndarray, out: np.ndarray) -> None:
    # The engine's shape of loop: one tanh per lane, which the compiler vectorises.
    for i in range(xs.shape[0]):
        out[i] = tanh(xs[i])


def _grid() -> np.ndarray:
    return np.concatenate(
        [
            np.linspace(-25.0, 25.0, 200_001),
            np.logspace(-300, 1.4, 20_000),
            -np.logspace(-300, 1.4, 20_000),
        ]
    )


def test_tanh_is_within_a_few_units_in_the_last_place_of_libm():
    xs = _grid()
    ours = np.empty_like(xs)
    _tanh_lanes(xs, ours)
    error = np.abs(ours - np.tanh(xs))
    assert error.max() <= 6e-16
    # Small arguments keep their relative precision (no cancellation near 0).
    small = np.abs(xs) < 1e-3
    assert np.all(error[small] <= 4 * np.spacing(np.abs(np.tanh(xs[small]))))


def test_vector_lanes_and_one_call_at_a_time_give_the_same_bits():
    # The engine's lanes (vector instructions), an agent's scalar call and the interpreted
    # function must agree to the last bit, or engine and robots would drift apart.
    xs = np.random.default_rng(5).normal(0.0, 4.0, 4099)
    lanes = np.empty_like(xs)
    _tanh_lanes(xs, lanes)
    assert np.array_equal(lanes, [tanh(float(x)) for x in xs])
    assert np.array_equal(lanes, [tanh.py_func(float(x)) for x in xs])


@given(st.floats(allow_nan=False, allow_infinity=True))
def test_tanh_stays_within_its_range_and_is_odd(x):
    t = tanh(x)
    assert -1.0 <= t <= 1.0
    assert tanh(-x) == -t
    assert abs(t - math.tanh(x)) <= 6e-16


def test_edges():
    assert tanh(0.0) == 0.0 and math.copysign(1.0, tanh(-0.0)) == -1.0
    assert tanh(1e-300) == 1e-300
    assert tanh(20.0) == 1.0 and tanh(1e300) == 1.0 and tanh(-math.inf) == -1.0
    assert math.isnan(tanh(math.nan))
    assert sigmoid(0.0) == 0.5 and sigmoid(-1e300) == 0.0 and sigmoid(1e300) == 1.0
    assert abs(sigmoid(1.3) - 1.0 / (1.0 + math.exp(-1.3))) <= 1e-15
