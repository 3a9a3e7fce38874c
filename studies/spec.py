"""A study file: named groups of runs, each a kind of run with its settings, seeds and sweeps.

::

    name: paper-sec5
    description: The paper's Sec. V simulation results
    defaults:                     # merged under every group's params
      setting: paper
    groups:
      - name: basic
        kind: evolved             # evolved | random | qd | grid-evolved | grid-random | ...
        params: {scenario: basic}
        seeds: {from: 1, to: 20}  # or a list [1, 2, 3], or a count: 20 (seeds 1..20)
        sweep:                    # every combination of the values (dotted keys go deep)
          simulation.arena_side: [0.7, 0.8, 0.9, 1.0, 1.5]
      - name: rerun               # a group that uses another group's runs
        kind: grid-rerun
        after: [evolved]          # runs once every run of these groups has ended
        params: {genome_run: "evolved/size=16/seed-{seed}"}   # below the study's runs/
    slurm: {queue: short, jobs: 10}   # with `run --slurm`: the workers' jobs (studies.slurm)

``params`` is the run kind's own configuration: for the Thymio kinds (``evolved``, ``random``) an
experiment file's content (docs/simulation.md), for the grid kinds the grid world's
(docs/gridworld.md). :func:`expand` turns a study into its tasks, one per run: plain data, so any
executor can run them and a task names its own run directory.

A group may use the runs of others (the grid world's reruns and damage of evolved genomes): it
names them in ``after`` and starts once every run of those groups has ended; a relative
``genome_run`` is a run below the study's ``runs/``, ``{seed}`` standing for the run's own seed.

A ``recorded`` group runs nothing: its ``params`` are ``{runs: [path or glob, ...]}``, finished
run directories relative to the study file (the lab's real-robot runs, :mod:`studies.recorded`);
it takes neither ``seeds``, ``sweep``, ``after`` nor the study's ``defaults``, and each directory
it matches is one task, ``<group>/<directory's name>``.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path
from typing import Annotated, Any

import msgspec

from minimize_surprise.config import Strict, decode, read_yaml
from minimize_surprise.errors import ConfigError
from studies.recorded import (
    RECORDED,
    RecordedParams,
    absolute_patterns,
    matching_runs,
    source_names,
)
from studies.slurm import SlurmOptions

__all__ = [
    "THYMIO_KINDS",
    "Group",
    "PaperResult",
    "SeedRange",
    "Study",
    "expand",
    "load_study",
    "run_name",
    "task_stages",
]

#: Run kinds of the Thymio simulation (the grid world adds its own, see studies.tasks).
THYMIO_KINDS = ("evolved", "random", "qd")

_NAME = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")]
Seed = Annotated[int, msgspec.Meta(ge=0)]


class SeedRange(Strict, frozen=True):
    """Seeds ``from`` .. ``to``, both included."""

    #: the first seed
    from_: Seed = msgspec.field(name="from")
    #: the last seed (included)
    to: Seed

    def __post_init__(self) -> None:
        if self.to < self.from_:
            raise ValueError("`to`: must be at least `from`")


class PaperResult(Strict, frozen=True):
    """What a paper reports for a group, so that the report puts the group's runs beside it
    (``report/paper.csv`` and ``paper.md``)."""

    #: the paper's lower bound on the median best fitness of every condition of the group
    median_fitness_at_least: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] | None = None
    #: the paper's upper bound on the median best fitness of every condition of the group
    median_fitness_at_most: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] | None = None
    #: the behaviour classes the paper found, in its words
    classes: str = ""
    #: where the paper says so (section, figure)
    source: str = ""


class Group(Strict, frozen=True):
    """One group of runs: a kind, its parameters, its seeds, and an optional sweep."""

    #: the group's name (1 to 64 letters, digits, ``.``, ``_``, ``-``): its runs' directory
    name: _NAME
    #: the run kind: ``evolved`` (an evolved run on the engine), ``random`` (one random network
    #: pair), ``qd`` (a MAP-Elites run on the engine), ``recorded`` (finished run directories
    #: read, not run: the lab's real-robot runs), or a kind another installed package adds
    kind: str
    #: the run kind's configuration (for ``evolved``, ``random`` and ``qd``: an experiment file's
    #: content), merged over the study's ``defaults``; for ``recorded``: ``runs``, the run
    #: directories (paths or globs relative to the study file), without the defaults
    params: dict[str, Any] = msgspec.field(default_factory=dict)
    #: a list of seeds, a range, or a count N (seeds 1..N)
    seeds: list[Seed] | SeedRange | Annotated[int, msgspec.Meta(ge=1)] = 1
    #: dotted parameter -> values; every combination of the values is run with every seed
    sweep: dict[str, list[Any]] = msgspec.field(default_factory=dict)
    #: groups whose runs this group's runs use: it starts once every run of them has ended
    after: list[str] = msgspec.field(default_factory=list)
    #: what the paper reports for this group (optional): the report puts the runs beside it
    paper: PaperResult | None = None

    def __post_init__(self) -> None:
        for key, values in self.sweep.items():
            if not values:
                raise ValueError(f"`sweep.{key}`: give at least one value")
        if isinstance(self.seeds, list) and len(set(self.seeds)) != len(self.seeds):
            raise ValueError("`seeds`: a seed is listed twice")

    def seed_list(self) -> list[int]:
        """The seeds, in order."""
        if isinstance(self.seeds, int):
            return list(range(1, self.seeds + 1))
        if isinstance(self.seeds, SeedRange):
            return list(range(self.seeds.from_, self.seeds.to + 1))
        return list(self.seeds)


class Study(Strict, frozen=True):
    """A study file (see the module docstring)."""

    #: the study's name (1 to 64 letters, digits, ``.``, ``_``, ``-``)
    name: _NAME
    #: the groups of runs (at least one; names unique)
    groups: list[Group]
    #: what the study is for
    description: str = ""
    #: parameters merged under every group's own (a group's win)
    defaults: dict[str, Any] = msgspec.field(default_factory=dict)
    #: where ``surprise-study run --slurm`` starts the workers (used only with ``--slurm``,
    #: whose options override it)
    slurm: SlurmOptions | None = None

    def __post_init__(self) -> None:
        if not self.groups:
            raise ValueError("`groups`: a study needs at least one group")
        names = [g.name for g in self.groups]
        for name in names:
            if names.count(name) > 1:
                raise ValueError(f"`groups`: the name {name!r} is used twice")
        for index, group in enumerate(self.groups):
            for other in group.after:
                if other not in names:
                    raise ValueError(f"`groups[{index}].after`: no group is named {other!r}")
        self.stages()  # a circle of `after`s fails here, by name

    def stages(self) -> list[list[str]]:
        """The groups' names in the order they may run: each stage's groups need only groups
        of earlier stages (``after``)."""
        return _layers({group.name: set(group.after) for group in self.groups})


def _layers(needs: dict[str, set[str]]) -> list[list[str]]:
    # Names in layers, each needing only names of earlier layers; a needed name that is not a
    # key (a group whose runs have all finished) holds nothing up.
    left = {name: wanted & needs.keys() for name, wanted in needs.items()}
    layers: list[list[str]] = []
    done: set[str] = set()
    while left:
        ready = [name for name, wanted in left.items() if wanted <= done]
        if not ready:
            circle = ", ".join(sorted(left))
            raise ValueError(f"`groups`: the groups {circle} wait for each other (`after`)")
        layers.append(ready)
        done.update(ready)
        for name in ready:
            del left[name]
    return layers


def load_study(path: str | Path, *, find_runs: bool = False) -> Study:
    """Load a study file; every error names the file and the key. The run kinds are checked
    against those this installation knows (:data:`studies.tasks.KINDS`).

    A ``recorded`` group's paths are made absolute (relative ones are the study file's). With
    ``find_runs`` (a study about to run) each of them must match a run directory; without, a
    path that matches nothing yet adds no run (the shipped example lists a lab's runs)."""
    from studies.tasks import KINDS

    raw = read_yaml(path)
    study = decode(raw, Study, file=path)
    for index, group in enumerate(study.groups):
        if group.kind not in KINDS:
            raise ConfigError(
                f"unknown run kind {group.kind!r}; expected one of: {', '.join(KINDS)}",
                file=str(path),
                key=f"groups[{index}].kind",
            )
    study = _recorded_groups(study, raw, path, find_runs=find_runs)
    _check_params(study, path)
    return study


#: What a recorded group cannot have, and why: it runs nothing.
_NOT_RECORDED = {
    "seeds": "a recorded group's runs have run: it takes no seeds",
    "sweep": "a recorded group's runs have run: it takes no sweep",
    "after": "a recorded group runs nothing, so it waits for no group",
}


def _recorded_groups(
    study: Study, raw: dict[str, Any], path: str | Path, *, find_runs: bool
) -> Study:
    # Checked against the file's own keys: `seeds: 1` and the default look alike once decoded.
    groups = []
    for index, group in enumerate(study.groups):
        if group.kind != RECORDED:
            groups.append(group)
            continue
        where = f"groups[{index}]"
        for key, reason in _NOT_RECORDED.items():
            if key in raw["groups"][index]:
                raise ConfigError(reason, file=str(path), key=f"{where}.{key}")
        try:
            params = decode(group.params, RecordedParams)
        except ConfigError as exc:
            key = f"{where}.params" + (f".{exc.key}" if exc.key else "")
            raise ConfigError(exc.reason, file=str(path), key=key) from None
        patterns = absolute_patterns(params.runs, Path(path).parent)
        for number, pattern in enumerate(patterns):
            if find_runs and not matching_runs(pattern):
                raise ConfigError(
                    f"no run directory matches {params.runs[number]!r} ({pattern})",
                    file=str(path),
                    key=f"{where}.params.runs[{number}]",
                )
        groups.append(msgspec.structs.replace(group, params={"runs": patterns}))
    return msgspec.structs.replace(study, groups=groups)


def _check_params(study: Study, path: str | Path) -> None:
    # Every run's parameters decode before any run starts: a bad key fails the study at once,
    # by name, not each of its runs later. One task per group and sweep value (seeds aside).
    from studies.tasks import check_task

    index = {group.name: i for i, group in enumerate(study.groups)}
    seen: set[tuple[str, str]] = set()
    for task in expand(study):
        label = (task["group"], repr(task["sweep"]))
        if label in seen:
            continue
        seen.add(label)
        try:
            check_task(task)
        except ConfigError as exc:
            where = f"groups[{index[task['group']]}].params"
            sweep = ", ".join(f"{k}={v}" for k, v in task["sweep"].items())
            raise ConfigError(
                f"{exc.reason}" + (f" (with {sweep})" if sweep else ""),
                file=str(path),
                key=f"{where}.{exc.key}" if exc.key else where,
            ) from None


def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    node = data
    for part in parts[:-1]:
        child = node.get(part)
        if not isinstance(child, dict):
            child = {}
        node[part] = child = dict(child)
        node = child
    node[parts[-1]] = value


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def run_name(group: str, sweep: dict[str, Any], seed: int) -> str:
    """A run's directory below the study's ``runs/``: ``group/key=value,.../seed-N``."""
    parts = [group]
    if sweep:
        label = ",".join(f"{key.split('.')[-1]}={value}" for key, value in sweep.items())
        parts.append(re.sub(r"[^A-Za-z0-9._=,-]", "_", label))
    parts.append(f"seed-{seed}")
    return "/".join(parts)


def expand(study: Study) -> list[dict[str, Any]]:
    """Every run of the study as a task: plain data naming the group, kind, seed, sweep values,
    the merged parameters and the run's directory (relative to the study's ``runs/``)."""
    tasks = []
    for group in study.groups:
        if group.kind == RECORDED:
            tasks += _recorded_tasks(study, group)
            continue
        keys = list(group.sweep)
        combos = itertools.product(*(group.sweep[k] for k in keys)) if keys else [()]
        for combo in combos:
            sweep = dict(zip(keys, combo, strict=True))
            params = _merge(study.defaults, group.params)
            for key, value in sweep.items():
                _set_dotted(params, key, value)
            for seed in group.seed_list():
                tasks.append(
                    {
                        "study": study.name,
                        "group": group.name,
                        "kind": group.kind,
                        "seed": seed,
                        "sweep": sweep,
                        "params": params,
                        "run": run_name(group.name, sweep, seed),
                        "after": list(group.after),
                    }
                )
    return tasks


def _recorded_tasks(study: Study, group: Group) -> list[dict[str, Any]]:
    # One task per run directory the group's paths match, each once, in the paths' order; the
    # "seed" only numbers them (a real run's randomness is the world's).
    sources: list[Path] = []
    for pattern in group.params.get("runs", []):
        sources += [p for p in matching_runs(pattern) if p not in sources]
    return [
        {
            "study": study.name,
            "group": group.name,
            "kind": group.kind,
            "seed": number,
            "sweep": {},
            "params": {"source": str(source)},
            "run": f"{group.name}/{name}",
            "after": [],
        }
        for number, (source, name) in enumerate(zip(sources, source_names(sources), strict=True), 1)
    ]


def task_stages(tasks: list[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    """``tasks`` (of :func:`expand`) in stages: a task's ``after`` groups all lie in earlier
    stages; within a stage, the tasks keep their order."""
    needs: dict[str, set[str]] = {}
    for task in tasks:
        needs.setdefault(task["group"], set()).update(task.get("after", ()))
    layers = _layers(needs)
    stage_of = {name: index for index, layer in enumerate(layers) for name in layer}
    stages: list[list[dict[str, Any]]] = [[] for _ in layers]
    for task in tasks:
        stages[stage_of[task["group"]]].append(task)
    return stages
