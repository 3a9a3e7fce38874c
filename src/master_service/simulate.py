"""``surprise-master sim``: the whole system on one machine, on a simulated swarm.

The master and N real agents (:class:`robot_agent.agent.Agent`, the code that runs on a robot's Pi)
run in one event loop and talk over loopback TCP exactly as in a lab; the agents drive simulated
Thymios (:mod:`sim_stub`) that share one world. In lockstep (the default) the world advances one
step once every robot has sent its command, so a run goes as fast as the CPU allows and repeats
exactly for a seed; ``realtime`` paces the world at 10 Hz of wall-clock time instead.

Before the post-evaluation the arena is reset (new random start poses, or the centre, and freshly
scattered boxes), as the paper does; the boxes' positions before and after it are kept in
``simulation.json`` so that the report can measure the box displacement d_B.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from master_service.config import MasterConfig
from master_service.master import Master, Progress, RunSummary
from master_service.report import SIMULATION_FILE
from master_service.rundir import write_atomic
from robot_agent.agent import Agent
from robot_agent.config import AgentConfig, LoopConfig
from robot_agent.config import MasterConfig as AgentMasterConfig
from sim_stub.body import SimSwarm
from sim_stub.scenarios import SCENARIOS, WorldConfig, scenario_config
from sim_stub.settings import SETTINGS, safety_config, world_overrides
from sim_stub.world import World
from surprise.backoff import BackoffConfig
from surprise.config import ExperimentConfig, decode_experiment, read_yaml
from surprise.errors import ConfigError
from surprise.safety import SafetyConfig

__all__ = [
    "SCENARIOS",
    "SIMULATION_FILE",
    "SimulatedRun",
    "SimulatedSwarm",
    "quiet_agents",
    "robot_ids",
    "simulated_loop",
    "simulated_safety",
    "simulation_experiment",
    "summary_text",
    "world_config",
]

#: In-process agents reconnect at once: the master is on the same machine and never far away.
_RECONNECT = BackoffConfig(initial=0.05, max=0.5, jitter=0.5)


def robot_ids(count: int) -> list[str]:
    """The simulated robots' ids: ``sim-0`` .. ``sim-<count-1>``."""
    return [f"sim-{i}" for i in range(count)]


def simulation_experiment(
    scenario: str | None = None,
    *,
    setting: str | None = None,
    arena: float | None = None,
    config_file: str | Path | None = None,
    robots: int | None = None,
    evaluations: int | None = None,
    seed: int | None = None,
    data: dict[str, Any] | None = None,
) -> ExperimentConfig:
    """The experiment of a simulated run.

    Layers, each overriding the one before: the setting's defaults (``paper`` unless the file or
    ``setting`` names another; see ``sim_stub.settings``), the scenario's robots and sensors, the
    experiment file ``config_file`` (or the experiment ``data`` given), then the arguments given
    (``arena``: the carpet's side in metres). A bad file or value raises :class:`ConfigError`
    naming the file and key.
    """
    if data is None:
        data = {} if config_file is None else read_yaml(config_file)
    data = dict(data)
    if scenario is not None:
        data["scenario"] = scenario
    if setting is not None:
        data["setting"] = setting
    data.setdefault("setting", "paper")
    if arena is not None:
        if not arena > 0:
            raise ConfigError(f"expected a positive side in metres, got {arena}", key="--arena")
        data["simulation"] = {**(data.get("simulation") or {}), "arena_side": arena}
    name = data.get("scenario", "basic")
    world = _world(data.get("setting"), name, data.get("simulation"), config_file)
    data.setdefault("robots", world.robots)
    data.setdefault("sensors", list(world.sensors))
    for key, value in (("robots", robots), ("seed", seed)):
        if value is not None:
            data[key] = value
    if evaluations is not None:
        data["evolution"] = {**(data.get("evolution") or {}), "evaluations": evaluations}
    experiment = decode_experiment(data, file=config_file)
    missing = [s for s in experiment.sensors if s not in world.sensors]
    if missing:
        raise ConfigError(
            f"the {name} scenario's robots do not carry {', '.join(missing)} "
            f"(they carry {', '.join(world.sensors)})",
            file=str(config_file) if config_file else None,
            key="sensors",
        )
    simulated_safety(experiment, file=config_file)  # a bad safety key fails now, by name
    world_config(experiment, file=config_file)
    return experiment


