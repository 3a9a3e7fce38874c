"""A lab day rehearsed without robots: ``surprise-sim-robots --backend playground`` starts Aseba
Playground's Thymios behind real ``asebamedulla`` processes, real ``surprise-agent`` processes
drive them with the configurations it wrote, ``surprise-master run`` runs a short evolution, and
SIGTERM ends every process the server started (docs/rehearsal.md).

Every process is started as ``python -m <module>`` (the helpers of
test_separate_processes.py); a failing test prints their output's tails.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

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

from needs import pids, processes
from robot_agent.config import load_agent_config
from standins.playground import PLAYGROUND_SPEED_SCALE

pytestmark = pytest.mark.slow

ROBOTS = 2
EVALUATIONS = 4
#: One evaluation is STEPS * 0.1 s of wall-clock time: a short run, yet several control steps.
STEPS = 10
SECRET = "rehearsal-secret\n"
#: Seconds for the whole run: four one-second evaluations and the post-evaluation take about 6 s,
#: the agents' start (importing, attaching, loading the failsafe program) a few more.
RUN_TIMEOUT = 45.0
#: What the server starts besides itself, by command name: Playground, a medulla per robot, a
#: dbus-daemon per robot and one for Playground's world.
EXPECTED = {"asebaplayground": 1, "asebamedulla": ROBOTS, "dbus-daemon": ROBOTS + 1}


def _started_by(pid: int) -> dict[int, str]:
    """The processes ``pid`` started that the server starts (by command name)."""
    return {p.pid: p.name for p in processes() if p.ppid == pid and p.name in EXPECTED}


def test_a_lab_day_rehearsed_with_playground_robots(procs: Processes, tmp_path: Path):  # noqa: F811
    require_aseba()
    port = free_port()
    secret = tmp_path / "secret.key"
    secret.write_text(SECRET)
    robots_dir = tmp_path / "robots"
    procs.start(
        "sim",
        "standins.serve",
        *("--backend", "playground", "--robots", str(ROBOTS), "--seed", "5"),
        *("--dir", str(robots_dir), "--master-port", str(port), "--secret-file", str(secret)),
        *("--reconnect-initial", "0.1", "--reconnect-max", "1.0"),
    )
    announced = robots_dir / "robots.json"
    wait_for(announced.exists, START_TIMEOUT, "robots.json", procs, alive=("sim",))
    info = json.loads(announced.read_text())
    assert info["pid"] == procs.pid("sim") and info["backend"] == "playground"

    started = _started_by(info["pid"])
    counts = {name: list(started.values()).count(name) for name in EXPECTED}
    assert counts == EXPECTED, procs.report()
    for index, robot in enumerate(info["robots"]):
        config = load_agent_config(robot["config"])
        assert config.robot_id == robot["robot_id"] == f"sim-{index}"
        thymio = config.body.thymio
        assert thymio.bus == robot["bus"] and thymio.speed_scale == PLAYGROUND_SPEED_SCALE
        assert thymio.failsafe and thymio.restart_medulla
        assert config.master.port == port and config.safety.profile == "stop"

    master_config = tmp_path / "master.yaml"
    master_config.write_text(
        yaml.safe_dump(
            {
                "experiment": {
                    "scenario": "basic",
                    "robots": ROBOTS,
                    "seed": 5,
                    "evaluation_steps": STEPS,
                    "post_evaluation_steps": STEPS,
                    "evolution": {"evaluations": EVALUATIONS},
                },
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
        procs.start(f"agent-{index}", "robot_agent.cli", "--config", robot["config"])
    # The preflight, as a lab does it before the run (docs/preflight.md).
    procs.start("check", "master_service", "check", str(master_config), "--json")
    assert procs.wait("check", RUN_TIMEOUT) == 0, procs.report()
    output = procs.logs[-1].read_text()  # the JSON, among the log lines of the robots joining
    rows, _ = json.JSONDecoder().raw_decode(output, output.index("[\n"))
    assert [(r["robot"], r["fit"]) for r in rows] == [("sim-0", True), ("sim-1", True)], rows
    for row in rows:
        # Playground's Thymio declares no _vbat: unknown, never invented; its carpet is darker
        # than the ground rule's boundary, so the robots will drive.
        assert row["battery_v"] is None and "battery unknown" in row["notes"][0]
        assert max(row["readings"]["ground.0"], row["readings"]["ground.1"]) < 0.55
    run = tmp_path / "run"
    master = ("run", "--config", str(master_config), "--out", str(run))
    procs.start("master", "master_service", *master)
    assert procs.wait("master", RUN_TIMEOUT) == 0, procs.report()
    rows = read_rows(run)
    assert [int(r["evaluation"]) for r in rows] == list(range(1, EVALUATIONS + 1)), procs.report()
    # What the robots reported: no battery from Playground (unknown, left empty), no failed read.
    assert {r["battery_v_sim-0"] for r in rows} == {""}
    assert {r["read_failures_sim-1"] for r in rows} == {"0"}

    # The best genome replayed on the same robots: the gap beside the run's own post-evaluation.
    replay = tmp_path / "replay"
    procs.start("replay", "master_service", "replay", str(run), "--config", str(master_config),
                "--out", str(replay))  # fmt: skip
    assert procs.wait("replay", RUN_TIMEOUT) == 0, procs.report()
    gap = json.loads((replay / "metrics.json").read_text())["reality_gap"]
    assert gap["source_run"] == str(run.resolve()) and gap["steps"]["replay"] == STEPS
    assert [(r["source_robot"], r["replay_robot"]) for r in gap["robots"]] == [
        ("sim-0", "sim-0"), ("sim-1", "sim-1")
    ]  # fmt: skip
    assert all(0.0 < r["replay_fitness"] <= 1.0 for r in gap["robots"])

    for index in range(ROBOTS):
        procs.kill(f"agent-{index}", signal.SIGTERM)
    for index in range(ROBOTS):
        assert procs.wait(f"agent-{index}", STOP_TIMEOUT) == 0, procs.report()
    procs.kill("sim", signal.SIGTERM)
    # Each process gets STOP_TIMEOUT after SIGTERM, one after another in the worst case.
    assert procs.wait("sim", STOP_TIMEOUT * len(started)) == 0, procs.report()
    left = set(started) & pids()
    assert not left, f"left running: {[started[pid] for pid in left]}\n{procs.report()}"
    assert not announced.exists()
