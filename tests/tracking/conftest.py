"""The tracking tests' shared fixture: a simulated post-evaluation, filmed and tracked once."""

from __future__ import annotations

import pytest
from filmed_run import Filmed, film


@pytest.fixture(scope="session")
def filmed(tmp_path_factory: pytest.TempPathFactory) -> Filmed:
    """The run, its video and the tracker's result (see filmed_run.py)."""
    return film(tmp_path_factory.mktemp("tracking"))
