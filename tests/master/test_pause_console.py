"""Enter on the master's terminal ends a pause (master_service.pause.PauseGate), in a real
pseudo-terminal: the master in the foreground of its own session, as in a lab's shell. A line
typed before the pause began does not end it."""

from __future__ import annotations

import os
import pty
import select
import sys
import textwrap
import time
from pathlib import Path

#: The master's side: a PauseGate with the console on; it says when it pauses and when it goes on.
SCRIPT = textwrap.dedent(
    """
    import asyncio, logging, sys, time
    from master_service.pause import Pause, PauseGate
    from master_service.rundir import RunDir
    logging.basicConfig(stream=sys.stdout, level=logging.INFO, format="%(message)s")
    print("ready", flush=True)
    time.sleep(1.0)  # the test types a line meanwhile, before the pause
    gate = PauseGate(RunDir(sys.argv[1]), logging.getLogger("pause"), console=True)
    asyncio.run(gate.wait(Pause("battery", "swap the battery of r1", ("r1",))))
    print("went on", flush=True)
    """
)


def read_until(fd: int, text: str, timeout: float = 20.0) -> str:
    """What the terminal shows, up to and including ``text``; fails after ``timeout``."""
    seen = ""
    deadline = time.monotonic() + timeout
    while text not in seen:
        left = deadline - time.monotonic()
        assert left > 0, f"{text!r} not shown; the terminal showed {seen!r}"
        ready, _, _ = select.select([fd], [], [], left)
        if ready:
            try:
                seen += os.read(fd, 4096).decode(errors="replace")
            except OSError:  # the child closed the terminal
                break
    assert text in seen, seen
    return seen


def test_enter_on_the_terminal_ends_a_pause_but_a_line_typed_before_it_does_not(tmp_path: Path):
    run = tmp_path / "run"
    run.mkdir()
    pid, fd = pty.fork()  # the child leads a new session whose controlling terminal is the pty
    if pid == 0:  # pragma: no cover - the child
        os.execv(sys.executable, [sys.executable, "-c", SCRIPT, str(run)])
    try:
        read_until(fd, "ready")
        os.write(fd, b"typed too early\n")
        shown = read_until(fd, "(or Enter here)")
        assert "paused: swap the battery of r1" in shown
        assert (run / "pause.json").exists()
        time.sleep(1.0)  # the early line, had it been kept, would have ended the pause by now
        assert (run / "pause.json").exists()
        os.write(fd, b"\n")
        read_until(fd, "went on")
        assert not (run / "pause.json").exists()
    finally:
        _, status = os.waitpid(pid, 0)
        os.close(fd)
    assert os.waitstatus_to_exitcode(status) == 0
