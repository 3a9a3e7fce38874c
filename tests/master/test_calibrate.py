"""``surprise-master calibrate ROBOT`` on a simulated robot whose right wheel drives at 95 % of its
command, on a floor darker than the lab's (0.2 against 0.4), its rim the lab's mirror film.

A real agent drives the simulated body; the test plays the person: it moves the robot onto the
floor, then onto the rim, when the command says so, and when told to stop filming it films the
drive with the synthetic overhead camera (the world's recorded poses, the start flash) and
saves the video where the command's ``--video`` says. The command tracks it, recovers the
asymmetry within 1 % and puts the ground threshold between floor and rim, and the inventory
holds both, its other lines unchanged. Mistakes are refused with what was wrong.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import random
import socket
from pathlib import Path

import numpy as np
import pytest

from master_service import cli_fleet
from master_service.calibration import (
    CalibrationError,
    drive_speeds,
    ground_threshold,
    wheel_scales,
    write_calibration,
)
from master_service.inventory import load_inventory
from minimize_surprise.backoff import BackoffConfig
from minimize_surprise.errors import ConfigError
from robot_agent.agent import Agent
from robot_agent.config import AgentConfig
from robot_agent.config import MasterConfig as AgentMasterConfig
from simulator.body import SimSwarm
from simulator.world import World, WorldConfig
from standins.overhead_camera import OverheadScene, OverheadVideo

SECRET = b"calibration secret"
ROBOT = "thymio-3"
MARKER = 12
#: The simulated robot's wheels: the right one drives at 95 % of its command.
WHEELS = (1.0, 0.95)
FLEET = """\
# The lab's fleet (comments and order stay as they are)
robots:
  - name: thymio-1
    address: thymio-1.local
    marker: 10
  - name: thymio-3            # the one on the bench
    address: thymio-3.local
    marker: 12
  - {name: thymio-4, address: thymio-4.local, marker: 13, spare: true}
