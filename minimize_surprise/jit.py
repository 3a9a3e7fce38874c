"""Compiled kernels: the per-step pieces of the method, compiled with numba where it is installed.

A kernel is a plain Python function over numpy arrays and numbers, written with explicit loops in
the subset of Python that numba compiles. :func:`kernel` compiles it when numba can be imported
and returns it unchanged otherwise. The same source therefore serves the robot's agent, which
calls it for one robot ten times a second (compiled on a laptop, interpreted on a Pi without
numba), and the simulator's engine, which calls it from its own compiled loops for every robot of
every run; the two cannot drift apart. ``SURPRISE_NO_JIT=1`` in the environment switches
compilation off (for debugging; everything still works, slowly).

Compiled code is cached on disk (numba's ``cache=True``), so only the first use on a machine
pays the compilation, a few seconds per kernel. numba tells a stale cache entry by its own
source file only: a kernel whose file did not change keeps the compiled code of the kernels it
calls as they were, and after an update that changed a callee's arguments the process dies in
LLVM ("Symbol not found"). So the cache lives in a directory named by a fingerprint of every
module that defines kernels (:func:`kernel_fingerprint`), under
``~/.cache/minimize-surprise/numba`` (``$XDG_CACHE_HOME`` is honoured; without a writable home, a
directory of the user's own in the temporary directory; with no writable place at all nothing is
cached; a ``NUMBA_CACHE_DIR`` of the user's own is left as it is): an update compiles afresh,
once.
"""

from __future__ import annotations

import functools
import hashlib
import linecache
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, Literal, TypeVar

__all__ = [
    "JIT",
    "BorrowError",
    "borrow",
    "cache_directory",
    "compiled_on_disk",
    "kernel",
    "typed_list",
    "typed_list_plan",
]

F = TypeVar("F", bound=Callable[..., Any])
T = TypeVar("T")

_numba: ModuleType | None
try:  # numba is optional: the `sim` extra brings it, a robot may do without
    if os.environ.get("SURPRISE_NO_JIT", "") not in ("", "0"):
        raise ImportError("SURPRISE_NO_JIT is set")
    import numba as _numba
except ImportError:  # pragma: no cover - depends on the installation
    _numba = None

#: Whether kernels are compiled.
JIT: bool = _numba is not None

#: The packages whose modules may define kernels (those importing this module).
_PACKAGES = ("minimize_surprise", "simulator", "gridworld", "robot_agent", "master_service")
#: A module defines or calls kernels when it holds this.
_MARK = b"from minimize_surprise.jit import"
#: Cache directories of other fingerprints untouched this long are removed (seconds).
_STALE_AFTER = 7 * 24 * 3600.0


def kernel_fingerprint(root: Path, packages: tuple[str, ...] = _PACKAGES) -> str:
    """A digest of the path and content of every module under ``root``'s ``packages`` that
    uses kernels (and of this one): it changes when any kernel's source does."""
    digest = hashlib.blake2b(digest_size=8)
    files = sorted(f for package in packages for f in (root / package).rglob("*.py"))
    for path in files:
        content = path.read_bytes()
        if _MARK in content or path.name == "jit.py":
            digest.update(str(path.relative_to(root)).encode() + b"\0" + content + b"\0")
    return digest.hexdigest()


def _cache_roots() -> list[Path]:
    # Where fingerprinted caches may live, best first: the user's cache directory, then one of
    # this user's own in the temporary directory (a container's user without a home).
    bases = []
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    if os.path.isabs(xdg):  # the XDG rule: a relative path is to be ignored
        bases.append(Path(xdg) / "minimize-surprise")
    home = os.path.expanduser("~")
    if os.path.isabs(home) and home != "/":
        bases.append(Path(home) / ".cache" / "minimize-surprise")
    bases.append(Path(tempfile.gettempdir()) / f"minimize-surprise-{os.getuid()}")
    return [base / "numba" for base in bases]


def _writable(directory: Path) -> bool:
    # Made if need be, owned by us and really writable (a probe file: permission bits do not
    # tell for root without its capabilities, nor on a read-only mount).
    try:
        directory.mkdir(parents=True, exist_ok=True)
        if directory.stat().st_uid != os.getuid():
            return False
        fd, probe = tempfile.mkstemp(dir=directory)
        os.close(fd)
        os.unlink(probe)
        return True
    except OSError:
        return False


