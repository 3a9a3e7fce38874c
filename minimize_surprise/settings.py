"""Everything a named setting gives, in one place (docs/simulation.md): ``paper`` is the authors'
Webots simulation (the paper's Sec. V results), ``lab`` the real robots.

A setting gives defaults at three places, each overridable by the experiment file:

* the experiment's own timing and genome numbers (:class:`ExperimentDefaults`, taken by
  :func:`minimize_surprise.config.with_setting` for every key the file leaves out);
* the simulated world, on top of the scenario's own (:attr:`SettingDefaults.world` and
  :attr:`SettingDefaults.scenario_world`; the experiment's ``simulation`` mapping overrides both).
  ``lab`` changes nothing there: the scenarios' own values (``simulator.scenarios.WorldConfig``)
  are the real robots';
* the simulated robots' safety layer per scenario (:attr:`SettingDefaults.safety`, keys of
  :class:`minimize_surprise.safety.SafetyConfig`; the experiment's ``safety`` mapping overrides
  it). ``simulator.experiment`` applies the last two.

An experiment names its setting (default ``lab``, in a file as in code), so a lab's real-robot
run keeps the real robots' numbers; ``surprise-master sim`` without an experiment file runs the
``paper`` setting, and ``--setting`` picks either.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

__all__ = [
    "SETTINGS",
    "WEBOTS_IR_TABLE",
    "ExperimentDefaults",
    "Setting",
    "SettingDefaults",
    "experiment_defaults",
    "setting_defaults",
]

Setting = Literal["paper", "lab"]
#: The settings' names.
SETTINGS: tuple[str, ...] = ("paper", "lab")


@dataclass(frozen=True)
class ExperimentDefaults:
    """The experiment-level numbers of a setting (see :func:`experiment_defaults`)."""

    #: seconds per control step
    step_period: float
    #: steps of an evaluation and of the post-evaluation of the best genome
    evaluation_steps: int
    post_evaluation_steps: int
    #: evaluations of a run
    evaluations: int
    #: the first genome is uniform in [-initial_range, initial_range]
    initial_range: float
    #: the first genome evaluated: the random one, or a mutant of it (the authors' code)
    first_genome: Literal["random", "mutant"]
    #: a(-1), the previous action the actor sees at the first step of every evaluation
    initial_action: float
    #: hidden neurons of the actor for a given number of sensors
    actor_hidden: dict[int, int]
    #: the actor's hidden size for a sensor count not listed
    actor_hidden_default: int

    def actor_hidden_for(self, sensors: int) -> int:
        """The actor's hidden size for ``sensors`` sensors."""
        return self.actor_hidden.get(sensors, self.actor_hidden_default)


@dataclass(frozen=True)
class SettingDefaults:
    """Everything one setting gives (see the module docstring)."""

    experiment: ExperimentDefaults
    #: world parameters of every scenario (``WorldConfig`` keys)
    world: dict[str, Any] = field(default_factory=dict)
    #: world parameters of one scenario, over :attr:`world`
    scenario_world: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: the simulated robots' safety layer per scenario (``SafetyConfig`` keys); a scenario not
    #: listed gets the ``stop`` profile
    safety: dict[str, dict[str, Any]] = field(default_factory=dict)


_EXPERIMENT: dict[str, ExperimentDefaults] = {
    # The authors' Webots code: 10 ms steps, 1000-step evaluations, a 10,000-step post-evaluation,
    # 1000 evaluations; genes uniform in [-1, 1), the first genome sent a mutant of a random one;
    # a(-1) all ones; actors of 7 hidden neurons for 9 or 10 sensors, 8 for 12.
    "paper": ExperimentDefaults(
        step_period=0.01,
        evaluation_steps=1000,
        post_evaluation_steps=10_000,
        evaluations=1000,
        initial_range=1.0,
        first_genome="mutant",
        initial_action=1.0,
        actor_hidden={9: 7, 10: 7, 12: 8},
        actor_hidden_default=8,
    ),
    # The real robots at 10 Hz: 100-step evaluations, a 1000-step post-evaluation, the paper's
    # 350 evaluations of its real-robot runs (a battery's life); the paper's text for the first
    # genome ([-0.5, 0.5]); a(-1) zero; actors of 8 hidden neurons (ours).
    "lab": ExperimentDefaults(
        step_period=0.1,
        evaluation_steps=100,
        post_evaluation_steps=1000,
        evaluations=350,
        initial_range=0.5,
        first_genome="random",
        initial_action=0.0,
        actor_hidden={},
        actor_hidden_default=8,
    ),
}


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


_SETTINGS: dict[str, SettingDefaults] = {
    "paper": SettingDefaults(
        experiment=_EXPERIMENT["paper"],
        world=_PAPER_WORLD,
        scenario_world=_PAPER_SCENARIOS,
        safety=_PAPER_SAFETY,
    ),
    "lab": SettingDefaults(experiment=_EXPERIMENT["lab"], safety=_LAB_SAFETY),
}


def setting_defaults(setting: str) -> SettingDefaults:
    """Everything ``setting`` gives (``KeyError`` for an unknown name)."""
    return _SETTINGS[setting]


def experiment_defaults(setting: str) -> ExperimentDefaults:
    """The experiment-level numbers of ``setting`` (``KeyError`` for an unknown name)."""
    return _SETTINGS[setting].experiment