"""
#: The floor between the corner markers, and the carpet on it (docs/tracking.md).
FLOOR = 1.3
CARPET = 1.1


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def lab(tmp_path: Path) -> Path:
    (tmp_path / "fleet.yaml").write_text(FLEET)
    (tmp_path / "secret").write_bytes(SECRET)
    (tmp_path / "secret").chmod(0o600)
    (tmp_path / "master.yaml").write_text(
        "experiment: {robots: 2, seed: 1}\nhost: 127.0.0.1\n"
        f"port: {_free_port()}\ninventory: fleet.yaml\nsecret_file: secret\n"
    )
    (tmp_path / "tracking.yaml").write_text(
        f"floor: [{FLOOR}, {FLOOR}]\nrobots: {{offset: [0.02, 0.0]}}\ncamera: {{height: 2.0}}\n"
    )
    return tmp_path


async def test_a_robot_s_floor_rim_and_wheels_are_measured_into_the_inventory(lab: Path):
    world = World(
        WorldConfig(robots=1, arena_side=CARPET, ground_carpet=0.2, ground_noise=0.02), seed=4
    )
    swarm = SimSwarm(world, attach_all=True)
    port = int((lab / "master.yaml").read_text().split("port: ")[1].split()[0])
    video = lab / "drive.avi"
    asked: list[str] = []

    async def person(text: str) -> None:
        asked.append(text)
        if "start filming" in text:
            world.set_pose(0, -0.3, -0.1, 0.2)
            world.start_recording()
        elif "on the arena's floor" in text:
            world.set_pose(0, -0.2, 0.1, 0.0)
        elif "over the rim" in text:
            # Both ground sensors (at the front) beyond the carpet's edge, the body on it.
            world.set_pose(0, CARPET / 2 - 0.03, 0.0, 0.0)
        elif "stop filming" in text:
            poses = world.recorded_poses()
            scene = OverheadScene(
                floor=(FLOOR, FLOOR),
                carpet=CARPET,
                robots=(ROBOT,),
                markers=(MARKER,),
                marker_offset=(0.02, 0.0),
            )
            OverheadVideo(scene, poses, pre_roll=1.0, seed=2).write(video, "MJPG")

    args = argparse.Namespace(
        robot=ROBOT,
        config=lab / "master.yaml",
        inventory=None,
        skip_ground=False,
        video=video,
        tracking=lab / "tracking.yaml",
        timeout=30.0,
    )
    async with contextlib.AsyncExitStack() as stack:
        body = await stack.enter_async_context(swarm.body(0))
        body.wheel_scale = WHEELS
        config = AgentConfig(
            robot_id=ROBOT,
            master=AgentMasterConfig(host="127.0.0.1", port=port, secret_file="(in-process)"),
            reconnect=BackoffConfig(initial=0.05, max=0.2, jitter=0.5),
        )
        agent = await stack.enter_async_context(
            Agent(config, body, body.clock, SECRET, rng=random.Random(1))
        )
        task = asyncio.create_task(agent.run())
        try:
            code = await asyncio.to_thread(
                cli_fleet.calibrate_command, args, lambda text: person(text)
            )
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
    assert code == 0
    assert [a.split(" ")[0] for a in asked] == ["place", "place", "start", "stop"]

    entry = load_inventory(lab / "fleet.yaml").robot(ROBOT)
    assert entry is not None and entry.calibration is not None
    calibration = entry.calibration
    assert calibration.ground_floor is not None and calibration.ground_rim is not None
    assert max(calibration.ground_floor) < 0.3 < 0.9 < min(calibration.ground_rim)
    asymmetry = calibration.wheel_right / calibration.wheel_left
    assert asymmetry == pytest.approx(WHEELS[1] / WHEELS[0], rel=0.01)
    assert calibration.wheel_left == pytest.approx(WHEELS[0], rel=0.01)
    assert calibration.wheel_right == pytest.approx(WHEELS[1], rel=0.01)
    # Every other line of the file is as it was.
    text = (lab / "fleet.yaml").read_text().splitlines()
    assert [line for line in text if "calibration" not in line] == FLEET.splitlines()


def test_the_threshold_lies_between_floor_and_rim_on_the_agent_s_side():
    assert ground_threshold((0.2, 0.22), (0.95, 0.9), "above") == pytest.approx(0.56)
    assert ground_threshold((0.6, 0.62), (0.05, 0.1), "below") == pytest.approx(0.35)
    with pytest.raises(CalibrationError, match=r"the floor reads 0\.40/0\.42 and the rim 0\.45"):
        ground_threshold((0.4, 0.42), (0.45, 0.5), "above")


def test_the_wheels_of_an_exact_arc_are_recovered_exactly():
    # Left at 0.5 x 10.6 cm/s, right at 95 % of that, for 5 s; the exact arc at 10 frames a s.
    max_speed, base, command = 0.106, 0.094, 0.5
    left, right = command * max_speed, command * max_speed * 0.95
    v, w = (left + right) / 2, (right - left) / base
    times = np.arange(51) * 0.1
    theta = 0.3 + w * times
    x = 0.1 + v / w * (np.sin(theta) - np.sin(0.3))
    y = -0.2 - v / w * (np.cos(theta) - np.cos(0.3))
    poses = np.column_stack([x, y, theta])
    # The ends are means of five frames, a hair inside the arc: exact to 1e-5.
    assert drive_speeds(times, poses) == pytest.approx((v, w), rel=1e-4)
    assert wheel_scales(times, poses, command, max_speed=max_speed, wheel_base=base) == (
        pytest.approx(1.0, abs=1e-4),
        pytest.approx(0.95, abs=1e-4),
    )
    with pytest.raises(CalibrationError, match=r"followed the robot for 0\.5 s"):
        wheel_scales(times[:6], poses[:6], command, max_speed=max_speed, wheel_base=base)
    with pytest.raises(CalibrationError, match=r"left wheel drove at 5\.00 of its command"):
        wheel_scales(times, poses, 0.1, max_speed=max_speed, wheel_base=base)


def test_a_robot_not_in_the_inventory_or_an_unwritable_layout_is_refused(tmp_path: Path):
    path = tmp_path / "fleet.yaml"
    path.write_text(FLEET)
    with pytest.raises(ConfigError, match="no robot is named 'thymio-9'"):
        write_calibration(path, "thymio-9", wheels=(1.0, 0.95))
    assert path.read_text() == FLEET
    written = write_calibration(path, "thymio-4", wheels=(0.98, 1.0))
    assert written.wheel_left == 0.98 and written.ground_floor is None
    # A second calibration keeps what it did not measure again.
    again = write_calibration(path, "thymio-4", ground_floor=(0.2, 0.2), ground_rim=(0.9, 0.9))
    assert again.wheel_left == 0.98 and again.ground_rim == (0.9, 0.9)
    assert "- {name: thymio-4, address: thymio-4.local, marker: 13, spare: true, calibration:" in (
        path.read_text()
    )
