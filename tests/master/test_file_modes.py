"""Files are as readable as ``open()`` makes them: a run directory is readable by the lab's group
like its evaluations.csv, and only a secret is private."""

from __future__ import annotations

import os
import stat
from collections.abc import Callable, Iterator
from pathlib import Path

import msgspec
import pytest

from master_service.cli import main
from master_service.config import load_secret
from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulation_setup import simulation_experiment
from minimize_surprise.files import PRIVATE_MODE, write_atomic
from standins.serve import SECRET_FILE, _secret_file


@pytest.fixture
def umask() -> Iterator[Callable[[int], int]]:
    """``os.umask`` for the test; the process's own umask comes back after it."""
    old = os.umask(0o022)
    yield os.umask
    os.umask(old)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_a_run_directory_is_readable_by_group_and_others(tmp_path, umask):
    umask(0o022)
    experiment = simulation_experiment("boxes", robots=2, evaluations=3, seed=1)
    experiment = msgspec.structs.replace(experiment, evaluation_steps=20, post_evaluation_steps=30)
    run = tmp_path / "run"
    FastRun(experiment).run(run, plots=False)
    files = {p.relative_to(run).as_posix(): mode(p) for p in run.rglob("*") if p.is_file()}
    # Every kind of file a simulated run writes, atomically or not, is there...
    assert {
        "config.yaml",
        "checkpoint.json",
        "evaluations.csv",
        "best_genome.json",
        "post_evaluation.json",
        "traces/sim-0.npz",
        "simulation.json",
        "box_track.npz",
        "metrics.json",
    } <= set(files)
    # ... and each has the mode a plain open() gives under umask 022, as evaluations.csv does.
    assert files == dict.fromkeys(files, 0o644)
    # No temporary file is left behind.
    assert not [name for name in files if name.endswith(".tmp")]


def test_atomic_writes_follow_the_umask_or_the_mode_asked_for(tmp_path, umask):
    umask(0o077)
    write_atomic(tmp_path / "plain", b"data")
    assert mode(tmp_path / "plain") == 0o600  # as open() under umask 077
    umask(0o002)
    write_atomic(tmp_path / "plain", b"new data", durable=False)
    assert mode(tmp_path / "plain") == 0o664
    assert (tmp_path / "plain").read_bytes() == b"new data"
    umask(0o077)
    write_atomic(tmp_path / "program", b"x", mode=0o644)  # readable by another user's medulla
    assert mode(tmp_path / "program") == 0o644
    umask(0)
    write_atomic(tmp_path / "key", b"secret", mode=PRIVATE_MODE)
    assert mode(tmp_path / "key") == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["key", "plain", "program"]


def test_the_generated_shared_secret_is_private(tmp_path, umask):
    umask(0)  # even where every new file would be world-writable
    path = _secret_file(None, tmp_path)
    assert path == tmp_path / SECRET_FILE
    assert mode(path) == 0o600
    secret = path.read_text(encoding="utf-8")
    assert len(secret.strip()) == 64 and int(secret, 16) > 0  # 256 bits, as hex
    # An existing secret is kept, not replaced.
    assert _secret_file(None, tmp_path).read_text(encoding="utf-8") == secret


def test_surprise_master_secret_writes_a_private_secret_and_never_replaces_one(
    tmp_path, umask, capsys
):
    umask(0)
    path = tmp_path / "secret.key"
    assert main(["secret", str(path)]) == 0
    assert mode(path) == 0o600
    secret = path.read_text(encoding="utf-8")
    assert len(secret) == 65 and secret.endswith("\n") and int(secret, 16) > 0
    assert f"sudo deploy/install-pi.sh ROBOT_ID {path}" in capsys.readouterr().out
    # The master reads it as the robots' agents do.
    assert load_secret(path) == secret.strip().encode()
    assert main(["secret", str(path)]) == 1
    assert "exists: keep it" in capsys.readouterr().err
    assert path.read_text(encoding="utf-8") == secret
    other = main(["secret", str(path.with_name("second.key"))])
    assert other == 0 and path.with_name("second.key").read_text() != secret
