"""The paper's real-robot experiment rehearsed in separate processes: ``surprise-sim-robots
--scenario boxes --arena real-objects`` serves 4 robots whose force sensor is an emulated ADS1115
behind an I2C bridge socket each, 4 ``surprise-agent`` processes read it with the real force
driver, and ``surprise-master run`` runs the shipped
deploy/examples/experiment-object-manipulation.yaml for a few short evaluations
(docs/separate-processes.md, docs/rehearsal.md).

With ``--backend sim`` the chips read the world's force on each blade; with ``--backend
playground`` Enki has no blade, so the force reads an unloaded blade: zero at every step. The
gradient scenario's robots read their two light sensors, behind a multiplexer, the same way.
"""

from __future__ import annotations

import json
import signal
import stat
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from aseba_stack import require_aseba
from test_separate_processes import (
    START_TIMEOUT,
    STOP_TIMEOUT,
    Processes,
    free_port,
    procs,  # noqa: F401  # the fixture
    read_rows,
    wait_for,
)

from robot_agent.config import load_agent_config
from standins.i2c_bridge import SERVED_FORCE

pytestmark = pytest.mark.slow

SHIPPED = Path(__file__).resolve().parents[2] / "deploy" / "examples"
EXPERIMENT = SHIPPED / "experiment-object-manipulation.yaml"
ROBOTS = 4
EVALUATIONS = 3
#: One evaluation is STEPS * 0.1 s of wall-clock time: a short run, yet several control steps.
STEPS = 10
SECRET = "object-rehearsal-secret\n"
#: Seconds for the whole run: three one-second evaluations and the post-evaluation take about
#: 5 s, the agents' start (importing, zeroing the force sensor, attaching) a few more.
RUN_TIMEOUT = 60.0


def _short_experiment(directory: Path) -> Path:
    """The shipped experiment as it is but for its length: a few evaluations of a second."""
    data = yaml.safe_load(EXPERIMENT.read_text())
    assert (data["scenario"], data["arena"], data["robots"]) == ("boxes", "real-objects", ROBOTS)
    assert "force" in data["sensors"]
    data["evolution"]["evaluations"] = EVALUATIONS
    data["evaluation_steps"] = data["post_evaluation_steps"] = STEPS
    path = directory / "experiment.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _rehearse(lab: Processes, tmp_path: Path, backend: str) -> dict[str, np.ndarray]:
    """Serve, run and stop a rehearsal on ``backend``; each robot's post-evaluation force."""
    port = free_port()
    secret = tmp_path / "secret.key"
    secret.write_text(SECRET)
    robots_dir = tmp_path / "robots"
    lab.start(
        "sim",
        "standins.serve",
        *("--backend", backend, "--scenario", "boxes", "--arena", "real-objects"),
        *("--seed", "1", "--dir", str(robots_dir)),
        *("--master-port", str(port), "--secret-file", str(secret)),
        *("--reconnect-initial", "0.1", "--reconnect-max", "1.0"),
    )
    announced = robots_dir / "robots.json"
    wait_for(announced.exists, START_TIMEOUT, "robots.json", lab, alive=("sim",))
    info: dict[str, Any] = json.loads(announced.read_text())
    bridges = [Path(robot["i2c_bridge"]) for robot in info["robots"]]
    assert len(set(bridges)) == ROBOTS and "I2C chips" in info["i2c"]
    for robot, bridge in zip(info["robots"], bridges, strict=True):
        assert stat.S_ISSOCK(bridge.stat().st_mode)
        body = load_agent_config(robot["config"]).body
        assert body.i2c_bridge == str(bridge) and body.force == SERVED_FORCE
        assert body.light == [] and "force" in body.sensor_names()

    master_config = tmp_path / "master.yaml"
    master_config.write_text(
        yaml.safe_dump(
            {
                "experiment_file": str(_short_experiment(tmp_path)),
                "host": "127.0.0.1",
                "port": port,
                "secret_file": str(secret),
                "allowed_robots": [robot["robot_id"] for robot in info["robots"]],
                # A round's deadline is 1 s + this: room for a slow agent on a loaded machine.
                "round_margin": 3.0,
                "heartbeat_interval": 1.0,
            }
        )
    )
    for index, robot in enumerate(info["robots"]):
        lab.start(f"agent-{index}", "robot_agent.cli", "--config", robot["config"])
    run = tmp_path / "run"
    master = ("run", "--config", str(master_config), "--out", str(run))
    lab.start("master", "master_service", *master)
    assert lab.wait("master", RUN_TIMEOUT) == 0, lab.report()

    rows = read_rows(run)
    assert [int(r["evaluation"]) for r in rows] == list(range(1, EVALUATIONS + 1)), lab.report()
    for robot in info["robots"]:
        assert {r[f"read_failures_{robot['robot_id']}"] for r in rows} == {"0"}, lab.report()
    sensors = yaml.safe_load((run / "config.yaml").read_text())["experiment"]["sensors"]
    column = sensors.index("force")
    forces = {}
    for robot in info["robots"]:
        with np.load(run / "traces" / f"{robot['robot_id']}.npz") as trace:
            assert trace["sensors"].shape == (STEPS, len(sensors))
            forces[robot["robot_id"]] = trace["sensors"][:, column]

    for index in range(ROBOTS):
        lab.kill(f"agent-{index}", signal.SIGTERM)
    for index in range(ROBOTS):
        assert lab.wait(f"agent-{index}", STOP_TIMEOUT) == 0, lab.report()
    lab.kill("sim", signal.SIGTERM)
    assert lab.wait("sim", STOP_TIMEOUT * 3) == 0, lab.report()
    assert not any(bridge.exists() for bridge in bridges), "bridge sockets left behind"
    assert not bridges[0].parent.exists()
    return forces


