"""Every file of a run directory, as typed and versioned structures: the one definition that the
master, ``status``, ``report``, the dashboard, the replay and the studies write and read.

Why one file of over 600 lines: it is the run directory's one definition, every file side by side
with its format, so that a change to one is made where the others are seen, and the schema's
tests find every file by walking one module's structures.

Layout (docs/runs.md shows each file)::

    config.yaml            the resolved master configuration (experiment inline, paths absolute);
                           readers below the master read the part they need as RunConfig
    checkpoint.json        Checkpoint: the commit point, evolution state and run bookkeeping
    evaluations.csv        one row per counted evaluation (EVALUATION_COLUMNS, format_row)
    best_genome.json       BestGenome: the current best genome, its fitness and network shape
    master.log             the master's log
    live.json              Live: while a master serves the run (master_alive says if it still does)
    pause.json             PauseFile: while the run waits for a person
    events.jsonl           Event lines: what happened when (the experimenter's escapes, the
                           post-evaluation's start, the swarm's changes), appended by the master
    requests/              EscapeRequest, SwapRequest and StopRequest files a person's command
                           drops for the running master
    post_evaluation.json   PostEvaluation: the post-evaluation's per-robot fitness and statistics
    traces/<robot>.npz     the post-evaluation trace of each robot
    metrics.json, plots/   written by ``surprise-master report`` (and at the end of ``sim``)
    simulation.json        Simulation: in simulation, the world, and the boxes before and after
                           the post-evaluation
    box_track.npz          in simulation with boxes: the boxes during the post-evaluation
    tracked_positions.csv  a real run: the robots' poses an overhead camera tracked
                           (``surprise-master track``; the columns in reporting.tracker)
    tracked_positions.boxes.json
                           TrackedBoxes: the boxes the camera found at the post-evaluation's
                           start and end, beside the positions' file (tracked_boxes_path)
    camera.json            CameraView: while ``surprise-master track --live`` watches the run,
                           where the camera sees the robots now (the dashboard shows it)
    replay.json            Replay: in a replay's directory, where its genome came from
    qd.json                QDSummary: a MAP-Elites run (``sim --optimizer map-elites``): its
                           experiment, progress and each class's best elite; beside it
                           archive.csv, qd_progress.csv, qd_checkpoint.pkl and elites/<class>/
                           (docs/quality-diversity.md)
    software.json          SoftwareRecord: the master's software, and each robot's software and
                           Thymio firmware as it last joined (docs/fleet.md)

Versions. Each JSON file carries its ``format``, the version of its structure here (a file written
before formats were written down has none and counts as format 1). :func:`read` decodes a file of
any format this version knows and refuses a newer one with a message naming both versions; when a
structure changes, its ``FORMAT`` goes up and :func:`read` learns to read the old one (or to
refuse it by name). Unknown keys are ignored, so an older reader still reads a file that only
gained keys.

Whether a master still serves a run is decided in one place, :func:`master_alive`: it says
``running``, it rewrote the file within :data:`STALE_AFTER` seconds, and its process exists when it
names one on this machine.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Final, Literal, TypeVar

import msgspec

from minimize_surprise import files
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import FileWriteError, SurpriseError
from minimize_surprise.network import NetworkSpec
from minimize_surprise.wire import EvaluationStats

__all__ = [
    "ARCHIVE",
    "BASELINE_FILE",
    "BOX_TRACK",
    "CAMERA_INTERVAL",
    "CONFIG_SNAPSHOT",
    "EVALUATIONS",
    "EVALUATION_COLUMNS",
    "EVENTS",
    "EVENT_ARENA",
    "EVENT_ESCAPE",
    "EVENT_FLEET_STOP",
    "EVENT_MARK",
    "EVENT_POST_EVALUATION",
    "EVENT_SWARM_CHANGE",
    "LIVE_INTERVAL",
    "LOG",
    "METRICS",
    "PLOTS",
    "QD_CHECKPOINT",
    "QD_ELITES",
    "QD_PROGRESS",
    "QD_PROGRESS_COLUMNS",
    "REQUESTS",
    "ROBOT_STAT_PREFIXES",
    "STALE_AFTER",
    "SWARM_COLUMN",
    "TRACES",
    "BestGenome",
    "BoxesMoved",
    "CameraPose",
    "CameraView",
    "Checkpoint",
    "EscapeRequest",
    "Event",
    "Live",
    "MarkRequest",
    "PauseFile",
    "PauseNote",
    "Phase",
    "PostEvaluation",
    "PostRobot",
    "QDElite",
    "QDSummary",
    "Replay",
    "RunConfig",
    "RunDirError",
    "RunFile",
    "SimulatedWorld",
    "Simulation",
    "Software",
    "SoftwareRecord",
    "StopRequest",
    "SwapRequest",
    "SwarmChange",
    "TrackedBoxes",
    "append_event",
    "decode",
    "encode",
    "evaluation_header",
    "format_row",
    "load_baseline",
    "master_alive",
    "read",
    "read_config",
    "read_events",
    "read_if_readable",
    "read_rows",
    "render_row",
    "robot_stat_columns",
    "row_cells",
    "tracked_boxes_path",
    "widen_header",
    "write",
    "write_atomic",
    "writing",
]

CONFIG_SNAPSHOT: Final = "config.yaml"
EVALUATIONS: Final = "evaluations.csv"
LOG: Final = "master.log"
TRACES: Final = "traces"
METRICS: Final = "metrics.json"
PLOTS: Final = "plots"
#: In simulation with boxes: where the boxes were during the post-evaluation (``positions``
#: (frames, boxes, 2) in metres, a frame every ``every`` steps).
BOX_TRACK: Final = "box_track.npz"
#: A baseline's results in its output directory (``surprise-master baseline``).
BASELINE_FILE: Final = "baseline.json"
#: What happened to the run when, one :class:`Event` a line, appended by the master.
EVENTS: Final = "events.jsonl"
#: Where a person's command drops its requests for the running master (:class:`EscapeRequest`).
REQUESTS: Final = "requests"
#: Event kinds: the experimenter asked for a robot's escape, and how it went.
EVENT_ESCAPE: Final = "escape"
#: Event kinds: ``surprise-master fleet stop`` stopped every robot's motors and paused the run.
EVENT_FLEET_STOP: Final = "fleet-stop"
#: Event kinds: an attempt of the post-evaluation went out to the robots (they flash).
EVENT_POST_EVALUATION: Final = "post-evaluation-start"
#: Event kinds: the swarm changed (a robot gone, a spare swapped in), or a swap was refused.
EVENT_SWARM_CHANGE: Final = "swarm-change"
#: Event kinds: one of the experiment's ``events`` changed the arena (docs/changing-arenas.md).
EVENT_ARENA: Final = "arena-change"
#: Event kinds: a person marked something they did (``surprise-master mark``).
EVENT_MARK: Final = "mark"

#: How often a master rewrites live.json at the least.
LIVE_INTERVAL: Final = 2.0
#: A live.json that says ``running`` but is older than this is a master that died: five missed
#: refreshes are no hiccup.
STALE_AFTER: Final = 5 * LIVE_INTERVAL
#: How often a live tracker rewrites camera.json at the most: the dashboard polls about once a
#: second, and a robot moves 2 cm in this time; more writes would only cost the disk.
CAMERA_INTERVAL: Final = 0.2

#: A MAP-Elites run's archive: one row per elite (cell, fitness, measures, class, genome as a
#: JSON list), written when the run ends.
ARCHIVE: Final = "archive.csv"
#: A MAP-Elites run's progress, one row per batch (:data:`QD_PROGRESS_COLUMNS`).
QD_PROGRESS: Final = "qd_progress.csv"
QD_PROGRESS_COLUMNS: Final = ("evaluations", "coverage", "qd_score", "best_fitness", "classes")
#: A MAP-Elites run's checkpoint: the pickled scheduler (archive, emitters, their random
#: numbers) and the progress so far; only ever read by the same software's resume.
QD_CHECKPOINT: Final = "qd_checkpoint.pkl"
#: A MAP-Elites run's post-evaluated elites: one replay run directory per behaviour class.
QD_ELITES: Final = "elites"

#: Where a run stands: evolving, post-evaluating the best genome, or finished.
Phase = Literal["evolution", "post-evaluation", "done"]


class RunDirError(SurpriseError, RuntimeError):
    """The run directory cannot be used: it exists already, a file of it cannot be read, or its
    files contradict each other."""


# -- writing ---------------------------------------------------------------------------------


@contextlib.contextmanager
def writing(path: Path) -> Iterator[None]:
    """Inside, an OSError is a :class:`FileWriteError` naming ``path``."""
    try:
        yield
    except FileWriteError:
        raise
    except OSError as exc:
        raise FileWriteError.from_os_error(str(path), exc) from exc


def write_atomic(
    path: str | Path, data: bytes, *, durable: bool = True, mode: int | None = None
) -> None:
    """:func:`minimize_surprise.files.write_atomic`, whose OSError is a :class:`FileWriteError`
    naming ``path`` (the error itself may name the temporary file)."""
    with writing(Path(path)):
        files.write_atomic(path, data, durable=durable, mode=mode)


# -- the JSON files --------------------------------------------------------------------------


class RunFile(msgspec.Struct, frozen=True, kw_only=True):
    """A JSON file of the run directory: ``FILE`` is its name, ``FORMAT`` the version written.

    The ``format`` key is added when the file is written and checked when it is read; it is not
    a field, so that a structure is the file's data only.
    """

    FILE: ClassVar[str]
    FORMAT: ClassVar[int]
    #: indentation of the written JSON (None: one line), as each file has always been written
    INDENT: ClassVar[int | None] = None
    #: keys left out when they hold None, for files that never wrote them as null
    OMIT_NONE: ClassVar[tuple[str, ...]] = ()


class PauseNote(RunFile, frozen=True, kw_only=True):
    """Why a run waits: ``kind`` (``battery`` or ``before-post-evaluation``), one line for a
    person (``reason``), the robots concerned (none: the whole swarm)."""

    FILE: ClassVar[str] = "pause.json"
    FORMAT: ClassVar[int] = 1

    kind: str
    reason: str
    robots: list[str] = msgspec.field(default_factory=list)


class PauseFile(PauseNote, frozen=True, kw_only=True):
    """``pause.json``: the pause, and since when (seconds since the epoch)."""

    since: float


class Live(RunFile, frozen=True, kw_only=True):
    """``live.json``: written by a master serving robots, first once it accepts connections,
    then after every change and at least every :data:`LIVE_INTERVAL` seconds; ``running`` false
    once it stopped."""

    FILE: ClassVar[str] = "live.json"
    FORMAT: ClassVar[int] = 1

    pid: int
    running: bool
    host: str
    port: int
    #: the robots connected now
    robots: list[str]
    phase: Phase
    #: waiting for robots to connect
    waiting: bool
    evaluations: int
    time_left_s: float | None
    paused: PauseNote | None
    #: per robot what it reported last (``battery_v``, ``overruns``, ``read_failures``, ...)
    robot_state: dict[str, dict[str, Any]]
    updated_at: float


class SwarmChange(msgspec.Struct, frozen=True, kw_only=True):
    """One change of a run's swarm (``checkpoint.json``'s ``swarms``): from counted evaluation
    ``from_evaluation`` on the swarm is ``robots``; robot ``left`` was gone for good, ``joined``
    the spare that took its place (None: the run went on without it, ``min_robots``); ``time``
    when (seconds since the epoch)."""

    from_evaluation: int
    robots: list[str]
    left: str
    joined: str | None = None
    time: float = 0.0


class Checkpoint(RunFile, frozen=True, kw_only=True):
    """``checkpoint.json``: the commit point (rundir.py says how a commit is made exactly once).

    ``optimizer`` is :meth:`minimize_surprise.evolution.OnePlusOne.state` (versioned on its
    own); ``simulation`` a simulated run's world and robots at this commit, so that it resumes
    exactly. ``swarms`` the swarm's changes in order (a robot gone for good, a spare swapped
    in), ``roster`` being the swarm after the last; left out while the swarm never changed, so
    a run's checkpoint reads as it did before swaps existed.
    """

    FILE: ClassVar[str] = "checkpoint.json"
    FORMAT: ClassVar[int] = 1
    OMIT_NONE: ClassVar[tuple[str, ...]] = ("swarms", "events_applied")

    run_id: str
    phase: Phase
    next_evaluation_id: int
    attempts: int
    failed_attempts: int
    #: how many rows of evaluations.csv this state accounts for
    csv_rows: int
    #: the swarm's robot ids once fixed (the CSV's per-robot columns)
    roster: list[str] | None
    elapsed_s: float = 0.0
    written_at: float = 0.0
    optimizer: dict[str, Any] = msgspec.field(default_factory=dict)
    simulation: dict[str, Any] | None = None
    swarms: list[SwarmChange] | None = None
    #: the experiment's events (their indexes in its ``events``) that happened, in order
    events_applied: list[int] | None = None

    @property
    def evaluations(self) -> int:
        """The evaluations counted."""
        value = self.optimizer.get("evaluations", 0)
        return value if isinstance(value, int) else 0

    @property
    def best_fitness(self) -> float | None:
        """The best genome's fitness, None before the first evaluation."""
        value = self.optimizer.get("best_fitness")
        return float(value) if isinstance(value, int | float) else None


