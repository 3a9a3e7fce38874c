"""The agent as systemd runs it, in fresh interpreters: what ``--stop-motors`` imports (it runs
within the unit's stop timeout on a slow Pi), and the priorities of its lines in the journal."""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import sys
from pathlib import Path

from standins.fake_medulla import StaticThymioModel, serve_fake_medulla

#: Modules the stop path must not import: each takes seconds to import on a slow Pi (numpy alone
#: 1.7 s on an emulated one), and the agent's own side (the safety layer, the agent) brings them.
HEAVY = ("numpy", "numba", "llvmlite", "scipy", "matplotlib", "pandas", "minimize_surprise.safety")

# Runs the command line, then names on stderr the heavy modules it imported.
_RUN_CLI = f"""
import sys
from robot_agent import cli
code = cli.main(sys.argv[1:])
print("heavy:", *sorted(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)
sys.exit(code)
"""

_LOG_LINES = """
import logging
from robot_agent.journal import setup_logging
setup_logging("DEBUG")
log = logging.getLogger("robot_agent")
log.debug("d")
log.info("i")
log.warning("w")
log.error("e")
log.critical("c")
try:
    1 / 0
except ZeroDivisionError:
    log.exception("crashed")
"""


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    return env | extra


def _journal_stream(path: Path) -> str:
    status = os.stat(path)
    return f"{status.st_dev}:{status.st_ino}"


def _heavy(stderr: str) -> list[str]:
    lines = [line for line in stderr.splitlines() if line.startswith("heavy:")]
    assert lines, stderr
    return lines[-1].split()[1:]


async def test_stop_motors_stops_without_importing_numpy_and_logs_to_the_journal(
    tmp_path, dbus_address
):
    """ExecStopPost end to end in a fresh interpreter: the robot stops, nothing heavy is
    imported, and the line lands in the journal with its priority and without a time stamp."""
    config = tmp_path / "agent.yaml"
    config.write_text(f"body: {{thymio: {{bus: '{dbus_address}'}}}}\n")
    out = tmp_path / "stdout"
    model = StaticThymioModel()
    model.targets = {"left": 150, "right": 150}
    async with serve_fake_medulla(dbus_address, model):
        with out.open("w") as stdout:
            process = await asyncio.create_subprocess_exec(
                sys.executable,
                "-c",
                _RUN_CLI,
                *("--config", str(config), "--stop-motors"),
                stdout=stdout,
                stderr=subprocess.PIPE,
                env=_env(JOURNAL_STREAM=_journal_stream(out)),
            )
            _, stderr = await asyncio.wait_for(process.communicate(), 60)
    err = stderr.decode()
    assert process.returncode == 0, err
    assert model.targets == {"left": 0, "right": 0}
    assert _heavy(err) == []
    assert out.read_text() == "<6>INFO robot_agent: motors stopped\n"


def test_the_command_line_and_the_stop_configuration_import_nothing_heavy(tmp_path):
    """The same without D-Bus: importing the CLI and reading the Thymio's section."""
    config = tmp_path / "agent.yaml"
    config.write_text("body: {thymio: {bus: system}}\n")
    code = (
        "import sys\n"
        "from robot_agent.cli import load_thymio_config\n"
        f"load_thymio_config({str(config)!r})\n"
        f"print('heavy:', *sorted(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=_env()
    )
    assert result.returncode == 0, result.stderr
    assert _heavy(result.stderr) == []


def _log_to(path: Path, *, journal_stream: str | None) -> list[str]:
    extra = {} if journal_stream is None else {"JOURNAL_STREAM": journal_stream}
    with path.open("w") as stdout:
        subprocess.run(
            [sys.executable, "-c", _LOG_LINES],
            stdout=stdout,
            env=_env(**extra),
            timeout=60,
            check=True,
        )
    return path.read_text().splitlines()


def test_lines_on_the_journal_stream_carry_their_priority_and_no_time(tmp_path):
    out = tmp_path / "stdout"
    out.touch()
    lines = _log_to(out, journal_stream=_journal_stream(out))
    assert lines[:5] == [
        "<7>DEBUG robot_agent: d",
        "<6>INFO robot_agent: i",
        "<4>WARNING robot_agent: w",
        "<3>ERROR robot_agent: e",
        "<2>CRITICAL robot_agent: c",
    ]
    # journald makes every line an entry: a traceback's lines keep the error's priority.
    assert lines[5] == "<3>ERROR robot_agent: crashed"
    assert lines[6] == "<3>Traceback (most recent call last):"
    assert lines[-1] == "<3>ZeroDivisionError: division by zero"
    assert all(line.startswith("<3>") for line in lines[5:])


def test_lines_elsewhere_keep_their_time_stamp(tmp_path):
    """Outside systemd, and when stdout is not the stream systemd named (redirected by hand)."""
    other = tmp_path / "other"
    other.touch()
    stamp = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} "
    for journal_stream in (None, _journal_stream(other), "garbage"):
        lines = _log_to(tmp_path / "stdout", journal_stream=journal_stream)
        assert re.fullmatch(stamp + "DEBUG robot_agent: d", lines[0]), lines[0]
        assert re.fullmatch(stamp + "ERROR robot_agent: crashed", lines[5]), lines[5]
        assert lines[6] == "Traceback (most recent call last):"


def test_an_error_on_the_journal_stream_is_an_error(tmp_path):
    """What the agent prints instead of logging (here: a configuration it cannot read)."""
    err = tmp_path / "stderr"
    err.touch()
    for journal_stream, prefix in ((_journal_stream(err), "<3>"), (None, "")):
        extra = {} if journal_stream is None else {"JOURNAL_STREAM": journal_stream}
        with err.open("w") as stderr:
            code = subprocess.run(
                [sys.executable, "-m", "robot_agent.cli", "--config", "nowhere.yaml"],
                stderr=stderr,
                env=_env(**extra),
                cwd=tmp_path,
                timeout=60,
            ).returncode
        assert code == 2
        assert err.read_text().startswith(prefix + "surprise-agent: nowhere.yaml: cannot read")
