""".ci/run runs exactly the README's test command, and .ci/fresh-root finds the quick start."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def quick_start_blocks() -> list[str]:
    """The code blocks of the README's "Quick start" section, in order."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("\n## Quick start\n", 1)[1].split("\n## ", 1)[0]
    return [block.strip() for block in re.findall(r"^```\n(.*?)^```", section, re.M | re.S)]


def test_ci_runs_the_readme_s_test_command_verbatim():
    run, test = quick_start_blocks()[:2]
    lines = [line for line in (ROOT / ".ci/run").read_text().splitlines() if line.strip()]
    assert lines[-1] == test
    assert "pip install -e '.[dev]'" in test and "pytest" in test
    assert "surprise-master sim" in run


def test_fresh_root_extracts_the_quick_start_command():
    """The awk line of .ci/fresh-root gives the README's first quick-start block."""
    script = (ROOT / ".ci/fresh-root").read_text()
    (awk,) = re.findall(r"quick=\$\(awk '([^']*)'", script)
    found = subprocess.run(
        ["awk", awk, str(ROOT / "README.md")], capture_output=True, text=True, check=True
    )
    assert found.stdout.strip() == quick_start_blocks()[0]


def test_ci_scripts_parse():
    for name in ("run", "fresh-root", "roots.sh", "pi-root", "fleet-roots"):
        subprocess.run(["bash", "-n", str(ROOT / ".ci" / name)], check=True)
