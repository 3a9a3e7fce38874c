"""The run directory: everything a run leaves behind, written so that a crash loses nothing.

The files and their structures are defined once, in :mod:`runfiles.schema`; this module is the
master's side: creating a run, committing evaluations exactly once, the log, and the artefacts.

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
import io
import logging
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import msgspec
import numpy as np
import yaml

from master_service.config import MasterConfig
from minimize_surprise.config import ExperimentConfig, load_yaml
from minimize_surprise.errors import ConfigError, FileWriteError
from minimize_surprise.evolution import EvolutionStateError, OnePlusOne
from minimize_surprise.network import NetworkSpec
from minimize_surprise.wire import Hello, Result
from runfiles import schema
from runfiles.schema import (
    CONFIG_SNAPSHOT,
    EVALUATIONS,
    LOG,
    SWARM_COLUMN,
    TRACES,
    BestGenome,
    Checkpoint,
    Live,
    Phase,
    PostEvaluation,
    PostRobot,
    RunDirError,
    Software,
    SoftwareRecord,
    SwarmChange,
    evaluation_header,
    format_row,
    write_atomic,
    writing,
)

__all__ = [
    "FILE_ONLY",
    "RunDir",
    "RunDirError",
    "RunLog",
    "RunState",
    "evaluation_header",
    "for_console",
    "format_row",
    "write_atomic",
    "writing",
]

#: ``extra`` of a log call whose line belongs in master.log but not on the console, where the
#: command line says the same thing in its own last line.
FILE_ONLY: Final = {"file_only": True}


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
    accounts for. ``roster`` is the swarm's robot ids once fixed (the CSV's per-robot columns);
    ``swarms`` its changes since (a robot gone for good, a spare swapped in), in order.
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
    swarms: list[SwarmChange] = field(default_factory=list)
    #: the experiment's events that happened (indexes in its ``events``), in order
    events_applied: list[int] = field(default_factory=list)

    @property
    def swarm_number(self) -> int:
        """Which swarm evaluates now: 0 the first, one more per change (the CSV's ``swarm``)."""
        return len(self.swarms)

    def to_checkpoint(self) -> Checkpoint:
        """The checkpoint of this state, stamped now."""
        return Checkpoint(
            run_id=self.run_id,
            phase=self.phase,
            next_evaluation_id=self.next_evaluation_id,
            attempts=self.attempts,
            failed_attempts=self.failed_attempts,
            csv_rows=self.csv_rows,
            roster=self.roster,
            elapsed_s=self.elapsed_s,
            written_at=time.time(),
            optimizer=self.optimizer.state(),
            simulation=self.simulation,
            swarms=list(self.swarms) or None,
            events_applied=list(self.events_applied) or None,
        )

    @classmethod
    def from_checkpoint(cls, config: MasterConfig, checkpoint: Checkpoint) -> RunState:
        """Rebuild the state written by :meth:`to_checkpoint`; raises :class:`RunDirError`."""
        assert config.experiment is not None
        try:
            optimizer = OnePlusOne.from_state(config.experiment.evolution, checkpoint.optimizer)
        except (KeyError, TypeError, ValueError, EvolutionStateError) as exc:
            raise RunDirError(f"the checkpoint cannot be read: {exc}") from None
        return cls(
            run_id=checkpoint.run_id,
            optimizer=optimizer,
            phase=checkpoint.phase,
            next_evaluation_id=checkpoint.next_evaluation_id,
            attempts=checkpoint.attempts,
            failed_attempts=checkpoint.failed_attempts,
            csv_rows=checkpoint.csv_rows,
            roster=checkpoint.roster,
            elapsed_s=checkpoint.elapsed_s,
            simulation=checkpoint.simulation,
            swarms=list(checkpoint.swarms or ()),
            events_applied=list(checkpoint.events_applied or ()),
        )


class RunDir:
    """The files of one run (see the module docstring); every method is blocking file I/O."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._csv: Any = None
        self._log: RunLog | None = None
        self._software: SoftwareRecord | None = None

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

    def read_checkpoint(self) -> Checkpoint | None:
        """The checkpoint, or None before the first commit (RunDirError when unreadable)."""
        return schema.read(self.path, Checkpoint)

    def read_state(self, config: MasterConfig) -> RunState | None:
        """The checkpointed :class:`RunState`, or None before the first commit."""
        checkpoint = self.read_checkpoint()
        return None if checkpoint is None else RunState.from_checkpoint(config, checkpoint)

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

    def commit(self, checkpoint: Checkpoint, row: str | None, header: Sequence[str]) -> None:
        """Append ``row`` (if any) to the CSV durably, then write the checkpoint atomically.

        ``checkpoint`` must already count the row (``csv_rows``). ``header`` is written before
        the first row. A line the log could not take since is raised first
        (:class:`FileWriteError`), so a run stops when its disk is full even if the commit itself
        would still fit.
        """
        if self._log is not None and self._log.error is not None:
            raise self._log.error
        if row is not None:
            with writing(self.file(EVALUATIONS)):
                self._append_row(row, header)
        schema.write(self.path, checkpoint)

    def rewrite_header(self, header: Sequence[str]) -> None:
        """Give ``evaluations.csv`` the wider ``header`` (columns only added, at the end; see
        :func:`runfiles.schema.widen_header`), every row padded with empty cells, and
        :data:`~runfiles.schema.SWARM_COLUMN` 0 in rows that had none: they were the first
        swarm's. Atomic: a crash leaves the old file or the new one, with the same rows, and
        the rows of either are read by their columns' names. Nothing to do without a header.
        """
        old = self.csv_header()
        if old is None or list(old) == list(header):
            return
        path = self.file(EVALUATIONS)
        self.close()  # the append handle would go on writing to the replaced file
        with writing(path):
            lines = path.read_text(encoding="utf-8").splitlines(keepends=True)[1:]
            out = [",".join(header) + "\n"]
            for line in lines:
                if not line.endswith("\n"):
                    break  # torn, past the checkpoint's count: resume cuts it anyway
                cells = dict(zip(old, line.rstrip("\n").split(","), strict=False))
                cells.setdefault(SWARM_COLUMN, "0")
                out.append(",".join(cells.get(column, "") for column in header) + "\n")
        write_atomic(path, "".join(out).encode("utf-8"))

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
        best = BestGenome(
            evaluation=evaluation,
            fitness=float(fitness),
            genome=[float(x) for x in np.asarray(genome, dtype=np.float64)],
            spec=spec,
        )
        schema.write(self.path, best, durable=False)

    def record_master_software(self, master: Software) -> None:
        """Write ``software.json`` with this master's software, keeping what the robots reported
        before (a resumed run); not durable: a record, not a commit point."""
        old = schema.read_if_readable(self.path, SoftwareRecord)
        if old is None:
            self._software = SoftwareRecord(master=master)
        else:
            self._software = msgspec.structs.replace(old, master=master)
        schema.write(self.path, self._software, durable=False)

    def record_robot_software(self, robot: str, software: Software, now: float) -> Software | None:
        """Note ``robot``'s software as it joins; rewrites ``software.json`` only when it is new
        or changed (reconnections cost no write). Returns the robot's software before when it
        changed, None otherwise."""
        record = self._software
        if record is None:
            raise RuntimeError("record_master_software first")
        before = record.robots.get(robot)
        if before == software:
            return None
        self._software = msgspec.structs.replace(
            record,
            robots={**record.robots, robot: software},
            joined_at={**record.joined_at, robot: now},
        )
        schema.write(self.path, self._software, durable=False)
        return before

    def note_software(self, hello: Hello, log: logging.Logger) -> None:
        """Record the software a robot names in its ``hello`` as it joins
        (:meth:`record_robot_software`); a change since it last joined is logged, a write that
        fails too: the record is for people, never a reason to refuse a robot."""
        software = Software(
            version=hello.software_version,
            commit=hello.software_commit,
            firmware=hello.thymio_firmware,
        )
        try:
            before = self.record_robot_software(hello.robot_id, software, time.time())
        except OSError as exc:
            log.warning("software.json not written: %s", exc)
            return
        if before is not None:
            log.warning(
                "robot %s joined with other software than before: %s -> %s",
                hello.robot_id,
                before,
                software,
            )

    def write_live(self, live: Live) -> None:
        """Write ``live.json`` (not durable: it only describes the running process)."""
        schema.write(self.path, live, durable=False)

    def write_post_evaluation(
        self,
        evaluation_id: int,
        genome_fitness: float | None,
        steps: int,
        results: dict[str, Result],
        *,
        started_at: float | None = None,
    ) -> None:
        """Write every robot's trace to ``traces/<robot>.npz`` and the summary JSON
        (``started_at``: when the counted attempt went out, for an overhead camera)."""
        traces = self.file(TRACES)
        with writing(traces):
            traces.mkdir(exist_ok=True)
        robots: dict[str, PostRobot] = {}
        for robot_id, result in results.items():
            trace = None
            if result.trace is not None:
                name = f"{robot_id}.npz"
                write_atomic(traces / name, _trace_npz(result))
                trace = f"{TRACES}/{name}"
            robots[robot_id] = PostRobot(fitness=result.fitness, stats=result.stats, trace=trace)
        fitnesses = [r.fitness for r in results.values()]
        summary = PostEvaluation(
            evaluation_id=evaluation_id,
            steps=steps,
            genome_fitness=genome_fitness,
            swarm_fitness=float(np.mean(fitnesses)) if fitnesses else None,
            robots=robots,
            started_at=started_at,
        )
        schema.write(self.path, summary)

    def read_rows(self) -> list[dict[str, str]]:
        """The rows of ``evaluations.csv`` as dicts of strings (empty if there is none)."""
        return schema.read_rows(self.path)


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
