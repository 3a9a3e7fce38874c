"""Compiled kernels: the per-step pieces of the method, compiled with numba where it is installed.

A kernel is a plain Python function over numpy arrays and numbers, written with explicit loops in
the subset of Python that numba compiles. :func:`kernel` compiles it when numba can be imported
and returns it unchanged otherwise. The same source therefore serves the robot's agent, which
calls it for one robot ten times a second (compiled on a laptop, interpreted on a Pi without
numba), and the simulator's engine, which calls it from its own compiled loops for every robot of
every run; the two cannot drift apart. ``SURPRISE_NO_JIT=1`` in the environment switches
compilation off (for debugging; everything still works, slowly).

Compiled code is cached next to the sources (numba's ``cache=True``), so only the first use on a
machine pays the compilation, a few seconds per kernel.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from types import ModuleType
from typing import Any, Literal, TypeVar

__all__ = ["JIT", "kernel"]

F = TypeVar("F", bound=Callable[..., Any])

_numba: ModuleType | None
try:  # numba is optional: the `sim` extra brings it, a robot may do without
    if os.environ.get("SURPRISE_NO_JIT", "") not in ("", "0"):
        raise ImportError("SURPRISE_NO_JIT is set")
    import numba as _numba
except ImportError:  # pragma: no cover - depends on the installation
    _numba = None

#: Whether kernels are compiled.
JIT: bool = _numba is not None


def kernel(function: F | None = None, *, error_model: Literal["python", "numpy"] = "python") -> Any:
    """Compile ``function`` with numba (no Python objects, cached on disk) if available.

    The original function stays reachable as ``.py_func`` either way, so tests can check that the
    interpreted and the compiled kernel agree. ``@kernel(error_model="numpy")`` compiles without
    Python's division-by-zero check (x / 0 gives inf or nan): the check is a branch that keeps
    loops from being vectorised, so an arithmetic kernel whose divisor is never 0 uses it.
    """
    if function is None:
        return lambda f: kernel(f, error_model=error_model)
    if _numba is None:
        function.py_func = function  # type: ignore[attr-defined]
        return function
    return _numba.njit(cache=True, nogil=True, error_model=error_model)(function)
