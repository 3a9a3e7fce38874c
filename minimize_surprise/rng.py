"""Counter-based random numbers for kernels: the same numbers compiled or interpreted.

A 32-bit integer hash (lowbias32, by Chris Wellons) turns a key into well-mixed bits. Products
may exceed 64 bits in Python and wrap in compiled code; only their low 32 bits are kept, which are
the same either way, so a seed gives the same stream on a robot without numba and in the engine.
"""

from __future__ import annotations

from minimize_surprise.jit import kernel

__all__ = ["mix32", "next_state", "unit"]


@kernel
def mix32(x: int) -> int:
    """A 32-bit hash of the low 32 bits of ``x``."""
    x &= 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    x = (x * 0x846CA68B) & 0xFFFFFFFF
    x ^= x >> 16
    return x


@kernel
def next_state(state: int) -> int:
    """The next state of a generator whose state is one 32-bit integer (its draws are the
    successive states)."""
    return mix32(state + 0x9E3779B9)


@kernel
def unit(bits: int) -> float:
    """32 random bits as a number in [0, 1)."""
    return (bits & 0xFFFFFFFF) / 4294967296.0
