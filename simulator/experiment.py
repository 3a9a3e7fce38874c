"""The simulated world and safety layer of an experiment: its scenario in its setting.

Every way of simulating an experiment (the agents over TCP, the compiled engine, baselines,
studies) and the report's pictures build the world from an experiment file the same way, here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from minimize_surprise.config import ExperimentConfig, Strict, decode
from minimize_surprise.errors import ConfigError
from minimize_surprise.safety import SafetyConfig
from minimize_surprise.settings import SETTINGS, setting_defaults
from simulator.arenas import Arena, load_arena
from simulator.scenarios import SCENARIOS, WorldConfig, scenario_arena, scenario_config

__all__ = [
    "check_setting",
    "experiment_arena",
    "safety_config",
    "scenario_world",
    "simulated_safety",
    "world_config",
    "world_overrides",
]


def check_setting(setting: object, file: str | Path | None = None) -> None:
    """Raise :class:`ConfigError` (key ``setting``, naming ``file``) unless ``setting`` is one of
    :data:`~minimize_surprise.settings.SETTINGS`."""
    if setting not in SETTINGS:
        raise ConfigError(
            f"unknown setting {setting!r}; expected one of: {', '.join(SETTINGS)}",
            file=str(file) if file else None,
            key="setting",
        )


def world_overrides(setting: str, arena: str) -> dict[str, Any]:
    """What ``setting`` changes in the world of the arena named ``arena`` (the ``lab`` setting:
    nothing; the ``paper`` setting: Webots' sensors everywhere, and the authors' layouts in the
    shipped arenas they stand for)."""
    check_setting(setting)
    given = setting_defaults(setting)
    return {**given.world, **given.scenario_world.get(arena, {})}


def safety_config(
    setting: str,
    scenario: str,
    overrides: dict[str, Any] | None = None,
    *,
    file: str | Path | None = None,
) -> SafetyConfig:
    """The simulated robots' safety layer in ``setting`` and ``scenario``, with the experiment's
    ``safety`` overrides; a bad key raises :class:`ConfigError` naming ``safety.<key>``."""
    check_setting(setting, file)
    table = setting_defaults(setting).safety
    merged = {**table.get(scenario, {"profile": "stop"}), **(overrides or {})}
    return decode({"safety": merged}, _SafetyDocument, file=file).safety


class _SafetyDocument(Strict, frozen=True):
    # Wrapping the safety in a ``safety`` key makes decode() name keys as the experiment file
    # spells them, e.g. "safety.force_threshold".
    safety: SafetyConfig


def experiment_arena(
    scenario: str, arena: str | None, file: str | Path | None = None
) -> Arena | None:
    """The arena an experiment runs in: its ``arena`` (a shipped name or a file's path), else
    its scenario's own; None for an unknown scenario (left for the caller to reject by name)."""
    if arena is not None:
        return load_arena(arena, file=file)
    if scenario not in SCENARIOS:
        return None
    return load_arena(scenario_arena(scenario))


def scenario_world(
    setting: Any,
    scenario: str,
    overrides: Any,
    file: str | Path | None = None,
    *,
    arena: str | None = None,
) -> WorldConfig:
    """Scenario ``scenario`` in ``setting`` and in ``arena`` (default: the scenario's own), with
    the world parameters ``overrides`` (an experiment file's ``simulation`` section); a
    ConfigError names ``file`` (or the arena file) and the key."""
    check_setting(setting, file)
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(
            "expected a mapping of world parameters",
            file=str(file) if file else None,
            key="simulation",
        )
    if scenario not in SCENARIOS:
        return scenario_config(scenario, file=file)  # raises, naming the scenario
    chosen = experiment_arena(scenario, arena, file)
    assert chosen is not None
    return scenario_config(
        scenario,
        {**world_overrides(setting, chosen.name), **(overrides or {})},
        file=file,
        arena=chosen,
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
    return scenario_world(
        experiment.setting, experiment.scenario, overrides, file, arena=experiment.arena
    )


def simulated_safety(
    experiment: ExperimentConfig, *, file: str | Path | None = None
) -> SafetyConfig:
    """The simulated robots' safety layer: the setting's for the scenario, with the experiment's
    ``safety`` overrides."""
    return safety_config(experiment.setting, experiment.scenario, experiment.safety, file=file)
