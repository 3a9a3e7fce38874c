"""Compiling ahead: the kernels a first run will call, compiled side by side before it calls them.

numba compiles one function at a time per process, and a kernel's callees one after the other
while it compiles the kernel, so the first run on a machine waits for all of them in turn
(docs/simulation.md, "The first run"). A :data:`Plan` names kernels with the signatures they
will be called with (:func:`signature`, built from example arguments; :class:`ListOf` stands for a
typed list without building it); :func:`compile_ahead` compiles a plan in this process and
helpers forked from it, into the disk cache that :mod:`minimize_surprise.jit` keeps, where the
run then finds them.
"""

from __future__ import annotations

import contextlib
import os
import time
from typing import Any

from minimize_surprise import jit as _jit

__all__ = ["ListOf", "Plan", "compile_ahead", "cores", "signature"]

#: Kernels to compile, each with the signature of a call (:func:`signature`).
Plan = list[tuple[Any, tuple[Any, ...]]]


class ListOf:
    """In :func:`signature`'s arguments (or in a named tuple among them), a :func:`typed_list` of
    items like ``item``, which building would compile."""

    def __init__(self, item: Any) -> None:
        self.item = item


def signature(function: Any, *args: Any) -> tuple[Any, ...]:
    """The numba types of ``args`` as ``function`` (a :func:`kernel`) is called with them: the
    signature it is compiled for; empty without numba."""
    if not _jit.JIT:
        return ()
    return tuple(_type_of(function, arg) for arg in args)


def _type_of(function: Any, value: Any) -> Any:
    from numba import types

    if isinstance(value, ListOf):
        return types.ListType(function.typeof_pyval(value.item))
    if isinstance(value, tuple) and any(isinstance(member, ListOf) for member in value):
        # As numba types a tuple: a named tuple of one type for all members, or of each's own.
        members = [_type_of(function, member) for member in value]
        return types.BaseTuple.from_types(members, type(value))
    return function.typeof_pyval(value)


def compile_ahead(
    plan: Plan, then: Plan | None = None, last: Plan | None = None, *, processes: int | None = None
) -> int:
    """Compile what the on-disk cache lacks of ``plan`` in ``processes`` processes at once (this
    one and helpers forked from it; default: one per core this process may use), so that a
    kernel calling them, compiled next, loads them from the cache instead of compiling each in
    turn. numba compiles one function at a time per process, and a kernel's callees one after
    the other while it compiles the kernel; the first run on a machine waits for all of them
    (docs/simulation.md, "The first run"). ``last``: kernels that call the plan's, compiled
    here once the plan is; ``then``: kernels needed later, compiled by the helpers meanwhile
    and after this returns (they end before this process exits). Returns the number of
    processes that compiled (0: nothing to do, or no cache to share the results through).

    A helper that fails leaves its kernels to be compiled where they are called, which reports
    any error there; nothing here changes what is compiled or how."""
    cache = _jit.cache_directory()
    if cache is None:  # no numba, or nothing cached: the helpers' work would be lost
        return 0
    now, later, final = (
        [(function, types) for function, types in part or () if not _in_cache(function, types)]
        for part in (plan, then, last)
    )
    if processes is None:
        processes = cores()
    processes = min(processes, len(now) + len(later))
    if processes < 1:
        _compile_share(final, None, None, 0)
        return 1 if final else 0
    _lock_cache_saves(cache)
    import multiprocessing  # here: it imports sockets, which the core keeps out (no I/O)

    if processes == 1 or "fork" not in multiprocessing.get_all_start_methods():
        _compile_share(now + final, None, None, 0)  # ``then`` compiles where it is used
        return 1
    # Forked, not spawned: a helper starts at once with every module and kernel of this process
    # (spawning would import them all again, a second or more per helper). Nothing else runs
    # in this process while they start: the caller forks before any thread of its own.
    context = multiprocessing.get_context("fork")
    taken, done = context.Value("i", 0), context.Value("i", 0)
    todo = now + later
    helpers = [
        context.Process(
            target=_compile_share,
            args=(todo, taken, done, len(now)),
            name=f"compile-{k}",
            daemon=False,
        )
        for k in range(1, processes)
    ]
    for helper in helpers:
        helper.start()
    _compile_share(todo, taken, done, len(now), stop=len(now))
    while done.value < len(now) and any(helper.is_alive() for helper in helpers):
        time.sleep(_WAIT)
    _compile_share(final, None, None, 0)
    return processes


#: How often the process that compiles ahead looks whether its helpers are done (seconds): a
#: kernel takes a tenth of a second or more to compile.
_WAIT = 0.01


def cores() -> int:
    """The cores this process may run on (its affinity: all of them, or a ``taskset``'s)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


def _in_cache(function: Any, types: tuple[Any, ...]) -> bool:
    # Whether ``function`` has code for ``types`` in this process or in the on-disk cache.
    if types in function.overloads:
        return True
    try:
        return function._cache.load_overload(types, function.targetctx) is not None
    except Exception:  # unreadable: compiling it tells
        return False


def _compile_share(
    plan: Plan, taken: Any, done: Any, counted: int, stop: int | None = None
) -> None:
    # Take the next kernel not yet taken and compile it, until none is left (or none before
    # ``stop``): the processes share the plan's order (largest first) and end together.
    # ``done`` counts the first ``counted`` kernels compiled, the ones the caller waits for.
    k, last = -1, len(plan) if stop is None else stop
    while True:
        if taken is None:
            k += 1
        else:
            with taken.get_lock():
                k = taken.value
                if k >= last:
                    return
                taken.value += 1
        if k >= last:
            return
        function, types = plan[k]
        # A failure leaves the kernel to its caller's compile, which reports it there.
        with contextlib.suppress(Exception):
            function.compile(types)
        if done is not None and k < counted:
            with done.get_lock():
                done.value += 1


def _lock_cache_saves(cache: str) -> None:
    # numba saves a kernel's compiled code as a data file named by its number in the kernel's
    # index, and the index: two processes saving two signatures of one kernel at once could
    # both take number 1, and the index end up naming the other's code. So from the first
    # compile ahead on, every save of this process (and of the helpers it forks) holds a lock
    # on a file in the cache directory; once, for the process's life (helpers may outlive the
    # call that forked them).
    from numba.core import caching

    original = caching.IndexDataCacheFile.save
    if getattr(original, "_locked", False):
        return
    lock_path = os.path.join(cache, ".save-lock")

    def save(self: Any, key: Any, data: Any) -> None:
        import fcntl

        with open(lock_path, "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
            original(self, key, data)

    save._locked = True  # type: ignore[attr-defined]
    caching.IndexDataCacheFile.save = save  # type: ignore[method-assign]
