"""Positions of real robots from an overhead tracker, aligned with a run's post-evaluation.

A real robot's trace holds no positions (it does not know where it is); a lab's tracker (a camera
over the arena and a marker on each robot) does. ``surprise-master report RUN --positions FILE``
reads its CSV file and gives each robot's trace the poses a simulated robot's trace holds, so that
the behaviour metrics, classes and the trajectories are those of a simulated run (docs/runs.md).

The file: a header row naming at least the columns ``time`` (seconds, the tracker's clock),
``robot`` (the robot's id in the run, as in ``post_evaluation.json``), ``x``, ``y`` (metres) and
``heading`` (radians); other columns are ignored but ``seen``: a row whose ``seen`` is 0 holds a
pose the tracker filled in for a frame in which it did not see the robot (``surprise-master
track`` writes them, so that its file has every robot in every frame), and is skipped here, so
that the gaps are measured and filled as in any tracker's file. The rows may come in any order.
The frame is the simulator's (``simulator.scenarios``): origin at the centre of the carpet, x to
the right, y up, a robot's position the point between its wheels, its heading counter-clockwise
from the x axis.

Boxes: ``surprise-master track`` writes beside the file the boxes it found when the
post-evaluation started and ended (``runfiles.schema.TrackedBoxes``, named by
:func:`runfiles.schema.tracked_boxes_path`); when that file is there the report takes d_B from it
(:func:`tracked_boxes`), as a simulated run's from ``simulation.json``.

Alignment: the trace's step k was taken at tracker time ``offset + k * step_period``; ``offset``
is the first time in the file unless given. Each robot's samples are interpolated linearly onto
those times, the heading unwrapped first (so a turn through +-pi is not interpolated the long way
round) and wrapped into [-pi, pi) again after. Steps outside the span a robot was tracked take its
first or last tracked pose, as long as they are at most 5 % of its steps (:data:`MIN_COVERAGE`).
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
from collections.abc import Collection, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np

from minimize_surprise.errors import ConfigError
from runfiles import schema
from runfiles.schema import BoxesMoved, TrackedBoxes

__all__ = [
    "COLUMNS",
    "MIN_COVERAGE",
    "Track",
    "TrackedPositions",
    "TrackerError",
    "add_tracked_poses",
    "read_tracker",
    "resample",
    "tracked_boxes",
    "tracked_poses",
]

#: The columns a tracker file must have (any others are ignored).
COLUMNS: Final = ("time", "robot", "x", "y", "heading")
#: The least share of a robot's post-evaluation steps that must lie within the time it was
#: tracked. A tracker started a moment after the robots, or stopped a moment early, should not
#: void a report: 5 % of the paper's 100 s post-evaluation is the 5 s a person needs to press a
#: second button. Beyond that the held poses would cut d_R short and, at the end, most of the
#: window c_o and the clusters are measured over: the report refuses instead of misleading.
MIN_COVERAGE: Final = 0.95
#: Tracker times this close (seconds) to the span's ends count as inside it: the step grid is
#: ``offset + k * step_period`` in floating point, a microsecond is below any tracker's clock.
_EPSILON: Final = 1e-6


class TrackerError(ConfigError):
    """A tracker file that cannot be used: ``file`` names it, ``line`` its line (1 = the header;
    None when the whole file or a robot is at fault), ``column`` the column and ``robot`` the
    robot at fault (each None when it is not one), ``reason`` what was expected."""

    def __init__(
        self,
        reason: str,
        *,
        file: str,
        line: int | None = None,
        column: str | None = None,
        robot: str | None = None,
    ) -> None:
        super().__init__(reason, file=file, key=column)
        self.line = line
        self.column = column
        self.robot = robot
        where = file
        if line is not None:
            where += f", line {line}"
        if column is not None:
            where += f", column '{column}'"
        if robot is not None:
            where += f", robot '{robot}'"
        self.args = (f"{where}: {reason}",)


@dataclass(frozen=True)
class Track:
    """One robot's tracked samples in time order: ``times`` (K,) in seconds of the tracker's
    clock, ``poses`` (K, 3) ``x, y, heading`` with the heading unwrapped (continuous), ``lines``
    (K,) the file's line of each sample."""

    times: np.ndarray
    poses: np.ndarray
    lines: np.ndarray


@dataclass(frozen=True)
class TrackedPositions:
    """The poses of a post-evaluation from a tracker file: ``poses`` per robot, (steps, 3) on the
    trace's step grid as a simulated trace holds them; ``source`` what ``metrics.json`` records
    of where they came from (file, sha256, offset, per robot coverage)."""

    poses: dict[str, np.ndarray]
    source: dict[str, Any]