def _world(setting: Any, scenario: str, overrides: Any, file: str | Path | None) -> WorldConfig:
    if setting not in SETTINGS:
        raise ConfigError(
            f"unknown setting {setting!r}; expected one of: {', '.join(SETTINGS)}",
            file=str(file) if file else None,
            key="setting",
        )
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(
            "expected a mapping of world parameters",
            file=str(file) if file else None,
            key="simulation",
        )
    if scenario not in SCENARIOS:
        return scenario_config(scenario, file=file)  # raises, naming the scenario
    return scenario_config(
        scenario, {**world_overrides(setting, scenario), **(overrides or {})}, file=file
    )


def world_config(experiment: ExperimentConfig, *, file: str | Path | None = None) -> WorldConfig:
    """The world an experiment runs in: its scenario in its setting with its ``simulation``
    overrides, stepping at the experiment's step period (one world step per control step)."""
    given = experiment.simulation.get("dt")
    if given is not None and given != experiment.step_period:
        raise ConfigError(
            f"the world steps once per control step: simulation.dt ({given}) must equal "
            f"step_period ({experiment.step_period}), or be left out",
            file=str(file) if file else None,
            key="simulation.dt",
        )
    overrides = {
        **experiment.simulation,
        "robots": experiment.robots,
        "dt": experiment.step_period,
    }
    return _world(experiment.setting, experiment.scenario, overrides, file)


def simulated_safety(
    experiment: ExperimentConfig, *, file: str | Path | None = None
) -> SafetyConfig:
    """The simulated robots' safety layer: the setting's for the scenario, with the experiment's
    ``safety`` overrides."""
    return safety_config(experiment.setting, experiment.scenario, experiment.safety, file=file)


@dataclass(frozen=True)
class SimulatedRun:
    """What a simulated run leaves: the master's summary and the report's metrics."""

    summary: RunSummary
    metrics: dict[str, Any]


