"""``surprise-master fleet logs --since T``: each enabled robot's journal over ssh into the run
directory's ``journals/``. The tests cannot ssh to robots: a fake ``ssh`` on ``PATH`` prints
canned journal lines for the addresses it knows and fails as ssh does for the one that is off
(docs/fleet.md)."""

from __future__ import annotations

import shlex
import stat
from pathlib import Path

import pytest

from master_service.cli import main
from master_service.cli_fleet import journal_command

FLEET = """\
robots:
  - {name: alpha, address: alpha.local}
  - {name: beta, address: 192.0.2.8}
  - {name: gamma, address: gamma.local}
  - {name: away, address: away.local, enabled: false}
"""
# The fake ssh: its last argument is the remote command, the one before it the address; it
# records each call and answers like a robot's journalctl (gamma is switched off).
FAKE_SSH = """#!/bin/sh
for last; do :; done
eval "host=\\${$(($# - 1))}"
printf '%s\\n' "$*" >> "$(dirname "$0")/calls"
if [ "$host" = gamma.local ]; then
    echo "ssh: connect to host gamma.local port 22: No route to host" >&2
    exit 255
fi
echo "2025-03-01T14:00:01+0000 $host surprise-agent[412]: welcomed into run 20250301-1400"
echo "2025-03-01T14:00:02+0000 $host asebamedulla[388]: Found Thymio-II on /dev/ttyACM0"
"""


@pytest.fixture
def lab(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    (tmp_path / "fleet.yaml").write_text(FLEET)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    ssh = bin_dir / "ssh"
    ssh.write_text(FAKE_SSH)
    ssh.chmod(ssh.stat().st_mode | stat.S_IXUSR)
    monkeypatch.setenv("PATH", f"{bin_dir}:/usr/bin:/bin")
    (tmp_path / "run").mkdir()
    return tmp_path


def test_the_journals_land_in_the_run_and_the_robot_that_is_off_is_named(
    lab: Path, capsys: pytest.CaptureFixture[str]
):
    argv = ["fleet", "logs", "--inventory", str(lab / "fleet.yaml"), "--run", str(lab / "run")]
    code = main([*argv, "--since", "2025-03-01 14:00"])
    out, err = capsys.readouterr()
    assert code == 1, out + err
    journals = lab / "run" / "journals"
    assert sorted(p.name for p in journals.iterdir()) == ["alpha.log", "beta.log"]
    alpha = (journals / "alpha.log").read_text().splitlines()
    assert alpha[0].endswith("alpha.local surprise-agent[412]: welcomed into run 20250301-1400")
    assert "asebamedulla" in alpha[1]
    assert f"alpha: {journals / 'alpha.log'}" in out
    assert "gamma: not gathered: ssh gamma.local exited 255: ssh: connect to host" in err
    calls = (lab / "bin" / "calls").read_text().splitlines()
    assert len(calls) == 3 and not any("away.local" in call for call in calls)  # disabled
    (alpha_call,) = [call for call in calls if "alpha.local" in call]
    assert "journalctl --no-pager -o short-iso --since '2025-03-01 14:00'" in alpha_call
    assert "-u surprise-agent -u asebamedulla" in alpha_call


def test_the_remote_command_keeps_the_time_one_word():
    command = journal_command("thymio-1.local", "1 hour ago")
    assert command[:2] == ["ssh", "-o"] and command[-2] == "thymio-1.local"
    remote = shlex.split(command[-1])
    assert remote[remote.index("--since") + 1] == "1 hour ago"
