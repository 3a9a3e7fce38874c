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
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from minimize_surprise import jit
from minimize_surprise.jit import kernel_fingerprint

MODULE = "from minimize_surprise.jit import kernel\n\n\n@kernel\ndef f(x):\n    return x + {}\n"


def package(root: Path) -> Path:
    (root / "simulator").mkdir(parents=True)
    (root / "simulator" / "k.py").write_text(MODULE.format(1))
    (root / "simulator" / "plain.py").write_text("X = 1\n")
    return root


def test_the_fingerprint_changes_with_a_kernel_module_and_only_then(tmp_path):
    root = package(tmp_path)
    first = kernel_fingerprint(root)
    assert kernel_fingerprint(root) == first
    (root / "simulator" / "plain.py").write_text("X = 2\n")  # no kernel in it
    assert kernel_fingerprint(root) == first
    (root / "simulator" / "k.py").write_text(MODULE.format(2))
    changed = kernel_fingerprint(root)
    assert changed != first
    (root / "simulator" / "k2.py").write_text(MODULE.format(3))  # a new kernel module
    assert kernel_fingerprint(root) not in (first, changed)


@pytest.mark.parametrize("home", ["usable", "unusable"])
def test_a_process_caches_kernels_under_its_fingerprint(tmp_path, home):
    # A fresh interpreter: numba's cache directory is ours, named by the installation's
    # fingerprint, in the user's cache, or (no usable cache home: a container's user whose home
    # is /) in a directory of the user's own in the temporary directory; a compiled kernel
    # leaves its files there, not next to the sources.
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    expected = tmp_path / "cache" / "minimize-surprise" / "numba"
    if home == "unusable":
        (tmp_path / "not-a-dir").write_text("")
        (tmp_path / "tmp").mkdir()
        env.update(
            XDG_CACHE_HOME=str(tmp_path / "not-a-dir"), HOME="/", TMPDIR=str(tmp_path / "tmp")
        )
        expected = tmp_path / "tmp" / f"minimize-surprise-{os.getuid()}" / "numba"
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
    assert Path(cache_dir) == expected / fingerprint
    assert any(Path(cache_dir).rglob("*.nbi"))


def fake_numba() -> SimpleNamespace:
    return SimpleNamespace(config=SimpleNamespace(CACHE_DIR=""))


def test_the_cache_in_use_is_kept_and_other_fingerprints_unused_for_a_week_go(
    tmp_path, monkeypatch
):
    root = tmp_path / "numba"
    monkeypatch.setattr(jit, "_cache_roots", lambda: [root])
    here = root / kernel_fingerprint(Path(jit.__file__).resolve().parent.parent)
    week = 8 * 24 * 3600
    for name, age in ((here.name, week), ("old", week), ("recent", 3600)):
        (root / name / "sub").mkdir(parents=True)
        os.utime(root / name, (time.time() - age,) * 2)
    numba = fake_numba()
    assert jit._use_fingerprinted_cache(numba)
    assert str(here) == numba.config.CACHE_DIR
    assert sorted(p.name for p in root.iterdir()) == sorted([here.name, "recent"])
    assert time.time() - here.stat().st_mtime < 60  # marked in use


def test_with_no_writable_place_kernels_are_not_cached(tmp_path, monkeypatch):
    # numba would fall back to caches next to the sources, where a stale callee survives.
    (tmp_path / "file").write_text("")
    monkeypatch.setattr(jit, "_cache_roots", lambda: [tmp_path / "file" / "numba"])
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    numba = fake_numba()
    assert not jit._use_fingerprinted_cache(numba)
    assert numba.config.CACHE_DIR == ""


def test_a_fresh_cache_says_a_kernel_is_not_compiled_until_it_is(tmp_path):
    # What `surprise-master sim` asks before it says "compiling the simulator ...".
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("SURPRISE_NO_JIT", None)
    script = textwrap.dedent(
        """
        import numpy as np
        import minimize_surprise.jit as jit
        from minimize_surprise.fitness import step_score
        print(jit.compiled_on_disk(step_score))
        step_score(np.zeros(2), np.ones(2))
        print(jit.compiled_on_disk(step_score), jit.cache_directory())
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
    )
    before, after, directory = done.stdout.split()
    assert (before, after) == ("False", "True")
    assert directory.startswith(str(tmp_path / "cache"))


def test_the_simulated_run_says_when_it_compiles(monkeypatch, capsys):
    from master_service.experiments.simulate import print_if_compiling

    for answer, said in ((False, True), (True, False), (None, False)):
        monkeypatch.setattr(jit, "compiled_on_disk", lambda kernel, answer=answer: answer)
        assert print_if_compiling("fast") == said
        out = capsys.readouterr().out
        assert ("compiling the simulator for this machine" in out) == said