def _use_fingerprinted_cache(numba: ModuleType) -> bool:
    # Point numba's cache at this installation's fingerprint (module docstring) in the first
    # writable place, mark it used, and forget other fingerprints unused for a week. False when
    # no place is writable: numba would then fall back to caches next to the sources, where a
    # stale callee survives, so kernels are not cached at all.
    if os.environ.get("NUMBA_CACHE_DIR"):
        return True
    fingerprint = kernel_fingerprint(Path(__file__).resolve().parent.parent)
    for root in _cache_roots():
        here = root / fingerprint
        if not _writable(here):
            continue
        numba.config.CACHE_DIR = str(here)
        try:
            os.utime(here)  # in use: not stale for another installation's clean-up
            for other in root.iterdir():
                if other != here and time.time() - other.stat().st_mtime > _STALE_AFTER:
                    shutil.rmtree(other, ignore_errors=True)
        except OSError:
            pass
        return True
    return False


#: Whether compiled kernels are cached on disk (see the module docstring).
_CACHE: bool = _numba is not None and _use_fingerprinted_cache(_numba)


def kernel(
    function: F | None = None,
    *,
    error_model: Literal["python", "numpy"] = "numpy",
    inline: bool = False,
) -> Any:
    """Compile ``function`` with numba (no Python objects, cached on disk) if available.

    The original function stays reachable as ``.py_func`` either way, so tests can check that the
    interpreted and the compiled kernel agree. ``@kernel(inline=True)`` has LLVM inline the kernel
    into every kernel that calls it (numba's ``forceinline``): a call costs more than a small
    helper's own work, and a call of a large one in the engine's loop over robots a tenth of the
    run (docs/simulation.md, "The first run"). The kernel is still compiled once, as a function
    of its own, and its callers are compiled as calling it; numba's own inlining
    (``inline="always"``) would compile a copy of it into each caller instead, at every call
    site, which made the first run on a machine three times as long. Division is numpy's by
    default (``error_model="numpy"``: x / 0 gives inf or nan,
    an integer // or % by 0 gives 0, where the interpreted kernel raises; so a kernel keeps its
    divisors away from 0). With
    Python's, every division is a path that may raise, which keeps numba from pruning the
    reference counts along it and the compiler from vectorising the loop around it.
    """
    if function is None:
        return lambda f: kernel(f, error_model=error_model, inline=inline)
    if _numba is None:
        function.py_func = function  # type: ignore[attr-defined]
        return function
    return _numba.njit(cache=_CACHE, nogil=True, error_model=error_model, forceinline=inline)(
        function
    )


def compiled_on_disk(function: Any) -> bool | None:
    """Whether ``function`` (a :func:`kernel`) has compiled code in the on-disk cache, so that
    its first call loads it instead of compiling; None when there is no telling (no numba, no
    cache, or numba's cache keeps its files elsewhere than this version of numba did)."""
    if _numba is None or not _CACHE:
        return None
    try:
        index = function._cache._cache_file._index_path
    except AttributeError:
        return None
    return os.path.exists(index)


def cache_directory() -> str | None:
    """Where compiled kernels are kept on disk (None: not cached)."""
    return str(_numba.config.CACHE_DIR) if _numba is not None and _CACHE else None


def _members(tuple_type: Any) -> tuple[Any, ...]:
    # A numba tuple type's member types (numba has no type hints).
    return tuple(tuple_type.types)


def _owns_memory(numba_type: Any) -> bool:
    # Whether a value of this numba type holds arrays (whose memory numba reference-counts).
    from numba import types

    if isinstance(numba_type, types.Array):
        return True
    if isinstance(numba_type, types.BaseTuple):
        return any(_owns_memory(member) for member in _members(numba_type))
    return False


def _unowned(context: Any, builder: Any, numba_type: Any, value: Any) -> Any:
    # ``value`` with the owner of every array in it set to null (the LLVM value of an array is
    # a struct whose ``meminfo`` numba counts references on, a tuple a struct of its members).
    from numba import types
    from numba.core import cgutils

    if isinstance(numba_type, types.Array):
        array = cgutils.create_struct_proxy(numba_type)(context, builder, value=value)
        array.meminfo = cgutils.get_null_value(array.meminfo.type)
        array.parent = cgutils.get_null_value(array.parent.type)
        return array._getvalue()
    if isinstance(numba_type, types.BaseTuple):
        for k, member in enumerate(_members(numba_type)):
            if _owns_memory(member):
                item = _unowned(context, builder, member, builder.extract_value(value, k))
                value = builder.insert_value(value, item, k)
    return value


