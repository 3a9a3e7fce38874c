"""The experiment configuration: YAML decoded into typed, validated structures.

:func:`load_yaml` and :func:`decode` are shared by every configuration in the project (experiment,
agent, master): a bad document raises one :class:`~minimize_surprise.errors.ConfigError` naming the
file, the dotted key and what was expected.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import msgspec
import yaml

from minimize_surprise.errors import ConfigError
from minimize_surprise.events import ArenaEvent, check_events
from minimize_surprise.optimizer import OptimizerConfig
from minimize_surprise.sensors import check_sensor_names
from minimize_surprise.settings import SETTINGS, Setting, experiment_defaults

T = TypeVar("T")

_PATH_RE = re.compile(r"^(?P<reason>.*?)(?: - at `\$(?P<path>[^`]*)`)?$", re.S)
_UNKNOWN_RE = re.compile(r"unknown field `(?P<field>[^`]+)`")
_MISSING_RE = re.compile(r"missing required field `(?P<field>[^`]+)`")
# ``__post_init__`` checks name the sub-key they reject as a leading "`key`: reason".
_SUBKEY_RE = re.compile(r"^`(?P<key>[^`]+)`: (?P<reason>.*)$", re.S)

Probability = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
PositiveInt = Annotated[int, msgspec.Meta(ge=1)]
NonNegativeFloat = Annotated[float, msgspec.Meta(ge=0.0)]


class Strict(msgspec.Struct, forbid_unknown_fields=True, kw_only=True, frozen=True):
    """Base of every configuration structure: unknown keys are errors, fields are keyword-only."""


def _dotted(path: str) -> str:
    # msgspec paths look like ".evolution.rates[2].x"; we report "evolution.rates[2].x".
    return path[1:] if path.startswith(".") else path


def decode(data: Any, type_: type[T], *, file: str | Path | None = None) -> T:
    """Convert plain data (as loaded from YAML) into ``type_``, or raise :class:`ConfigError`."""
    if data is None:
        data = {}
    try:
        return msgspec.convert(data, type_, strict=False)
    except msgspec.ValidationError as exc:
        match = _PATH_RE.match(str(exc))
        assert match is not None  # the pattern accepts any text
        reason, path = match["reason"], _dotted(match["path"] or "")
        for pattern, what in (
            (_UNKNOWN_RE, "unknown key"),
            (_MISSING_RE, "required key is missing"),
        ):
            found = pattern.search(reason)
            if found:
                path = f"{path}.{found['field']}" if path else found["field"]
                reason = what
        sub = _SUBKEY_RE.match(reason)
        if sub:
            path = f"{path}.{sub['key']}" if path else sub["key"]
            reason = sub["reason"]
        raise ConfigError(reason, file=str(file) if file else None, key=path or None) from None


def read_yaml(path: str | Path) -> dict[str, Any]:
    """The top-level mapping of a YAML file (empty for an empty file), or :class:`ConfigError`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read the file: {exc.strerror or exc}", file=str(path)) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML: {exc}", file=str(path)) from None
    if data is not None and not isinstance(data, dict):
        raise ConfigError("expected a mapping of keys at the top level", file=str(path))
    return data or {}


def load_yaml(path: str | Path, type_: type[T]) -> T:
    """Read a YAML file and decode it into ``type_``; every failure is a :class:`ConfigError`."""
    return decode(read_yaml(path), type_, file=path)


def to_builtins(config: msgspec.Struct) -> dict[str, Any]:
    """Plain data for a configuration structure (for snapshots and YAML dumps)."""
    return msgspec.to_builtins(config)


#: The longest recorded evaluation (post-evaluation): its trace must fit one wire frame. A step of
#: a 12-sensor trace is 31 packed float64 values (248 bytes) and a short safety word, so 20,000
#: steps (33 minutes at 10 Hz) are about 5 MB, inside the 8 MiB frame limit with room to spare
#: (even at the protocol's most sensors, ``minimize_surprise.wire.MAX_SENSORS``).
MAX_RECORDED_STEPS = 20_000

#: The longest control step an experiment may ask for, in seconds. Real robots run at 0.1 s and
#: refuse what their watchdog cannot follow; this bound only catches units mistaken (ms for s)
#: and keeps every deadline derived from the period finite.
MAX_STEP_PERIOD = 10.0


class NetworkConfig(Strict, frozen=True):
    """Sizes of the actor-predictor pair.

    ``predictor_hidden`` defaults to R + 1 where R is the number of sensors. ``initial_action`` is
    a(-1), the previous action fed to the actor at the first step of an evaluation.
    """

    #: hidden neurons of the actor (the paper setting: 7 for 9 or 10 sensors, 8 for 12)
    actor_hidden: PositiveInt = 8
    #: hidden neurons of the predictor; ``null``: the number of sensors + 1
    predictor_hidden: PositiveInt | None = None
    #: a(-1): the previous action (both wheels) the actor sees at the first step of an evaluation
    initial_action: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)] = 0.0