def read_tracker(
    path: str | Path, robots: Collection[str], *, ignore: Collection[str] = ()
) -> tuple[dict[str, Track], str]:
    """Every robot's :class:`Track` from the tracker file ``path`` and the file's sha256.

    Each of ``robots`` must have at least two samples; rows of the other robots in ``ignore``
    (robots of the run without a trace) are skipped; any other robot is an error. Raises
    :class:`TrackerError` naming the file, line and column or robot at fault.
    """
    name = str(path)
    try:
        raw = Path(path).read_bytes()
        text = raw.decode("utf-8-sig")  # a spreadsheet's byte order mark is not part of a name
    except OSError as exc:
        raise TrackerError(f"cannot read it: {exc.strerror or exc}", file=name) from None
    except UnicodeDecodeError as exc:
        raise TrackerError(f"not a UTF-8 text file: {exc.reason}", file=name) from None
    rows: dict[str, list[tuple[float, float, float, float, int]]] = {r: [] for r in robots}
    lines = _rows(text, name)
    first = next(lines, None)
    if first is None:
        raise TrackerError("the file is empty; expected a header row", file=name, line=1)
    header_line, header = first
    names = [column.strip() for column in header]
    for column in COLUMNS:
        if column not in names:
            raise TrackerError(
                f"the header has no column '{column}' (it needs {', '.join(COLUMNS)})",
                file=name,
                line=header_line,
                column=column,
            )
    index = {column: names.index(column) for column in COLUMNS}
    width = max(index.values()) + 1
    seen = names.index("seen") if "seen" in names else None
    for line, row in lines:
        if not row or not "".join(row).strip():
            continue  # a blank line, as a hand-edited file's last one often is
        if len(row) < width:
            missing = next(c for c in COLUMNS if index[c] >= len(row))
            raise TrackerError(
                f"the row has {len(row)} fields and ends before this column",
                file=name,
                line=line,
                column=missing,
            )
        if seen is not None and seen < len(row) and row[seen].strip() == "0":
            continue  # filled in by the tracker, not seen
        robot = row[index["robot"]].strip()
        if robot not in rows and robot in ignore:
            continue
        if robot not in rows:
            raise TrackerError(
                f"no robot '{robot}' in the run's post-evaluation (it has {', '.join(rows)})",
                file=name,
                line=line,
                column="robot",
            )
        t, x, y, heading = (_number(row[index[c]], name, line, c) for c in COLUMNS if c != "robot")
        rows[robot].append((t, x, y, heading, line))
    tracks = {robot: _track(samples, name, robot) for robot, samples in rows.items()}
    return tracks, hashlib.sha256(raw).hexdigest()


def _rows(text: str, name: str) -> Iterator[tuple[int, list[str]]]:
    # Each row with its line; the csv module's own complaint (a NUL byte, an open quote at the
    # end) is a bad file like any other.
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        for row in reader:
            yield reader.line_num, row
    except csv.Error as exc:
        raise TrackerError(f"not CSV: {exc}", file=name, line=reader.line_num) from None


