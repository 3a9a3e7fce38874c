"""What ``surprise-master dashboard`` shows, read from a run directory into plain data.

:class:`RunReader` looks at a run directory (rundir.py describes its files) and returns a
:class:`Snapshot`: where the run stands, the fitness curve, one :class:`RobotRow` per robot, the
post-evaluation's trajectories and, while ``surprise-master track --live`` watches the run, where
the overhead camera sees the robots (``camera.json``). It only reads, never writes, and re-reads
a file only when its size, modification time or inode changed since the last look;
``evaluations.csv`` it reads from where it stopped last time, so a poll costs a few ``stat``
calls while nothing happens.

Files are read while a master writes them. The JSON files are replaced atomically, but a file may
be missing (an older run, the fast engine writes no ``live.json``), or hold what this code does
not expect; then the snapshot leaves that part out and names the file in :attr:`Snapshot.problems`
instead of failing. The CSV's last line may be half written: only lines ending in a newline count.

The per-robot columns are discovered, not listed: every ``<key>_<robot id>`` column of the CSV
whose robot id also has a ``fitness_<robot id>`` column, and every key of ``live.json``'s
``robot_state`` entries, becomes a column of the robots' table (``battery_v``, ``overruns``,
``read_failures`` from robots that report them; whatever is added later too). Bokeh is not needed
here: this module is tested on its own (tests/master/test_dashboard_data.py).
"""

from __future__ import annotations

import csv
import math
import os
import time
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from minimize_surprise.errors import SurpriseError
from runfiles import schema
from runfiles.schema import (
    CONFIG_SNAPSHOT,
    EVALUATION_COLUMNS,
    EVALUATIONS,
    STALE_AFTER,
    TRACES,
    CameraView,
    Checkpoint,
    Live,
    PauseFile,
    PauseNote,
    PostEvaluation,
    RunConfig,
    RunFile,
    Simulation,
    master_alive,
)

__all__ = [
    "ACTIVE_WINDOW",
    "MAX_TRACE_POINTS",
    "STALE_AFTER",
    "Curve",
    "Pause",
    "RobotRow",
    "RunReader",
    "Snapshot",
    "Trajectories",
    "parse_value",
    "robot_keys",
]

#: A run without ``live.json`` (the fast engine) counts as running while its checkpoint is younger
#: than this many seconds: it commits every evaluation, which takes well under a second there.
ACTIVE_WINDOW: Final = 10.0
#: Points drawn per robot's trajectory: a 10,000-step post-evaluation thinned to this many still
#: shows every turn at screen resolution, and keeps the page's data small.
MAX_TRACE_POINTS: Final = 2000

#: The order of the robots' table for the columns known today; others follow alphabetically.
_KNOWN_KEYS: Final = ("fitness", "safety_share", "battery_v", "overruns", "read_failures")

#: A cell of the CSV or a value of a JSON file, as :func:`parse_value` reads it.
Value = int | float | str | None


def parse_value(text: str) -> Value:
    """A CSV cell as a number where it is one: ``""`` is None (unknown), ``"3"`` 3, ``"0.5"`` 0.5,
    anything else the text itself."""
    if text == "":
        return None
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def robot_keys(header: Sequence[str]) -> tuple[list[str], list[str]]:
    """The robots and the per-robot keys of an ``evaluations.csv`` header: robots are the ids of
    the ``fitness_<id>`` columns, keys every prefix ``<key>`` of a ``<key>_<id>`` column."""
    robots = [c.removeprefix("fitness_") for c in header if c.startswith("fitness_")]
    keys: set[str] = set()
    for column in header:
        if column in EVALUATION_COLUMNS:
            continue
        key = _split_robot_column(column, robots)
        if key is not None:
            keys.add(key[0])
    return robots, _ordered(keys)


def _split_robot_column(column: str, robots: Sequence[str]) -> tuple[str, str] | None:
    # The longest matching id wins: robot ids may themselves hold underscores ("lab_1", "lab_11").
    found = [r for r in robots if column.endswith("_" + r) and len(column) > len(r) + 1]
    if not found:
        return None
    robot = max(found, key=len)
    return column[: -len(robot) - 1], robot


def _ordered(keys: set[str]) -> list[str]:
    known = [k for k in _KNOWN_KEYS if k in keys]
    return known + sorted(keys - set(_KNOWN_KEYS))


@dataclass(frozen=True)
class Pause:
    """A pause of the run: one line for a person, the robots concerned (none: the swarm)."""

    reason: str
    robots: tuple[str, ...] = ()
    since: float | None = None


