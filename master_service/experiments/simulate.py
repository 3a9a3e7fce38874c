"""``surprise-master sim``: the whole system on one machine, on a simulated swarm.

The master and N real agents (:class:`robot_agent.agent.Agent`, the code that runs on a robot's Pi)
run in one event loop and talk over loopback TCP exactly as in a lab; the agents drive simulated
Thymios (:mod:`simulator`) that share one world. In lockstep (the default) the world advances one
step once every robot has sent its command, so a run goes as fast as the CPU allows and repeats
exactly for a seed; ``realtime`` paces the world at 10 Hz of wall-clock time instead.

Before the post-evaluation the arena is reset (new random start poses, or the centre, and freshly
scattered boxes), as the paper does; the boxes' positions before and after it are kept in
``simulation.json`` so that the report can measure the box displacement d_B.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import secrets
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from master_service.arena_events import leaving
from master_service.config import DEFAULT_ROBOT_GONE_AFTER, MasterConfig
from master_service.evaluation import ArenaChange, Progress
from master_service.experiments.simulation_setup import (
    SimulatedRun,
    robot_ids,
    simulated_safety,
    simulation_experiment,
    world_config,
    write_box_track,
    write_simulation_file,
)
from master_service.master import Master
from master_service.replay import ReplaySource
from master_service.rundir import RunDir
from minimize_surprise.backoff import BackoffConfig
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import ConfigError
from minimize_surprise.events import ArenaEvent, RobotsJoin, RobotsLeave, describe
from minimize_surprise.safety import SafetyState
from robot_agent.agent import Agent
from robot_agent.config import AgentConfig, LoopConfig
from robot_agent.config import MasterConfig as AgentMasterConfig
from simulator import metrics as sim_metrics
from simulator.battery import SimBattery
from simulator.body import SimSwarm
from simulator.events import apply_to_world, check_arena_events, event_rng
from simulator.scenarios import SCENARIOS
from simulator.world import World, box_frame_steps

__all__ = [
    "SCENARIOS",
    "SimulatedRun",
    "SimulatedSwarm",
    "print_if_compiling",
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


class SimulatedSwarm:
    """A master and ``experiment.robots`` agents on simulated Thymios in one shared world.

    ``await run(run_dir)`` evolves, post-evaluates and writes the report; ``on_progress`` sees the
    master's progress. ``batteries`` (optional, robot by robot) give the robots batteries that
    drain as they drive, to rehearse a battery swap (docs/runs.md); ``pause_before_post`` waits
    for ``surprise-master continue`` before the post-evaluation. ``spares`` names robots the
    master admits besides the swarm's, to rehearse losing one for good: :meth:`stop_agent`
    stops a robot's agent and its body for good, :meth:`start_spare` starts a spare's agent on
    the body of a robot that stopped (the spare put where the dead robot stood), and
    ``robot_gone_after`` is the master's (docs/runs.md).
    """

    def __init__(
        self,
        experiment: ExperimentConfig,
        *,
        realtime: bool = False,
        on_progress: Callable[[Progress], None] | None = None,
        batteries: Sequence[SimBattery | None] = (),
        pause_before_post: bool = False,
        spares: Sequence[str] = (),
        robot_gone_after: float | None = DEFAULT_ROBOT_GONE_AFTER,
    ) -> None:
        self.experiment = experiment
        #: robots the master admits besides the swarm's (``surprise-master swap``)
        self.spares = list(spares)
        self.robot_gone_after = robot_gone_after
        self.realtime = realtime
        self.on_progress = on_progress
        #: the robots' batteries, in robot order (none: the robots report no battery)
        self.batteries = list(batteries)
        #: wait for ``surprise-master continue`` before the post-evaluation, as a lab does
        self.pause_before_post = pause_before_post
        config = world_config(experiment)
        check_arena_events(experiment.events, config)
        for index, event in enumerate(experiment.events):
            if isinstance(event, RobotsJoin):
                raise ConfigError(
                    "robots join only on the fast engine (--engine fast); with agents, a spare "
                    "joins through `surprise-master swap`",
                    key=f"events[{index}].kind",
                )
        self.world = World(config, seed=experiment.seed)
        self.ids = robot_ids(experiment.robots)
        # Nobody outside this process talks to this master: a fresh random secret per run.
        self._secret = secrets.token_bytes(32)
        self._boxes_before: list[list[float]] | None = None
        self._safety_before: list[list[int]] | None = None
        self._replay_safety: list[list[int]] | None = None
        self._agents: list[Agent] = []
        # Per body: the robot whose agent drives it now, None once its agent stopped for good.
        self._drivers: list[str | None] = list(self.ids)
        self._tasks: dict[str, asyncio.Task[None]] = {}
        self._stack: contextlib.AsyncExitStack | None = None
        #: the run's master and the swarm of simulated bodies while :meth:`run` runs (the
        #: swarm after it too: its robots' top LEDs, for a synthetic camera)
        self.master: Master | None = None
        self.swarm: SimSwarm | None = None

    def master_config(self) -> MasterConfig:
        """The master's configuration: loopback, any free port, only the simulated robots."""
        return MasterConfig(
            experiment=self.experiment,
            host="127.0.0.1",
            port=0,
            # A resumed run's spares that joined its swarm are its robots now.
            allowed_robots=list(
                dict.fromkeys([*self.ids, *self.spares, *filter(None, self._drivers)])
            ),
            robot_gone_after=self.robot_gone_after,
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
        if self.swarm is not None:
            self.swarm.clear_top_leds()  # the world's steps count anew, and so do the LEDs'
        self._boxes_before = self.world.box_positions.tolist()
        if self._replay_safety is not None:
            for agent, state in zip(self._agents, self._replay_safety, strict=True):
                agent.runner.safety_state = SafetyState.from_array(np.array(state, np.int64))
        self._safety_before = [a.runner.safety_state.to_array().tolist() for a in self._agents]
        self.world.start_recording()  # the boxes' track, for the report's animation

    async def _change_arena(self, event: ArenaEvent, index: int) -> ArenaChange:
        # Every robot is idle between two rounds. A robot that leaves stops its agent, as one
        # gone for good does: its body stays in the world, standing still.
        if isinstance(event, RobotsLeave):
            assert self.master is not None and self.master.state is not None
            left = leaving(event, self.master.state.roster or [])
            for robot in left:
                await self.stop_agent(robot)
            return ArenaChange(describe(event), left=left)
        apply_to_world(self.world, event, event_rng(self.experiment.seed, index))
        return ArenaChange(describe(event))

    def _snapshot(self) -> dict[str, Any]:
        # The master commits between rounds, while every robot is idle: a consistent state.
        # Same shape as the engine's (simulator.engine.Swarm.snapshot), and which robot drives
        # which body once that changed (a robot stopped for good, a spare on its body).
        snapshot: dict[str, Any] = {
            "world": self.world.snapshot(),
            "safety": [agent.runner.safety_state.to_array().tolist() for agent in self._agents],
        }
        if self._drivers != self.ids:
            snapshot["drivers"] = list(self._drivers)
        return snapshot

    def _restore(self, snapshot: dict[str, Any]) -> None:
        self.world.restore(snapshot["world"])
        for agent, state in zip(self._agents, snapshot["safety"], strict=True):
            agent.runner.safety_state = SafetyState.from_array(np.array(state, dtype=np.int64))

    async def stop_agent(self, robot_id: str) -> None:
        """Stop ``robot_id``'s agent for good, as a dead battery or a crashed Pi would: its
        connection closes, its body leaves the lockstep and stands still; it never comes back
        (its safety state stays in the snapshot, as the world keeps its body)."""
        index = self._drivers.index(robot_id)
        self._drivers[index] = None
        task = self._tasks.pop(robot_id)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await self._agents[index].__aexit__(None, None, None)
        if self.swarm is not None:
            self.swarm.detach(index)

    async def start_spare(self, spare_id: str, replacing: str) -> None:
        """Start spare ``spare_id``'s agent on the body ``replacing`` drove before its agent
        stopped (:meth:`stop_agent`); it connects to the master, which admits it as a spare."""
        assert self._stack is not None and self.swarm is not None and self.master is not None
        index = self.ids.index(replacing) if replacing in self.ids else None
        if index is None or self._drivers[index] is not None:
            index = self._drivers.index(None)  # any body whose agent stopped
        await self._start_agent(self._stack, spare_id, index, self.master.port)

    async def _start_agent(
        self, stack: contextlib.AsyncExitStack, robot_id: str, index: int, port: int
    ) -> None:
        assert self.swarm is not None
        body = await stack.enter_async_context(self.swarm.body(index))
        if index < len(self.batteries):
            body.battery = self.batteries[index]
        agent = Agent(
            self.agent_config(robot_id, port),
            body,
            body.clock,
            self._secret,
            rng=random.Random(self.experiment.seed * 1000 + index),
        )
        entered = await stack.enter_async_context(agent)
        if index < len(self._agents):
            entered.runner.safety_state = self._agents[index].runner.safety_state
            self._agents[index] = entered
        else:
            self._agents.append(entered)
        self._drivers[index] = robot_id
        self._tasks[robot_id] = asyncio.create_task(entered.run(), name=f"agent-{robot_id}")

    async def run(
        self, run_dir: str | Path, *, resume: bool = False, replay: ReplaySource | None = None
    ) -> SimulatedRun:
        """Run the experiment into ``run_dir`` and report; the run and its metrics.

        A new run needs ``run_dir`` new or empty. With ``resume`` it continues the run there
        from its checkpoint, the world and the robots' safety layers as they were at that
        commit, to the result it would have reached without the stop. Cancelled (Ctrl-C), the
        run stops with its checkpoint current and the robots' motors stopped. ``replay`` (a new
        run only) post-evaluates that genome instead of evolving one.
        """
        from reporting.report import write_report  # matplotlib: only when reporting

        run_dir = Path(run_dir)
        checkpoint = None
        if resume:
            directory = RunDir(run_dir)
            checkpoint = directory.read_state(directory.load_config())
        simulation = None if checkpoint is None else checkpoint.simulation
        # A resumed run's bodies are driven as at its checkpoint (a spare on a gone robot's).
        self._drivers = list((simulation or {}).get("drivers") or self.ids)
        swarm = self.swarm = SimSwarm(self.world, realtime=self.realtime, attach_all=True)
        master = self.master = Master(
            self.master_config(),
            run_dir,
            secret=self._secret,
            resume=resume,
            on_progress=self.on_progress,
            before_post_evaluation=self._reset_arena,
            snapshot=self._snapshot,
            replay=replay,
            change_arena=self._change_arena,
        )
        master.evolution.pause_before_post = self.pause_before_post
        self._agents = []
        self._tasks = {}
        self._replay_safety = None if replay is None else replay.safety_for(len(self.ids))
        failure: Exception | None = None
        async with contextlib.AsyncExitStack() as stack:
            self._stack = stack
            await stack.enter_async_context(master)
            if not resume:
                self._write_simulation_file(run_dir)
            if self.realtime:
                await stack.enter_async_context(swarm)
            for index, robot_id in enumerate(list(self._drivers)):
                # A body whose robot is gone for good still takes a robot's place in the
                # world (and its safety state the snapshot's): an agent that never runs.
                await self._start_agent(stack, robot_id or self.ids[index], index, master.port)
                if robot_id is None:
                    await self.stop_agent(self.ids[index])
                    self._drivers[index] = None
            if simulation is not None:
                # The events that happened set the world up (a moved lamp); the snapshot then
                # gives its state (robots that left: their drivers, above).
                for index in [] if checkpoint is None else checkpoint.events_applied:
                    event = self.experiment.events[index]
                    if not isinstance(event, RobotsLeave):
                        apply_to_world(self.world, event, event_rng(self.experiment.seed, index))
                self._restore(simulation)
            try:
                summary = await master.run()
            except Exception as exc:
                # Raised only once the agents are closed: an error passing through their task
                # groups would come out wrapped in an exception group per agent.
                failure = exc
            finally:
                tasks = list(self._tasks.values())
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
                self._stack = None
        if failure is not None:
            raise failure
        self._write_simulation_file(run_dir)
        if self._boxes_before is not None:
            steps = self.experiment.post_evaluation_steps
            write_box_track(
                run_dir, self.world.recorded_boxes(steps), box_frame_steps(self.world.config.dt)
            )
            self.world.stop_recording()
        metrics = await asyncio.to_thread(write_report, run_dir)
        return SimulatedRun(summary, metrics)

    def _write_simulation_file(self, run_dir: Path) -> None:
        write_simulation_file(
            run_dir,
            self.experiment,
            self.world,
            engine="agents",
            realtime=self.realtime,
            boxes_before=self._boxes_before,
            safety_before=self._safety_before,
        )


def simulated_loop(experiment: ExperimentConfig) -> LoopConfig:
    """The control loop's limits for a simulated body: the experiment's period is the shortest
    (a simulated sensor has no update rate) and its longest evaluation fits."""
    longest = max(experiment.evaluation_steps, experiment.post_evaluation_steps)
    return LoopConfig(
        min_period=min(experiment.step_period, LoopConfig().min_period),
        max_steps=max(longest, LoopConfig().max_steps),
    )


def summary_text(
    metrics: dict[str, Any], out: Path, seconds: float, *, resumed: bool = False
) -> str:
    """What ``surprise-master sim`` prints at the end: where, how good, which behaviour, how much
    of it the safety layer drove."""
    from reporting.report import safety_lines

    best = metrics.get("best_fitness")
    lines = [
        f"run directory: {out}",
        f"evaluations: {metrics['evaluations']} "
        + (f"(resumed; {seconds:.1f} s since)" if resumed else f"in {seconds:.1f} s"),
        f"best fitness: {'-' if best is None else f'{best:.4f}'}",
    ]
    post = metrics.get("post_evaluation") or {}
    if post.get("swarm_fitness") is not None:
        lines.append(
            f"post-evaluation fitness: {post['swarm_fitness']:.4f} ({post['steps']} steps)"
        )
    b = post.get("behaviour")
    if b:
        figures = (
            f"rotation c_o {b['rotation']:.1f} rad, mean cluster size "
            f"{b['mean_cluster_size']:.2f}, distance d_R {b['distance_covered']:.2f} m"
        )
        if b.get("box_displacement") is not None:
            figures += f", box displacement d_B {b['box_displacement']:.3f} m"
            if b.get("backward_share") is not None:
                figures += f", {100 * b['backward_share']:.0f} % of moves backwards"
        lines.append(f"behaviour: {sim_metrics.behaviour_label(b)} ({figures})")
    lines += safety_lines(metrics)
    lines.append(f"plots: {out / 'plots'}")
    return "\n".join(lines)


@contextlib.contextmanager
def quiet_agents() -> Iterator[None]:
    """While inside, the in-process agents log only warnings: their connections, at INFO, stay
    out of the progress display (the level is put back afterwards)."""
    logger = logging.getLogger("robot_agent")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def print_if_compiling(engine: str) -> bool:
    """Say so when this run compiles the simulator first (the first run on a machine, or after
    an update: docs/simulation.md, "The first run"), before the progress sits still for it;
    whether it does."""
    from minimize_surprise import jit, precompile
    from simulator import physics
    from simulator.engine import evaluate

    if jit.compiled_on_disk(evaluate if engine == "fast" else physics.step_world) is not False:
        return False
    cores = precompile.cores() if engine == "fast" else 1  # the fast engine compiles on every core
    on = f" on {cores} cores" if cores > 1 else ""
    print(
        f"compiling the simulator for this machine{on}: once, 5 to 15 s; later runs load it "
        f"from {jit.cache_directory()}",
        flush=True,
    )
    return True
