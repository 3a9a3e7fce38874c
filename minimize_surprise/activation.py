"""The networks' activations, ``tanh`` and ``sigmoid``, computed by arithmetic alone.

libm's ``tanh`` is a call the compiler cannot turn into vector instructions, and a robot's
networks spent more than half their time in it (docs/method.md). :func:`tanh` here is plain
multiplications, additions, one division and a clamp, so a loop over many robots runs several
lanes at once, and the scalar code (a robot's agent, compiled or interpreted) computes the very
same bits: IEEE arithmetic in the same order gives the same result in every lane.

tanh(x) = E / (E + 2) with E = expm1(2x). E is computed for 2x / 2^7 by its Taylor series to
the 13th power (the series' remainder is below a 1e-16th of the sum there), then brought back by
seven doublings, expm1(2a) = expm1(a) (expm1(a) + 2). No step subtracts nearly equal numbers, so
small arguments keep their relative precision; against libm the error is at most a few units in
the last place (5.6e-16 absolute over [-25, 25], tests/core/test_activation.py). It is computed for
|x| and takes the sign of x, so it is exactly odd. Beyond |x| = 20 tanh is 1 to double
precision, and |x| is clamped there so E never overflows.
"""

from __future__ import annotations

import math
from math import factorial

from minimize_surprise.jit import kernel

__all__ = ["sigmoid", "tanh"]

#: Arguments are clamped to [-_CLAMP, _CLAMP]: tanh(19.1) already rounds to 1.0.
_CLAMP = 20.0
#: Doublings after the series: the series is summed at 2x / 2^_DOUBLINGS.
_DOUBLINGS = 7
_SCALE = 2.0 / 2.0**_DOUBLINGS
#: Taylor coefficients of expm1, highest power first (Horner's scheme): 1/13!, ..., 1/2!, 1.
_SERIES = tuple(1.0 / factorial(k) for k in range(13, 0, -1))


@kernel  # E + 2 >= 2: the division never meets zero
def tanh(x: float) -> float:
    """The hyperbolic tangent of ``x`` (see the module docstring); NaN gives NaN."""
    # On |x|, the sign copied back: exactly odd, and E >= 0 never nears the pole at -2.
    y = min(abs(x), _CLAMP) * _SCALE
    p = 0.0
    for c in _SERIES:
        p = p * y + c
    e = p * y
    for _ in range(_DOUBLINGS):
        e = e * (e + 2.0)
    return math.copysign(e / (e + 2.0), x)


@kernel
def sigmoid(x: float) -> float:
    """The logistic function of ``x``, written ``(tanh(x / 2) + 1) / 2``: never overflows."""
    return 0.5 * (tanh(0.5 * x) + 1.0)
