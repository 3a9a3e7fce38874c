"""The simulated world and safety layer of an experiment: its scenario in its setting.

Every way of simulating an experiment (the agents over TCP, the compiled engine, baselines,
studies) and the report's pictures build the world from an experiment file the same way, here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import ConfigError
from minimize_surprise.safety import SafetyConfig
from simulator.scenarios import SCENARIOS, WorldConfig, scenario_config
from simulator.settings import check_setting, safety_config, world_overrides

__all__ = ["scenario_world", "simulated_safety", "world_config"]


def scenario_world(
    setting: Any, scenario: str, overrides: Any, file: str | Path | None = None
) -> WorldConfig:
    """Scenario ``scenario`` in ``setting`` with the world parameters ``overrides`` (an
    experiment file's ``simulation`` section); a ConfigError names ``file`` and the key."""
    check_setting(setting, file)
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
    return scenario_world(experiment.setting, experiment.scenario, overrides, file)


def simulated_safety(
    experiment: ExperimentConfig, *, file: str | Path | None = None
) -> SafetyConfig:
    """The simulated robots' safety layer: the setting's for the scenario, with the experiment's
    ``safety`` overrides."""
    return safety_config(experiment.setting, experiment.scenario, experiment.safety, file=file)
