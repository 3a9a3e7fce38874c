"""The agent's side of ``fleet stop`` and ``fleet status`` (docs/fleet.md): a stop is never
refused, it confirms only what the robot confirmed, and a stop that fails hands the motors to
the watchdog; the Pi's ``vcgencmd get_throttled`` flags are read where the tool exists."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest
from agent_fakes import FakeBody, FakeClock

from minimize_surprise.errors import HardwareError
from robot_agent import checkup
from robot_agent.checkup import read_throttled
from robot_agent.runner import EvaluationRunner
from robot_agent.watchdog import Watchdog


async def test_a_stop_with_nothing_running_is_confirmed_not_refused():
    body = FakeBody()
    body.motors = (0.4, 0.4)  # something left them driving
    runner = EvaluationRunner(body, FakeClock())
    reply = await runner.stop_all(3, None)
    assert reply.seq == 3 and reply.confirmed and reply.evaluation_id is None
    assert body.motors == (0.0, 0.0) and body.stops == 1


async def test_a_stop_the_robot_does_not_confirm_says_so_and_trips_the_watchdog():
    class Deaf(FakeBody):
        async def stop(self) -> None:
            raise HardwareError("no answer from the Thymio")

    body = Deaf()
    async with Watchdog(body.stop) as watchdog:
        runner = EvaluationRunner(body, FakeClock(), watchdog=watchdog)
        reply = await runner.stop_all(4, 17)
        assert not reply.confirmed and reply.evaluation_id == 17
        assert "no answer from the Thymio" in reply.detail
        assert watchdog.tripped and watchdog.tripped_reason == "fleet stop failed"


def _tool(folder: Path, text: str) -> None:
    tool = folder / "vcgencmd"
    tool.write_text(text)
    tool.chmod(tool.stat().st_mode | stat.S_IXUSR)


async def test_the_pi_flags_come_from_vcgencmd_where_it_exists(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setenv("PATH", f"{tmp_path}:/usr/bin:/bin")
    assert await read_throttled() is None  # not a Pi: unknown
    _tool(tmp_path, "#!/bin/sh\necho throttled=0x50005\n")
    assert await read_throttled() == 0x50005
    _tool(tmp_path, "#!/bin/sh\necho 'VCHI initialization failed' >&2\nexit 255\n")
    assert await read_throttled() is None
    _tool(tmp_path, "#!/bin/sh\nexec sleep 30\n")
    monkeypatch.setattr(checkup, "THROTTLED_TIMEOUT", 0.2)
    assert await read_throttled() is None  # a hung firmware tool does not hold the check
