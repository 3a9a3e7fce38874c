"""``precompile.compile_ahead``: the plan's kernels and the last ones are on disk when it
returns, the later ones once its helpers end, and a second call finds nothing to do. In a fresh
interpreter with an empty cache, on kernels of a module written for the test (numba caches only
kernels defined in files)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

from needs import require_module

KERNELS = textwrap.dedent(
    """
    from minimize_surprise.jit import kernel

    @kernel
    def one(x: float) -> float:
        return x + 1.0

    @kernel
    def two(x: float) -> float:
        return one(x) * 2.0

    @kernel
    def three(x: int) -> int:
        return x * 3

    @kernel
    def four(x: float) -> float:
        return x - 4.0

    @kernel
    def five(x: int) -> int:
        return x - 5

    @kernel
    def both(x: float) -> float:
        return two(x) + one(x)
    """
)

SCRIPT = textwrap.dedent(
    """
    import json, multiprocessing
    from minimize_surprise import jit, precompile
    import tiny

    def plan(*names):
        value = {"three": 1, "five": 1}
        return [
            (getattr(tiny, n), precompile.signature(getattr(tiny, n), value.get(n, 1.0)))
            for n in names
        ]

    names = ("one", "two", "three", "four", "five", "both")
    processes = precompile.compile_ahead(
        plan("one", "two"), then=plan("three", "four", "five"), last=plan("both"), processes=3
    )
    on_return = {n: jit.compiled_on_disk(getattr(tiny, n)) for n in ("one", "two", "both")}
    for helper in multiprocessing.active_children():
        helper.join()
    at_end = {n: jit.compiled_on_disk(getattr(tiny, n)) for n in names}
    again = precompile.compile_ahead(plan(*names), processes=3)
    print(json.dumps({"processes": processes, "on_return": on_return, "at_end": at_end,
                      "again": again, "value": tiny.both(1.0)}))
    """
)


def test_compiling_ahead_leaves_every_kernel_on_disk(tmp_path):
    require_module("numba", "master")
    (tmp_path / "tiny.py").write_text(KERNELS)
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), *sys.path])
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("SURPRISE_NO_JIT", None)
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["processes"] == 3
    assert result["on_return"] == {"one": True, "two": True, "both": True}
    assert all(result["at_end"].values()), result["at_end"]
    assert result["again"] == 0
    assert result["value"] == 6.0
