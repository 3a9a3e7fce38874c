"""The configuration reference, ``docs/configuration.md``, generated from the typed configuration.

Every configuration file of the project is YAML decoded into msgspec structures (experiment,
agent, master, study; the experiment's ``simulation`` and ``safety`` sections; the ``params`` of
a study's grid-world groups). This module walks
those structures and writes one table per file: every key (nested sections as dotted keys, list
items as ``key[]``), its type, its default and its meaning, so the reference cannot drift from the
code. ::

    python docs/tools/config_reference.py           # write docs/configuration.md
    python docs/tools/config_reference.py --check   # exit 1 if it is not current

Where a key's meaning comes from: the ``#:`` comment lines directly above the field in its class
body (read from the class's source with :mod:`ast`); a field without one falls back to the
sentence of the class docstring that names it in double backquotes. A field with neither is an
error, so every key has a meaning. Types and constraints come from the annotations
(:func:`msgspec.structs.fields`), defaults from the structures themselves (a nested section's keys
from its parent's default, e.g. ``telemetry.reconnect.initial``), and the keys an experiment's
``setting`` fills in from :func:`minimize_surprise.config.with_setting`.

Why one file of over 600 lines: it is a script run by path
(``python docs/tools/config_reference.py``), beside the page it writes; more than half of it
is the pages' own text.
"""

from __future__ import annotations

import argparse
import ast
import collections
import functools
import inspect
import re
import sys
import textwrap
import types
import typing
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import yaml

from master_service.config import MasterConfig as MasterFileConfig
from master_service.inventory import Inventory
from minimize_surprise.config import ExperimentConfig, with_setting
from minimize_surprise.events import ArenaEvent
from minimize_surprise.safety import SafetyConfig
from minimize_surprise.sensors import ALL_SENSORS
from minimize_surprise.settings import SETTINGS
from robot_agent.config import AgentConfig
from simulator.arenas import Arena, shipped_arenas
from simulator.experiment import safety_config, world_overrides
from simulator.scenarios import SCENARIOS, WorldConfig, scenario_config
from studies.recorded import RecordedParams
from studies.spec import Study
from telemetry.config import TelemetryConfig

__all__ = ["DEFAULT_OUTPUT", "Document", "Row", "documents", "generate", "main", "meanings", "rows"]

#: The page this writes: beside this file's folder (docs/tools/ -> docs/).
DEFAULT_OUTPUT = Path(__file__).resolve().parents[1] / "configuration.md"

_COMMAND = "python docs/tools/config_reference.py"


# --- meanings -------------------------------------------------------------------------------------


def meanings(cls: type) -> dict[str, str]:
    """Field name -> meaning for a configuration class (see the module docstring), its base
    classes' fields included (each read from the class that declares it).

    Raises ``ValueError`` naming the class and field if a field has no meaning.
    """
    found: dict[str, str] = {}
    for base in reversed(cls.__mro__):
        if inspect.get_annotations(base) and issubclass(base, msgspec.Struct):
            found.update(_own_meanings(base))
    return found


@functools.cache
def _own_meanings(cls: type) -> dict[str, str]:
    # The meanings of the fields declared in cls's own body.
    source = textwrap.dedent(inspect.getsource(cls))
    lines = source.splitlines()
    tree = ast.parse(source)
    node = tree.body[0]
    assert isinstance(node, ast.ClassDef), cls
    docstring = ast.get_docstring(node) or ""
    found: dict[str, str] = {}
    for statement in node.body:
        if not (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)):
            continue
        name = statement.target.id
        comment: list[str] = []
        index = statement.lineno - 2  # the line above the field, 0-based
        while index >= 0 and lines[index].strip().startswith("#:"):
            comment.insert(0, lines[index].strip()[2:].strip())
            index -= 1
        text = " ".join(comment) or _docstring_mention(docstring, name)
        if not text:
            raise ValueError(
                f"{cls.__module__}.{cls.__qualname__}.{name} has no meaning: add a `#:` comment "
                "line directly above it"
            )
        found[name] = text
    return found


