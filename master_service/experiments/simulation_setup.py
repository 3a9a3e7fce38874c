"""How a simulated experiment is set up: the experiment, the world, the simulated robots' safety.

Shared by ``surprise-master sim`` with either engine (:mod:`master_service.experiments.simulate`,
:mod:`master_service.experiments.engine_run`), ``baseline`` and the studies; it knows nothing of how
the robots are run.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from master_service.evaluation import RunSummary
from minimize_surprise.config import (
    ExperimentConfig,
    decode_experiment,
    read_yaml,
    resolve_arena,
)
from minimize_surprise.errors import ConfigError
from runfiles import schema
from runfiles.schema import BOX_TRACK, BoxesMoved, SimulatedWorld, Simulation, write_atomic
from simulator.engine import robot_ids
from simulator.experiment import scenario_world, simulated_safety, world_config
from simulator.scenarios import WorldConfig
from simulator.world import TooManyRobotsError, World

__all__ = [
    "ENGINES",
    "SimulatedRun",
    "read_simulation_file",
    "robot_ids",
    "setting_note",
    "simulated_safety",
    "simulation_experiment",
    "world_config",
    "write_box_track",
    "write_simulation_file",
]

#: The two ways of running a simulated swarm: the compiled engine, or real agents over TCP.
ENGINES: Final = ("fast", "agents")


@dataclass(frozen=True)
class SimulatedRun:
    """What a simulated run leaves: the master's summary and the report's metrics."""

    summary: RunSummary
    metrics: dict[str, Any]


def setting_note(config_file: str | Path) -> str | None:
    """A note for a person when the experiment file names no setting (it is then ``lab``, as
    everywhere an experiment is read); None when it names one."""
    data = read_yaml(config_file)
    if isinstance(data, dict) and "setting" not in data:
        return (
            f"note: {config_file} names no setting: lab (the real robots' numbers), as for "
            "`surprise-master run`; `setting: paper` is the authors' Webots simulation"
        )
    return None


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

    Layers, each overriding the one before: the setting's defaults (see
    ``minimize_surprise.settings``), the scenario's robots and sensors, the experiment file
    ``config_file`` (or the experiment ``data`` given), then the arguments given (``arena``: the
    carpet's side in metres). The setting is ``setting`` if given, else the experiment's; an
    experiment that names none is ``lab``, as everywhere an experiment is read, and without any
    experiment (neither file nor data) it is ``paper``, the simulation the paper's results come
    from. A bad file or value raises :class:`ConfigError` naming the file and key.
    """
    if data is None:
        data = {"setting": "paper"} if config_file is None else read_yaml(config_file)
    data = dict(data)
    if scenario is not None:
        data["scenario"] = scenario
    if setting is not None:
        data["setting"] = setting
    data.setdefault("setting", "lab")
    if arena is not None:
        if not arena > 0:
            raise ConfigError(f"expected a positive side in metres, got {arena}", key="--arena")
        data["simulation"] = {**(data.get("simulation") or {}), "arena_side": arena}
    if config_file is not None:
        data = resolve_arena(data, Path(config_file).resolve().parent)
    name = data.get("scenario", "basic")
    arena_name = data.get("arena")
    if arena_name is not None and not isinstance(arena_name, str):
        raise ConfigError(
            f"expected an arena's name or an arena file's path, got {arena_name!r}",
            file=str(config_file) if config_file else None,
            key="arena",
        )
    world = scenario_world(
        data.get("setting"), name, data.get("simulation"), config_file, arena=arena_name
    )
    robots_in_file = "robots" in data
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
    _check_robots_fit(
        experiment,
        world_config(experiment, file=config_file),
        given="--robots" if robots is not None else "robots" if robots_in_file else None,
        arena_given=arena is not None,
        file=config_file,
    )
    return experiment


def _check_robots_fit(
    experiment: ExperimentConfig,
    world: WorldConfig,
    *,
    given: str | None,
    arena_given: bool,
    file: str | Path | None,
) -> None:
    """Raise :class:`ConfigError` naming the limit and the option or key to change unless the
    robots fit at the start of the run and of its post-evaluation (each arena seeded apart)."""
    short: list[TooManyRobotsError] = []
    for seed in (experiment.seed, experiment.seed + 1):
        try:
            World(world, seed=seed)
        except TooManyRobotsError as exc:
            short.append(exc)
    if not short:
        return
    # Fewer than the fewest either start placed fit both (see World._place_robots).
    error = min(short, key=lambda exc: exc.fit)
    if error.larger == "start_ring":
        larger = "a wider start ring (simulation.start_ring)"
    elif arena_given or given == "--robots":
        larger = "a larger --arena"
    else:
        larger = "a larger carpet (simulation.arena_side)"
    on_command_line = given == "--robots" or (given is None and arena_given)
    fewer = "fewer with --robots" if on_command_line else "fewer robots"
    if given is not None:
        key = given
    elif arena_given:
        key = "--arena"
    else:
        key = f"simulation.{error.larger}"
    raise ConfigError(
        f"{error.reason}; ask for {fewer} or {larger}",
        key=key,
        file=str(file) if file and not key.startswith("--") else None,
    ) from None


def write_simulation_file(
    run_dir: str | Path,
    experiment: ExperimentConfig,
    world: World,
    *,
    engine: str,
    realtime: bool = False,
    boxes_before: list[list[float]] | None = None,
    safety_before: list[list[int]] | None = None,
) -> None:
    """Write ``simulation.json``: the run is simulated, on which engine, in which world; with
    ``boxes_before`` (the boxes when the post-evaluation began) also where the boxes went, and
    with ``safety_before`` every robot's safety state then (a replay starts from it: the escape
    profile's turns are random draws that go on from the evolution's).

    Written when the run starts, so that ``surprise-master resume`` knows to restart the
    simulated robots, and again at its end, for the report's box displacement.
    """
    boxes = None
    if boxes_before is not None and len(world.box_positions):
        boxes = BoxesMoved(start=boxes_before, end=world.box_positions.tolist())
    simulation = Simulation(
        scenario=experiment.scenario,
        setting=experiment.setting,
        engine=engine,  # type: ignore[arg-type]  # one of ENGINES, checked by the caller
        realtime=realtime,
        world=SimulatedWorld(
            arena_side=world.config.arena_side,
            robots=world.config.robots,
            boxes=len(world.box_positions),
            arena_height=world.config.arena_height,
            arena=experiment.arena_name if experiment.arena else None,
        ),
        post_evaluation_boxes=boxes,
        post_evaluation_safety=safety_before,
    )
    schema.write(run_dir, simulation)


def read_simulation_file(run_dir: str | Path) -> Simulation | None:
    """``simulation.json`` of ``run_dir``, or None for a run of real robots (RunDirError naming
    the file and the key when it cannot be read)."""
    return schema.read(run_dir, Simulation)


def write_box_track(run_dir: str | Path, positions: np.ndarray, every: int) -> None:
    """Write ``box_track.npz``: the boxes' positions during the post-evaluation, a frame every
    ``every`` steps (nothing when the arena has no boxes)."""
    if positions.size == 0:
        return
    buffer = io.BytesIO()
    np.savez_compressed(buffer, positions=positions.astype(np.float32), every=np.int64(every))
    write_atomic(Path(run_dir) / BOX_TRACK, buffer.getvalue())