def _number(text: str, file: str, line: int, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise TrackerError(
            f"'{text}' is not a number", file=file, line=line, column=column
        ) from None
    if not math.isfinite(value):
        raise TrackerError(f"'{text}' is not a finite number", file=file, line=line, column=column)
    return value


def _track(samples: list[tuple[float, float, float, float, int]], file: str, robot: str) -> Track:
    if len(samples) < 2:
        found = f"only line {samples[0][4]}" if samples else "no row"
        raise TrackerError(
            f"has {found}; at least two samples are needed to follow it", file=file, robot=robot
        )
    data = np.array(samples, dtype=float)
    data = data[np.argsort(data[:, 0], kind="stable")]
    same = np.flatnonzero(np.diff(data[:, 0]) == 0)
    keep = np.ones(len(data), dtype=bool)
    for i in same:
        if np.array_equal(data[i, 1:4], data[i + 1, 1:4]):
            keep[i + 1] = False  # the same frame written twice: one sample
            continue
        raise TrackerError(
            f"lines {int(data[i, 4])} and {int(data[i + 1, 4])} place it differently at the same "
            f"time {data[i, 0]:g} s",
            file=file,
            line=int(data[i + 1, 4]),
            column="time",
            robot=robot,
        )
    data = data[keep]
    if len(data) < 2:
        raise TrackerError(
            "has a single time; at least two are needed to follow it", file=file, robot=robot
        )
    poses = data[:, 1:4].copy()
    # Unwrapped, a turn from 3.1 to -3.1 rad is 0.08 rad, not 6.2 rad back the other way; this
    # holds while a robot turns less than pi between two samples (a Thymio II: > 1 s).
    poses[:, 2] = np.unwrap(poses[:, 2])
    return Track(times=data[:, 0], poses=poses, lines=data[:, 4].astype(np.int64))


def resample(track: Track, times: np.ndarray) -> np.ndarray:
    """``track``'s poses at ``times`` (T,), (T, 3), by linear interpolation; outside the tracked
    span the first or last pose. The heading is wrapped into [-pi, pi), as the simulator's."""
    times = np.asarray(times, dtype=float)
    out = np.empty((len(times), 3))
    for axis in range(3):
        out[:, axis] = np.interp(times, track.times, track.poses[:, axis])
    out[:, 2] = (out[:, 2] + math.pi) % (2 * math.pi) - math.pi
    return out


def _largest_gap(times: np.ndarray, grid: np.ndarray) -> float | None:
    # The intervals between samples that overlap the post-evaluation, the ones its poses use.
    if len(grid) == 0:
        return None
    gaps = np.diff(times)
    overlap = (times[1:] > grid[0]) & (times[:-1] < grid[-1])
    return float(gaps[overlap].max()) if overlap.any() else None


def tracked_poses(
    path: str | Path,
    steps: Mapping[str, int],
    step_period: float,
    *,
    offset: float | None = None,
    ignore: Collection[str] = (),
) -> TrackedPositions:
    """The poses of each robot's post-evaluation trace of ``steps[robot]`` steps of
    ``step_period`` seconds, from the tracker file ``path``.

    The trace's first step was taken at tracker time ``offset`` (default: the file's first time
    among those robots). Robots in ``ignore`` may appear in the file and are skipped. Raises
    :class:`TrackerError` for a bad file, and when less than :data:`MIN_COVERAGE` of a robot's
    steps lie within the time it was tracked.
    """
    name = str(path)
    if not steps:
        raise TrackerError(
            "the run has no post-evaluation traces to align positions with", file=name
        )
    tracks, digest = read_tracker(path, list(steps), ignore=ignore)
    start = min(t.times[0] for t in tracks.values()) if offset is None else float(offset)
    poses: dict[str, np.ndarray] = {}
    robots: dict[str, Any] = {}
    for robot, track in tracks.items():
        grid = start + step_period * np.arange(steps[robot])
        inside = (grid >= track.times[0] - _EPSILON) & (grid <= track.times[-1] + _EPSILON)
        coverage = float(inside.mean()) if len(grid) else 1.0
        if coverage < MIN_COVERAGE:
            end = start + step_period * max(steps[robot] - 1, 0)
            raise TrackerError(
                f"tracked from {track.times[0]:g} s to {track.times[-1]:g} s (tracker clock), "
                f"its post-evaluation ran from {start:g} s to {end:g} s: that covers "
                f"{100 * coverage:.1f} % of its steps, at least {100 * MIN_COVERAGE:g} % are "
                "needed (is --positions-offset right?)",
                file=name,
                robot=robot,
            )
        poses[robot] = resample(track, grid)
        robots[robot] = {
            "samples": len(track.times),
            "coverage": coverage,
            "held_steps": int(np.count_nonzero(~inside)),
            # An occluded marker shows as a long gap: its poses are a straight line across it.
            "largest_gap_s": _largest_gap(track.times, grid),
        }
    source = {
        "file": name,
        "sha256": digest,
        "offset_s": start,
        "offset_given": offset is not None,
        "robots": robots,
    }
    return TrackedPositions(poses=poses, source=source)


def add_tracked_poses(
    path: str | Path | None,
    traces: Mapping[str, dict[str, np.ndarray]],
    step_period: float,
    *,
    offset: float | None = None,
    ignore: Collection[str] = (),
) -> dict[str, Any] | None:
    """Put the poses of the tracker file ``path`` into each of a run's post-evaluation
    ``traces`` (robot: arrays as in ``traces/<robot>.npz``) as ``poses``, where a simulated
    trace holds them, replacing any; return :attr:`TrackedPositions.source` (None, and nothing
    done, without a ``path``). See :func:`tracked_poses`."""
    if path is None:
        if offset is not None:
            raise ConfigError("needs --positions, the tracker's file", key="--positions-offset")
        return None
    steps = {robot: len(trace["sensors"]) for robot, trace in traces.items()}
    found = tracked_poses(path, steps, step_period, offset=offset, ignore=ignore)
    for robot, poses in found.poses.items():
        traces[robot]["poses"] = poses
    return found.source


def tracked_boxes(positions: str | Path) -> tuple[BoxesMoved, dict[str, Any]] | None:
    """The boxes found with the tracker file ``positions`` (its
    :func:`~runfiles.schema.tracked_boxes_path`), paired start to end, and what ``metrics.json``
    records of them; None when the tracker wrote no boxes. A file that cannot be read or decoded
    raises :class:`TrackerError` or :class:`runfiles.schema.RunDirError` naming it."""
    path = schema.tracked_boxes_path(positions)
    if not path.is_file():
        return None
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise TrackerError(f"cannot read it: {exc.strerror or exc}", file=str(path)) from None
    found = schema.decode(TrackedBoxes, raw, name=str(path))
    pairs = len(found.boxes.start)
    if len(found.boxes.end) != pairs:
        raise TrackerError(
            f"{pairs} boxes at the start are paired with {len(found.boxes.end)} at the end",
            file=str(path),
            column="boxes",
        )
    source = {
        "file": str(path),
        "sha256": hashlib.sha256(raw).hexdigest(),
        "video": found.source,
        "pairs": pairs,
        "unpaired_start": len(found.unpaired_start),
        "unpaired_end": len(found.unpaired_end),
    }
    return found.boxes, source
