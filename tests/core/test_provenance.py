"""Which commit an installation reports: a built package's stamp, else git in its checkout, else
unknown, never an error (docs/fleet.md)."""

from __future__ import annotations

import subprocess
import sys
import types

import pytest

from minimize_surprise import provenance
from minimize_surprise.provenance import COMMIT_PATTERN, commit_from_git, software_commit


def _repo(root):
    git = ["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    (root / "tracked").write_text("a")
    subprocess.run([*git, "add", "tracked"], check=True)
    subprocess.run([*git, "commit", "-qm", "one"], check=True)
    out = subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True)
    return out.stdout.strip()


def test_a_checkout_s_commit_marked_dirty_by_tracked_changes_only(tmp_path):
    head = _repo(tmp_path)
    assert commit_from_git(tmp_path) == head
    (tmp_path / "untracked").write_text("a run's files")
    assert commit_from_git(tmp_path) == head
    (tmp_path / "tracked").write_text("b")
    assert commit_from_git(tmp_path) == f"{head}-dirty"


def test_no_checkout_or_no_git_is_an_unknown_commit(tmp_path, monkeypatch):
    assert commit_from_git(tmp_path) is None  # no .git: no process started
    _repo(tmp_path)
    monkeypatch.setenv("PATH", str(tmp_path / "nowhere"))
    assert commit_from_git(tmp_path) is None


def test_a_built_package_reports_its_stamp(monkeypatch):
    stamped = "0123456789abcdef0123456789abcdef01234567"
    software_commit.cache_clear()
    try:
        monkeypatch.setitem(
            sys.modules, "minimize_surprise._build", types.SimpleNamespace(COMMIT=stamped)
        )
        assert software_commit() == stamped
        software_commit.cache_clear()
        monkeypatch.setitem(
            sys.modules, "minimize_surprise._build", types.SimpleNamespace(COMMIT="junk")
        )
        assert software_commit() is None
    finally:
        software_commit.cache_clear()


@pytest.mark.parametrize("good", [True, False])
def test_the_commit_pattern(good):
    import re

    text = "a" * 40 + "-dirty" if good else "A" * 40
    assert bool(re.match(COMMIT_PATTERN, text)) is good
    assert provenance.DIRTY == "-dirty"
