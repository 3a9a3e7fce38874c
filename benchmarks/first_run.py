"""The quick start's first run on a machine against a later one: ``surprise-master sim`` with an
empty kernel cache (everything compiled), then again with the cache it filled (everything
loaded), each in a child process, wall seconds. The target (issue 34): the first run within two
times a later one. docs/simulation.md, "The first run", says where the compile time goes.

``--cores N`` runs the children on N of the cores this process may use (1: as a one-core
machine, which compiles everything in one process). ``--kernels`` also prints, for one more
first run in one process, the seconds numba spent on each kernel of this project it compiled
(a kernel's time includes the kernels it compiled on the way; nested ones are indented).

Prints ``name: value unit`` lines. Run: ``python benchmarks/first_run.py [--repeats 2]
[--cores N] [--kernels]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

#: Prints every compile of a kernel of this project, nested as numba compiled it (a child's
#: script: numba's compile events are the one record of what was compiled and for how long).
_KERNELS = textwrap.dedent(
    """
    import sys, time
    from numba.core import event
    from master_service.cli import main

    open_ = []

    class Listener(event.Listener):
        def on_start(self, ev):
            function = ev.data["dispatcher"].py_func
            open_.append((f"{function.__module__}.{function.__qualname__}", time.perf_counter()))

        def on_end(self, ev):
            name, started = open_.pop()
            if name.split(".")[0] in ("simulator", "minimize_surprise"):
                took = time.perf_counter() - started
                print(f"{'  ' * len(open_)}compile {name}: {took:.2f} s", file=sys.stderr)

    event.register("numba:compile", Listener())
    sys.argv = ["surprise-master", "sim", "--evaluations", "2", "--out", sys.argv[1]]
    main()
    """
)


def _run(command: list[str], cache: Path, cores: set[int] | None) -> float:
    # Wall seconds of ``command`` with kernels cached in ``cache``, on ``cores``.
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    env.pop("SURPRISE_NO_JIT", None)

    def pin() -> None:
        if cores is not None:
            os.sched_setaffinity(0, cores)

    started = time.perf_counter()
    subprocess.run(
        command, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        preexec_fn=pin,
    )  # fmt: skip
    return time.perf_counter() - started


def main() -> None:
    """Time first and later runs; print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=1, help="first/later pairs (median)")
    parser.add_argument("--cores", type=int, default=None, help="run the children on N cores")
    parser.add_argument("--kernels", action="store_true", help="each kernel's compile time")
    args = parser.parse_args()
    available = sorted(os.sched_getaffinity(0))
    if args.cores is not None and not 1 <= args.cores <= len(available):
        parser.error(f"--cores: 1 to {len(available)} here")
    cores = set(available[: args.cores]) if args.cores is not None else None
    sim = [sys.executable, "-m", "master_service", "sim"]
    firsts, laters = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            cache = Path(tmp) / f"cache-{k}"
            firsts.append(_run([*sim, "--out", f"{tmp}/first-{k}"], cache, cores))
            laters.append(_run([*sim, "--out", f"{tmp}/later-{k}"], cache, cores))
        first, later = statistics.median(firsts), statistics.median(laters)
        print(f"cores: {len(cores) if cores is not None else len(available)}")
        print(f"first_run_s: {first:.2f} s")
        print(f"later_run_s: {later:.2f} s")
        print(f"first_over_later: {first / later:.2f} x")
        if args.kernels:
            env = {**os.environ, "NUMBA_CACHE_DIR": f"{tmp}/cache-kernels"}
            done = subprocess.run(
                [sys.executable, "-c", _KERNELS, f"{tmp}/kernels"], env=env, check=True,
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                preexec_fn=(lambda: os.sched_setaffinity(0, {available[0]})),
            )  # fmt: skip
            for line in done.stderr.splitlines():
                if line.lstrip().startswith("compile "):
                    print(line)


if __name__ == "__main__":
    main()