@dataclass(frozen=True)
class RobotRow:
    """One robot's line: ``connected`` is None when unknown (no master, the fast engine);
    ``values`` holds the raw text of each key (as in the CSV: exact, for a test to compare) and
    ``numbers`` the parsed value."""

    robot: str
    connected: bool | None
    values: dict[str, str] = field(default_factory=dict)
    numbers: dict[str, Value] = field(default_factory=dict)


@dataclass(frozen=True)
class Curve:
    """The fitness over the counted evaluations; ``generation`` changes whenever earlier points
    changed (the CSV was cut back on resume or replaced), so a plot redraws instead of appending."""

    generation: int
    evaluation: list[int]
    fitness: list[float]
    best_fitness: list[float]


@dataclass(frozen=True)
class Trajectories:
    """The post-evaluation's paths: per robot the thinned x and y (metres), the steps, and the
    carpet's side when ``simulation.json`` gives it (centred on the origin)."""

    xs: dict[str, list[float]]
    ys: dict[str, list[float]]
    steps: int
    arena_side: float | None
    signature: tuple[Any, ...]
    #: the carpet's extent along y when it is not square
    arena_height: float | None = None


@dataclass(frozen=True)
class Snapshot:
    """Everything the dashboard shows, as read at :attr:`read_at` (see the module docstring)."""

    name: str
    read_at: float
    #: ``not started``, ``evolution``, ``post-evaluation`` or ``done``
    phase: str
    #: ``running``, ``waiting for robots``, ``paused``, ``finished``, ``stopped``, ``not started``
    state: str
    evaluations: int
    planned: int | None
    best_fitness: str | None
    #: the last counted row of evaluations.csv, raw text by column
    last_row: dict[str, str] | None
    time_left_s: float | None
    pause: Pause | None
    master: str | None
    robots: list[RobotRow]
    keys: list[str]
    curve: Curve
    post_fitness: float | None
    post_robots: dict[str, dict[str, Value]]
    trajectories: Trajectories | None
    problems: list[str]
    #: where an overhead camera sees the robots now (``track --live``), while its file is fresh
    camera: CameraView | None = None


class _Csv:
    """``evaluations.csv``, read incrementally: the header, every complete row."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.header: list[str] | None = None
        self.rows: list[list[str]] = []
        #: each row's (evaluation, fitness, best fitness), None where a cell is not a number
        self.points: list[tuple[int, float, float] | None] = []
        self.generation = 0
        self._ino: int | None = None
        self._offset = 0
        self._last_line = b""

    def _reset(self) -> None:
        if self.header is not None or self.rows:
            self.generation += 1
        self.header, self.rows, self.points = None, [], []
        self._ino, self._offset, self._last_line = None, 0, b""

    def update(self) -> None:
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            self._reset()
            return
        if self._ino is not None and (st.st_ino != self._ino or st.st_size < self._offset):
            self._reset()
        if st.st_size == self._offset:
            return
        with open(self.path, "rb") as file:
            if self._last_line:
                # A resume cuts the rows past the checkpoint and appends others: what was read
                # last must still be there, or everything is read again.
                file.seek(self._offset - len(self._last_line))
                if file.read(len(self._last_line)) != self._last_line:
                    self._reset()
                    file.seek(0)
            data = file.read()
        self._ino = st.st_ino
        complete = data[: data.rfind(b"\n") + 1]  # a half-written last line waits for next time
        if not complete:
            return
        self._offset += len(complete)
        lines = complete.decode("utf-8", errors="replace").splitlines()
        self._last_line = (lines[-1] + "\n").encode("utf-8")
        for cells in csv.reader(lines):
            if self.header is None:
                self.header = cells
            elif len(cells) == len(self.header):  # a damaged line is left out, not guessed at
                self.rows.append(cells)
                self.points.append(_point(self.header, cells))


def _point(header: Sequence[str], cells: Sequence[str]) -> tuple[int, float, float] | None:
    row = dict(zip(header, cells, strict=True))
    try:
        return int(row["evaluation"]), float(row["fitness"]), float(row["best_fitness"])
    except (KeyError, ValueError):
        return None


class _Watched:
    """A file re-read only when its (inode, size, mtime) changes; a read that fails keeps the
    last good value and is tried again at the next look."""

    def __init__(self, path: Path, load: Callable[[Path], Any]) -> None:
        self.path = path
        self._load = load
        self._key: tuple[int, int, int] | None = None
        self.value: Any = None
        self.problem: str | None = None

    def update(self) -> bool:
        """Look again; True when the value changed."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            changed = self.value is not None
            self._key, self.value, self.problem = None, None, None
            return changed
        key = (st.st_ino, st.st_size, st.st_mtime_ns)
        if key == self._key:
            return False
        try:
            self.value = self._load(self.path)
        except (OSError, SurpriseError) as exc:
            self.problem = f"{self.path.name}: {exc}"
            return False
        self._key, self.problem = key, None
        return True


