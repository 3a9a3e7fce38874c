"""The two simulation settings, by name: ``paper`` and ``lab`` (docs/simulation.md).

``paper`` is the authors' Webots simulation, from which the paper's Sec. V results come: 10 ms
steps, Webots' Thymio II sensors (one IR ray with its lookup table and 1 % noise, ground sensors
that read the dark carpet and nothing beyond it), the arenas and boxes of the authors' worlds,
and the safety rules of the authors' Webots controllers. ``lab`` is the real robots: 100 ms
steps, Enki's Thymio II sensor model (checked against Enki in the tests), the real robots' safety
numbers.

A setting gives defaults at three places, each overridable by the experiment file:

* the world (:func:`world_overrides`, on top of the scenario's own; the experiment's
  ``simulation`` mapping overrides both);
* the safety layer of the simulated robots (:func:`safety_config`; the experiment's ``safety``
  mapping overrides it);
* the experiment's own timing and genome settings (``minimize_surprise.settings``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from minimize_surprise.config import Strict, decode
from minimize_surprise.errors import ConfigError
from minimize_surprise.safety import SafetyConfig
from minimize_surprise.settings import SETTINGS

__all__ = ["SETTINGS", "check_setting", "safety_config", "world_overrides"]

# Webots' Thymio II distance sensor (Thymio2DistanceSensor.proto): effective distance in metres
# -> raw value, normalised by 4500 as the authors' controllers do; 0 from 9.33 cm on.
_WEBOTS_IR_RAW = (
    (0.0, 4235), (0.00333, 4308), (0.00666, 4298), (0.01, 4279), (0.01333, 4253),
    (0.01666, 4201), (0.02, 4139), (0.02333, 3981), (0.02666, 3733), (0.03, 3515),
    (0.03333, 3326), (0.03666, 3141), (0.04, 2965), (0.04333, 2860), (0.04666, 2696),
    (0.05, 2570), (0.05333, 2475), (0.05666, 2344), (0.06, 2248), (0.06333, 2182),
    (0.06666, 2044), (0.07, 1941), (0.07333, 1835), (0.07666, 1689), (0.08, 1597),
    (0.08333, 1473), (0.08666, 1345), (0.09, 1195), (0.09333, 0),
)  # fmt: skip
WEBOTS_IR_TABLE = tuple((d, raw / 4500.0) for d, raw in _WEBOTS_IR_RAW)

#: The paper's Webots world, for every scenario (docs/simulation.md lists the sources).
_PAPER_WORLD: dict[str, Any] = {
    "dt": 0.01,
    "max_speed": 0.126,  # 6 rad/s on 21 mm wheels
    "wheel_base": 0.10,  # Webots' Thymio II: wheels at +-5 cm
    "wall_margin": 0.115,  # walls centred 12 cm beyond the carpet, 1 cm thick
    "ir_model": "ray",
    "ir_table": [list(row) for row in WEBOTS_IR_TABLE],
    "ir_range": 0.09333,
    "ir_noise": 0.01,
    # Webots divides the distance by 0.2 + 0.8 x (the hit surface's red): the robots' white
    # body about 0.96; the walls' roughcast reflects less (the newer Webots formula's 0.6).
    "ir_robot_reflectance": 0.96,
    "ir_wall_reflectance": 0.6,
    # Ground: normalised by 1100; the dark carpet reads 0.18-0.49 depending on its texture and
    # Webots' version (0.3 is ours, within both estimates); beyond the carpet there is nothing to
    # see: exactly 0. Webots' 1 % noise.
    "ground_carpet": 0.3,
    "ground_outside": 0.0,
    "ground_noise": 0.01,
    "force_per_box": 0.025,  # 1 N -> 1.0; the authors: 0.25 is about 10 boxes
}
_PAPER_SCENARIOS: dict[str, dict[str, Any]] = {
    # Uniform random poses, body centres at least 16.4 cm apart (2 x 8.2 cm).
    "basic": {"start_clearance": 0.048},
    # 4 robots 10 cm from the centre facing outwards along the axes; about 270 boxes on the
    # authors' jittered grid, none in the central 0.5 x 0.5 m; 5 cm walls, seen by the IR.
    "boxes": {
        "start_ring": 0.1,
        "start_ring_phase": 0.0,
        "box_layout": "grid",
        "box_clear_centre": 0.5,
    },
    # As boxes, with a ceiling light 0.27 m above the floor (0.21 m above the light sensors, which
    # face up: irradiance h / d^3): 0.68 under it, 0.012 in the corners.
    "gradient": {
        "start_ring": 0.1,
        "start_ring_phase": 0.0,
        "box_layout": "grid",
        "box_clear_centre": 0.5,
        "light_centre": 0.68,
        "light_corner": 0.012,
        "light_exponent": 1.5,
        "light_sensor_offsets": [[0.08, 0.0], [-0.03, 0.0]],
    },
}

#: The paper's safety rules (the authors' Webots controllers), per scenario.
_PAPER_SAFETY: dict[str, dict[str, Any]] = {
    "basic": {
        "profile": "stop",
        "stop_ir_threshold": 0.9,
        "ground_boundary": "below",
        "ground_threshold": 0.01,
        "stop_both_wheels": True,
        "stop_ground_when_reversing": True,
    },
    "boxes": {
        "profile": "escape",
        "escape_front_threshold": 0.6,
        "escape_rear_threshold": 0.7,
        "force_threshold": 0.25,
        "ground_boundary": "below",
        "ground_threshold": 0.01,  # off the carpet reads exactly 0
        "escape_drive_steps": 50,
        "turn_steps_min": 70,
        "turn_steps_max": 119,
        "turn_clockwise_probability": 49 / 99,
        "boundary_turn_ratio": 1 / 3,
        "escape_looks_ahead": False,
        "skip_rules_when_still": True,
        "backward_limit_steps": 899,  # the 900th backward step stops the robot
        "backward_needs_both_wheels": True,
    },
}
_PAPER_SAFETY["gradient"] = _PAPER_SAFETY["boxes"]

#: The real robots' safety profile per scenario; every number is SafetyConfig's default.
_LAB_SAFETY: dict[str, dict[str, Any]] = {
    "basic": {"profile": "stop"},
    "boxes": {"profile": "escape"},
    "gradient": {"profile": "escape"},
}


def check_setting(setting: object, file: str | Path | None = None) -> None:
    """Raise :class:`ConfigError` (key ``setting``, naming ``file``) unless ``setting`` is one of
    :data:`SETTINGS`."""
    if setting not in SETTINGS:
        raise ConfigError(
            f"unknown setting {setting!r}; expected one of: {', '.join(SETTINGS)}",
            file=str(file) if file else None,
            key="setting",
        )


def world_overrides(setting: str, scenario: str) -> dict[str, Any]:
    """What ``setting`` changes in ``scenario``'s world (the ``lab`` setting: nothing)."""
    check_setting(setting)
    if setting == "lab":
        return {}
    return {**_PAPER_WORLD, **_PAPER_SCENARIOS.get(scenario, {})}


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
    table = _PAPER_SAFETY if setting == "paper" else _LAB_SAFETY
    merged = {**table.get(scenario, {"profile": "stop"}), **(overrides or {})}
    return decode({"safety": merged}, _SafetyDocument, file=file).safety


class _SafetyDocument(Strict, frozen=True):
    # Wrapping the safety in a ``safety`` key makes decode() name keys as the experiment file
    # spells them, e.g. "safety.force_threshold".
    safety: SafetyConfig