def _docstring_mention(docstring: str, name: str) -> str:
    """The first sentence of ``docstring`` that names ``name`` in double backquotes, or ''."""
    text = " ".join(docstring.split())
    for sentence in re.split(r"(?<=[.;])\s+(?=[A-Z`(])", text):
        if f"``{name}``" in sentence:
            return sentence
    return ""


# --- types ----------------------------------------------------------------------------------------


def _is_struct(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, msgspec.Struct)


def _unwrap(tp: Any) -> tuple[Any, list[msgspec.Meta]]:
    """``tp`` without ``Annotated``, and the constraints it carried."""
    metas: list[msgspec.Meta] = []
    while typing.get_origin(tp) is typing.Annotated:
        tp, *extras = typing.get_args(tp)
        metas += [m for m in extras if isinstance(m, msgspec.Meta)]
    return tp, metas


def _number(value: float, hex_: bool = False) -> str:
    if hex_ and isinstance(value, int):
        return f"0x{value:02X}"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _bounds(metas: list[msgspec.Meta], hex_: bool = False) -> str:
    """The numeric bounds and other constraints of ``metas`` as text (``in [0, 7]``, ``≥ 1``)."""
    low = high = None
    others: list[str] = []
    for meta in metas:
        if meta.gt is not None:
            low = ("(", meta.gt)
        if meta.ge is not None:
            low = ("[", meta.ge)
        if meta.lt is not None:
            high = (")", meta.lt)
        if meta.le is not None:
            high = ("]", meta.le)
        if meta.min_length is not None and meta.max_length is not None:
            others.append(f"of {meta.min_length} to {meta.max_length} characters")
        elif meta.min_length is not None:
            others.append(f"of at least {meta.min_length} characters")
        elif meta.max_length is not None:
            others.append(f"of at most {meta.max_length} characters")
        if meta.pattern is not None:
            others.append(f"matching `{meta.pattern}`")
    parts = []
    if low and high:
        parts.append(f"in {low[0]}{_number(low[1], hex_)}, {_number(high[1], hex_)}{high[0]}")
    elif low:
        parts.append(f"{'>' if low[0] == '(' else '≥'} {_number(low[1], hex_)}")
    elif high:
        parts.append(f"{'<' if high[0] == ')' else '≤'} {_number(high[1], hex_)}")
    return ", ".join(parts + others)


