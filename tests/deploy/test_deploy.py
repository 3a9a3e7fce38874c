"""deploy/: the example configurations load, the systemd units verify, the install script parses."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from master_service.config import load_master_config
from robot_agent.config import load_agent_config

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
EXAMPLES = DEPLOY / "examples"


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("agent-*.yaml")), ids=lambda p: p.name)
def test_example_agent_configurations_load(path):
    config = load_agent_config(path)
    assert config.robot_id.startswith("thymio-")
    assert config.body.thymio is not None


def test_example_master_configuration_loads_with_the_example_experiment(tmp_path):
    for name in ("master.yaml", "experiment.yaml"):
        shutil.copy(EXAMPLES / name, tmp_path / name)
    (tmp_path / "secret.key").write_text("lab secret\n")
    config = load_master_config(tmp_path / "master.yaml")
    assert config.experiment.robots == 4 and config.experiment.evolution.evaluations == 350
    assert len(config.allowed_robots) == 4


def test_example_robot_ids_are_the_masters_allow_list(tmp_path):
    for name in ("master.yaml", "experiment.yaml"):
        shutil.copy(EXAMPLES / name, tmp_path / name)
    (tmp_path / "secret.key").write_text("s")
    allowed = set(load_master_config(tmp_path / "master.yaml").allowed_robots)
    ids = {load_agent_config(p).robot_id for p in EXAMPLES.glob("agent-thymio-*.yaml")}
    assert ids == allowed


def _stub(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("#!/bin/sh\n")
    path.chmod(0o755)


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_units_verify(tmp_path):
    """Verify in a throw-away root holding the distribution's units and the binaries the units
    run, so the check is about our units, not about what this machine has installed."""
    system = Path("/usr/lib/systemd/system")
    if not (system / "sysinit.target").exists():
        pytest.skip("no systemd unit tree on this machine")
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


def test_install_script_parses():
    assert subprocess.run(["bash", "-n", str(DEPLOY / "install-pi.sh")]).returncode == 0


def test_dbus_policy_is_well_formed_xml():
    import xml.etree.ElementTree as ET

    root = ET.parse(DEPLOY / "dbus/ch.epfl.mobots.Aseba.conf").getroot()
    owns = [e.get("own") for e in root.iter("allow")]
    assert "ch.epfl.mobots.Aseba" in owns
