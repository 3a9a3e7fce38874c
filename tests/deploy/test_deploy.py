"""deploy/: the example configurations load, the systemd units verify and agree with the code,
the install script parses and builds outside the checkout."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from drivers.config import RUNTIME_PROGRAM_DIR, ThymioConfig
from master_service.config import load_master_config
from needs import missing, require_binary
from robot_agent.cli import STOP_CLOSE_TIMEOUT, STOP_ONCE_TIMEOUT
from robot_agent.config import load_agent_config

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
EXAMPLES = DEPLOY / "examples"
INSTALL = DEPLOY / "install-pi.sh"
#: Seconds a fresh interpreter may take on a slow Pi to reach the motor stop of ``--stop-motors``.
#: Measured 0.1 s on a desktop, where numpy imports in 0.05 s; numpy takes 1.7 s on an emulated
#: Pi, 35 times as long, which makes 3.5 s.
SLOW_PI_START = 5.0


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("agent-*.yaml")), ids=lambda p: p.name)
def test_example_agent_configurations_load(path):
    config = load_agent_config(path)
    assert config.robot_id.startswith("thymio-")
    assert config.body.thymio is not None


def test_example_master_configuration_loads_with_the_example_experiment(tmp_path):
    for name in ("master.yaml", "experiment.yaml", "fleet.yaml"):
        shutil.copy(EXAMPLES / name, tmp_path / name)
    (tmp_path / "secret.key").write_text("lab secret\n")
    config = load_master_config(tmp_path / "master.yaml")
    assert config.experiment.robots == 4 and config.experiment.evolution.evaluations == 350
    assert len(config.allowed_robots) == 4


def test_every_example_experiment_names_its_setting():
    """A key left out takes the setting's default: the file should say which one it is."""
    experiments = [p for p in EXAMPLES.glob("*.yaml") if "experiment" in p.name]
    assert experiments
    for path in experiments:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        assert data.get("setting") in ("lab", "paper"), f"{path.name} names no setting"


def test_example_robot_ids_are_the_masters_allow_list(tmp_path):
    for name in ("master.yaml", "experiment.yaml", "fleet.yaml"):
        shutil.copy(EXAMPLES / name, tmp_path / name)
    (tmp_path / "secret.key").write_text("s")
    allowed = set(load_master_config(tmp_path / "master.yaml").allowed_robots)
    ids = {load_agent_config(p).robot_id for p in EXAMPLES.glob("agent-thymio-*.yaml")}
    assert ids == allowed


def test_the_readmes_rehearsal_runs_the_example_files_as_they_are(tmp_path):
    """The README's rehearsal serves the robots the example master allows, with agent files of
    their names, and runs the experiment's number of robots."""
    import re

    for name in ("master.yaml", "experiment.yaml", "fleet.yaml"):
        shutil.copy(EXAMPLES / name, tmp_path / name)
    (tmp_path / "secret.key").write_text("s")
    config = load_master_config(tmp_path / "master.yaml")
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    rehearsal = readme[readme.index("To rehearse a lab day") :]
    ids = re.search(r"--ids (\S+)", rehearsal)
    assert ids is not None, "the README's rehearsal names no --ids"
    served = ids.group(1).split(",")
    assert served == config.allowed_robots and len(served) == config.experiment.robots
    loop = re.search(
        r"for i in ([\d ]+); do surprise-agent --config robots/agent-(\S+?)\$i", rehearsal
    )
    assert loop is not None
    agents = [f"{loop.group(2)}{i}" for i in loop.group(1).split()]
    assert agents == served
    assert "--config master.yaml" in rehearsal


def test_one_recipe_for_the_shared_secret():
    pages = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
    for page in pages:
        text = page.read_text(encoding="utf-8")
        for other in ("urandom", "token_hex", "openssl rand"):
            assert other not in text, f"{page.name} makes a secret with {other}"
    assert "surprise-master secret secret.key" in (REPO / "README.md").read_text(encoding="utf-8")