def type_text(tp: Any, hex_: bool = False) -> str:
    """A short, YAML-minded description of an annotation (``int ≥ 1``, ``list of str``, ...);
    with ``hex_`` numeric bounds are written in hexadecimal (I2C addresses)."""
    tp, metas = _unwrap(tp)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Literal:
        return " or ".join(f"`{_yaml(a)}`" for a in args)
    if origin in (typing.Union, types.UnionType) and all(_tag(a) for a in args):
        # Structures told apart by their ``kind``: each by its tag.
        return " or ".join(f"`{_tag(a)}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        present = [a for a in args if a not in (type(None), msgspec.UnsetType)]
        text = " or ".join(type_text(a, hex_) for a in present)
        return f"{text} or `null`" if type(None) in args else text
    if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
        text = "[" + ", ".join(type_text(a, hex_) for a in args) + "]"
    elif origin in (list, tuple):
        text = f"list of {type_text(args[0], hex_)}" if args else "list"
    elif origin is dict:
        text = f"mapping of {type_text(args[0])} to {type_text(args[1])}"
    elif _is_struct(tp):
        text = "section"
    elif tp is typing.Any:
        text = "any"
    elif isinstance(tp, type):
        text = {bool: "bool", int: "int", float: "number", str: "str"}.get(tp, tp.__name__)
    else:
        text = str(tp)
    limits = _bounds(metas, hex_)
    return f"{text} {limits}" if limits else text


def _yaml(value: Any) -> str:
    """``value`` as a short YAML flow scalar or collection (floats to 6 significant digits)."""
    if isinstance(value, msgspec.Struct) or (
        isinstance(value, list | tuple) and any(isinstance(v, msgspec.Struct) for v in value)
    ):
        value = msgspec.to_builtins(value)
    value = _plain(value)
    if value == "":
        return '""'
    text = yaml.safe_dump(value, default_flow_style=True, width=10**6, sort_keys=False).strip()
    return text.removesuffix("\n...").removesuffix("...").strip()


def _plain(value: Any) -> Any:
    """Tuples as lists and floats rounded to 6 significant digits, for :func:`_yaml`."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, float):
        return float(f"{value:.6g}")
    return value


def _tag(tp: Any) -> str | None:
    """The ``kind`` a tagged structure is known by (None: not one)."""
    if not _is_struct(tp):
        return None
    tag = tp.__struct_config__.tag
    return tag if isinstance(tag, str) else None


def _struct_members(tp: Any) -> tuple[list[type], bool]:
    """The structure classes a field's type holds (directly, in a union, or as list items), and
    whether they are list items."""
    tp, _ = _unwrap(tp)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if _is_struct(tp):
        return [tp], False
    if origin in (typing.Union, types.UnionType):
        found = [_unwrap(a)[0] for a in args]
        structs = [a for a in found if _is_struct(a)]
        if structs:
            return structs, False
        for a in found:  # a list of sections or null
            members, is_list = _struct_members(a)
            if members:
                return members, is_list
        return [], False
    listed = origin is list or (origin is tuple and len(args) == 2 and args[1] is Ellipsis)
    if listed and args and _is_struct(_unwrap(args[0])[0]):
        return [_unwrap(args[0])[0]], True
    if origin is list and args and typing.get_origin(args[0]) in (typing.Union, types.UnionType):
        found = [_unwrap(a)[0] for a in typing.get_args(args[0])]
        return [a for a in found if _is_struct(a)], True
    return [], False


# --- rows -----------------------------------------------------------------------------------------

_NO_DEFAULT = object()


@dataclass(frozen=True)
class Row:
    """One key of a reference table."""

    key: str
    type: str
    default: str
    meaning: str


@dataclass
class Document:
    """One configuration file or section: a root structure and how its keys are shown."""

    title: str
    anchor: str
    root: type
    intro: str
    #: key prefix of every row (``simulation.`` for the experiment's simulation section)
    prefix: str = ""
    #: structures shown in their own section: class -> (anchor, title); not expanded here
    elsewhere: dict[type, tuple[str, str]] = field(default_factory=dict)
    #: untyped mappings whose keys another section lists: field path -> (anchor, title)
    see: dict[str, tuple[str, str]] = field(default_factory=dict)
    #: default text per dotted key, replacing the structure's own default
    defaults: dict[str, str] = field(default_factory=dict)


def _default_of(info: msgspec.structs.FieldInfo, parent: Any) -> Any:
    if parent is not None:
        return getattr(parent, info.name)
    if info.default is not msgspec.NODEFAULT:
        return info.default
    if info.default_factory is not msgspec.NODEFAULT:
        return info.default_factory()
    return _NO_DEFAULT


def _default_text(value: Any, source_hex: bool) -> str:
    if value is _NO_DEFAULT:
        return "required"
    if value is None:
        return "`null`"
    if value is msgspec.UNSET:
        return "*unset*"
    if isinstance(value, msgspec.Struct):
        return "(section)"
    if isinstance(value, int) and not isinstance(value, bool) and source_hex:
        return f"`0x{value:02X}`"
    if isinstance(value, (list, tuple, dict)) and not value:
        return "`[]`" if not isinstance(value, dict) else "`{}`"
    return f"`{_yaml(value)}`"


@functools.cache
def _hex_fields(cls: type) -> frozenset[str]:
    """Fields whose default is written in hexadecimal in the source (I2C addresses)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    node = tree.body[0]
    assert isinstance(node, ast.ClassDef)
    source = textwrap.dedent(inspect.getsource(cls))
    out = set()
    for statement in node.body:
        if isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name):
            segment = ast.get_source_segment(source, statement.value) if statement.value else ""
            if segment and segment.lower().startswith("0x"):
                out.add(statement.target.id)
    return frozenset(out)


def rows(document: Document) -> list[Row]:
    """Every key of ``document``, depth first in declaration order."""
    return list(_walk(document, document.root, document.prefix, None, ""))