class BestGenome(RunFile, frozen=True, kw_only=True):
    """``best_genome.json``: the best genome (bit-exact floats), its current fitness, the counted
    evaluation that found it, and its network's shape."""

    FILE: ClassVar[str] = "best_genome.json"
    FORMAT: ClassVar[int] = 1

    evaluation: int
    fitness: float
    genome: list[float]
    spec: NetworkSpec


class PostRobot(msgspec.Struct, frozen=True, kw_only=True):
    """One robot's post-evaluation: its fitness, statistics, and its trace's path in the run
    (None where it sent none)."""

    fitness: float
    stats: EvaluationStats
    trace: str | None = None


class PostEvaluation(RunFile, frozen=True, kw_only=True):
    """``post_evaluation.json``: the best genome's post-evaluation, robot by robot.

    ``started_at`` is the wall-clock time (seconds since the epoch, the master's clock) at which
    the counted attempt went out to the robots, which flash their top LED as it starts: an
    overhead camera's tracker aligns its video by it. None in a file written before it existed.
    """

    FILE: ClassVar[str] = "post_evaluation.json"
    FORMAT: ClassVar[int] = 1
    INDENT: ClassVar[int | None] = 2
    OMIT_NONE: ClassVar[tuple[str, ...]] = ("started_at",)

    evaluation_id: int
    steps: int
    #: the genome's fitness during evolution
    genome_fitness: float | None
    #: the mean of the robots' fitness in the post-evaluation
    swarm_fitness: float | None
    robots: dict[str, PostRobot]
    started_at: float | None = None


