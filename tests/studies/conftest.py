"""Fixtures of the study tests."""

from __future__ import annotations

import pytest
from study_helpers import TINY_RUNS, table, write_study

from studies.executors import LocalPool
from studies.runner import run_study


@pytest.fixture(scope="session")
def local_table(tmp_path_factory):
    """The tiny study's runs.csv on the local pool: what every other executor, and every study
    broken and run again, must give."""
    tmp = tmp_path_factory.mktemp("local")
    pool = LocalPool(2)
    try:
        counts = run_study(write_study(tmp), tmp / "study", pool)
    finally:
        pool.close()
    assert counts.done == TINY_RUNS and counts.failed == 0
    return table(tmp / "study")