class EvolutionConfig(Strict, frozen=True):
    """(1+1) online evolution with re-evaluation (paper Sec. V-A)."""

    #: counted evaluations of a run before the post-evaluation (failed rounds do not count; the
    #: paper: 1000 in simulation, 350 on real robots, the lab setting's default); ``null``: an
    #: endless run, stopped by the person and resumable (docs/changing-arenas.md)
    evaluations: PositiveInt | None = 350
    #: probability that a round evaluates the current best again instead of an offspring
    reevaluation_probability: Probability = 0.2
    #: weight of the new fitness in F = w f + (1 - w) F when the best is re-evaluated
    reevaluation_weight: Probability = 0.2
    #: probability that a gene of an offspring is mutated
    mutation_probability: Probability = 0.1
    #: a mutated gene gets uniform [-mutation_range, mutation_range] added
    mutation_range: NonNegativeFloat = 0.4
    #: the initial genome is uniform in [-initial_range, initial_range]
    initial_range: NonNegativeFloat = 0.5
    #: the first genome evaluated: the random one, or a mutant of it (the authors' code)
    first_genome: Literal["random", "mutant"] = "random"


class ExperimentConfig(Strict, frozen=True):
    """Everything that defines one experiment, whatever runs it (simulator or real robots).

    ``setting`` names the bundle of defaults the experiment starts from
    (``minimize_surprise.settings``: ``paper``, the authors' Webots simulation, or ``lab``, the real
    robots); a file decoded with
    :func:`decode_experiment` takes every timing and genome value it leaves out from it.
    ``predefined`` maps sensor names to fixed predictions in [0, 1] (paper Sec. IV-F).
    ``min_robots`` lets a run go on with fewer robots when some are gone for good.
    ``simulation`` and ``safety`` hold overrides of the simulated world's parameters and of the
    simulated robots' safety layer; ``simulator`` decodes them, real robots ignore them (their
    safety layer is in each robot's own configuration).
    """

    #: the bundle of defaults the experiment starts from: ``paper`` (the authors' Webots
    #: simulation) or ``lab`` (the real robots); see docs/simulation.md. A file that names none
    #: is ``lab`` wherever it is read (``run``, ``check``, ``sim --config``, a study)
    setting: Setting = "lab"

    #: the sensors the networks see, by name, in this order (``ir.f0`` .. ``ir.f4``, ``ir.b0``,
    #: ``ir.b1``, ``ground.0``, ``ground.1``, ``force``, ``light.0``, ``light.1``); every robot
    #: must have them. A simulated run defaults to what its scenario's robots carry
    sensors: list[str] = msgspec.field(
        default_factory=lambda: [
            "ir.f0", "ir.f1", "ir.f2", "ir.f3", "ir.f4", "ir.b0", "ir.b1", "ground.0", "ground.1",
        ]
    )  # fmt: skip
    #: the actor-predictor network pair
    network: NetworkConfig = msgspec.field(default_factory=NetworkConfig)
    #: the (1+1) online evolution
    evolution: EvolutionConfig = msgspec.field(default_factory=EvolutionConfig)
    #: sensor name -> fixed prediction in [0, 1] (paper Sec. IV-F); the predictor predicts only
    #: the others, and is left out when every sensor is fixed
    predefined: dict[str, float] = msgspec.field(default_factory=dict)
    #: control steps of one evaluation
    evaluation_steps: PositiveInt = 100
    #: control steps of the post-evaluation of the best genome (0: none)
    post_evaluation_steps: Annotated[int, msgspec.Meta(ge=0, le=MAX_RECORDED_STEPS)] = 1000
    #: seconds per control step on every robot (the real robots: 0.1 s, their sensors' 10 Hz;
    #: the paper's Webots simulation: 0.01 s); sent with every evaluation
    step_period: Annotated[float, msgspec.Meta(gt=0.0, le=MAX_STEP_PERIOD)] = 0.1
    #: the simulated arena: ``basic``, ``boxes`` or ``gradient`` (docs/simulation.md)
    scenario: str = "basic"
    #: the arena (docs/arenas.md): a shipped arena's name (``basic``, ``boxes``, ``gradient``,
    #: ``real-objects``) or an arena file's path, relative to the experiment file; left out,
    #: the scenario's own. Simulation runs in it; a real run's report draws it
    arena: str | None = None
    #: robots in the swarm, all evaluating the same genome at once (a simulated run defaults to
    #: its scenario's number)
    robots: PositiveInt = 10
    #: the fewest robots the run may go on with when robots are gone for good (the master's
    #: ``robot_gone_after``): a swarm of fewer than ``robots`` is another experiment, so
    #: ``null`` (the default) never lets a robot go: the run pauses for a spare instead
    #: (docs/runs.md)
    min_robots: PositiveInt | None = None
    #: seed of the evolution's random numbers (and of the simulated world)
    seed: Annotated[int, msgspec.Meta(ge=0)] = 0
    #: overrides of the simulated world's parameters; real robots ignore it
    simulation: dict[str, Any] = msgspec.field(default_factory=dict)
    #: overrides of the simulated robots' safety layer; real robots ignore it (theirs is in each
    #: robot's agent file)
    safety: dict[str, Any] = msgspec.field(default_factory=dict)
    #: the optimizer: left out, the (1+1) of ``evolution``; ``{name: map-elites, measures:
    #: [...], ...}`` quality diversity (docs/quality-diversity.md)
    optimizer: OptimizerConfig | None = None
    #: changes of the arena during the evolution, each at an evaluation or after some seconds
    #: (docs/changing-arenas.md)
    events: list[ArenaEvent] = msgspec.field(default_factory=list)

    @property
    def arena_name(self) -> str:
        """The arena as a person names it: the shipped arena's name or the arena file's stem;
        the scenario's name when the experiment names no arena."""
        if self.arena is None:
            return self.scenario
        return Path(self.arena).stem if self.arena.endswith((".yaml", ".yml")) else self.arena

    @property
    def place(self) -> str:
        """The scenario and the arena it runs in, as a person reads it: ``boxes in
        real-objects``, or only the scenario when the experiment names no arena."""
        return self.scenario + (f" in {self.arena_name}" if self.arena else "")

    def __post_init__(self) -> None:
        if not self.sensors:
            raise ValueError("`sensors`: at least one sensor is needed")
        if self.min_robots is not None and self.min_robots > self.robots:
            raise ValueError(
                f"`min_robots`: {self.min_robots} is more than the swarm's {self.robots} robots"
            )
        try:
            check_sensor_names(self.sensors)
        except ValueError as exc:
            raise ValueError(f"`sensors`: {exc}") from None
        for name, value in self.predefined.items():
            if name not in self.sensors:
                raise ValueError(f"`predefined.{name}`: not among the experiment's sensors")
            if not 0.0 <= value <= 1.0:
                raise ValueError(
                    f"`predefined.{name}`: expected a prediction in [0, 1], got {value}"
                )
        check_events(self.events, self.evolution.evaluations, self.robots)