def _file(kind: type[RunFile]) -> Callable[[Path], Any]:
    def load(path: Path) -> Any:
        return schema.decode(kind, path.read_bytes(), name=path.name)

    return load


def _config(path: Path) -> RunConfig:
    return schema.read_config(path.parent)


def _thin(points: np.ndarray) -> np.ndarray:
    step = max(1, math.ceil(len(points) / MAX_TRACE_POINTS))
    thinned = points[::step]
    if len(points) and (len(points) - 1) % step:
        thinned = np.concatenate([thinned, points[-1:]])  # the path ends where the robot stopped
    return thinned


class RunReader:
    """Reads one run directory into :class:`Snapshot` objects (see the module docstring)."""

    def __init__(self, path: str | Path, clock: Callable[[], float] = time.time) -> None:
        self.path = Path(path)
        self._clock = clock
        self._csv = _Csv(self.path / EVALUATIONS)
        self._config = _Watched(self.path / CONFIG_SNAPSHOT, _config)
        self._checkpoint = _Watched(self.path / Checkpoint.FILE, _file(Checkpoint))
        self._live = _Watched(self.path / Live.FILE, _file(Live))
        self._pause = _Watched(self.path / PauseFile.FILE, _file(PauseFile))
        self._post = _Watched(self.path / PostEvaluation.FILE, _file(PostEvaluation))
        self._simulation = _Watched(self.path / Simulation.FILE, _file(Simulation))
        self._camera = _Watched(self.path / CameraView.FILE, _file(CameraView))
        self._traces_key: tuple[Any, ...] = ()
        self._trajectories: Trajectories | None = None

    def read(self) -> Snapshot:
        """Look at the run directory again and return what it holds now."""
        problems: list[str] = []
        files = (self._config, self._checkpoint, self._live, self._pause, self._post)
        # The checkpoint before the CSV: the CSV then holds at least the rows it counts.
        for watched in (*files, self._simulation, self._camera):
            watched.update()
        try:
            self._csv.update()
        except OSError as exc:
            problems.append(f"{EVALUATIONS}: {exc}")
        problems += [w.problem for w in (*files, self._simulation, self._camera) if w.problem]
        try:
            trajectories = self._read_trajectories()
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            problems.append(f"{TRACES}: {exc}")  # a trace copied in by hand, cut short
            trajectories = self._trajectories
        return self._snapshot(trajectories, problems)

    # -- the pieces --------------------------------------------------------------------------

    def _snapshot(self, trajectories: Trajectories | None, problems: list[str]) -> Snapshot:
        now = self._clock()
        checkpoint: Checkpoint | None = self._checkpoint.value
        live: Live | None = self._live.value
        post: PostEvaluation | None = self._post.value
        config: RunConfig | None = self._config.value
        header = self._csv.header or []
        rows = self._csv.rows
        counted = None if checkpoint is None else checkpoint.csv_rows
        if counted is not None and 0 <= counted <= len(rows):
            rows = rows[:counted]  # a row past the checkpoint is not counted yet (rundir.py)
        last = dict(zip(header, rows[-1], strict=True)) if rows else None
        evaluations = len(rows) if checkpoint is None else checkpoint.evaluations
        fresh = master_alive(live, now)
        pause = _pause(self._pause.value or (live.paused if fresh and live is not None else None))
        phase = "not started" if checkpoint is None else checkpoint.phase
        best = last.get("best_fitness") if last else None
        if best is None and checkpoint is not None and checkpoint.best_fitness is not None:
            best = repr(checkpoint.best_fitness)
        post_robots = _post_robots(post)
        robots, keys = self._robots(header, last, live, fresh, checkpoint, post_robots)
        return Snapshot(
            name=self.path.resolve().name,
            read_at=now,
            phase=phase,
            state=_state(phase, fresh, live, pause, checkpoint, now),
            evaluations=evaluations,
            planned=None
            if config is None or config.experiment is None
            else config.experiment.evolution.evaluations,
            best_fitness=best,
            last_row=last,
            time_left_s=_number(live.time_left_s) if fresh and live is not None else None,
            pause=pause,
            master=f"{live.host}:{live.port} (pid {live.pid})"
            if fresh and live is not None
            else None,
            robots=robots,
            keys=keys,
            curve=_curve(self._csv.points[: len(rows)], self._csv.generation),
            post_fitness=None if post is None else _number(post.swarm_fitness),
            post_robots=post_robots,
            trajectories=trajectories,
            problems=problems,
            camera=_fresh_camera(self._camera.value, now),
        )

    def _robots(
        self,
        header: Sequence[str],
        last: Mapping[str, str] | None,
        live: Live | None,
        fresh: bool,
        checkpoint: Checkpoint | None,
        post_robots: Mapping[str, Any],
    ) -> tuple[list[RobotRow], list[str]]:
        csv_robots, csv_keys = robot_keys(header)
        # A master that stopped has no robot connected; without live.json nobody knows.
        state = live.robot_state if fresh and live is not None else {}
        connected = None if live is None else live.robots if fresh else []
        roster = [] if checkpoint is None or checkpoint.roster is None else checkpoint.roster
        names = _unique([*roster, *csv_robots, *(connected or []), *state, *post_robots])
        keys = set(csv_keys)
        table = []
        for robot in names:
            values: dict[str, str] = {}
            if last is not None:
                for key in csv_keys:
                    text = last.get(f"{key}_{robot}")
                    if text is not None:
                        values[key] = text
            # While the master runs its robot_state is newer than the last row.
            for key, value in _mapping(state.get(robot)).items():
                keys.add(str(key))
                values[str(key)] = "" if value is None else str(value)
            table.append(
                RobotRow(
                    robot=str(robot),
                    connected=None if connected is None else robot in map(str, connected),
                    values=values,
                    numbers={k: parse_value(v) for k, v in values.items()},
                )
            )
        return table, _ordered(keys)

    def _read_trajectories(self) -> Trajectories | None:
        directory = self.path / TRACES
        try:
            entries = sorted(
                (e for e in os.scandir(directory) if e.name.endswith(".npz")), key=lambda e: e.name
            )
        except FileNotFoundError:
            self._traces_key, self._trajectories = (), None
            return None
        stats = [(e.name, e.stat()) for e in entries]
        simulation: Simulation | None = self._simulation.value
        side = None if simulation is None else simulation.world.arena_side
        height = None if simulation is None else simulation.world.arena_height
        key = (*((n, s.st_size, s.st_mtime_ns) for n, s in stats), side, height)
        if key == self._traces_key:
            return self._trajectories
        xs: dict[str, list[float]] = {}
        ys: dict[str, list[float]] = {}
        steps = 0
        for name, _ in stats:
            with np.load(directory / name) as npz:
                if "poses" not in npz.files:
                    continue  # a real robot's trace: it does not know where it is
                poses = np.asarray(npz["poses"], dtype=np.float64)
            if poses.ndim != 2 or poses.shape[1] < 2 or not len(poses):
                continue
            steps = max(steps, len(poses))
            path = _thin(poses[:, :2])
            xs[name.removesuffix(".npz")] = path[:, 0].tolist()
            ys[name.removesuffix(".npz")] = path[:, 1].tolist()
        self._traces_key = key
        self._trajectories = (
            Trajectories(xs, ys, steps, _number(side), signature=key, arena_height=_number(height))
            if xs
            else None
        )
        return self._trajectories