def _walk(document: Document, cls: type, prefix: str, parent: Any, path: str) -> Iterator[Row]:
    meaning = meanings(cls)
    hex_fields = _hex_fields(cls)
    for info in msgspec.structs.fields(cls):
        key = f"{prefix}{info.encode_name}"
        dotted = f"{path}{info.encode_name}"
        default = _default_of(info, parent)
        text = meaning[info.name]
        members, is_list = _struct_members(info.type)
        shown_elsewhere = [m for m in members if m in document.elsewhere]
        links = list(dict.fromkeys(document.elsewhere[m] for m in shown_elsewhere))
        if dotted in document.see:
            links.append(document.see[dotted])
        for anchor, title in links:
            text = f"{text.rstrip('.')}; its keys: [{title}](#{anchor})"
        yield Row(
            key=f"`{key}`",
            type=type_text(info.type, info.name in hex_fields),
            default=document.defaults.get(dotted)
            or _default_text(default, info.name in hex_fields),
            meaning=text,
        )
        for member in members:
            if member in document.elsewhere:
                continue
            inner = default if isinstance(default, member) else None
            step = "[]." if is_list else "."
            yield from _walk(document, member, f"{key}{step}", inner, f"{dotted}{step}")


# --- the experiment's setting ---------------------------------------------------------------------