def _stub(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("#!/bin/sh\n")
    path.chmod(0o755)


def test_systemd_units_verify(tmp_path):
    """Verify in a throw-away root holding the distribution's units and the binaries the units
    run, so the check is about our units, not about what this machine has installed."""
    require_binary("systemd-analyze")
    system = Path("/usr/lib/systemd/system")
    if not (system / "sysinit.target").exists():
        missing("no systemd unit tree on this machine: install the Debian package systemd")
    root = tmp_path / "root"
    shutil.copytree(system, root / "usr/lib/systemd/system", symlinks=True)
    units = sorted((DEPLOY / "systemd").glob("*.service"))
    dest = root / "etc/systemd/system"
    dest.mkdir(parents=True)
    for unit in units:
        shutil.copy(unit, dest / unit.name)
        for line in unit.read_text().splitlines():
            if line.startswith(("ExecStart=", "ExecStopPost=")):
                _stub(root / line.split("=", 1)[1].split()[0].lstrip("/"))
    result = subprocess.run(
        [
            "systemd-analyze",
            "verify",
            f"--root={root}",
            *(f"/etc/systemd/system/{u.name}" for u in units),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    # verify exits 0 even for some parse errors ("ignoring"): any output at all is a finding.
    assert result.returncode == 0 and result.stderr.strip() == "", result.stderr


def test_dbus_policy_is_well_formed_xml():
    import xml.etree.ElementTree as ET

    root = ET.parse(DEPLOY / "dbus/ch.epfl.mobots.Aseba.conf").getroot()
    owns = [e.get("own") for e in root.iter("allow")]
    assert "ch.epfl.mobots.Aseba" in owns


# --------------------------------------------------------------------------- the units' settings


def _unit(name: str) -> dict[str, dict[str, list[str]]]:
    """The settings of a unit in deploy/systemd: section, then key, then its values in order."""
    sections: dict[str, dict[str, list[str]]] = {}
    section: dict[str, list[str]] = {}
    for raw in (DEPLOY / "systemd" / name).read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = sections.setdefault(line.strip("[]"), {})
        else:
            key, _, value = line.partition("=")
            section.setdefault(key.strip(), []).append(value.strip())
    return sections


def _one(unit: str, section: str, key: str) -> str:
    (value,) = _unit(unit)[section][key]
    return value


def test_the_program_dir_hint_is_the_agents_runtime_directory():
    """The directory the configuration suggests for the programs' copies is the one the unit
    creates, writable under ProtectSystem=strict and readable by medulla."""
    service = "surprise-agent.service"
    assert "/run/" + _one(service, "Service", "RuntimeDirectory") == RUNTIME_PROGRAM_DIR
    with pytest.raises(ValueError, match=RUNTIME_PROGRAM_DIR):
        ThymioConfig(node="thymio-7")
    assert RUNTIME_PROGRAM_DIR in (REPO / "docs/configuration.md").read_text()
    # medulla runs as the directory's owner (both units: User=surprise) and reads and lists it.
    assert _one(service, "Service", "User") == _one("asebamedulla.service", "Service", "User")
    assert int(_one(service, "Service", "RuntimeDirectoryMode"), 8) & 0o500 == 0o500
    # Not removed by a stop or restart under a medulla that may be loading from it.
    assert _one(service, "Service", "RuntimeDirectoryPreserve") in ("yes", "restart")


def test_the_stop_timeout_leaves_time_for_the_stop_after_the_agent():
    """TimeoutStopSec bounds ExecStopPost too: a fresh interpreter plus the stop's own bounds."""
    timeout = _one("surprise-agent.service", "Service", "TimeoutStopSec")
    assert timeout.isdigit(), "plain seconds, so that this test can read it"
    assert int(timeout) >= STOP_ONCE_TIMEOUT + STOP_CLOSE_TIMEOUT + SLOW_PI_START
    (stop,) = _unit("surprise-agent.service")["Service"]["ExecStopPost"]
    assert stop.endswith("--stop-motors")


def test_medulla_s_tcp_port_is_reachable_from_nowhere():
    """asebamedulla listens on 0.0.0.0:33333 and cannot bind another address: it gets a network
    namespace of its own (.ci/pi-root checks on a booted systemd that the port is closed)."""
    service = _unit("asebamedulla.service")["Service"]
    assert service["PrivateNetwork"] == ["yes"]


# --------------------------------------------------------------------------- install-pi.sh

#: A pip that, like the real one, builds in the tree it installs from. It notes that tree and
#: what it held.
_FAKE_PIP = """#!/usr/bin/env bash
set -eu
for arg in "$@"; do
  case "$arg" in
    *"[robot]")
      tree=${{arg%"[robot]"}}
      echo "$tree" > {where}
      echo "${{MINIMIZE_SURPRISE_COMMIT-unset}}" > {where}.commit
      (cd "$tree" && find . -mindepth 1 | sort) > {seen}
      mkdir -p "$tree/build/lib" "$tree/minimize_surprise.egg-info"
      ;;
  esac
done
"""


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    """Every path below ``root`` with its owner and modification time."""
    found = {}
    for path in root.rglob("*"):
        status = path.lstat()
        found[str(path.relative_to(root))] = (status.st_uid, status.st_mtime_ns)
    return found


@pytest.fixture
def checkout(tmp_path: Path) -> Path:
    """A copy of this repository as a robot's checkout, with what development leaves in one."""
    root = tmp_path / "checkout"
    shutil.copytree(
        REPO,
        root,
        ignore=shutil.ignore_patterns(
            ".git", ".venv", "*.egg-info", "__pycache__", ".*_cache", ".hypothesis", "runs"
        ),
    )
    for junk in (
        ".git/HEAD",
        ".venv/bin/python",
        "runs/real-1/state.json",
        "build/lib/x.py",
        "minimize_surprise.egg-info/PKG-INFO",
    ):
        (root / junk).parent.mkdir(parents=True, exist_ok=True)
        (root / junk).write_text("")
    return root


def test_install_script_parses():
    assert subprocess.run(["bash", "-n", str(INSTALL)]).returncode == 0


def test_the_package_is_built_outside_the_checkout(tmp_path, checkout):
    """install-pi.sh runs as root: pip building in the pi user's checkout would leave root-owned
    build/ and *.egg-info there. It builds from a copy, removed when the script ends."""
    venv, where, seen = tmp_path / "venv", tmp_path / "where", tmp_path / "seen"
    (venv / "bin").mkdir(parents=True)
    pip = venv / "bin/pip"
    pip.write_text(_FAKE_PIP.format(where=where, seen=seen))
    pip.chmod(0o755)
    before = _tree(checkout)
    script = f'source {INSTALL} && install_package "$1" "$2"'
    result = subprocess.run(
        ["bash", "-c", script, "install-pi.sh", str(venv), str(checkout)],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "TMPDIR": str(tmp_path)},
    )
    assert result.returncode == 0, result.stderr
    assert _tree(checkout) == before  # nothing built, changed or left in the checkout
    tree = Path(where.read_text().strip())
    assert not tree.is_relative_to(checkout)
    assert not tree.exists()  # the copy is gone with the script
    copied = set(seen.read_text().splitlines())
    assert {"./pyproject.toml", "./README.md", "./robot_agent/cli.py"} <= copied
    assert "./drivers/failsafe.aesl" in copied  # package data
    for excluded in (".git", ".venv", "runs", "build", "minimize_surprise.egg-info"):
        assert f"./{excluded}" not in copied
    # The fixture's .git is no repository: the build is told that no commit is known.
    assert Path(f"{where}.commit").read_text() == "\n"


def test_the_checkout_s_commit_goes_to_the_build(tmp_path):
    """The copy pip builds from has no .git, so install-pi.sh passes the checkout's commit to
    the build (setup.py), "-dirty" with uncommitted changes."""
    root = tmp_path / "checkout"
    root.mkdir()
    git = ["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    (root / "file").write_text("a")
    subprocess.run([*git, "add", "file"], check=True)
    subprocess.run([*git, "commit", "-qm", "one"], check=True)
    head = subprocess.run(
        [*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True
    ).stdout.strip()

    def commit() -> str:
        script = f'source {INSTALL} && checkout_commit "$1"'
        return subprocess.run(
            ["bash", "-c", script, "install-pi.sh", str(root)],
            check=True, capture_output=True, text=True,
        ).stdout.strip()  # fmt: skip

    assert commit() == head
    (root / "file").write_text("b")
    assert commit() == f"{head}-dirty"
    (root / "untracked").write_text("runs leave files")
    (root / "file").write_text("a")
    assert commit() == head


def _setup_module():
    """The repository's setup.py as a module (its setup() runs only as a script)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("setup_under_test", REPO / "setup.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_build_bakes_in_the_commit_it_is_given_or_finds(tmp_path, monkeypatch):
    setup = _setup_module()
    given = "0123456789abcdef0123456789abcdef01234567"
    monkeypatch.setenv(setup.COMMIT_ENV, given)
    assert setup.source_commit(tmp_path) == given
    monkeypatch.setenv(setup.COMMIT_ENV, "not a commit")
    with pytest.raises(SystemExit, match="not a commit"):
        setup.source_commit(tmp_path)
    monkeypatch.setenv(setup.COMMIT_ENV, "")  # install-pi.sh outside a checkout: none known
    assert setup.source_commit(tmp_path) is None
    # An sdist's tree carries the stamp of the build that made it.
    setup.stamp(tmp_path, given + "-dirty")
    assert setup.source_commit(tmp_path) == given + "-dirty"
    assert setup.source_commit(REPO) is not None  # this checkout, from git
    setup.stamp(tmp_path / "build", None)
    text = (tmp_path / "build/minimize_surprise/_build.py").read_text()
    assert "COMMIT = None" in text
