"""The run directory: everything a run leaves behind, written so that a crash loses nothing.

Layout::

    config.yaml            the resolved master configuration (experiment inline, paths absolute)
    checkpoint.json        the commit point: evolution state and run bookkeeping (atomic)
    evaluations.csv        one row per counted evaluation (see EVALUATION_COLUMNS)
    best_genome.json       the current best genome with its fitness and network spec
    master.log             the master's log
    live.json              while the master runs: pid, address, connected robots (refreshed)
    pause.json             while the run waits for a person: why, which robots, since when
    post_evaluation.json   the post-evaluation's per-robot fitness and statistics
    traces/<robot>.npz     the post-evaluation trace of each robot
    metrics.json, plots/   written by ``surprise-master report`` (and at the end of ``sim``)
    simulation.json        in simulation: the world, and the boxes before and after the
                           post-evaluation
    box_track.npz          in simulation with boxes: the boxes during the post-evaluation

Exactly-once rows: a commit first appends the new row to ``evaluations.csv`` and fsyncs it, then
replaces ``checkpoint.json`` (temp file, fsync, rename, fsync of the directory). The checkpoint
records how many rows it accounts for; on resume the CSV is cut back to that many rows, so a crash
between the two writes neither loses nor duplicates a row.

The run holds no secret: every file gets the permissions ``open()`` gives (``0644`` under the
usual umask), so that the lab's group can read a run as it reads ``evaluations.csv``.

A file that cannot be written (a full disk, a directory made read-only) raises
:class:`~minimize_surprise.errors.FileWriteError` naming that file, never the temporary name of an
atomic write; a line ``master.log`` cannot take is kept back as such an error (:class:`RunLog`) and
raised by the next commit. Either way the run stops with its last checkpoint on disk, and resumes
from it once the disk takes writes again.

The ``attempts`` column counts the attempts sent for that evaluation (an attempt in flight when the
master stopped counts too), ``duration_s`` is the time from the counted attempt's Evaluate to its
last Result, ``safety_share`` the share of the robots' steps in which the safety layer changed the
network's command, and ``fitness_<robot id>`` holds each robot's fitness, the swarm's
``fitness`` being their mean. With robots (not the compiled engine) three more columns per robot
follow (:func:`robot_stat_columns`): ``battery_v_<robot id>``, the battery read after the
evaluation (empty where the robot does not report one), ``overruns_<robot id>``, the control steps
that missed their deadline, and ``read_failures_<robot id>``, the sensor reads that failed or
timed out. A run started before these columns existed keeps its own header on resume.
The ``kind`` column holds ``initial`` for the first row (the random
initial genome is neither an offspring nor a re-evaluation), then ``offspring`` or
``reevaluation``.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal

import msgspec
import numpy as np
import yaml

from master_service.config import MasterConfig
from minimize_surprise import files
from minimize_surprise.config import ExperimentConfig, load_yaml
from minimize_surprise.errors import ConfigError, FileWriteError, SurpriseError
from minimize_surprise.evolution import EvolutionStateError, OnePlusOne
from minimize_surprise.network import NetworkSpec
from minimize_surprise.wire import EvaluationStats, Result

__all__ = [
    "BASELINE_FILE",
    "BEST_GENOME",
    "BOX_TRACK",
    "CHECKPOINT",
    "CONFIG_SNAPSHOT",
    "EVALUATIONS",
    "EVALUATION_COLUMNS",
    "FILE_ONLY",
    "LIVE",
    "LOG",
    "METRICS",
    "PAUSE",
    "PLOTS",
    "POST_EVALUATION",
    "ROBOT_STAT_PREFIXES",
    "SIMULATION_FILE",
    "TRACES",
    "Phase",
    "RunDir",
    "RunDirError",
    "RunLog",
    "RunState",
    "evaluation_header",
    "for_console",
    "format_row",
    "load_baseline",
    "robot_stat_columns",
    # the run directory's writers, for the modules that write files into a run
    "write_atomic",
    "writing",
]

#: A baseline's results in its output directory (``surprise-master baseline``).
BASELINE_FILE: Final = "baseline.json"
CONFIG_SNAPSHOT: Final = "config.yaml"
CHECKPOINT: Final = "checkpoint.json"
EVALUATIONS: Final = "evaluations.csv"
BEST_GENOME: Final = "best_genome.json"
LOG: Final = "master.log"
LIVE: Final = "live.json"
#: While a run waits for a person: why, and which robots (master_service.pause).
PAUSE: Final = "pause.json"
POST_EVALUATION: Final = "post_evaluation.json"
TRACES: Final = "traces"
METRICS: Final = "metrics.json"
#: Written by ``surprise-master sim``: how the run is simulated (scenario, setting, engine) and
#: the boxes before and after the post-evaluation.
SIMULATION_FILE: Final = "simulation.json"
#: Written by ``surprise-master sim`` in an arena with boxes: where the boxes were during the
#: post-evaluation (``positions`` (frames, boxes, 2) in metres, a frame every ``every`` steps).
BOX_TRACK: Final = "box_track.npz"
PLOTS: Final = "plots"

#: The fixed columns of ``evaluations.csv``; one ``fitness_<robot id>`` column per robot follows.
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

#: Version of checkpoint.json's shape; bump when it changes.
CHECKPOINT_FORMAT: Final = 1

#: Where a run stands: evolving, post-evaluating the best genome, or finished.
Phase = Literal["evolution", "post-evaluation", "done"]

#: ``extra`` of a log call whose line belongs in master.log but not on the console, where the
#: command line says the same thing in its own last line.
FILE_ONLY: Final = {"file_only": True}


class RunDirError(SurpriseError, RuntimeError):
    """The run directory cannot be used: it exists already, or its files contradict each other."""


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


def for_console(record: logging.LogRecord) -> bool:
    """A filter for console handlers: drops the lines logged with :data:`FILE_ONLY`."""
    return not getattr(record, "file_only", False)


class RunLog(logging.FileHandler):
    """The handler writing a run's ``master.log``.

    Logging's handlers print a traceback to stderr for every line they cannot write: on a full
    disk, one per line logged. This one keeps the first such error as :attr:`error` (a
    :class:`FileWriteError` naming the log) and says nothing; :meth:`RunDir.commit` raises it.
    """

    def __init__(self, path: Path) -> None:
        with writing(path):
            super().__init__(path, encoding="utf-8")
        self.path = path
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        #: the first line that could not be written, as the error to stop the run with
        self.error: FileWriteError | None = None

    def handleError(self, record: logging.LogRecord) -> None:
        exc = sys.exc_info()[1]
        if not isinstance(exc, OSError):
            super().handleError(record)  # a bug in a log call: logging's own report
        elif self.error is None:
            self.error = FileWriteError.from_os_error(str(self.path), exc)

    def close(self) -> None:
        # Closing flushes what a full disk refused again; that error is known already.
        with contextlib.suppress(OSError):
            super().close()


@dataclass
class RunState:
    """What the checkpoint holds: the optimizer and the run's bookkeeping.

    ``next_evaluation_id`` is the id the next attempt will get (the master reserves an id before
    the commit that precedes its attempt; a resumed master skips one more, as the commit of the
    attempt in flight may not have reached the disk). ``attempts`` counts the attempts started
    for the current candidate (or post-evaluation), ``failed_attempts`` all attempts of the run
    that did not count. ``csv_rows`` is the number of rows of ``evaluations.csv`` this state
    accounts for. ``roster`` is the swarm's robot ids once fixed (the CSV's per-robot columns).
    """

    run_id: str
    optimizer: OnePlusOne
    phase: Phase = "evolution"
    next_evaluation_id: int = 0
    attempts: int = 0
    failed_attempts: int = 0
    csv_rows: int = 0
    roster: list[str] | None = None
    elapsed_s: float = 0.0
    #: a simulated run's world and robots at this commit, so that it resumes exactly
    simulation: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        """The checkpoint's plain data."""
        return {
            "format": CHECKPOINT_FORMAT,
            "run_id": self.run_id,
            "phase": self.phase,
            "next_evaluation_id": self.next_evaluation_id,
            "attempts": self.attempts,
            "failed_attempts": self.failed_attempts,
            "csv_rows": self.csv_rows,
            "roster": self.roster,
            "elapsed_s": self.elapsed_s,
            "written_at": time.time(),
            "optimizer": self.optimizer.state(),
            "simulation": self.simulation,
        }

    @classmethod
    def from_json(cls, config: MasterConfig, data: dict[str, Any]) -> RunState:
        """Rebuild the state written by :meth:`to_json`; raises :class:`RunDirError`."""
        assert config.experiment is not None
        try:
            if data["format"] != CHECKPOINT_FORMAT:
                raise RunDirError(f"checkpoint format {data['format']} is not supported")
            phase = data["phase"]
            if phase not in ("evolution", "post-evaluation", "done"):
                raise RunDirError(f"unknown phase {phase!r} in the checkpoint")
            return cls(
                run_id=str(data["run_id"]),
                optimizer=OnePlusOne.from_state(config.experiment.evolution, data["optimizer"]),
                phase=phase,
                next_evaluation_id=int(data["next_evaluation_id"]),
                attempts=int(data["attempts"]),
                failed_attempts=int(data["failed_attempts"]),
                csv_rows=int(data["csv_rows"]),
                roster=None if data["roster"] is None else [str(r) for r in data["roster"]],
                elapsed_s=float(data.get("elapsed_s", 0.0)),
                simulation=data.get("simulation"),
            )
        except (KeyError, TypeError, ValueError, EvolutionStateError) as exc:
            raise RunDirError(f"the checkpoint cannot be read: {exc}") from None