class BorrowError(TypeError):
    """A kernel borrows memory it owns (:data:`borrow`): raised when numba compiles it."""


# Where a borrowed value may come from: the kernel's arguments, constants, and what they hold
# (an attribute, an item, a view, a loop's items). Anything else the kernel computed (a call,
# arithmetic on arrays, an item taken with an array of indices) is memory the kernel owns.
_THROUGH = ("getattr", "static_getitem", "getitem", "typed_getitem", "exhaust_iter", "cast")
_THROUGH_ITER = ("pair_first", "iternext", "getiter")
_NOTHING = ("null", "undef")


def _where(loc: Any) -> str:
    # "file:line (`source`)" of a numba IR location.
    line = linecache.getline(loc.filename, loc.line).strip()
    return f"{loc.short()} (`{line}`)" if line else loc.short()


class _Lender:
    # One function's IR after type inference (and after numba inlined its ``inline=True``
    # callees): every call of ``borrow`` in it, traced back to where its argument comes from.

    def __init__(self, ir: Any, types: Any, func_ir: Any, typemap: Any, lend: Any) -> None:
        self.ir, self.types, self.typemap = ir, types, typemap
        self.defs: dict[str, list[Any]] = {}
        lenders = set()
        for block in func_ir.blocks.values():
            for inst in block.find_insts(ir.Assign):
                self.defs.setdefault(inst.target.name, []).append(inst.value)
                if isinstance(inst.value, (ir.Global, ir.FreeVar)) and inst.value.value is lend:
                    lenders.add(inst.target.name)
        self.lenders = lenders

    def is_borrow(self, expr: Any) -> bool:
        return (
            isinstance(expr, self.ir.Expr)
            and expr.op == "call"
            and expr.func.name in self.lenders
            and len(expr.args) == 1
        )

    def check(self, func_ir: Any) -> None:
        if not self.lenders:
            return
        for block in func_ir.blocks.values():
            for inst in block.find_insts(self.ir.Assign):
                if not self.is_borrow(inst.value):
                    continue
                arg = inst.value.args[0]
                if not _owns_memory(self.typemap.get(arg.name)):
                    continue  # nothing counted in it: borrowing changes nothing
                owned = self.owned(arg.name, set())
                if owned is not None:
                    what, loc = owned
                    raise BorrowError(
                        f"jit.borrow at {_where(inst.loc)} borrows memory the kernel owns "
                        f"({what} at {_where(loc)}), which numba frees after its last use "
                        "while the borrowed value is still read. Borrow only the kernel's "
                        "arguments and what they hold; an array the kernel needs borrowed is "
                        "allocated by its caller and passed in."
                    )

    def owned(self, name: str, seen: set[str]) -> tuple[str, Any] | None:
        # None when ``name`` is the kernel's argument or held by one, else what made it.
        if name in seen:
            return None  # a loop's back edge: its other definitions decide
        seen.add(name)
        for value in self.defs.get(name, ()):
            found = self.value_owned(value, seen)
            if found is not None:
                return found
        return None

    def value_owned(self, value: Any, seen: set[str]) -> tuple[str, Any] | None:
        ir = self.ir
        if isinstance(value, (ir.Arg, ir.Global, ir.FreeVar, ir.Const)):
            return None  # an argument, or a constant numba never frees
        if isinstance(value, ir.Var):
            return self.owned(value.name, seen)
        if not isinstance(value, ir.Expr):
            return (f"a {type(value).__name__}", value.loc)
        op = value.op
        if op in _NOTHING:
            return None
        if self.is_borrow(value):
            return self.owned(value.args[0].name, seen)
        if op == "getitem" and isinstance(self.typemap.get(value.index.name), self.types.Array):
            return ("an item taken with an array of indices, a copy", value.loc)
        if op in _THROUGH or op in _THROUGH_ITER:
            return self.owned(value.value.name, seen)
        if op in ("build_tuple", "phi"):
            items = value.items if op == "build_tuple" else value.incoming_values
            for item in items:
                found = self.value_owned(item, seen)
                if found is not None:
                    return found
            return None
        if op == "call":
            return ("the result of a call", value.loc)
        return (f"the result of {op}", value.loc)


