"""A run compiles only the physics it runs: an arena without boxes no box physics, a swarm below
``grid_robots`` no grid (docs/simulation.md, "The first run"). Checked in a fresh interpreter with
an empty kernel cache, where numba lists every specialisation it compiled."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

from needs import require_module

SCRIPT = textwrap.dedent(
    """
    import json, sys
    from simulator.scenarios import scenario_config
    from simulator.world import World
    from simulator.physics import boxes, contacts, motion, sensing

    world = World(scenario_config(sys.argv[1], json.loads(sys.argv[2])), seed=1)
    world.sensor_matrix()
    world.step()
    kernels = {
        "push_boxes": boxes._push_boxes,
        "step_with_boxes": motion._step_with_boxes,
        "sense": sensing._sense,
        "separate": contacts._separate,
    }
    print(json.dumps({name: len(k.signatures) for name, k in kernels.items()}))
    """
)


def compiled(tmp_path, scenario: str, **overrides: object) -> dict[str, int]:
    require_module("numba", "master")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / f"cache-{scenario}-{len(overrides)}")}
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("SURPRISE_NO_JIT", None)
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, scenario, json.dumps(overrides)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(done.stdout)


def test_a_small_swarm_without_boxes_compiles_neither_boxes_nor_grid(tmp_path):
    assert compiled(tmp_path, "basic", robots=10) == {
        "push_boxes": 0,
        "step_with_boxes": 0,
        "sense": 1,
        "separate": 1,
    }


def test_boxes_and_a_large_swarm_compile_what_they_run(tmp_path):
    boxes = compiled(tmp_path, "boxes")
    assert boxes["push_boxes"] == 1 and boxes["step_with_boxes"] == 1
    large = compiled(tmp_path, "basic", robots=60, arena_side=2.5)
    assert large["push_boxes"] == 0
    # From grid_robots on: the grid, and all pairs where the grid would be a single cell.
    assert large["sense"] == 2 and large["separate"] == 2