#: The per-robot statistics robots report, each a column per robot after the fitness columns.
ROBOT_STAT_PREFIXES: Final = ("battery_v_", "overruns_", "read_failures_")


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


class RunDir:
    """The files of one run (see the module docstring); every method is blocking file I/O."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._csv: Any = None
        self._log: RunLog | None = None

    def file(self, name: str) -> Path:
        """The path of a file of the run directory."""
        return self.path / name

    # -- creating and opening --------------------------------------------------------------

    def check_new(self) -> None:
        """Raise :class:`RunDirError` unless the directory is absent or empty."""
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise RunDirError(
                f"{self.path} exists and is not empty: choose another --out, or continue that run "
                f"with `surprise-master resume {self.path}`"
            )

    def create(self, config: MasterConfig) -> None:
        """Make the directory and write the configuration snapshot."""
        self.check_new()
        self.path.mkdir(parents=True, exist_ok=True)
        text = yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False)
        write_atomic(self.file(CONFIG_SNAPSHOT), text.encode("utf-8"))

    def load_config(self) -> MasterConfig:
        """The configuration snapshot (a ConfigError names the snapshot and the key)."""
        path = self.file(CONFIG_SNAPSHOT)
        if not path.is_file():
            raise RunDirError(f"{self.path} is not a run directory: {CONFIG_SNAPSHOT} is missing")
        return load_yaml(path, MasterConfig)

    def check_experiment(self, experiment: ExperimentConfig | None) -> None:
        """Raise ConfigError unless ``experiment`` is the one this run was started with (a
        resumed run must go on with the same experiment, or its rows would not belong together)."""
        if self.load_config().experiment != experiment:
            raise ConfigError(
                "the experiment differs from the one this run was started with",
                file=str(self.file(CONFIG_SNAPSHOT)),
                key="experiment",
            )

    def read_checkpoint_data(self) -> dict[str, Any] | None:
        """The checkpoint's plain data, or None before the first commit."""
        path = self.file(CHECKPOINT)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        try:
            return json.loads(text)
        except ValueError as exc:
            # Cannot happen with atomic writes unless the file was edited by hand.
            raise RunDirError(f"{path} is not valid JSON: {exc}") from None

    def read_state(self, config: MasterConfig) -> RunState | None:
        """The checkpointed :class:`RunState`, or None before the first commit."""
        data = self.read_checkpoint_data()
        return None if data is None else RunState.from_json(config, data)

    def csv_header(self) -> list[str] | None:
        """The header of ``evaluations.csv`` as written, None while it has none."""
        try:
            with open(self.file(EVALUATIONS), encoding="utf-8", newline="") as file:
                line = file.readline()
        except FileNotFoundError:
            return None
        return line.rstrip("\r\n").split(",") if line.endswith("\n") else None

    def prepare_resume(self, state: RunState) -> None:
        """Cut ``evaluations.csv`` back to the rows the checkpoint accounts for.

        Rows past that count were written by a commit that did not complete; they will be
        written again. Fewer rows than counted means the file was damaged: RunDirError.
        """
        path = self.file(EVALUATIONS)
        if not path.exists():
            if state.csv_rows:
                raise RunDirError(f"{path} is missing but the checkpoint counts {state.csv_rows}")
            return
        data = path.read_bytes()
        lines = data.splitlines(keepends=True)
        # Only complete lines count: a torn last line (no newline) is dropped too.
        complete = [line for line in lines if line.endswith(b"\n")]
        rows = max(len(complete) - 1, 0)
        if rows < state.csv_rows:
            raise RunDirError(
                f"{path} holds {rows} evaluations but the checkpoint counts {state.csv_rows}"
            )
        keep = sum(len(line) for line in complete[: 1 + state.csv_rows]) if state.csv_rows else 0
        if keep != len(data):
            with writing(path), open(path, "r+b") as file:
                file.truncate(keep)
                file.flush()
                os.fsync(file.fileno())

    # -- committing --------------------------------------------------------------------------

    def commit(self, state_json: dict[str, Any], row: str | None, header: Sequence[str]) -> None:
        """Append ``row`` (if any) to the CSV durably, then write the checkpoint atomically.

        ``state_json`` must already count the row (``csv_rows``). ``header`` is written before
        the first row. A line the log could not take since is raised first
        (:class:`FileWriteError`), so a run stops when its disk is full even if the commit itself
        would still fit.
        """
        if self._log is not None and self._log.error is not None:
            raise self._log.error
        if row is not None:
            with writing(self.file(EVALUATIONS)):
                self._append_row(row, header)
        write_atomic(self.file(CHECKPOINT), json.dumps(state_json).encode("utf-8"))

    def _append_row(self, row: str, header: Sequence[str]) -> None:
        if self._csv is None:
            self._csv = open(self.file(EVALUATIONS), "a", encoding="utf-8", newline="")  # noqa: SIM115
        if self._csv.tell() == 0:
            self._csv.write(",".join(header) + "\n")
        self._csv.write(row)
        self._csv.flush()
        os.fsync(self._csv.fileno())

    def close(self) -> None:
        """Close the CSV file if open."""
        if self._csv is not None:
            csv_file, self._csv = self._csv, None
            # What a full disk refused is flushed once more; a torn row is past the checkpoint's
            # count, and resume cuts it.
            with contextlib.suppress(OSError):
                csv_file.close()

    def open_log(self, logger: logging.Logger) -> RunLog:
        """Write ``logger``'s lines to ``master.log`` (appending) until :meth:`close_log`."""
        self._log = RunLog(self.file(LOG))
        logger.addHandler(self._log)
        return self._log

    def close_log(self, logger: logging.Logger) -> None:
        """Stop writing ``logger``'s lines to ``master.log`` and close it."""
        if self._log is not None:
            logger.removeHandler(self._log)
            self._log.close()
            self._log = None

    # -- artefacts ---------------------------------------------------------------------------

    def write_best(
        self, genome: np.ndarray, fitness: float, evaluation: int, spec: NetworkSpec
    ) -> None:
        """Write ``best_genome.json``: genome (repr floats, bit-exact), fitness, evaluation, spec.

        ``evaluation`` is the counted evaluation that found the genome (its row in
        ``evaluations.csv``), not how many have been counted; ``fitness`` is its current one,
        re-evaluations included. Not fsynced: the checkpoint holds the same genome and it is
        rewritten on resume.
        """
        data = {
            "evaluation": evaluation,
            "fitness": float(fitness),
            "genome": [float(x) for x in np.asarray(genome, dtype=np.float64)],
            "spec": msgspec.to_builtins(spec),
        }
        write_atomic(self.file(BEST_GENOME), json.dumps(data).encode("utf-8"), durable=False)

    def write_live(self, data: dict[str, Any]) -> None:
        """Write ``live.json`` (not durable: it only describes the running process)."""
        write_atomic(self.file(LIVE), json.dumps(data).encode("utf-8"), durable=False)

    def read_json(self, name: str) -> Any | None:
        """A JSON file of the run directory, or None if absent or unreadable."""
        try:
            return json.loads(self.file(name).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    def write_post_evaluation(
        self,
        evaluation_id: int,
        genome_fitness: float | None,
        steps: int,
        results: dict[str, Result],
    ) -> None:
        """Write every robot's trace to ``traces/<robot>.npz`` and the summary JSON."""
        traces = self.file(TRACES)
        with writing(traces):
            traces.mkdir(exist_ok=True)
        robots: dict[str, Any] = {}
        for robot_id, result in results.items():
            entry: dict[str, Any] = {
                "fitness": result.fitness,
                "stats": msgspec.to_builtins(result.stats),
                "trace": None,
            }
            if result.trace is not None:
                name = f"{robot_id}.npz"
                write_atomic(traces / name, _trace_npz(result))
                entry["trace"] = f"{TRACES}/{name}"
            robots[robot_id] = entry
        fitnesses = [r.fitness for r in results.values()]
        summary = {
            "evaluation_id": evaluation_id,
            "steps": steps,
            "genome_fitness": genome_fitness,
            "swarm_fitness": float(np.mean(fitnesses)) if fitnesses else None,
            "robots": robots,
        }
        write_atomic(self.file(POST_EVALUATION), json.dumps(summary, indent=2).encode("utf-8"))

    def read_rows(self) -> list[dict[str, str]]:
        """The rows of ``evaluations.csv`` as dicts of strings (empty if there is none)."""
        path = self.file(EVALUATIONS)
        if not path.exists():
            return []
        with open(path, encoding="utf-8", newline="") as file:
            return list(csv.DictReader(file))


def _trace_npz(result: Result) -> bytes:
    trace = result.trace
    assert trace is not None
    arrays: dict[str, np.ndarray] = {
        "sensors": trace.array("sensors"),
        "predictions": trace.array("predictions"),
        "actions": trace.array("actions"),
        "commands": trace.array("commands"),
        "safety": np.asarray(trace.safety, dtype=str),
    }
    if trace.poses is not None:
        arrays["poses"] = trace.array("poses")
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub: allow_pickle
    return buffer.getvalue()


def load_baseline(path: str | Path) -> dict[str, Any]:
    """``baseline.json`` from a baseline directory (or the file itself)."""
    path = Path(path)
    if path.is_dir():
        path = path / BASELINE_FILE
    return json.loads(path.read_text(encoding="utf-8"))