def test_the_object_experiment_rehearsed_with_the_worlds_force(
    procs: Processes,  # noqa: F811
    tmp_path: Path,
):
    forces = _rehearse(procs, tmp_path, "sim")
    # The world's force on each blade, normalised: whether a blade met a box in one second of
    # an evolved behaviour is chance, but every value is one the driver decoded.
    for values in forces.values():
        assert np.isfinite(values).all() and ((values >= 0.0) & (values <= 1.0)).all()
    output = procs.logs[0].read_text()
    assert "I2C bridge" in output and "the force on each robot's blade" in output


def test_the_object_experiment_rehearsed_in_playground_reads_no_force(
    procs: Processes,  # noqa: F811
    tmp_path: Path,
):
    require_aseba()
    forces = _rehearse(procs, tmp_path, "playground")
    assert {robot: float(np.abs(values).max()) for robot, values in forces.items()} == {
        f"sim-{i}": 0.0 for i in range(ROBOTS)
    }
    assert "Enki has no blade" in procs.logs[0].read_text()


def test_the_gradient_robots_read_their_light_sensors_over_the_bridge(
    procs: Processes,  # noqa: F811
    tmp_path: Path,
):
    port = free_port()
    secret = tmp_path / "secret.key"
    secret.write_text(SECRET)
    robots_dir = tmp_path / "robots"
    procs.start(
        "sim",
        "standins.serve",
        *("--scenario", "gradient", "--robots", "2", "--seed", "1", "--dir", str(robots_dir)),
        *("--master-port", str(port), "--secret-file", str(secret)),
    )
    announced = robots_dir / "robots.json"
    wait_for(announced.exists, START_TIMEOUT, "robots.json", procs, alive=("sim",))
    info = json.loads(announced.read_text())
    assert "the light at its light sensors" in info["i2c"]
    sensors = load_agent_config(info["robots"][0]["config"]).body.sensor_names()
    assert sensors[-3:] == ("force", "light.0", "light.1")
    master_config = tmp_path / "master.yaml"
    master_config.write_text(
        yaml.safe_dump(
            {
                "experiment": {"scenario": "gradient", "robots": 2, "sensors": list(sensors)},
                "host": "127.0.0.1",
                "port": port,
                "secret_file": str(secret),
                "allowed_robots": [robot["robot_id"] for robot in info["robots"]],
            }
        )
    )
    for index, robot in enumerate(info["robots"]):
        procs.start(f"agent-{index}", "robot_agent.cli", "--config", robot["config"])
    # The preflight reads every part of every robot (docs/preflight.md).
    procs.start("check", "master_service", "check", str(master_config), "--json")
    assert procs.wait("check", RUN_TIMEOUT) == 0, procs.report()
    output = procs.logs[-1].read_text()  # the JSON, among the log lines of the robots joining
    rows, _ = json.JSONDecoder().raw_decode(output, output.index("[\n"))
    for row in rows:
        readings = row["readings"]
        assert row["fit"] and readings["force"] == 0.0, row  # nothing pushed before the start
        # The lamp's light at the start ring, in the TSL45315's steps of 4 / 1024 (the preflight
        # prints 4 decimals: 0.00005 x 256 off at most).
        for name in ("light.0", "light.1"):
            assert 0.0 < readings[name] < 1.0, row
            assert readings[name] * 256 == pytest.approx(round(readings[name] * 256), abs=0.02)