class SimulatedWorld(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    """The simulated world of a run: the carpet's side (metres; its extent along x), robots and
    boxes; ``arena_height`` the carpet's extent along y when it is not square (written only
    then, so a square world's file reads as before), ``arena`` the arena's name when the
    experiment named one."""

    arena_side: float
    robots: int
    boxes: int
    arena_height: float | None = None
    arena: str | None = None

    @property
    def carpet(self) -> tuple[float, float]:
        """The carpet's (width, height), metres."""
        return self.arena_side, self.arena_side if self.arena_height is None else self.arena_height


class BoxesMoved(msgspec.Struct, frozen=True, kw_only=True):
    """Where the boxes were when the post-evaluation began and ended, ``[x, y]`` in metres."""

    start: list[list[float]]
    end: list[list[float]]


class Simulation(RunFile, frozen=True, kw_only=True):
    """``simulation.json``: the run is simulated, on which engine, in which world; written when
    the run starts (so that ``resume`` restarts the simulated robots) and again at its end."""

    FILE: ClassVar[str] = "simulation.json"
    FORMAT: ClassVar[int] = 1
    OMIT_NONE: ClassVar[tuple[str, ...]] = ("post_evaluation_boxes", "post_evaluation_safety")

    scenario: str
    setting: str
    engine: Literal["fast", "agents"] = "agents"
    realtime: bool = False
    world: SimulatedWorld
    post_evaluation_boxes: BoxesMoved | None = None
    #: every robot's safety state when the post-evaluation began (a replay starts from it)
    post_evaluation_safety: list[list[int]] | None = None


class TrackedBoxes(RunFile, frozen=True, kw_only=True):
    """``<positions>.boxes.json`` beside a tracker's positions file (:func:`tracked_boxes_path`):
    the boxes an overhead camera found on the floor when the post-evaluation started and ended.
    ``boxes`` pairs them (``start[i]`` went to ``end[i]``, metres) so that the sum of the
    distances is least, as boxes carry no identity; boxes found only at one end are left out of
    the pairs and listed in ``unpaired_start`` and ``unpaired_end``."""

    FILE: ClassVar[str] = "tracked_positions.boxes.json"
    FORMAT: ClassVar[int] = 1
    INDENT: ClassVar[int | None] = 2

    #: the video (or camera) the boxes were found in
    source: str
    #: seconds after the post-evaluation's start of the frames the boxes were found in
    start_time_s: float
    end_time_s: float
    boxes: BoxesMoved
    unpaired_start: list[list[float]] = msgspec.field(default_factory=list)
    unpaired_end: list[list[float]] = msgspec.field(default_factory=list)


class CameraPose(msgspec.Struct, frozen=True, kw_only=True):
    """Where an overhead camera sees one robot: ``x``, ``y`` (metres, the arena's frame) and
    ``heading`` (radians, counter-clockwise from x)."""

    x: float
    y: float
    heading: float


class CameraView(RunFile, frozen=True, kw_only=True):
    """``camera.json``: while ``surprise-master track --live`` watches a run, where the camera
    sees the robots now (those seen in its latest frame), rewritten at most every
    :data:`CAMERA_INTERVAL` seconds; the dashboard shows it while it is fresh
    (:data:`STALE_AFTER`)."""

    FILE: ClassVar[str] = "camera.json"
    FORMAT: ClassVar[int] = 1

    #: the camera (a device's index) or the video
    source: str
    #: the floor between the corner markers, (width, height) in metres around the origin
    floor: tuple[float, float]
    #: the frame's time in the video (seconds from its first frame)
    video_time: float
    robots: dict[str, CameraPose]
    #: wall-clock time of the write (``time.time()``)
    updated_at: float


def tracked_boxes_path(positions: str | Path) -> Path:
    """The boxes' file that goes with the tracker's positions file ``positions``:
    ``tracked_positions.csv`` has ``tracked_positions.boxes.json`` beside it."""
    path = Path(positions)
    return path.with_name(f"{path.stem}.boxes.json")


class Replay(RunFile, frozen=True, kw_only=True):
    """``replay.json``, in a replay's directory: the genome's file, its run, its fitness."""

    FILE: ClassVar[str] = "replay.json"
    FORMAT: ClassVar[int] = 1
    INDENT: ClassVar[int | None] = 2

    source: str
    source_run: str | None
    genome_fitness: float | None


class QDElite(msgspec.Struct, frozen=True, kw_only=True):
    """A behaviour class's best elite in a MAP-Elites archive and its post-evaluation."""

    #: the elite's fitness (its one evaluation) and its measures there
    fitness: float
    measures: dict[str, float]
    #: its replay's directory below the run's (None until post-evaluated)
    directory: str | None = None
    #: the post-evaluation's swarm fitness and the behaviour class it showed there
    post_fitness: float | None = None
    post_class: str | None = None


class QDSummary(RunFile, frozen=True, kw_only=True):
    """``qd.json``: a MAP-Elites run's experiment (what resume reads), where it stands, and at
    its end the archive's figures and each behaviour class's best elite."""

    FILE: ClassVar[str] = "qd.json"
    FORMAT: ClassVar[int] = 1
    INDENT: ClassVar[int | None] = 2

    experiment: ExperimentConfig
    done: bool = False
    evaluations: int = 0
    cells: int = 0
    coverage: float = 0.0
    qd_score: float = 0.0
    seconds: float = 0.0
    #: behaviour class -> its best elite (the classes of docs/quality-diversity.md)
    classes: dict[str, QDElite] = msgspec.field(default_factory=dict)


class Software(msgspec.Struct, frozen=True, kw_only=True):
    """One installation's software: the package's ``version``, the source's ``commit``
    (``minimize_surprise.provenance``; None: unknown) and, for a robot, its Thymio's
    ``firmware`` (``_fwversion[0]``; None: unknown or none)."""

    version: str
    commit: str | None
    firmware: int | None = None


class SoftwareRecord(RunFile, frozen=True, kw_only=True):
    """``software.json``: what ran the run. The ``master``'s software (as this run's master
    last started) and each robot's as it last joined, since when (``joined_at``, seconds since
    the epoch); rewritten when a robot joins with other software than before."""

    FILE: ClassVar[str] = "software.json"
    FORMAT: ClassVar[int] = 1

    master: Software
    robots: dict[str, Software] = msgspec.field(default_factory=dict)
    joined_at: dict[str, float] = msgspec.field(default_factory=dict)


class MarkRequest(RunFile, frozen=True, kw_only=True):
    """A request of ``surprise-master mark``: a person made a change (``text``) the running
    master is to note in ``events.jsonl`` with the evaluation it happened at, as an
    :class:`Event` of kind ``mark`` naming the same ``token`` (see :class:`EscapeRequest`)."""

    FILE: ClassVar[str] = "mark-request.json"
    FORMAT: ClassVar[int] = 1

    text: str
    token: str
    #: when the person asked (seconds since the epoch)
    requested_at: float


class EscapeRequest(RunFile, frozen=True, kw_only=True):
    """A request of ``surprise-master escape`` for the running master: robot ``robot`` is to run
    its safety layer's escape now. Written as ``requests/escape-<token>.json`` (``FILE`` is the
    name's pattern, the token unique per request); the master takes it away and appends an
    :class:`Event` of kind ``escape`` naming the same ``token``, the answer the command waits
    for."""

    FILE: ClassVar[str] = "escape-request.json"
    FORMAT: ClassVar[int] = 1

    robot: str
    token: str
    #: when the person asked (seconds since the epoch)
    requested_at: float


class SwapRequest(RunFile, frozen=True, kw_only=True):
    """A request of ``surprise-master swap`` for the running master: spare ``spare`` is to take
    the place of ``gone`` in the swarm. Written as ``requests/swap-request-<token>.json``; the
    master takes it away and appends an :class:`Event` of kind ``swarm-change`` naming the same
    ``token``, the answer the command waits for."""

    FILE: ClassVar[str] = "swap-request.json"
    FORMAT: ClassVar[int] = 1

    gone: str
    spare: str
    token: str
    #: when the person asked (seconds since the epoch)
    requested_at: float


class StopRequest(RunFile, frozen=True, kw_only=True):
    """A request of ``surprise-master fleet stop --run`` for the running master: every robot's
    motors are to stop now and the run to pause. Written as ``requests/stop-request-<token>.json``;
    the master takes it away and appends an :class:`Event` of kind ``fleet-stop`` naming the same
    ``token``, the answer the command waits for."""

    FILE: ClassVar[str] = "stop-request.json"
    FORMAT: ClassVar[int] = 1

    token: str
    #: when the person asked (seconds since the epoch)
    requested_at: float


class Event(msgspec.Struct, frozen=True, kw_only=True):
    """One line of ``events.jsonl``: something that happened to the run, at ``time`` (seconds
    since the epoch, the master's clock).

    ``escape``: the experimenter asked for ``robot``'s escape (``request`` the token of the
    :class:`EscapeRequest`); ``accepted`` whether the robot's safety layer starts it at its next
    step, in evaluation ``evaluation_id``, or why not (``detail``, one line).
    ``post-evaluation-start``: attempt ``evaluation_id`` of the post-evaluation went out to the
    robots, which flash their top LED at its first step (``post_evaluation.json``'s
    ``started_at`` is the one that counted).
    ``swarm-change``: ``robot`` left the swarm for good from counted evaluation
    ``evaluation_id`` on, ``joined`` the spare that took its place (none: the run goes on
    without it); asked by ``surprise-master swap`` (``request`` its token), ``accepted`` says
    whether the swarm changed, or why not (``detail``).
    ``fleet-stop``: ``surprise-master fleet stop`` asked (``request`` its token); the robots
    that ``confirmed`` their motors stopped and those that did not answer (``unanswered``);
    ``accepted`` when every robot confirmed.
    ``arena-change``: the experiment's event ``index`` (``detail`` what it did) happened after
    ``evaluation`` counted evaluations, the run served ``seconds`` seconds.
    ``mark``: a person marked ``detail`` (``surprise-master mark``, ``request`` its token) after
    ``evaluation`` counted evaluations.
    """

    #: the version of a line's structure; each line carries it as ``format``
    FORMAT: ClassVar[int] = 1

    time: float
    kind: str
    robot: str | None = None
    request: str | None = None
    accepted: bool | None = None
    evaluation_id: int | None = None
    detail: str = ""
    joined: str | None = None
    confirmed: list[str] | None = None
    unanswered: list[str] | None = None
    #: counted evaluations before it (``arena-change``, ``mark``)
    evaluation: int | None = None
    #: the run's served seconds then (``arena-change``, ``mark``)
    seconds: float | None = None
    #: the experiment's event (its index in ``events``) of an ``arena-change``
    index: int | None = None


def append_event(run_dir: str | Path, event: Event) -> None:
    """Append ``event`` as one line of ``events.jsonl`` (created if need be). One ``write`` of a
    whole line, so that a reader never sees half of one; not synced: a log, not a commit."""
    plain = {key: value for key, value in msgspec.to_builtins(event).items() if value is not None}
    line = json.dumps({"format": Event.FORMAT, **plain}) + "\n"
    path = Path(run_dir) / EVENTS
    with writing(path), open(path, "a", encoding="utf-8") as file:
        file.write(line)


def read_events(run_dir: str | Path) -> list[Event]:
    """Every event of ``events.jsonl`` in order (none when there is no file); a line this
    version cannot read (torn, a newer format) is skipped, as a log reader should."""
    try:
        text = (Path(run_dir) / EVENTS).read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    except OSError as exc:
        raise RunDirError(f"{Path(run_dir) / EVENTS} cannot be read: {exc}") from None
    events = []
    for line in text.splitlines():
        try:
            data = json.loads(line)
            version = data.pop("format", 1)
            if not isinstance(version, int) or version > Event.FORMAT:
                continue
            events.append(msgspec.convert(data, Event))
        except (ValueError, AttributeError, msgspec.ValidationError):
            continue
    return events


class RunConfig(msgspec.Struct, frozen=True, kw_only=True):
    """What a reader below the master needs of ``config.yaml`` (the master's whole configuration,
    ``master_service.config.MasterConfig``): the experiment, the swarm's size and the fleet's
    inventory."""

    experiment: ExperimentConfig | None = None
    expected_robots: int | None = None
    #: the fleet's inventory file the master file named (absolute), None when it named none
    inventory: str | None = None

    @property
    def robot_count(self) -> int | None:
        """How many robots form the swarm, None when the snapshot does not say."""
        if self.expected_robots is not None:
            return self.expected_robots
        return None if self.experiment is None else self.experiment.robots


_F = TypeVar("_F", bound=RunFile)


def encode(data: RunFile) -> bytes:
    """The file's bytes: ``format`` first, then the structure's fields in order."""
    plain = msgspec.to_builtins(data)
    for key in data.OMIT_NONE:
        if plain.get(key) is None:
            plain.pop(key, None)
    text = json.dumps({"format": data.FORMAT, **plain}, indent=data.INDENT)
    return text.encode("utf-8")


def write(run_dir: str | Path, data: RunFile, *, durable: bool = True) -> None:
    """Write ``data`` as its file of ``run_dir``, atomically."""
    write_atomic(Path(run_dir) / data.FILE, encode(data), durable=durable)


def decode(kind: type[_F], raw: bytes | str, *, name: str | None = None) -> _F:
    """Decode one file's text as ``kind``; :class:`RunDirError` naming the file (``name``), the
    key or the format when it is not one this version reads."""
    name = name or kind.FILE
    try:
        data = json.loads(raw)
    except ValueError as exc:
        raise RunDirError(f"{name} is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise RunDirError(f"{name} holds no object")
    version = data.pop("format", 1)
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise RunDirError(f"{name}: format {version!r} is not a version")
    if version > kind.FORMAT:
        raise RunDirError(
            f"{name} is format {version}, written by a newer minimize-surprise; this one reads "
            f"{kind.__name__} up to format {kind.FORMAT}: upgrade it to read this run"
        )
    try:
        return msgspec.convert(data, kind)
    except msgspec.ValidationError as exc:
        raise RunDirError(f"{name} cannot be read (format {version}): {exc}") from None


def read(run_dir: str | Path, kind: type[_F]) -> _F | None:
    """The file ``kind.FILE`` of ``run_dir`` as ``kind``; None when it does not exist.

    A file that exists but cannot be decoded raises :class:`RunDirError` naming it.
    """
    path = Path(run_dir) / kind.FILE
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise RunDirError(f"{path} cannot be read: {exc}") from None
    return decode(kind, raw, name=str(path))


def read_if_readable(run_dir: str | Path, kind: type[_F]) -> _F | None:
    """:func:`read` for a reader that only shows what it finds: None also for a file this
    version cannot decode (a newer format, a file copied in by hand)."""
    try:
        return read(run_dir, kind)
    except RunDirError:
        return None


def read_config(run_dir: str | Path) -> RunConfig:
    """The part of ``config.yaml`` a reader needs (:class:`RunConfig`); a ConfigError names the
    file and the key, a RunDirError a directory that is no run."""
    from minimize_surprise.config import load_yaml

    path = Path(run_dir) / CONFIG_SNAPSHOT
    if not path.is_file():
        raise RunDirError(f"{run_dir} is not a run directory: {CONFIG_SNAPSHOT} is missing")
    return load_yaml(path, RunConfig)


def master_alive(live: Live | None, now: float) -> bool:
    """Whether the master that wrote ``live`` still serves the run at ``now``: the one rule of
    ``status``, the dashboard and every other reader.

    It must say ``running`` and have rewritten the file within :data:`STALE_AFTER` seconds; a
    process id of this machine's that is gone means a master that died (one elsewhere, in a
    copied run, cannot be asked: the file's age decides). Only a positive id is asked about:
    ``os.kill`` of 0 or a negative id asks about process groups, which always answer.
    """
    if live is None or not live.running or now - live.updated_at > STALE_AFTER:
        return False
    if live.pid > 0:
        try:
            os.kill(live.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            pass  # another user's process: alive
    return True


# -- evaluations.csv -------------------------------------------------------------------------

#: The fixed columns of ``evaluations.csv``; one ``fitness_<robot id>`` column per robot follows,
#: then with robots (not the compiled engine) :func:`robot_stat_columns`.
EVALUATION_COLUMNS: Final = (
    "evaluation",
    "kind",
    "fitness",
    "best_fitness",
    "accepted",
    "attempts",
    "duration_s",
    "safety_share",
)

#: The per-robot statistics robots report, each a column per robot after the fitness columns.
ROBOT_STAT_PREFIXES: Final = ("battery_v_", "overruns_", "read_failures_")
#: The column added when a run's swarm first changes (:func:`widen_header`): which swarm
#: evaluated the row, 0 the first, then one more per change (``Checkpoint.swarms``). A run
#: whose swarm never changed has no such column: every row was the first swarm's.
SWARM_COLUMN: Final = "swarm"


def evaluation_header(roster: Sequence[str], *, robot_stats: bool) -> list[str]:
    """The header of a new ``evaluations.csv`` for the swarm ``roster``."""
    header = [*EVALUATION_COLUMNS, *(f"fitness_{robot}" for robot in roster)]
    return header + (robot_stat_columns(roster) if robot_stats else [])


def robot_stat_columns(roster: Sequence[str]) -> list[str]:
    """The per-robot statistics' columns: every robot's battery, then overruns, read failures."""
    return [f"{prefix}{robot}" for prefix in ROBOT_STAT_PREFIXES for robot in roster]


def format_row(
    evaluation: int,
    kind: str,
    fitness: float,
    best_fitness: float,
    accepted: bool,
    attempts: int,
    duration_s: float,
    safety_share: float,
    robot_fitness: Iterable[float],
    robot_stats: Sequence[EvaluationStats] | None = None,
) -> str:
    """One line of ``evaluations.csv``; floats in repr form so they read back bit for bit.

    ``robot_stats`` (the robots' in roster order) fills :func:`robot_stat_columns`; None for a
    file without them.
    """
    fields = [
        str(evaluation),
        kind,
        repr(float(fitness)),
        repr(float(best_fitness)),
        "true" if accepted else "false",
        str(attempts),
        f"{duration_s:.3f}",
        f"{safety_share:.4f}",
        *(repr(float(f)) for f in robot_fitness),
    ]
    if robot_stats is not None:
        fields += ["" if s.battery_v is None else f"{s.battery_v:.3f}" for s in robot_stats]
        fields += [str(s.overruns) for s in robot_stats]
        fields += [str(s.read_failures) for s in robot_stats]
    return ",".join(fields) + "\n"


def row_cells(
    evaluation: int,
    kind: str,
    fitness: float,
    best_fitness: float,
    accepted: bool,
    attempts: int,
    duration_s: float,
    safety_share: float,
    robots: Sequence[str],
    robot_fitness: Sequence[float],
    robot_stats: Sequence[EvaluationStats] | None = None,
    swarm: int = 0,
) -> dict[str, str]:
    """One row of ``evaluations.csv`` by column, for :func:`render_row`: the cells
    :func:`format_row` writes, each robot's named by its id in ``robots``, and the swarm's
    number (:data:`SWARM_COLUMN`)."""
    names = [*EVALUATION_COLUMNS, *(f"fitness_{robot}" for robot in robots)]
    values = format_row(
        evaluation,
        kind,
        fitness,
        best_fitness,
        accepted,
        attempts,
        duration_s,
        safety_share,
        robot_fitness,
        robot_stats,
    )
    if robot_stats is not None:
        names += robot_stat_columns(robots)
    cells = dict(zip(names, values.rstrip("\n").split(","), strict=True))
    cells[SWARM_COLUMN] = str(swarm)
    return cells


def render_row(cells: Mapping[str, str], header: Sequence[str]) -> str:
    """``cells`` as a line of a file with ``header``: a column the row has no cell for (a robot
    not in its swarm) is left empty, a cell the header has no column for is dropped."""
    return ",".join(cells.get(column, "") for column in header) + "\n"


def widen_header(header: Sequence[str], roster: Sequence[str], *, robot_stats: bool) -> list[str]:
    """``header`` with the columns a swarm of ``roster`` needs and it lacks, at the end (a spare
    that joined: its fitness, then its statistics), and :data:`SWARM_COLUMN`; the same header
    when it has them all. Readers find columns by name, so the order does not matter."""
    wanted = evaluation_header(roster, robot_stats=robot_stats)
    wider = list(header)
    wider += [column for column in wanted if column not in header]
    if SWARM_COLUMN not in wider:
        wider.append(SWARM_COLUMN)
    return wider


def read_rows(run_dir: str | Path) -> list[dict[str, str]]:
    """The rows of ``evaluations.csv`` as dicts of strings (empty if there is none); a torn last
    line is read as it stands (a commit's count, ``Checkpoint.csv_rows``, says which rows hold)."""
    path = Path(run_dir) / EVALUATIONS
    try:
        with open(path, encoding="utf-8", newline="") as file:
            return list(csv.DictReader(file))
    except FileNotFoundError:
        return []


# -- a baseline's directory ------------------------------------------------------------------


def load_baseline(path: str | Path) -> dict[str, Any]:
    """``baseline.json`` of a ``surprise-master baseline`` directory (or the file itself): the
    random pairs' results, as written by ``master_service.experiments.baseline``."""
    path = Path(path)
    if path.is_dir():
        path = path / BASELINE_FILE
    return json.loads(path.read_text(encoding="utf-8"))
