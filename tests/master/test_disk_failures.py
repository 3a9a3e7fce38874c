"""A full disk or a run directory made read-only stops a run with one line, and it resumes.

Issue 22 measured 7 tracebacks on the console for a full disk and 1 for a read-only run directory
(no data lost). Now the master says in one line which file it could not write, why, and how to go
on, exits with 1, and ``surprise-master resume`` finishes the run: for a master serving robots
(``surprise-master run`` with scripted robots; ``sim --engine agents``, the master and real agents
over loopback TCP) and for the compiled engine (``sim``). The full disk is real: a tiny tmpfs in a
mount namespace of the test's own (root only); in-process tests make the writes fail with ENOSPC
where that is not possible.

On a console that is no terminal the master of ``run`` and ``sim --engine agents`` writes its log
lines (INFO) to stderr as they come, by design: apart from those, stderr is the one line.
"""

from __future__ import annotations

import asyncio
import errno
import json
import logging
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
from master_helpers import (
    SECRET,
    assert_matches_reference,
    experiment,
    make_robots,
    master_config,
    robot_ids,
    write_experiment,
)

from master_service import Master
from master_service.rundir import RunDir, RunLog
from minimize_surprise.errors import FileWriteError
from needs import find_binary, missing, obeying_modes
from runfiles import schema
from runfiles import schema as rundir_module
from runfiles.schema import Checkpoint, Live

pytestmark = pytest.mark.slow

#: A console log line of the master (``%(asctime)s %(levelname)s``) at INFO: progress, by design.
INFO_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} INFO ")
#: Files of a run directory the master writes while it runs.
RUN_FILES = r"(checkpoint\.json|evaluations\.csv|master\.log|best_genome\.json|live\.json)"
#: The tiny disk: a few of the run's files fit, a few hundred evaluations' log lines do not.
FULL_DISK_SIZE = "128k"
#: Room enough afterwards to finish the run (its traces and pictures included).
FREED_DISK_SIZE = "64m"
#: Seconds a subprocess may take: far above what these small runs need.
COMMAND_TIMEOUT = 300


#: A checkpoint of a run that has counted nothing yet.
CHECKPOINT = Checkpoint(
    run_id="r",
    phase="evolution",
    next_evaluation_id=0,
    attempts=0,
    failed_attempts=0,
    csv_rows=0,
    roster=None,
)


def command(*argv: str) -> list[str]:
    return [sys.executable, "-m", "master_service", *argv]


def start(argv: list[str], cwd: Path, prefix: tuple[str, ...] = ()) -> subprocess.Popen[bytes]:
    """Start a command; its stdout and stderr go to files (:func:`finish` reads them), so that a
    master logging every evaluation never blocks on a full pipe while the test waits."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with open(cwd / "command.out", "w") as out, open(cwd / "command.err", "w") as err:
        return subprocess.Popen([*prefix, *argv], cwd=cwd, env=env, stdout=out, stderr=err)


def finish(process: subprocess.Popen[bytes], cwd: Path) -> tuple[int, str, str]:
    """Wait for a command of :func:`start`; its exit status, stdout and stderr."""
    status = process.wait(timeout=COMMAND_TIMEOUT)
    return status, (cwd / "command.out").read_text(), (cwd / "command.err").read_text()


def beyond_the_log(err: str) -> list[str]:
    """stderr without the master's INFO log lines."""
    return [line for line in err.strip().splitlines() if not INFO_LINE.match(line)]


def assert_one_line(err: str, run: Path, reason: str, remedy: str) -> None:
    lines = beyond_the_log(err)
    pattern = (
        rf"surprise-master: cannot write {re.escape(str(run))}/{RUN_FILES}: {reason}; "
        rf"{re.escape(remedy)} and run `surprise-master resume {re.escape(str(run))}`"
    )
    assert len(lines) == 1 and re.fullmatch(pattern, lines[0]), err


