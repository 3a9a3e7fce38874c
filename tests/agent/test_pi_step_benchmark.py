"""benchmarks/pi_step.py, whose figures docs/robot-agent.md quotes for a Pi, still runs what the
agent runs and runs it as a Pi installed with the ``robot`` extra does: without numba."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BENCHMARK = REPO / "benchmarks" / "pi_step.py"


def test_the_robot_extra_brings_no_numba() -> None:
    # docs/robot-agent.md says a Pi runs the kernels interpreted: deploy/install-pi.sh installs
    # the robot extra only.
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    robot = project["optional-dependencies"]["robot"]
    assert not [d for d in robot if d.lower().startswith("numba")]
    assert "[robot]" in (REPO / "deploy" / "install-pi.sh").read_text()


@pytest.mark.parametrize("part", ["basic_loop", "object_kernels"])
def test_the_benchmark_runs_interpreted(part: str) -> None:
    script = (
        "import runpy, sys\n"
        f"sys.argv = [{str(BENCHMARK)!r}, '--only', {part!r}, '--steps', '5']\n"
        f"runpy.run_path({str(BENCHMARK)!r}, run_name='__main__')\n"
        "from minimize_surprise import jit\n"
        "print('jit', jit.JIT)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd=REPO
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().splitlines()[-1] == "jit False"
