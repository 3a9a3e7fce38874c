"""Pictures of the scenarios (simulator.render); needs the optional matplotlib."""

from __future__ import annotations

import sys

import pytest

from needs import require_module
from simulator.scenarios import SCENARIOS, scenario_config
from simulator.world import World

require_module("matplotlib")

from simulator import render  # noqa: E402  (needs matplotlib, checked above)


def is_png(path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_each_scenario_renders_to_a_png(tmp_path, scenario):
    out = tmp_path / f"{scenario}.png"
    render.main([scenario, str(out), "--steps", "30", "--seed", "2"])
    assert is_png(out)
    assert out.stat().st_size > 10_000


def test_render_world_draws_trajectories_without_pyplot(tmp_path):
    world = World(scenario_config("boxes", {"robots": 2}), seed=0, record=True)
    world.set_commands([[1.0, 0.5], [0.5, 1.0]])
    for _ in range(10):
        world.step()
    fig = render.render_world(
        world, tmp_path / "w.png", trajectories=world.recorded_poses(), title="t"
    )
    ax = fig.axes[0]
    assert ax.get_title() == "t"
    assert len(ax.lines) >= 2  # one trajectory per robot (plus the blades)
    assert is_png(tmp_path / "w.png")
    # Drawing went through the Agg canvas, not pyplot's global figure manager.
    pyplot = sys.modules.get("matplotlib.pyplot")
    assert pyplot is None or not pyplot.get_fignums()


def test_importing_the_simulator_does_not_import_matplotlib():
    import subprocess

    code = "import simulator.world, simulator.body, simulator.metrics, simulator.render, sys; "
    code += "print('matplotlib' in sys.modules)"
    command = [sys.executable, "-c", code]
    result = subprocess.run(command, capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"
