"""Compiled kernels are cached where an update cannot leave a stale callee behind
(minimize_surprise.jit).

numba checks a cached kernel against its own source file only; a kernel that calls another,
whose file changed, would keep the old callee's code. Our cache directory is named by a
fingerprint of every module that uses kernels, so any change to one of them starts afresh.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

from minimize_surprise.jit import kernel_fingerprint

MODULE = "from minimize_surprise.jit import kernel\n\n\n@kernel\ndef f(x):\n    return x + {}\n"


def package(root: Path) -> Path:
    (root / "sim_stub").mkdir(parents=True)
    (root / "sim_stub" / "k.py").write_text(MODULE.format(1))
    (root / "sim_stub" / "plain.py").write_text("X = 1\n")
    return root


def test_the_fingerprint_changes_with_a_kernel_module_and_only_then(tmp_path):
    root = package(tmp_path)
    first = kernel_fingerprint(root)
    assert kernel_fingerprint(root) == first
    (root / "sim_stub" / "plain.py").write_text("X = 2\n")  # no kernel in it
    assert kernel_fingerprint(root) == first
    (root / "sim_stub" / "k.py").write_text(MODULE.format(2))
    changed = kernel_fingerprint(root)
    assert changed != first
    (root / "sim_stub" / "k2.py").write_text(MODULE.format(3))  # a new kernel module
    assert kernel_fingerprint(root) not in (first, changed)


def test_a_process_caches_kernels_under_its_fingerprint_in_the_user_cache(tmp_path):
    # A fresh interpreter with its own cache home: numba's cache directory is ours, named by
    # the installation's fingerprint, and a compiled kernel leaves its files there.
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path)}
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("SURPRISE_NO_JIT", None)
    script = textwrap.dedent(
        """
        from pathlib import Path
        import numba
        import minimize_surprise.jit as jit
        from minimize_surprise.fitness import step_score
        import numpy as np
        step_score(np.zeros(2), np.ones(2))
        root = Path(jit.__file__).resolve().parent.parent
        print(numba.config.CACHE_DIR)
        print(jit.kernel_fingerprint(root))
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
    )
    cache_dir, fingerprint = done.stdout.split()
    assert Path(cache_dir) == tmp_path / "minimize-surprise" / "numba" / fingerprint
    assert any(Path(cache_dir).rglob("*.nbi"))