def wait_for(predicate, process: subprocess.Popen[bytes], what: str, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert process.poll() is None, f"the command ended with {process.returncode}"
        assert time.monotonic() < deadline, f"no {what} in time"
        time.sleep(0.02)


def counted(run: Path) -> int:
    checkpoint = RunDir(run).read_checkpoint()
    return 0 if checkpoint is None else checkpoint.evaluations


def assert_finished(run: Path, evaluations: int) -> None:
    assert len(RunDir(run).read_rows()) == evaluations
    checkpoint = RunDir(run).read_checkpoint()
    assert checkpoint is not None and checkpoint.phase == "done"


# -- a read-only run directory ---------------------------------------------------------------------

#: (engine, evaluations, steps): the agents commit every evaluation, the engine every 2 s, so its
#: run directory turns read-only before its first commit.
SIM_RUNS = [("agents", 300, 20), ("fast", 2000, 40)]


@pytest.mark.parametrize(("engine", "evaluations", "steps"), SIM_RUNS)
def test_sim_in_a_directory_turned_read_only_is_one_line_and_resumes(
    tmp_path: Path, engine: str, evaluations: int, steps: int
):
    prefix = obeying_modes(tmp_path)
    config = write_experiment(tmp_path / "experiment.yaml", evaluations, steps)
    run = tmp_path / "run"
    argv = command("sim", "--config", str(config), "--engine", engine, "--out", str(run))
    process = start(argv, tmp_path, prefix)
    if engine == "agents":
        wait_for(lambda: counted(run) >= 1, process, "evaluation committed")
    else:
        wait_for(lambda: (run / "simulation.json").exists(), process, "run directory")
    run.chmod(0o500)
    try:
        status, _, err = finish(process, tmp_path)
    finally:
        run.chmod(0o700)
    assert status == 1, err
    assert_one_line(err, run, "Permission denied", f"make {run} writable")

    status, out, err = finish(start(command("resume", str(run)), tmp_path), tmp_path)
    assert status == 0, (out, err)
    assert_finished(run, evaluations)


def test_a_lab_run_in_a_directory_turned_read_only_is_one_line_and_resumes(tmp_path: Path):
    prefix = obeying_modes(tmp_path)
    exp = experiment(evaluations=150)
    (tmp_path / "secret.txt").write_bytes(SECRET)
    config = tmp_path / "master.yaml"
    config.write_text(
        json.dumps(
            {
                "experiment": {
                    "robots": exp.robots,
                    "evaluation_steps": exp.evaluation_steps,
                    "post_evaluation_steps": exp.post_evaluation_steps,
                    "seed": exp.seed,
                    "evolution": {"evaluations": exp.evolution.evaluations},
                },
                "port": 0,
                "secret_file": "secret.txt",
                "round_margin": 5.0,
                "heartbeat_interval": 0.5,
            }
        )
    )
    run = tmp_path / "run"
    process = start(command("run", "--config", str(config), "--out", str(run)), tmp_path, prefix)
    try:
        asyncio.run(serve_until(process, run, chmod_after_first_commit=True))
        status, _, err = finish(process, tmp_path)
    finally:
        run.chmod(0o700)
    assert status == 1, err
    assert_one_line(err, run, "Permission denied", f"make {run} writable")
    assert 0 < counted(run) < exp.evolution.evaluations

    process = start(command("resume", str(run)), tmp_path)
    asyncio.run(serve_until(process, run))
    status, out, err = finish(process, tmp_path)
    assert status == 0, (out, err)
    assert_matches_reference(run, exp, robot_ids(exp.robots))


async def serve_until(
    process: subprocess.Popen[bytes], run: Path, *, chmod_after_first_commit: bool = False
) -> None:
    """Scripted robots serve the master ``process`` runs into ``run`` until it ends (with the run
    directory made read-only after its first commit if asked)."""
    await asyncio.to_thread(wait_for_live_master, process, run)
    port = json.loads((run / "live.json").read_text())["port"]
    robots = make_robots(port, 3, delay=0.005)
    await asyncio.gather(*(robot.connect() for robot in robots))
    turned = not chmod_after_first_commit
    while process.poll() is None:
        if not turned and counted(run) >= 1:
            run.chmod(0o500)
            turned = True
        await asyncio.sleep(0.01)
    await asyncio.gather(*(robot.closed.wait() for robot in robots))


def wait_for_live_master(process: subprocess.Popen[bytes], run: Path) -> None:
    """Wait until the master ``process`` (not an earlier one) announces its port in live.json."""

    def announced() -> bool:
        live = schema.read(run, Live)
        return live is not None and live.running and live.pid == process.pid

    wait_for(announced, process, "live.json of this master")


# -- a full disk -----------------------------------------------------------------------------------

#: Exit status of the script below when the tmpfs cannot be mounted.
_CANNOT_MOUNT = 3
_FULL_DISK_SCRIPT = """
set -u
mount -t tmpfs -o size={small} surprise-full-disk {disk} || exit {cannot_mount}
{first} > {out}/first.out 2> {out}/first.err; echo $? > {out}/first.rc
mount -o remount,size={freed} {disk}
{resume} > {out}/resume.out 2> {out}/resume.err; echo $? > {out}/resume.rc
cp -a {disk}/run {out}/run || exit 4
"""


def full_disk_commands(tmp_path: Path, first: list[str], resume: list[str]) -> dict[str, str]:
    """Run ``first`` with a tiny tmpfs at ``tmp_path/disk`` (in a mount namespace of its own, so
    that the mount is gone with it), then ``resume`` with the tmpfs grown; their stdout, stderr,
    exit status and the run directory as they left them, under ``tmp_path/out``."""
    unshare = find_binary("unshare")
    if unshare is None or os.geteuid() != 0:
        missing("a real full disk needs root and unshare (util-linux) to mount a tiny tmpfs")
    disk, out = tmp_path / "disk", tmp_path / "out"
    disk.mkdir()
    out.mkdir()
    script = _FULL_DISK_SCRIPT.format(
        small=FULL_DISK_SIZE,
        freed=FREED_DISK_SIZE,
        disk=shlex.quote(str(disk)),
        out=shlex.quote(str(out)),
        cannot_mount=_CANNOT_MOUNT,
        first=shlex.join(first),
        resume=shlex.join(resume),
    )
    namespace = subprocess.run(
        [unshare, "--mount", "--propagation", "private", "--", "sh", "-c", script],
        cwd=tmp_path,
        timeout=2 * COMMAND_TIMEOUT,
    )
    if namespace.returncode in (1, _CANNOT_MOUNT):  # unshare itself, or the mount, refused
        missing("cannot mount a tmpfs here (unshare --mount and mount need CAP_SYS_ADMIN)")
    assert namespace.returncode == 0
    return {p.name: p.read_text() for p in out.iterdir() if p.is_file()}


@pytest.mark.parametrize(
    ("engine", "evaluations", "steps"), [("agents", 400, 20), ("fast", 3000, 40)]
)
def test_sim_on_a_full_disk_is_one_line_and_resumes_once_there_is_space(
    tmp_path: Path, engine: str, evaluations: int, steps: int
):
    config = write_experiment(tmp_path / "experiment.yaml", evaluations, steps)
    run = tmp_path / "disk" / "run"
    results = full_disk_commands(
        tmp_path,
        command("sim", "--config", str(config), "--engine", engine, "--out", str(run)),
        command("resume", str(run)),
    )
    assert results["first.rc"].strip() == "1", results["first.err"]
    assert "Traceback" not in results["first.err"]
    assert_one_line(results["first.err"], run, "No space left on device", "free some space")
    assert results["resume.rc"].strip() == "0", results["resume.err"]
    assert_finished(tmp_path / "out" / "run", evaluations)


# -- in-process: the file layer refuses ---------------------------------------------------------


def no_space(path: object) -> OSError:
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


async def test_a_master_whose_checkpoint_cannot_be_written_stops_and_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    exp = experiment(evaluations=12)
    run = tmp_path / "run"
    write_atomic = rundir_module.files.write_atomic
    commits = []

    def full_after_five(path, data, **kwargs):
        if Path(path).name == "checkpoint.json":
            commits.append(path)
            if len(commits) > 5:
                raise no_space(Path(path).with_name(".checkpoint.json.1234.tmp"))
        write_atomic(path, data, **kwargs)

    monkeypatch.setattr(rundir_module.files, "write_atomic", full_after_five)
    async with Master(master_config(exp), run, secret=SECRET) as master:
        robots = make_robots(master.port, exp.robots)
        task = asyncio.create_task(master.run())
        await asyncio.gather(*(robot.connect() for robot in robots))
        with pytest.raises(FileWriteError) as failure:
            await asyncio.wait_for(task, 15)
    # The file meant, not the temporary name the write failed on.
    assert failure.value.path == str(run / "checkpoint.json")
    assert failure.value.errno == errno.ENOSPC
    assert str(failure.value) == f"cannot write {run / 'checkpoint.json'}: No space left on device"
    log = (run / "master.log").read_text()
    assert "the run stopped: cannot write" in log and "Traceback" not in log

    monkeypatch.setattr(rundir_module.files, "write_atomic", write_atomic)
    async with Master(master_config(exp), run, secret=SECRET, resume=True) as master:
        robots = make_robots(master.port, exp.robots)
        task = asyncio.create_task(master.run())
        await asyncio.gather(*(robot.connect() for robot in robots))
        await asyncio.wait_for(task, 15)
    assert_matches_reference(run, exp, robot_ids(exp.robots))


class _FullStream:
    """A log file on a full disk."""

    def write(self, text: str) -> int:
        raise no_space("master.log")

    def flush(self) -> None:
        raise no_space("master.log")

    def close(self) -> None:
        pass


def test_a_log_line_that_cannot_be_written_is_kept_back_and_stops_the_next_commit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    directory = RunDir(tmp_path / "run")
    directory.path.mkdir()
    log = logging.getLogger("test_disk_failures.full_log")
    log.propagate = False
    handler = directory.open_log(log)
    handler.stream.close()
    handler.stream = _FullStream()  # type: ignore[assignment]
    for i in range(7):
        log.warning("line %d", i)
    # Logging's own handler prints a traceback to stderr for each of these lines.
    assert capsys.readouterr().err == ""
    assert isinstance(handler, RunLog)
    with pytest.raises(FileWriteError) as failure:
        directory.commit(CHECKPOINT, None, ())
    assert str(failure.value) == f"cannot write {directory.file('master.log')}: " + os.strerror(
        errno.ENOSPC
    )
    assert not directory.file("checkpoint.json").exists()
    directory.close_log(log)  # flushing again fails again, quietly
    assert capsys.readouterr().err == ""
