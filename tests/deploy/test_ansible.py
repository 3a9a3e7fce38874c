"""deploy/ansible: the fleet file as an Ansible inventory, the playbook's syntax, a new robot's
agent.yaml, and what the role installs agreeing with install-pi.sh (no robot needed; the
booted robots are .ci/fleet-roots's)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from drivers.config import RUNTIME_PROGRAM_DIR
from master_service.cli import main as master_main
from master_service.fleet_hosts import ansible_inventory
from master_service.inventory import load_inventory
from needs import missing, require_binary
from robot_agent.config import load_agent_config

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
ANSIBLE = DEPLOY / "ansible"
ROLE = ANSIBLE / "roles" / "surprise_agent"
FLEET = DEPLOY / "examples" / "fleet.yaml"


def ansible_tool(name: str) -> str:
    """The path of an ansible-core command (the fleet extra), next to this interpreter first."""
    beside = Path(sys.executable).parent / name
    found = str(beside) if beside.exists() else shutil.which(name)
    if found is None:
        missing(f"{name} is missing: pip install -e '.[fleet]'")
    assert found is not None
    return found


def run_ansible(tool: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ANSIBLE_CONFIG": str(ANSIBLE / "ansible.cfg"), "ANSIBLE_NOCOLOR": "1"}
    # Ansible keeps its temporary files and cache in the home directory: the test's own.
    env["HOME"] = str(cwd)
    return subprocess.run(
        [ansible_tool(tool), *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )


def write_fleet(tmp_path: Path) -> Path:
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text(
        "robots:\n"
        "  - {name: thymio-1, address: thymio-1.local, marker: 10}\n"
        "  - {name: thymio-2, address: 192.0.2.12, node: thymio-B, marker: 11}\n"
        "  - {name: thymio-5, address: thymio-5.local, spare: true}\n"
        "  - {name: thymio-6, address: thymio-6.local, enabled: false}\n"
    )
    return fleet


def test_the_inventory_has_every_robot_with_its_address_and_groups(tmp_path):
    hosts = ansible_inventory(load_inventory(write_fleet(tmp_path)))["all"]
    assert hosts["hosts"]["thymio-2"] == {"ansible_host": "192.0.2.12", "robot_node": "thymio-B"}
    assert hosts["hosts"]["thymio-1"]["robot_node"] == "thymio-II"
    groups = hosts["children"]
    assert list(groups["swarm"]["hosts"]) == ["thymio-1", "thymio-2"]
    assert list(groups["spares"]["hosts"]) == ["thymio-5"]
    assert list(groups["disabled"]["hosts"]) == ["thymio-6"]
    # The playbook's group: the swarm and the spares, never a disabled robot.
    assert set(groups["robots"]["children"]) == {"swarm", "spares"}


def test_ansible_resolves_the_generated_inventory(tmp_path, capsys):
    assert master_main(["fleet", "inventory", str(write_fleet(tmp_path))]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# Generated from ")
    (tmp_path / "hosts.yml").write_text(out)
    listed = run_ansible("ansible-inventory", "-i", "hosts.yml", "--list", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    inventory = json.loads(listed.stdout)
    assert sorted(inventory["robots"]["children"]) == ["spares", "swarm"]
    assert inventory["swarm"]["hosts"] == ["thymio-1", "thymio-2"]
    assert inventory["_meta"]["hostvars"]["thymio-2"]["ansible_host"] == "192.0.2.12"
    graph = run_ansible("ansible-inventory", "-i", "hosts.yml", "--graph", "robots", cwd=tmp_path)
    assert "thymio-5" in graph.stdout
    assert "thymio-6" not in graph.stdout


def test_the_shipped_fleet_becomes_an_inventory(tmp_path, capsys):
    assert master_main(["fleet", "inventory", str(FLEET)]) == 0
    inventory = yaml.safe_load(capsys.readouterr().out)
    assert len(inventory["all"]["hosts"]) == len(load_inventory(FLEET).robots)


def test_a_broken_fleet_is_refused_naming_the_key(tmp_path, capsys):
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text("robots:\n  - {name: a, address: x}\n  - {name: a, address: y}\n")
    assert master_main(["fleet", "inventory", str(fleet)]) == 2
    assert "robots[1].name" in capsys.readouterr().err


def test_the_playbook_passes_the_syntax_check(tmp_path):
    (tmp_path / "hosts.yml").write_text(yaml.safe_dump(ansible_inventory(load_inventory(FLEET))))
    checked = run_ansible(
        "ansible-playbook",
        "-i",
        "hosts.yml",
        str(ANSIBLE / "provision.yml"),
        "--syntax-check",
        cwd=tmp_path,
    )
    assert checked.returncode == 0, checked.stdout + checked.stderr
    # No task is unknown or deprecated: Ansible warns of both.
    assert "WARNING" not in checked.stderr, checked.stderr


def test_a_new_robots_agent_yaml_loads_with_its_name_master_and_node(tmp_path):
    """The role's agent.yaml template, rendered by Ansible itself, is the example with the
    robot's name, the laptop as master and its node."""
    template = ROLE / "templates" / "agent.yaml.j2"
    rendered = run_ansible(
        "ansible",
        "localhost",
        "-m",
        "ansible.builtin.debug",
        "-a",
        f"msg={{{{ lookup('ansible.builtin.template', '{template}') }}}}",
        "-e",
        f"agent_example={DEPLOY / 'examples' / 'agent-thymio-1.yaml'}",
        "-e",
        "inventory_hostname=thymio-7 laptop_address=192.0.2.99 robot_node=thymio-Z",
        "-o",
        cwd=tmp_path,
    )
    assert rendered.returncode == 0, rendered.stdout + rendered.stderr
    # One line: "localhost | SUCCESS => {...}".
    text = json.loads(rendered.stdout.split("=>", 1)[1])["msg"]
    (tmp_path / "agent.yaml").write_text(text)
    config = load_agent_config(tmp_path / "agent.yaml")
    assert config.robot_id == "thymio-7"
    assert config.master.host == "192.0.2.99"
    assert config.body.thymio is not None
    assert config.body.thymio.node == "thymio-Z"
    assert config.body.thymio.program_dir == RUNTIME_PROGRAM_DIR


