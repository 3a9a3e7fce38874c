"""What a test needs from the machine: a program from a Debian package (``require_binary``)."""

from __future__ import annotations

import os
import shutil

import pytest


def require_binary(name: str) -> None:
    """Skip the test when the program ``name`` is missing, except in CI (``CI=true``), where
    ``.ci/run`` installs it: a skipped test there would hide a missing install step."""
    if shutil.which(name) is None:
        if os.environ.get("CI", "").lower() in ("true", "1"):
            pytest.fail(f"{name} is not installed, but CI must run the tests that need it")
        pytest.skip(f"{name} is not installed")
