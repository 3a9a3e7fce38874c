"""``surprise-master check`` with an inventory: a robot whose agent runs another commit (or an
agent too old to name one) is UNFIT with the command that updates it, the inventory's spare is
admitted and checked, and a spare that stays away is only a note (docs/fleet.md)."""

from __future__ import annotations

import asyncio
from contextlib import AsyncExitStack
from pathlib import Path

import pytest
from test_preflight import SECRET, start_robot

import minimize_surprise
from master_service.config import load_master_config
from master_service.preflight import SPARE_GRACE, format_table, run_check, update_command
from minimize_surprise.provenance import software_commit

FLEET = """\
robots:
  - {name: same, address: same.local}
  - {name: behind, address: 192.0.2.7}
  - {name: ancient, address: ancient.local}
  - {name: spare-1, address: spare-1.local, spare: true}
  - {name: spare-2, address: spare-2.local, spare: true}
  - {name: away, address: away.local, enabled: false}
"""
OLD_COMMIT = "0123456789abcdef0123456789abcdef01234567"


@pytest.fixture
def config(tmp_path: Path):
    (tmp_path / "fleet.yaml").write_text(FLEET)
    (tmp_path / "master.yaml").write_text(
        "experiment: {robots: 3, seed: 1}\nhost: 127.0.0.1\nport: 0\ninventory: fleet.yaml\n"
    )
    return load_master_config(tmp_path / "master.yaml")


async def test_other_software_is_unfit_and_the_fix_is_named(config):
    assert config.allowed_robots == ["same", "behind", "ancient"]
    commit = software_commit()
    assert commit is not None, "the tests run from a git checkout"
    listening: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    async with AsyncExitStack() as stack:
        check = asyncio.create_task(
            run_check(config, SECRET, timeout=20, on_listening=listening.set_result)
        )
        port = await listening
        for robot in ("same", "behind", "ancient", "spare-1"):
            agent, _ = await start_robot(stack, robot, port, "(in-process)")
            # Set before the agent's first connection: the link's task has not run yet.
            if robot == "behind":
                agent.link.software_commit = OLD_COMMIT
            elif robot == "ancient":
                agent.link.software_commit = None
                agent.link.software_version = "0.0.9"
        rows = await asyncio.wait_for(check, 60)

    by = {row.robot: row for row in rows}
    assert [row.robot for row in rows] == ["same", "behind", "ancient", "spare-1", "spare-2"]
    assert [row.robot for row in rows if row.fit] == ["same", "spare-1", "spare-2"]
    assert by["same"].fix is None and by["same"].commit == commit and by["same"].firmware == 11

    (behind,) = by["behind"].problems
    short = commit.removesuffix("-dirty")[:10]
    assert behind.startswith(
        f"other software than the master's: commit 0123456789, the master's {short}"
    )
    # The master has a fleet file: the fix is the playbook from the master's own checkout.
    fleet_file = config.inventory
    assert by["behind"].fix == (
        f"in the master's checkout: deploy/ansible/provision {fleet_file} --limit behind"
    )
    (ancient,) = by["ancient"].problems
    assert f"version 0.0.9, the master's {minimize_surprise.__version__}" in ancient
    assert "it reports no commit" in ancient
    assert by["ancient"].fix is not None and by["ancient"].fix.endswith("--limit ancient")

    assert by["spare-1"].spare and by["spare-1"].connected and not by["spare-1"].problems
    spare = by["spare-2"]
    assert spare.spare and not spare.connected and spare.fit
    assert any("spare, not connected" in note for note in spare.notes)

    table = format_table(rows)
    assert "behind: fix: in the master's checkout: deploy/ansible/provision" in table
    assert "spare-1 (spare)  fit" in table
    assert table.endswith("3 of 5 robots fit: fix the above")
    assert SPARE_GRACE < 20  # an absent spare does not hold the check for its whole timeout


def test_the_update_command_without_an_inventory_or_a_known_commit():
    assert update_command("r1", None, "a" * 40 + "-dirty") == (
        f"on r1's Pi, in its checkout: git fetch && git checkout {'a' * 40} && "
        "sudo deploy/install-pi.sh r1"
    )
    assert update_command("r1", "r1.lab", None) == (
        "ssh r1.lab, in its checkout: git pull && sudo deploy/install-pi.sh r1"
    )
