"""``surprise-master fleet status`` and ``fleet stop`` without a run: the command listens where
the master file says, real agents on the fake medulla connect, and each is asked (docs/fleet.md).
One robot of the inventory never comes: it is not reachable, and the stop names it as not
answered (exit status 1). The Pi's ``vcgencmd`` is a script on ``PATH``."""

from __future__ import annotations

import asyncio
import socket
import stat
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

import pytest
import test_preflight
from test_preflight import SECRET, start_robot

import minimize_surprise
from master_service.cli import main
from master_service.config import load_master_config
from master_service.fleet import fleet_status, fleet_stop, format_status, throttled_text
from master_service.inventory import load_inventory
from master_service.stopall import format_stop
from minimize_surprise.provenance import software_commit
from standins.fake_medulla import StaticThymioModel

FLEET = """\
robots:
  - {name: alpha, address: alpha.local}
  - {name: beta, address: 192.0.2.8}
  - {name: gamma, address: gamma.local}
  - {name: delta, address: delta.local, spare: true}
  - {name: away, address: away.local, enabled: false}
"""
#: Seconds the command waits for the agents: the in-process agents reconnect within 0.1 s, and
#: gamma never comes, so this is the time the absent robot costs each test.
WAIT = 3.0


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def lab(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    (tmp_path / "fleet.yaml").write_text(FLEET)
    (tmp_path / "secret").write_bytes(SECRET)
    (tmp_path / "secret").chmod(0o600)
    (tmp_path / "master.yaml").write_text(
        "experiment: {robots: 3, seed: 1}\nhost: 127.0.0.1\nport: 0\n"
        "inventory: fleet.yaml\nsecret_file: secret\n"
    )
    # The Pi's firmware tool: under-voltage and throttling have occurred since boot, and the
    # voltage is low now.
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    vcgencmd = bin_dir / "vcgencmd"
    vcgencmd.write_text("#!/bin/sh\necho throttled=0x50001\n")
    vcgencmd.chmod(vcgencmd.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", f"{bin_dir}:{Path('/usr/bin')}:{Path('/bin')}")
    return tmp_path


async def test_status_lists_every_robot_with_its_software_battery_clock_and_pi_flags(lab: Path):
    config = load_master_config(lab / "master.yaml")
    fleet = load_inventory(lab / "fleet.yaml")
    listening: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    async with AsyncExitStack() as stack:
        status = asyncio.create_task(
            fleet_status(config, SECRET, fleet, timeout=WAIT, on_listening=listening.set_result)
        )
        port = await listening
        for robot in ("alpha", "beta", "delta"):
            await start_robot(stack, robot, port, "(in-process)", vbat=(760, 760))
        rows = await asyncio.wait_for(status, 30)

    table = format_status(rows)
    print(table)  # the table the docs show (pytest -s)
    by = {row.robot: row for row in rows}
    assert [row.robot for row in rows] == ["alpha", "beta", "gamma", "delta", "away"]
    commit = software_commit()
    for name in ("alpha", "beta", "delta"):
        row = by[name]
        assert row.reachable and row.problem is None
        assert row.software == minimize_surprise.__version__ and row.commit == commit
        assert row.firmware == 11 and row.battery_v == pytest.approx(3.8, abs=0.05)
        assert row.clock_offset_s is not None and abs(row.clock_offset_s) < 1.0
        assert row.throttled == 0x50001
    assert by["delta"].spare and not by["away"].enabled and not by["away"].reachable
    gamma = by["gamma"]
    assert not gamma.reachable and gamma.problem is not None
    assert gamma.problem.startswith("not reachable within 3 s")
    assert "under-voltage now, under-voltage has occurred, throttling has occurred" in table
    rows_of = {line.split()[0]: line.split() for line in table.splitlines()[1:6]}
    assert rows_of["away"] == ["away", "away.local", "disabled", "-", "-", "-", "-", "-", "-"]
    assert rows_of["gamma"][:4] == ["gamma", "gamma.local", "no", "-"]
    assert table.endswith("3 of 4 enabled robots reachable")


def test_the_pi_flags_read_for_a_person():
    assert throttled_text(None) == "n/a"
    assert throttled_text(0) == "ok"
    assert throttled_text(0x4) == "throttled now"
    assert throttled_text(0x100) == "0x100"


async def test_stop_confirms_each_agent_and_names_the_one_that_did_not_answer(lab: Path):
    config = load_master_config(lab / "master.yaml")
    fleet = load_inventory(lab / "fleet.yaml")
    listening: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    async with AsyncExitStack() as stack:
        stop = asyncio.create_task(
            fleet_stop(config, SECRET, fleet, timeout=WAIT, on_listening=listening.set_result)
        )
        port = await listening
        models = []
        for robot in ("alpha", "beta", "delta"):
            agent, _ = await start_robot(stack, robot, port, "(in-process)")
            models.append(agent)
        outcome = await asyncio.wait_for(stop, 30)

    assert outcome.confirmed == ["alpha", "beta", "delta"]
    assert list(outcome.unanswered) == ["gamma"]
    assert outcome.unanswered["gamma"] == "did not connect within 3 s"
    assert not outcome.complete
    assert format_stop(outcome).splitlines()[:2] == [
        "stopped (confirmed): alpha, beta, delta",
        "did not answer: gamma",
    ]


async def test_the_command_stops_what_drives_and_exits_1_for_the_missing_robot(
    lab: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
):
    models: list[StaticThymioModel] = []

    class Recorded(StaticThymioModel):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            models.append(self)

    monkeypatch.setattr(test_preflight, "StaticThymioModel", Recorded)
    # A fixed port: the command binds it in its own thread, the agents connect to it.
    port = _free_port()
    text = (lab / "master.yaml").read_text().replace("port: 0", f"port: {port}")
    (lab / "master.yaml").write_text(text)
    async with AsyncExitStack() as stack:
        for robot in ("alpha", "beta", "delta"):
            await start_robot(stack, robot, port, "(in-process)")
        for model in models:
            # Something left the motors driving (a crashed tool, a manual test): the stop
            # reaches the robot itself, not only an evaluation.
            model.targets = {"left": 250, "right": 250}
        code = await asyncio.to_thread(
            main,
            ["fleet", "stop", "--config", str(lab / "master.yaml"), "--timeout", str(WAIT)],
        )
    assert len(models) == 3
    assert all(model.targets == {"left": 0, "right": 0} for model in models)
    assert all(model.target_log[-2:] in (
        [("left", 0), ("right", 0)], [("right", 0), ("left", 0)]
    ) for model in models)  # fmt: skip
    out = capsys.readouterr().out
    assert code == 1, out
    assert "stopped (confirmed): alpha, beta, delta" in out
    assert "did not answer: gamma" in out and "gamma: did not connect within 3 s" in out
