"""The first run compiles the engine's kernels side by side (`precompile.compile_ahead`), then the
engine's loop around them, which must find every kernel it calls already compiled: the plan
(`engine.compile_plan`) copies the loop's calls, and a call that drifted from it would be
compiled again, one after the other, as before (docs/simulation.md, "The first run"). Checked in
a fresh interpreter with an empty kernel cache, where numba reports every compile."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from needs import require_module

SCRIPT = textwrap.dedent(
    """
    import json, multiprocessing, sys
    import numpy as np
    from numba.core import event
    from master_service.experiments.simulation_setup import (
        simulated_safety, simulation_experiment, world_config,
    )
    from minimize_surprise import precompile
    from minimize_surprise.network import spec_from_config
    from simulator import metrics
    from simulator.engine import Swarm, compile_plan, evaluate_swarms

    place, setting, batch = sys.argv[1], sys.argv[2], int(sys.argv[3])
    experiment = simulation_experiment(place, setting=setting, seed=1)
    spec = spec_from_config(experiment)
    swarms = [
        Swarm(world_config(experiment), simulated_safety(experiment), spec, seed)
        for seed in range(1, batch + 1)
    ]
    plan = compile_plan(swarms[0], batch=batch)
    processes = precompile.compile_ahead(
        plan.kernels, then=plan.lists + metrics.compile_plan(), last=plan.loop, processes=2
    )
    for helper in multiprocessing.active_children():
        helper.join()  # the lists and measures too, so that what follows compiles nothing
    compiled = []

    class Listener(event.Listener):
        def on_start(self, ev):
            function = ev.data["dispatcher"].py_func
            if function.__module__.split(".")[0] in ("simulator", "minimize_surprise"):
                compiled.append(f"{function.__module__}.{function.__qualname__}")

        def on_end(self, ev):
            pass

    event.register("numba:compile", Listener())
    genome = np.random.default_rng(1).normal(size=swarms[0].layout.size)
    evaluate_swarms(swarms, [genome] * batch, 20)
    traced = evaluate_swarms(swarms, [genome] * batch, 20, record=True)
    metrics.cluster_counts(traced[0].poses)
    again = precompile.compile_ahead(
        plan.kernels, then=plan.lists + metrics.compile_plan(), last=plan.loop, processes=2
    )
    print(json.dumps({
        "processes": processes,
        "compiled": compiled,
        "again": again,
    }))
    """
)


def run(tmp_path, place: str, setting: str, batch: int) -> dict[str, object]:
    require_module("numba", "master")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("SURPRISE_NO_JIT", None)
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT, place, setting, str(batch)],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@pytest.mark.parametrize(
    ("place", "setting", "batch"),
    [("basic", "paper", 1), ("boxes", "lab", 2)],
    ids=["the quick start", "boxes in a batch of two"],
)
def test_after_compiling_ahead_the_engine_compiles_nothing(tmp_path, place, setting, batch):
    result = run(tmp_path, place, setting, batch)
    assert result["processes"] == 2
    # Not even the loop: the evolution's and the recorded post-evaluation's calls are the
    # plan's, and the lists were compiled by the helpers.
    assert result["compiled"] == []
    assert result["again"] == 0  # all on disk: nothing left to compile ahead
