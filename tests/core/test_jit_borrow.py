"""Borrowed arrays and typed lists (minimize_surprise.jit.borrow, typed_list): a kernel reads
and writes borrowed arrays as its own, views of them count no references, and whatever a
borrowed tuple holds besides arrays (a typed list) stays alive and intact."""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np
import pytest

from minimize_surprise.jit import JIT, BorrowError, borrow, kernel, typed_list


class _Pair(NamedTuple):
    rows: np.ndarray
    scale: float
    names: Sequence[np.ndarray]  # a typed list of arrays
    ids: np.ndarray


@kernel
def _row_sums(pair: _Pair, out: np.ndarray) -> None:
    pair, out = borrow(pair), borrow(out)
    rows = pair.rows
    for i in range(rows.shape[0]):
        row = rows[i]  # a view of a borrowed array: no reference counted
        total = 0.0
        for k in range(row.shape[0]):
            total += row[k]
        out[i] = total * pair.scale
    for item in pair.names:
        out[0] += item[0]
    pair.ids[0] += 1


def _pair(rows: np.ndarray) -> _Pair:
    names = typed_list([np.array([0.5]), np.array([0.25])])
    return _Pair(rows, 2.0, names, np.zeros(1, dtype=np.int64))


def test_a_kernel_reads_and_writes_borrowed_arrays_as_its_own() -> None:
    rows = np.arange(12.0).reshape(4, 3)
    pair = _pair(rows)
    out = np.zeros(4)
    _row_sums(pair, out)
    assert out.tolist() == [6.0 + 0.75, 24.0, 42.0, 60.0]
    assert pair.ids[0] == 1


def test_what_a_borrowed_tuple_holds_besides_arrays_stays_alive() -> None:
    # The typed list in the tuple is counted as the caller's: borrowed a thousand times, it is
    # neither freed nor changed (a missing count frees it after the first call).
    pair = _pair(np.ones((2, 2)))
    out = np.zeros(2)
    for _ in range(1000):
        _row_sums(pair, out)
    assert [float(item[0]) for item in pair.names] == [0.5, 0.25]
    assert pair.ids[0] == 1000
    assert out.tolist() == [4.75, 4.0]


@pytest.mark.skipif(not JIT, reason="reference counts are numba's")
def test_views_of_borrowed_arrays_count_no_references() -> None:
    import numba

    fresh = numba.njit(_row_sums.py_func)  # not from the disk cache, which keeps no LLVM
    fresh(_pair(np.arange(12.0).reshape(4, 3)), np.zeros(4))
    llvm = "\n".join(fresh.inspect_llvm().values())
    body = re.search(r"define [^\n]*_row_sums[^\n]*\{(.*?)\n\}", llvm, re.S)
    assert body is not None
    # The typed list alone is counted (taken once, given back once), no array.
    assert len(re.findall(r"call void @NRT_incref", body[1])) <= 1


def test_a_typed_list_holds_the_items_in_order() -> None:
    items = [np.array([1.0, 2.0]), np.array([3.0, 4.0]), np.array([5.0, 6.0])]
    listed = typed_list(items)
    assert len(listed) == 3
    assert [item.tolist() for item in listed] == [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]


# --------------------------------------------------------------------------- what is refused


def _refusals() -> dict[str, tuple[Callable[..., float], tuple[Any, ...], str]]:
    # Kernels that borrow memory they own, made inside the test (each compiles once, when
    # called): numba frees such an array after its last use, while the borrowed view is read.
    import numba

    @numba.njit
    def allocated(n: int) -> float:
        made = np.zeros(n)
        view = borrow(made)
        return view[0]

    @numba.njit
    def a_copy(rows: np.ndarray, picks: np.ndarray) -> float:
        view = borrow(rows[picks])  # an array of indices: a copy the kernel made
        return view[0]

    @numba.njit
    def in_a_tuple(rows: np.ndarray) -> float:
        pair = borrow((rows, rows * 2.0))  # the product is the kernel's
        return pair[1][0]

    return {
        "allocated": (allocated, (3,), "made = np.zeros(n)"),
        "a_copy": (a_copy, (np.ones(3), np.array([0, 2])), "a copy"),
        "in_a_tuple": (in_a_tuple, (np.ones(3),), "rows * 2.0"),
    }


@pytest.mark.skipif(not JIT, reason="the check runs when numba compiles a kernel")
@pytest.mark.parametrize("case", ["allocated", "a_copy", "in_a_tuple"])
def test_borrowing_memory_the_kernel_owns_does_not_compile(case: str) -> None:
    function, args, made = _refusals()[case]
    with pytest.raises(BorrowError, match="borrows memory the kernel owns") as refused:
        function(*args)
    message = str(refused.value)
    assert made in message, message  # the line that made the memory
    assert "test_jit_borrow.py:" in message, message


@pytest.mark.skipif(not JIT, reason="the check runs when numba compiles a kernel")
def test_borrowing_arguments_and_what_they_hold_compiles() -> None:
    import numba

    @kernel(inline=True)
    def first(values: np.ndarray) -> float:
        values = borrow(values)
        return values[0]

    @numba.njit
    def held(pair: _Pair, rows: np.ndarray, flag: bool) -> float:
        rows = borrow(rows)
        total = first(rows) + first(pair.rows[1])  # inlined: an argument's own rows
        tail = borrow(rows[1:] if flag else rows)  # a view of an argument, either way
        for item in pair.names:
            total += borrow(item)[0]  # an item of an argument's list
        nothing = borrow(None)
        made = np.ones(2)
        total += made[0] if nothing is None else 0.0
        return total + tail[0] + borrow(pair).ids[0]

    pair = _pair(np.arange(6.0).reshape(3, 2))
    assert held(pair, np.arange(3.0), True) == 0.0 + 2.0 + 0.75 + 1.0 + 1.0 + 0.0


@pytest.mark.skipif(not JIT, reason="the check runs when numba compiles a kernel")
def test_an_inlined_kernel_borrows_what_its_caller_made_for_the_call() -> None:
    # ``inline=True`` inlines in LLVM, after the call is compiled as a call: the caller holds
    # its argument until the call returns, so the callee's borrow outlives nothing it reads.
    import numba

    @kernel(inline=True)
    def total(values: np.ndarray) -> float:
        values = borrow(values)
        out = 0.0
        for k in range(values.shape[0]):
            out += values[k]
        return out

    @numba.njit
    def made_here(n: int, rounds: int) -> float:
        out = 0.0
        for r in range(rounds):
            out += total(np.full(n, float(r)))  # a new array each round, freed after the call
        return out

    assert made_here(5, 200) == 5 * sum(range(200))
