"""What one hostile 8 MiB Result frame costs the master: memory and time to decode it.

The frame is a Result whose trace is as many empty rows as 8 MiB can hold (one byte each in
msgpack). A decoder that builds the rows before checking them holds one Python list per byte; one
that checks shape and size as it decodes refuses the frame before building anything.

Each figure comes from a fresh child process that feeds the frame to the master's decoder
(``transport.framing.FrameDecoder``, the path every received frame takes after its length
header): the growth of its peak resident memory, the peak of Python allocations (tracemalloc, in a
second child, since tracing slows decoding down) and the wall-clock time until the decoder answered
(with messages or an error). Works on any version of the code that has ``FrameDecoder`` (in
``transport.framing``, or in ``minimize_surprise.wire`` before framing moved) and
``MAX_FRAME_SIZE``, so the same script measures before and after a change.

Prints one figure a line as ``name: value unit``. Run: ``python benchmarks/hostile_trace.py``
"""

from __future__ import annotations

import multiprocessing
import resource
import struct
import time
import tracemalloc
from typing import Any

import msgspec


def hostile_payload(limit: int) -> bytes:
    """A Result whose trace's ``sensors`` is as many empty rows as fit in ``limit`` bytes."""
    head = msgspec.msgpack.encode(
        {
            "type": "result",
            "evaluation_id": 1,
            "fitness": 0.5,
            "stats": {"steps_run": 1, "overruns": 0, "interventions": {}},
        }
    )
    # Add one more map entry, "trace": {"sensors": [[], [], ...]}, by hand: a map of 5 entries.
    assert head[0] == 0x84
    prefix = bytes([0x85]) + head[1:] + msgspec.msgpack.encode("trace")
    prefix += bytes([0x81]) + msgspec.msgpack.encode("sensors")
    rows = limit - len(prefix) - 5
    return prefix + b"\xdd" + struct.pack(">I", rows) + b"\x90" * rows


def _decode(queue: Any, trace_allocations: bool) -> None:
    from minimize_surprise.wire import MAX_FRAME_SIZE

    try:
        from transport.framing import FrameDecoder
    except ImportError:  # a version from before framing moved out of the codec
        from minimize_surprise.wire import FrameDecoder  # type: ignore[attr-defined,no-redef]

    payload = hostile_payload(MAX_FRAME_SIZE)
    frame = struct.pack(">I", len(payload)) + payload
    decoder = FrameDecoder(MAX_FRAME_SIZE)
    if trace_allocations:
        tracemalloc.start()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    try:
        decoder.feed(frame)
        outcome = "accepted"
    except Exception as exc:  # the point: which error, how fast
        outcome = f"{type(exc).__name__}: {str(exc)[:120]}"
    elapsed = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    peak = tracemalloc.get_traced_memory()[1] if trace_allocations else 0
    queue.put((len(frame), outcome, elapsed, (after - before) * 1024, peak))


def _run(trace_allocations: bool) -> tuple[int, str, float, int, int]:
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    child = context.Process(target=_decode, args=(queue, trace_allocations))
    child.start()
    result = queue.get(timeout=300)
    child.join()
    return result


def main() -> None:
    """Print the figures."""
    size, outcome, elapsed, rss, _ = _run(trace_allocations=False)
    *_, peak = _run(trace_allocations=True)
    print(f"hostile_trace_frame_size: {size / 2**20:.2f} MiB")
    print(f"hostile_trace_outcome: {outcome}")
    print(f"hostile_trace_decode_time: {elapsed * 1e3:.1f} ms")
    print(f"hostile_trace_peak_rss_growth: {rss / 2**20:.1f} MiB")
    print(f"hostile_trace_peak_python_allocations: {peak / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