def _flatten(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def setting_defaults() -> dict[str, str]:
    """Default text of every experiment key a setting fills in: its value per setting, by
    sensor count where it depends on it (from :func:`minimize_surprise.config.with_setting`)."""
    counts = range(1, len(ALL_SENSORS) + 1)
    values: dict[str, dict[str, dict[int, Any]]] = collections.defaultdict(dict)
    for setting in SETTINGS:
        for n in counts:
            filled = _flatten(with_setting({"setting": setting, "sensors": ["s"] * n}))
            for key, value in filled.items():
                if key not in ("setting", "sensors"):
                    values[key].setdefault(setting, {})[n] = value
    out = {}
    for key, per_setting in values.items():
        parts = []
        for setting in SETTINGS:
            by_count = per_setting[setting]
            common, _ = collections.Counter(map(_yaml, by_count.values())).most_common(1)[0]
            text = f"`{common}`"
            others = collections.defaultdict(list)
            for n, value in by_count.items():
                if _yaml(value) != common:
                    others[_yaml(value)].append(n)
            if others:
                special = "; ".join(f"`{v}` for {_counts(ns)} sensors" for v, ns in others.items())
                text = f"{special}; else {text}"
            parts.append((setting, text))
        if len({text for _, text in parts}) == 1:
            out[key] = parts[0][1]
        else:
            out[key] = "<br>".join(f"{setting}: {text}" for setting, text in parts)
    return out


def _counts(numbers: list[int]) -> str:
    return " or ".join(map(str, numbers))


# --- what a scenario and a setting change ---------------------------------------------------------


def _changes(base: msgspec.Struct, changed: msgspec.Struct) -> str:
    """The keys in which ``changed`` differs from ``base``, as ``key: value`` items."""
    out = []
    for info in msgspec.structs.fields(type(base)):
        new = getattr(changed, info.name)
        if getattr(base, info.name) == new:
            continue
        text = _yaml(new)
        if len(text) > 60:
            out.append(f"`{info.encode_name}` ({len(new)} entries)")
        else:
            out.append(f"`{info.encode_name}: {text}`")
    return ", ".join(out) or "nothing"


def world_changes() -> list[str]:
    """One line per scenario and setting: the world keys that differ from the defaults."""
    return [
        f"- `{scenario}`, setting `{setting}`: "
        + _changes(WorldConfig(), scenario_config(scenario, world_overrides(setting, scenario)))
        for scenario in SCENARIOS
        for setting in SETTINGS
    ]


def safety_changes() -> list[str]:
    """One line per scenario and setting: the safety keys that differ from the defaults."""
    return [
        f"- `{scenario}`, setting `{setting}`: "
        + _changes(SafetyConfig(), safety_config(setting, scenario))
        for scenario in SCENARIOS
        for setting in SETTINGS
    ]


# --- the documents --------------------------------------------------------------------------------

_EXPERIMENT = ("the-experiment-file", "the experiment file")
_SIMULATION = ("the-simulation-section", "the simulation section")
_SAFETY = ("the-safety-section", "the safety section")
_EVENTS = ("the-events", "the events")


class _EventKeys(msgspec.Struct, kw_only=True):
    """Every key of the events, each kind's in its own (the reference's one table of them)."""

    #: what changes: `light-moves`, `boxes-added`, `boxes-removed`, `wall-appears`,
    #: `robots-leave` or `robots-join`
    kind: str
    #: the counted evaluation that is the first in the changed arena (1 .. `evaluations`)
    evaluation: typing.Annotated[int, msgspec.Meta(ge=1)] | None = None
    #: or: the run's served seconds (over its resumptions) after which the change happens
    seconds: typing.Annotated[float, msgspec.Meta(ge=0.0)] | None = None
    #: what a person reads in the report beside the event (default: what it does)
    note: str = ""
    #: `light-moves`: the point under the lamp then, [x, y] metres on the floor
    position: tuple[float, float] | None = None
    #: `boxes-added`, `boxes-removed`, `robots-leave`, `robots-join`: how many
    count: typing.Annotated[int, msgspec.Meta(ge=1)] | None = None
    #: `boxes-added`: [x0, y0, x1, y1] where the boxes appear (default: the whole floor)
    region: tuple[float, float, float, float] | None = None
    #: `boxes-removed`: every box instead of `count`
    all: bool = False
    #: `wall-appears`: one end of the wall, [x, y]; the wall is horizontal or vertical
    start: tuple[float, float] | None = None
    #: `wall-appears`: its other end, [x, y]
    end: tuple[float, float] | None = None


_TELEMETRY = ("the-telemetry-section", "the telemetry section")


def documents() -> list[Document]:
    """The reference's sections, in order."""
    return [
        Document(
            title="The experiment file",
            anchor=_EXPERIMENT[0],
            root=ExperimentConfig,
            intro=(
                "`minimize_surprise.config.ExperimentConfig`, "
                "with `NetworkConfig` under `network` and "
                "`EvolutionConfig` under `evolution`. What defines one experiment, whatever runs "
                "it: `surprise-master sim --config FILE`, the master file's `experiment_file` or "
                "inline `experiment`, a study group's `params` "
                "(example: `deploy/examples/experiment.yaml`). A key the file leaves out is taken "
                "from its `setting` where the default column names both settings "
                "(docs/simulation.md), else from the default shown. The method behind the keys: "
                "docs/method.md."
            ),
            see={"simulation": _SIMULATION, "safety": _SAFETY},
            defaults=setting_defaults(),
            elsewhere={kind: _EVENTS for kind in typing.get_args(ArenaEvent)},
        ),
        Document(
            title="The events",
            anchor=_EVENTS[0],
            root=_EventKeys,
            prefix="events[].",
            intro=(
                "`minimize_surprise.events`: each item of an experiment's `events` is one change "
                "of the arena, its `kind` one of `light-moves`, `boxes-added`, `boxes-removed`, "
                "`wall-appears`, `robots-leave`, `robots-join`, with the keys below that its kind "
                "has (docs/changing-arenas.md). Each needs `evaluation` or `seconds`."
            ),
        ),
        Document(
            title="The simulation section",
            anchor=_SIMULATION[0],
            root=WorldConfig,
            prefix="simulation.",
            intro=(
                "`simulator.scenarios.WorldConfig`: the simulated world, under `simulation:` in an "
                "experiment file (real robots ignore it). Lengths in metres, angles in degrees, "
                "times in seconds, sensor values normalised to [0, 1]; the origin is the carpet's "
                "centre. The defaults below are the structure's own; the experiment's `scenario` "
                "and `setting` change some of them (listed after the table), and the section "
                "overrides both."
            ),
        ),
        Document(
            title="The arena file",
            anchor="the-arena-file",
            root=Arena,
            intro=(
                "`simulator.arenas.Arena`, with `Floor` under `floor`, `Walls` under `walls`, "
                "`BoxField` under `boxes`, `Start` under `start` and `Light` under `light`: one "
                "arena, named by an experiment's `arena` key (a shipped arena's name: "
                + ", ".join(f"`{name}`" for name in shipped_arenas())
                + "; or a file's path). Metres, degrees, the origin at the floor's centre, x along "
                "its width (docs/arenas.md). A key marked *unset* takes the setting's or the "
                "simulation section's default; the experiment's `simulation:` section overrides "
                "what the arena gives."
            ),
        ),
        Document(
            title="The safety section",
            anchor=_SAFETY[0],
            root=SafetyConfig,
            prefix="safety.",
            intro=(
                "`minimize_surprise.safety.SafetyConfig`: "
                "the safety layer, the last step before the "
                "motors (docs/safety.md). A robot's agent file holds its own under `safety:`; an "
                "experiment file's `safety:` section overrides the simulated robots' (real robots "
                "ignore the experiment's). Thresholds are on normalised sensor values, steps are "
                "control steps, speeds normalised wheel speeds. The defaults are the real robots'; "
                "for simulated robots the scenario and setting change some of them (listed after "
                "the table)."
            ),
        ),
        Document(
            title="The agent file",
            anchor="the-agent-file",
            root=AgentConfig,
            intro=(
                "`robot_agent.config.AgentConfig`: one robot's `surprise-agent --config FILE` "
                "(on a robot `/etc/minimize-surprise/agent.yaml`; examples in `deploy/examples/`), "
                "with `MasterConfig` and `ClientTlsConfig` under `master`, `BodyConfig` under "
                "`body` (`ThymioConfig`, `LightSensorConfig`, `ForceSensorConfig`, `MuxConfig`; "
                "docs/thymio.md, docs/sensors.md), `LoopConfig` under `loop` and `BackoffConfig` "
                "under `reconnect`. Relative file names are relative to the file's directory."
            ),
            elsewhere={SafetyConfig: _SAFETY, TelemetryConfig: _TELEMETRY},
        ),
        Document(
            title="The master file",
            anchor="the-master-file",
            root=MasterFileConfig,
            intro=(
                "`master_service.config.MasterConfig`: `surprise-master run --config FILE` "
                "(example: `deploy/examples/master.yaml`), with `ServerTlsConfig` under `tls`. "
                "Relative file names are relative to the file's directory; a run directory keeps "
                "the resolved file (the experiment inline, every path absolute)."
            ),
            elsewhere={ExperimentConfig: _EXPERIMENT, TelemetryConfig: _TELEMETRY},
        ),
        Document(
            title="The inventory file",
            anchor="the-inventory-file",
            root=Inventory,
            intro=(
                "`master_service.inventory.Inventory`, with `Robot` for each item of `robots` "
                "and `Calibration` under its `calibration`: the lab's fleet, named by the master "
                "file's `inventory` (example: `deploy/examples/fleet.yaml`; docs/fleet.md). "
                "Names and marker ids are unique, and a spare must be enabled."
            ),
        ),
        Document(
            title="The telemetry section",
            anchor=_TELEMETRY[0],
            root=TelemetryConfig,
            prefix="telemetry.",
            intro=(
                "`telemetry.config.TelemetryConfig`, with `BackoffConfig` under `reconnect`: the "
                "same optional section in an agent file and in the master file (docs/telemetry.md)."
                " Absent, or without `broker`, telemetry is off."
            ),
        ),
        Document(
            title="The study file",
            anchor="the-study-file",
            root=Study,
            intro=(
                "`studies.spec.Study`, with `Group` for each item of `groups` and `SeedRange` for "
                "a range of seeds: `surprise-study run FILE` (docs/studies.md)."
            ),
        ),
        Document(
            title="The params of recorded groups",
            anchor="the-params-of-recorded-groups",
            root=RecordedParams,
            intro=(
                "`studies.recorded.RecordedParams`: the run directories a `recorded` group reads "
                "(the lab's real-robot runs beside simulated ones; docs/studies.md)."
            ),
        ),
        *_grid_documents(),
    ]


def _grid_documents() -> list[Document]:
    # A grid-world group's params, one table per kind (docs/gridworld.md).
    from gridworld.config import GridRunConfig
    from gridworld.tasks import DamageParams, RandomParams, RerunParams

    kinds = (
        ("grid-evolved and grid-novelty", GridRunConfig,
         "`gridworld.config.GridRunConfig`: an evolution run (also `surprise-grid evolve`'s "
         "options); `grid-novelty` sets `novelty: true`, `grid-qd` (MAP-Elites) "
         "`optimizer: map-elites`"),
        ("grid-random and grid-selected-random", RandomParams,
         "`gridworld.tasks.RandomParams`: one random genome, or the best of `candidates`, scored "
         "as the GA scores a genome"),
        ("grid-rerun", RerunParams,
         "`gridworld.tasks.RerunParams`: an evolved genome run again on another grid"),
        ("grid-damage", DamageParams,
         "`gridworld.tasks.DamageParams`: an evolved genome's structure damaged and repaired"),
    )  # fmt: skip
    return [
        Document(
            title=f"The params of {title} groups",
            anchor=f"the-params-of-{title.replace(' ', '-')}-groups",
            root=root,
            intro=f"{intro} (docs/gridworld.md).",
        )
        for title, root, intro in kinds
    ]


# --- the text -------------------------------------------------------------------------------------

_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")
_DOC = re.compile(r"`?\bdocs/([a-z-]+\.md)`?")


def _markdown(text: str) -> str:
    """Docstring markup as Markdown: ``x`` and :role:`x` become `x`, Python's ``None`` YAML's
    `null`; table pipes escaped."""
    text = _ROLE.sub(r"`\1`", text).replace("``", "`").replace("`None`", "`null`")
    text = _DOC.sub(r"[\1](\1)", text)  # the reference lives in docs/ itself
    return text.replace("|", "\\|")


def _table(document: Document) -> list[str]:
    lines = ["| key | type | default | meaning |", "| --- | --- | --- | --- |"]
    for row in rows(document):
        cells = (row.key, _markdown(row.type), row.default, _markdown(row.meaning))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


_HEADER = f"""\
# Configuration reference

<!-- Generated by `{_COMMAND}` from the configuration's types and
their `#:` comments: do not edit by hand; change the code and run the command again (a test checks
that this file is current). -->

Every configuration file is YAML, decoded into typed structures. An unknown key, a value of the
wrong type or out of range, or a missing required key stops the program before anything starts,
with one message naming the file, the dotted key and what was expected.

How to read the tables: a dotted key `a.b` is the key `b` inside the section `a`; `a[].b` is the
key `b` of each item of the list `a`. `null` is YAML's empty value (`null` or `~`); a section whose
default is `null` is absent unless the file gives it. Types: `number` is any number (integers
included); `[a, b]` is a closed range, `(a, b]` excludes `a`.
"""


def generate() -> str:
    """The whole text of ``docs/configuration.md``."""
    docs = documents()
    out = [_HEADER]
    out.append(
        "Sections: "
        + ", ".join(f"[{d.title.removeprefix('The ')}](#{d.anchor})" for d in docs)
        + ".\n"
    )
    for document in docs:
        out.append(f"## {document.title[0].upper()}{document.title[1:]}\n")
        intro = textwrap.fill(_markdown(document.intro), 100, break_on_hyphens=False)
        out.append(intro + "\n")
        out.append("\n".join(_table(document)) + "\n")
        if document.root is WorldConfig:
            out.append("What a scenario and a setting change in these defaults:\n")
            out.append("\n".join(world_changes()) + "\n")
        if document.root is SafetyConfig:
            out.append("What a scenario and a setting change for the simulated robots:\n")
            out.append("\n".join(safety_changes()) + "\n")
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    """Write the reference, or with ``--check`` exit 1 if the file is not current."""
    parser = argparse.ArgumentParser(
        prog=_COMMAND, description="Generate docs/configuration.md from the typed configuration."
    )
    parser.add_argument(
        "--check", action="store_true", help="do not write; exit 1 if the file is not current"
    )
    parser.add_argument(
        "--output", type=Path, default=DEFAULT_OUTPUT, help=f"default: {DEFAULT_OUTPUT}"
    )
    args = parser.parse_args(argv)
    text = generate()
    if args.check:
        try:
            current = args.output.read_text(encoding="utf-8")
        except OSError:
            current = None
        if current != text:
            print(
                f"{args.output} is not current with the configuration's code: run `{_COMMAND}`",
                file=sys.stderr,
            )
            return 1
        return 0
    args.output.write_text(text, encoding="utf-8")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
