"""The master's terminal for the whole run (master_service.console), in a real pseudo-terminal:
`escape ROBOT` drops the request `surprise-master escape` drops, a line it does not know says
what it knows, and Enter still ends a pause through the same console."""

from __future__ import annotations

import os
import pty
import sys
import textwrap
import time
from pathlib import Path

from test_pause_console import read_until

from runfiles.schema import REQUESTS, EscapeRequest

SCRIPT = textwrap.dedent(
    """
    import asyncio, logging, sys
    from master_service.console import Console
    from master_service.escape import escape_from_console
    from master_service.pause import Pause, PauseGate
    from master_service.rundir import RunDir
    logging.basicConfig(stream=sys.stdout, level=logging.INFO, format="%(message)s")
    log = logging.getLogger("master")
    run = RunDir(sys.argv[1])

    async def main():
        console = Console(log, escape=escape_from_console(run, log))
        with console.reading():
            print("reading" if console.active else "not reading", flush=True)
            while not list((run.path / "requests").glob("*.json")):
                await asyncio.sleep(0.05)
            print("request dropped", flush=True)
            gate = PauseGate(run, log, console=True, terminal=console)
            await gate.wait(Pause("battery", "swap the battery of r1", ("r1",)))
            print("went on", flush=True)

    asyncio.run(main())
    """
)


def test_escape_from_the_masters_terminal_and_enter_in_a_pause(tmp_path: Path):
    run = tmp_path / "run"
    run.mkdir()
    pid, fd = pty.fork()
    if pid == 0:  # pragma: no cover - the child
        os.execv(sys.executable, [sys.executable, "-c", SCRIPT, str(run)])
    try:
        read_until(fd, "reading")
        os.write(fd, b"go faster\n")
        read_until(fd, "the console knows: Enter")
        os.write(fd, b"escape sim-1\n")
        shown = read_until(fd, "request dropped")
        assert "the experimenter's escape for sim-1 asked from the console" in shown
        (request,) = (run / REQUESTS).glob("*.json")
        assert b'"robot":"sim-1"' in request.read_bytes().replace(b" ", b"")
        assert request.name.startswith(EscapeRequest.FILE.removesuffix(".json"))
        read_until(fd, "(or Enter here)")
        time.sleep(0.3)
        os.write(fd, b"\n")
        read_until(fd, "went on")
    finally:
        _, status = os.waitpid(pid, 0)
        os.close(fd)
    assert os.waitstatus_to_exitcode(status) == 0