def role_tasks() -> list[dict]:
    return yaml.safe_load((ROLE / "tasks" / "main.yml").read_text())


def test_the_role_installs_what_install_pi_sh_installs():
    defaults = yaml.safe_load((ROLE / "defaults" / "main.yml").read_text())
    install = (DEPLOY / "install-pi.sh").read_text()
    apt_line = next(line for line in install.splitlines() if "apt-get install -y" in line)
    for package in apt_line.split("-qq", 1)[1].split():
        assert package in defaults["surprise_packages"], package
    assert "chrony" in defaults["surprise_packages"]
    tasks = (ROLE / "tasks" / "main.yml").read_text()
    for unit in sorted((DEPLOY / "systemd").glob("*.service")):
        assert unit.name in tasks
    assert "ch.epfl.mobots.Aseba.conf" in tasks
    assert "en_US.UTF-8 UTF-8" in tasks


def test_the_secret_never_shows():
    secret = next(t for t in role_tasks() if "secret.key" in str(t.get("ansible.builtin.copy")))
    assert secret["no_log"] is True
    assert secret["diff"] is False
    assert secret["ansible.builtin.copy"]["mode"] == "0600"


@pytest.mark.parametrize("script", ["deploy/ansible/provision", ".ci/fleet-roots"])
def test_the_scripts_are_shellcheck_clean(script):
    shellcheck = require_binary("shellcheck")
    checked = subprocess.run(
        [shellcheck, "-x", script], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert checked.returncode == 0, checked.stdout
