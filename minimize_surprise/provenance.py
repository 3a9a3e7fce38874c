"""Which source this installation was built from: the package's version and the source's commit.

The commit comes from one of two places (docs/fleet.md):

1. ``minimize_surprise/_build.py``, written when a wheel or an sdist is built (the build hook in
   ``setup.py``), holding ``COMMIT``: what an installed robot or laptop reports. The hook takes the
   commit from ``MINIMIZE_SURPRISE_COMMIT`` (``deploy/install-pi.sh`` sets it: it builds from a
   copy without ``.git``), else from git in the source tree, else from a ``_build.py`` already
   there (a wheel built from an sdist).
2. Without that file (an editable install, a checkout on ``PYTHONPATH``): git, asked once per
   process in the checkout this package sits in, with a short timeout. No git, no checkout, or a
   git that fails: the commit is unknown (None), never an error.

A commit is 40 hexadecimal digits, followed by ``-dirty`` when the checkout had uncommitted
changes to tracked files (two dirty checkouts of one commit may still differ).
"""

from __future__ import annotations

import functools
import importlib
import re
from pathlib import Path
from typing import Final

__all__ = ["COMMIT_PATTERN", "DIRTY", "GIT_TIMEOUT", "commit_from_git", "software_commit"]

#: What a commit looks like: a SHA-1 or SHA-256 object name, maybe marked dirty.
COMMIT_PATTERN: Final = r"^[0-9a-f]{40}([0-9a-f]{24})?(-dirty)?$"
#: The mark of a checkout with uncommitted changes.
DIRTY: Final = "-dirty"
#: Seconds one git command may take: a lab laptop answers in milliseconds; a hung network file
#: system must not hold an agent's start.
GIT_TIMEOUT: Final = 2.0

_COMMIT_RE: Final = re.compile(COMMIT_PATTERN)
_BUILD_MODULE: Final = "minimize_surprise._build"


@functools.cache
def software_commit() -> str | None:
    """The commit this code was built from (see the module docstring), None when unknown."""
    try:
        # Imported by name: the module exists only in a built package, not in the checkout.
        build = importlib.import_module(_BUILD_MODULE)
    except ImportError:
        return commit_from_git(Path(__file__).resolve().parent.parent)
    commit = getattr(build, "COMMIT", None)
    return commit if isinstance(commit, str) and _COMMIT_RE.match(commit) else None


def commit_from_git(source: Path) -> str | None:
    """The commit checked out in ``source`` (``-dirty`` with uncommitted changes to tracked
    files), None when ``source`` is no git checkout or git is missing, fails or hangs."""
    if not (source / ".git").exists():
        # Cheap: no process started for an installed package, whose parent is site-packages.
        return None
    # Imported here: importing the core loads no process machinery (tests/core/test_free_of_io).
    import subprocess

    # safe.directory: a checkout of another user (the pi user's, built as root by install-pi.sh)
    # is otherwise refused by git as of 2.35.2.
    git = ["git", "-c", f"safe.directory={source}", "-C", str(source)]
    try:
        head = subprocess.run(
            [*git, "rev-parse", "--verify", "HEAD"],
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT,
            check=False,
        )
        if head.returncode != 0:
            return None
        commit = head.stdout.strip()
        if not _COMMIT_RE.match(commit):
            return None
        # Exit status 1: tracked files differ from HEAD. Untracked files (runs/, notes) do not
        # change what runs.
        diff = subprocess.run(
            [*git, "diff", "--quiet", "HEAD", "--"],
            capture_output=True,
            timeout=GIT_TIMEOUT,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return commit + DIRTY if diff.returncode == 1 else commit