def _fresh_camera(view: CameraView | None, now: float) -> CameraView | None:
    # A tracker that stopped leaves its last view behind: show it only while it is rewritten.
    if view is None or not 0 <= now - view.updated_at <= STALE_AFTER:
        return None
    return view


def _mapping(value: Any) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


def _unique(items: Sequence[Any]) -> list[str]:
    return list(dict.fromkeys(str(item) for item in items))


def _pause(note: PauseNote | None) -> Pause | None:
    if note is None:
        return None
    return Pause(
        reason=note.reason or note.kind or "paused",
        robots=tuple(note.robots),
        since=note.since if isinstance(note, PauseFile) else None,
    )


def _state(
    phase: str,
    fresh: bool,
    live: Live | None,
    pause: Pause | None,
    checkpoint: Checkpoint | None,
    now: float,
) -> str:
    if phase == "done":
        return "finished"
    if pause is not None:
        return "paused"
    if fresh and live is not None:
        return "waiting for robots" if live.waiting else "running"
    if live is not None:
        return "stopped"  # a master wrote live.json, and is gone
    if checkpoint is not None and now - checkpoint.written_at < ACTIVE_WINDOW:
        return "running"
    return "not started" if checkpoint is None else "stopped"


def _post_robots(post: PostEvaluation | None) -> dict[str, dict[str, Value]]:
    robots: dict[str, dict[str, Value]] = {}
    for robot, entry in ({} if post is None else post.robots).items():
        steps = entry.stats.steps_run
        share = None
        if steps > 0:
            share = sum(entry.stats.interventions.values()) / steps
        robots[robot] = {"fitness": _number(entry.fitness), "safety_share": share}
    return robots


def _curve(points: Sequence[tuple[int, float, float] | None], generation: int) -> Curve:
    kept = [p for p in points if p is not None]
    return Curve(
        generation,
        [p[0] for p in kept],
        [p[1] for p in kept],
        [p[2] for p in kept],
    )