_DEFAULT_SENSORS = len(ExperimentConfig().sensors)


def with_setting(data: dict[str, Any]) -> dict[str, Any]:
    """Experiment data with its setting's defaults under every value it leaves out.

    The setting is ``data["setting"]`` (default ``lab``); an unknown one is left for decoding to
    reject by name. The input is not modified.
    """
    if not isinstance(data, dict):
        return data
    setting = data.get("setting", "lab")
    if setting not in SETTINGS:
        return data
    d = experiment_defaults(setting)
    sensors = data.get("sensors")
    count = len(sensors) if isinstance(sensors, list) else _DEFAULT_SENSORS
    out = dict(data)
    for key, value in (
        ("step_period", d.step_period),
        ("evaluation_steps", d.evaluation_steps),
        ("post_evaluation_steps", d.post_evaluation_steps),
    ):
        out.setdefault(key, value)
    for section, values in (
        (
            "evolution",
            {
                "evaluations": d.evaluations,
                "initial_range": d.initial_range,
                "first_genome": d.first_genome,
            },
        ),
        (
            "network",
            {"initial_action": d.initial_action, "actor_hidden": d.actor_hidden_for(count)},
        ),
    ):
        given = out.get(section)
        if given is None or isinstance(given, dict):
            out[section] = {**values, **(given or {})}
    return out


def resolve_arena(data: Any, base: str | Path) -> Any:
    """Experiment data with an ``arena`` given as a relative file path made absolute against
    ``base`` (the experiment file's directory); a shipped arena's name is left as it is."""
    if not isinstance(data, dict):
        return data
    arena = data.get("arena")
    if not isinstance(arena, str) or not ("/" in arena or arena.endswith((".yaml", ".yml"))):
        return data
    path = Path(arena).expanduser()
    if not path.is_absolute():
        path = Path(base) / path
    return {**data, "arena": str(path.resolve())}


def decode_experiment(data: Any, *, file: str | Path | None = None) -> ExperimentConfig:
    """Decode experiment data, taking what it leaves out from its setting (:func:`with_setting`);
    an arena file's relative path is taken relative to ``file``'s directory."""
    if file is not None:
        data = resolve_arena(data, Path(file).resolve().parent)
    return decode(with_setting(data or {}), ExperimentConfig, file=file)


def load_experiment(path: str | Path) -> ExperimentConfig:
    """Load an experiment configuration file (see :class:`ExperimentConfig`)."""
    return decode_experiment(read_yaml(path), file=path)
