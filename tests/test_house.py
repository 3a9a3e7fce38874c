"""The house's rules (docs/architecture.md), checked as the next person would: lint and format
(ruff), the layers and no circle of imports (import-linter), the types (mypy), and no source file
too long to hold without a reason stated at its top. Each runs the tool on the whole repository
with the configuration in pyproject.toml, as ``.ci/run`` does through this suite."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The packages, as pyproject.toml installs them.
PACKAGES = (
    "minimize_surprise",
    "drivers",
    "simulator",
    "robot_agent",
    "master_service",
    "telemetry",
    "transport",
    "studies",
    "gridworld",
)
#: A source file longer than this says at its top why it is one file.
LONGEST = 600
#: The words that start that reason, in the module's docstring.
REASON = "Why one file"


def _tool(*argv: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """Run a tool of this Python's environment in the repository; its output for the message."""
    return subprocess.run(
        [sys.executable, *argv], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


def _explain(result: subprocess.CompletedProcess[str]) -> str:
    return (result.stdout + result.stderr)[-6000:]


def test_ruff_finds_nothing() -> None:
    result = _tool("-m", "ruff", "check", "--no-cache", ".")
    assert result.returncode == 0, _explain(result)


def test_every_file_is_formatted() -> None:
    result = _tool("-m", "ruff", "format", "--check", "--no-cache", ".")
    assert result.returncode == 0, _explain(result)


def test_imports_keep_the_layers_and_make_no_circle() -> None:
    script = "import sys; from importlinter.cli import lint_imports_command; lint_imports_command()"
    result = _tool("-c", script, "--no-cache")
    assert result.returncode == 0, _explain(result)
    assert "0 broken" in result.stdout, _explain(result)


@pytest.mark.slow
def test_the_packages_type_check() -> None:
    result = _tool("-m", "mypy", timeout=900)
    assert result.returncode == 0, _explain(result)
    assert "Success: no issues found" in result.stdout, _explain(result)


def test_no_file_too_long_without_a_reason() -> None:
    unexplained = []
    for package in (*PACKAGES, "docs/tools"):
        for path in sorted((REPO / package).rglob("*.py")):
            lines = path.read_text(encoding="utf-8").splitlines()
            if len(lines) > LONGEST and not any(REASON in line for line in lines[:40]):
                unexplained.append(f"{path.relative_to(REPO)} ({len(lines)} lines)")
    assert not unexplained, f"over {LONGEST} lines with no '{REASON} ...' at the top: " + ", ".join(
        unexplained
    )


def test_the_docs_index_lists_every_page() -> None:
    index = (REPO / "docs" / "README.md").read_text(encoding="utf-8")
    pages = sorted(p.name for p in (REPO / "docs").glob("*.md") if p.name != "README.md")
    missing = [page for page in pages if f"]({page})" not in index]
    assert not missing, f"docs/README.md does not list {', '.join(missing)}"