class SimulatedSwarm:
    """A master and ``experiment.robots`` agents on simulated Thymios in one shared world.

    ``await run(run_dir)`` evolves, post-evaluates and writes the report; ``on_progress`` sees the
    master's progress.
    """

    def __init__(
        self,
        experiment: ExperimentConfig,
        *,
        realtime: bool = False,
        on_progress: Callable[[Progress], None] | None = None,
    ) -> None:
        self.experiment = experiment
        self.realtime = realtime
        self.on_progress = on_progress
        self.world = World(world_config(experiment), seed=experiment.seed)
        self.ids = robot_ids(experiment.robots)
        # Nobody outside this process talks to this master: a fresh random secret per run.
        self._secret = secrets.token_bytes(32)
        self._boxes_before: list[list[float]] | None = None

    def master_config(self) -> MasterConfig:
        """The master's configuration: loopback, any free port, only the simulated robots."""
        return MasterConfig(
            experiment=self.experiment,
            host="127.0.0.1",
            port=0,
            allowed_robots=self.ids,
        )

    def agent_config(self, robot_id: str, port: int) -> AgentConfig:
        """One in-process agent's configuration (the secret is handed over directly).

        A simulated body's sensors have no update rate: the agents run whatever period the
        experiment gives (``loop.min_period`` is the experiment's own).
        """
        return AgentConfig(
            robot_id=robot_id,
            master=AgentMasterConfig(host="127.0.0.1", port=port, secret_file="(in-process)"),
            safety=simulated_safety(self.experiment),
            loop=simulated_loop(self.experiment),
            reconnect=_RECONNECT,
        )

    async def _reset_arena(self) -> None:
        # Every robot is idle between two rounds, so nobody is inside a step of the world.
        self.world.reset(seed=self.experiment.seed + 1)
        self._boxes_before = self.world.box_positions.tolist()

    async def run(self, run_dir: str | Path) -> SimulatedRun:
        """Run the experiment into ``run_dir`` (created; must not hold another run)."""
        from master_service.report import write_report  # matplotlib: only when reporting

        run_dir = Path(run_dir)
        swarm = SimSwarm(self.world, realtime=self.realtime, attach_all=True)
        master = Master(
            self.master_config(),
            run_dir,
            secret=self._secret,
            on_progress=self.on_progress,
            before_post_evaluation=self._reset_arena,
        )
        async with contextlib.AsyncExitStack() as stack:
            await stack.enter_async_context(master)
            if self.realtime:
                await stack.enter_async_context(swarm)
            agents = []
            for index, robot_id in enumerate(self.ids):
                body = await stack.enter_async_context(swarm.body(index))
                agent = Agent(
                    self.agent_config(robot_id, master.port),
                    body,
                    body.clock,
                    self._secret,
                    rng=random.Random(self.experiment.seed * 1000 + index),
                )
                agents.append(await stack.enter_async_context(agent))
            tasks = [asyncio.create_task(a.run(), name=f"agent-{i}") for i, a in enumerate(agents)]
            try:
                summary = await master.run()
            finally:
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
        self._write_simulation_file(run_dir)
        metrics = await asyncio.to_thread(write_report, run_dir)
        return SimulatedRun(summary, metrics)

    def _write_simulation_file(self, run_dir: Path) -> None:
        data: dict[str, Any] = {
            "scenario": self.experiment.scenario,
            "world": {
                "arena_side": self.world.config.arena_side,
                "robots": self.world.config.robots,
                "boxes": len(self.world.box_positions),
            },
        }
        if self._boxes_before is not None and len(self.world.box_positions):
            data["post_evaluation_boxes"] = {
                "start": self._boxes_before,
                "end": self.world.box_positions.tolist(),
            }
        write_atomic(run_dir / SIMULATION_FILE, json.dumps(data).encode("utf-8"))


def simulated_loop(experiment: ExperimentConfig) -> LoopConfig:
    """The control loop's limits for a simulated body: the experiment's period is the shortest
    (a simulated sensor has no update rate) and its longest evaluation fits."""
    longest = max(experiment.evaluation_steps, experiment.post_evaluation_steps)
    return LoopConfig(
        min_period=min(experiment.step_period, LoopConfig().min_period),
        max_steps=max(longest, LoopConfig().max_steps),
    )


def summary_text(metrics: dict[str, Any], out: Path, seconds: float) -> str:
    """What ``surprise-master sim`` prints at the end: where, how good, which behaviour."""
    best = metrics.get("best_fitness")
    lines = [
        f"run directory: {out}",
        f"evaluations: {metrics['evaluations']} in {seconds:.1f} s",
        f"best fitness: {'-' if best is None else f'{best:.4f}'}",
    ]
    post = metrics.get("post_evaluation") or {}
    if post.get("swarm_fitness") is not None:
        lines.append(
            f"post-evaluation fitness: {post['swarm_fitness']:.4f} ({post['steps']} steps)"
        )
    b = post.get("behaviour")
    if b:
        kind = f"{b['motion']}, {b['grouping']}"
        figures = (
            f"rotation c_o {b['rotation']:.1f} rad, mean cluster size "
            f"{b['mean_cluster_size']:.2f}, distance d_R {b['distance_covered']:.2f} m"
        )
        if b.get("box_displacement") is not None:
            kind += ", pushing" if b["pushing"] else ", not pushing"
            figures += f", box displacement d_B {b['box_displacement']:.3f} m"
        lines.append(f"behaviour: {kind} ({figures})")
    lines.append(f"plots: {out / 'plots'}")
    return "\n".join(lines)


def quiet_agents() -> None:
    """In-process agents log their connections at INFO: keep them out of the progress display."""
    logging.getLogger("robot_agent").setLevel(logging.WARNING)