def _borrow_intrinsic(numba: ModuleType) -> Any:
    @numba.extending.intrinsic
    def borrow(typingctx: Any, value: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            out = _unowned(context, builder, signature.args[0], args[0])
            # What is left counted (a typed list in a tuple) is the caller's new reference.
            if context.enable_nrt:
                context.nrt.incref(builder, signature.return_type, out)
            return out

        return value(value), codegen

    _refuse_owned_borrows(borrow)
    return borrow


def _refuse_owned_borrows(lend: Any) -> None:
    # The check of :data:`borrow`, at compile time: numba runs its "after-inference" rewrites on
    # every function it compiles in nopython mode, after type inference. Each kernel is checked
    # on its own: an ``inline=True`` kernel is inlined by LLVM after its call was compiled as a
    # call, so its caller holds the arguments until it returns. This one rewrites nothing.
    from numba.core import ir, rewrites, types

    @rewrites.register_rewrite("after-inference")
    class RefuseOwnedBorrows(rewrites.Rewrite):
        def __init__(self, state: Any) -> None:
            super().__init__(state)
            lender = _Lender(ir, types, state.func_ir, state.typemap, lend)
            lender.check(state.func_ir)

        def match(self, func_ir: Any, block: Any, typemap: Any, calltypes: Any) -> bool:
            return False


def _identity(value: T) -> T:
    return value


#: ``borrow(value)`` in a kernel: ``value`` (an array, or a tuple holding arrays) with no
#: ownership of its arrays' memory, so that numba counts no references on it nor on any view
#: or item taken from it. Every view of an owned array takes and drops a reference, an atomic
#: operation; in the engine's loop over robots those cost more than the robots' arithmetic
#: (docs/simulation.md, "Two engines"). Borrow only what outlives the kernel's use of it: the
#: kernel's own arguments (the caller holds them for the call) or what they hold (fields,
#: views, items of an argument's list). An array the kernel allocates is refused: numba frees
#: it after its owner's last use, so its borrowed view would be read after it is freed; compiling
#: such a kernel raises :class:`BorrowError` naming both lines. A called kernel, ``inline=True``
#: or not, may borrow its arguments: its caller holds them for the call. Never return or store a
#: borrowed array. Without numba it is the
#: identity, and nothing is checked (nothing is freed early either).
borrow: Callable[[T], T] = _borrow_intrinsic(_numba) if _numba is not None else _identity


@functools.cache
def _list_kernels() -> tuple[Callable[[Any], Any], Callable[[Any, Any], None]] | None:
    # A list started with its first item, and an item appended: compiled per item type only
    # (a kernel taking the items as one tuple would be compiled again for every length).
    # Made at the first use: numba's typed lists take a tenth of a second to import.
    if _numba is None:
        return None
    from numba.typed import List

    def start(item: Any) -> Any:
        out = List()
        out.append(item)
        return out

    def append(out: Any, item: Any) -> None:
        out.append(item)

    return _numba.njit(cache=_CACHE)(start), _numba.njit(cache=_CACHE)(append)


def typed_list(items: Sequence[T]) -> Sequence[T]:
    """numba's typed list of ``items`` (at least one, all of one type), as a kernel takes a list
    of named tuples; without numba, a plain list. It is built by compiled kernels, cached on
    disk like the others: numba building one from Python compiles its list methods for the item
    type in every process, about half a second a type, not cached."""
    if not items:
        raise ValueError("typed_list: no items (their type makes the list's)")
    kernels = _list_kernels()
    if kernels is None:
        return list(items)
    start, append = kernels
    out = start(items[0])
    for item in items[1:]:
        append(out, item)
    return out


def typed_list_plan(item: Any, *, appended: bool = False) -> list[tuple[Any, tuple[Any, ...]]]:
    """What :func:`typed_list` compiles for a list of items like ``item`` (of one item; with
    ``appended``, of more), as a :data:`~minimize_surprise.precompile.Plan`."""
    kernels = _list_kernels()
    if kernels is None:
        return []
    from numba import types

    start, append = kernels
    item_type = start.typeof_pyval(item)  # type: ignore[attr-defined]
    plan: list[tuple[Any, tuple[Any, ...]]] = [(start, (item_type,))]
    if appended:
        plan.append((append, (types.ListType(item_type), item_type)))
    return plan
