"""The simulated Thymio behind the fake medulla, in-process: raw values, motor targets, and reads
that wait for the world's next step, seen through the real Thymio driver."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import time

import numpy as np
import pytest

from drivers.config import SPEED_SCALE, ThymioConfig
from drivers.thymio import ThymioBase
from minimize_surprise.errors import HardwareError
from simulator.battery import SimBattery
from simulator.body import SimSwarm
from simulator.scenarios import scenario_config
from standins import serve
from standins.medulla_model import (
    STEP_WAIT_TIMEOUT,
    SignallingWorld,
    SimThymio,
    serve_sim_thymio,
)
from standins.serve import servable_scenarios

#: A driver timeout longer than the medulla's bounded wait, so the bound is what a test sees.
DRIVER_TIMEOUT = 2.0


def world(robots: int = 2) -> SignallingWorld:
    """A basic world of ``robots`` robots (not stepping until a real-time swarm runs it)."""
    return SignallingWorld(scenario_config("basic", {"robots": robots}), seed=4)


def test_raw_values_are_the_drivers_scaling_inverted():
    w = world()
    w.set_pose(0, 0.0, 0.0, 0.0)
    w.set_pose(1, 0.17, 0.0, np.pi)  # in front of robot 0: its front IR see it
    robot = SimThymio(w, 0)
    normalised = w.sensor_matrix()[0]
    prox = robot.prox_horizontal()
    assert prox == [round(v * 4500) for v in normalised[:7]]
    assert max(prox) > 0 and all(0 <= v <= 4500 for v in prox)
    carpet = round(w.config.ground_carpet * 1023)
    assert robot.ground("prox.ground.reflected") == [carpet, carpet]
    assert robot.ground("prox.ground.delta") == [carpet, carpet]
    w.set_pose(0, 0.0, w.config.arena_side / 2 + 0.02, np.pi / 2)  # facing out over the edge
    outside = round(w.config.ground_outside * 1023)
    assert robot.ground("prox.ground.reflected") == [outside, outside]


def test_motor_targets_become_the_world_command_clamped():
    w = world()
    robot = SimThymio(w, 1, speed_scale=300)
    robot.set_target("left", 150)
    robot.set_target("right", -600)
    assert w.commands[1].tolist() == [0.5, -1.0]
    assert w.commands[0].tolist() == [0.0, 0.0]
    assert robot.targets == {"left": 150, "right": -600}


def test_a_world_without_the_thymio_sensors_is_refused():
    boxes = SignallingWorld(scenario_config("basic", {"robots": 1, "sensors": ["ir.f0"]}))
    with pytest.raises(ValueError, match=r"ground\.0"):
        SimThymio(boxes, 0)


async def test_each_read_waits_for_the_next_world_step(dbus_address: str):
    w = world()
    model = SimThymio(w, 0)
    async with (
        serve_sim_thymio(dbus_address, model),
        SimSwarm(w, realtime=True),
    ):
        base = ThymioBase(ThymioConfig(bus=dbus_address, timeout=DRIVER_TIMEOUT))
        await base.open()
        try:
            steps = []
            for _ in range(4):
                values = await base.read()
                steps.append(w.steps)
            assert all(b > a for a, b in itertools.pairwise(steps)), steps
            # The driver sees the current step's values (normalised back: raw / 4500, / 1023).
            assert values[7:].tolist() == pytest.approx([round(0.4 * 1023) / 1023] * 2)
            await base.set_speeds(0.5, 0.5)
            await base.is_connected()  # a round trip: the targets have arrived
            assert w.commands[0].tolist() == pytest.approx(
                [round(0.5 * SPEED_SCALE) / SPEED_SCALE] * 2
            )
        finally:
            await base.close()
        assert w.commands[0].tolist() == [0.0, 0.0]  # close() stopped the motors


async def test_the_battery_reads_as_a_real_thymios_and_drains_while_driving(dbus_address: str):
    # A served simulated Thymio declares _vbat as a real one does (the preflight and the run's
    # battery columns then have a value, not "unknown"); it drains while the motors turn.
    w = world()
    model = SimThymio(w, 0, battery=SimBattery(drain_v_per_step=0.01))
    async with (
        serve_sim_thymio(dbus_address, model),
        SimSwarm(w, realtime=True),
    ):
        base = ThymioBase(ThymioConfig(bus=dbus_address, timeout=DRIVER_TIMEOUT))
        await base.open()
        try:
            assert await base.read_battery() == pytest.approx(4.2, abs=0.005)
            await base.read()  # a step with the motors still: no drain
            assert await base.read_battery() == pytest.approx(4.2, abs=0.005)
            await base.set_speeds(0.3, 0.3)
            for _ in range(5):
                await base.read()
            volts = await base.read_battery()
            assert volts is not None and 3.0 < volts < 4.2 - 0.04
        finally:
            await base.close()


async def test_the_top_led_is_recorded_with_the_world_s_step(dbus_address: str):
    # A served simulated Thymio declares leds.top as a real one does; its model records each
    # write with the step a camera over the world would have seen it from.
    w = world()
    model = SimThymio(w, 0)
    async with (
        serve_sim_thymio(dbus_address, model),
        SimSwarm(w, realtime=True),
    ):
        base = ThymioBase(ThymioConfig(bus=dbus_address, timeout=DRIVER_TIMEOUT))
        await base.open()
        try:
            await base.read()
            await base.set_top_led(0.0, 1.0, 0.0)
            lit_at = w.steps
            for _ in range(3):
                await base.read()
            await base.set_top_led(0.0, 0.0, 0.0)
        finally:
            await base.close()
    (on, green), (off, dark) = model.led_log
    assert (green, dark) == ([0, 32, 0], [0, 0, 0])
    assert on <= lit_at and off >= on + 3  # three reads: three new steps at least


async def test_a_read_is_answered_after_the_bound_when_the_world_stalls(dbus_address: str):
    w = world()  # never stepped
    async with serve_sim_thymio(dbus_address, SimThymio(w, 0)):
        base = ThymioBase(ThymioConfig(bus=dbus_address, timeout=DRIVER_TIMEOUT))
        await base.open()
        try:
            start = time.monotonic()
            await base.read_ir()
            waited = time.monotonic() - start
        finally:
            await base.close()
    assert STEP_WAIT_TIMEOUT - 0.05 <= waited < DRIVER_TIMEOUT


async def test_shutting_down_releases_the_waiting_reads_at_once(dbus_address: str):
    w = world()  # never stepped, so the read waits
    base = ThymioBase(ThymioConfig(bus=dbus_address, timeout=DRIVER_TIMEOUT))
    async with serve_sim_thymio(dbus_address, SimThymio(w, 0)) as medulla:
        await base.open()
        read = asyncio.ensure_future(base.read_ir())
        while not medulla.pending:
            await asyncio.sleep(0.01)
        start = time.monotonic()
    # Leaving the context answered the read (with an error) well before the bounded wait.
    assert time.monotonic() - start < STEP_WAIT_TIMEOUT
    with pytest.raises(HardwareError):
        await read
    await base.close()


# --------------------------------------------------------------------------- the command line


def test_every_scenario_is_served_its_i2c_sensors_over_a_bridge(tmp_path, capsys):
    # The force and light sensors are emulated I2C chips (standins/i2c_bridge.py).
    assert servable_scenarios() == ("basic", "boxes", "gradient")
    with pytest.raises(SystemExit) as exit_:
        serve.main(["--scenario", "lamp", "--dir", str(tmp_path)])
    assert exit_.value.code == serve.EXIT_USAGE
    assert "invalid choice: 'lamp'" in capsys.readouterr().err


def test_a_directory_served_by_a_live_process_is_refused(tmp_path, capsys):
    # Our parent process is alive: the directory counts as served by it.
    (tmp_path / "robots.json").write_text(json.dumps({"pid": os.getppid()}))
    assert serve.main(["--dir", str(tmp_path), "--robots", "1"]) == serve.EXIT_FAILURE
    assert f"served by another surprise-sim-robots (pid {os.getppid()})" in capsys.readouterr().err
    assert not (tmp_path / "secret.key").exists()  # nothing was started


@pytest.mark.parametrize(
    "argv, said",
    [
        (["--ids", "a,a"], "the ids repeat"),
        (["--ids", "a,b c"], "'b c' is no robot id"),
    ],
)
def test_bad_robot_ids_are_usage_errors(tmp_path, capsys, argv, said):
    with pytest.raises(SystemExit) as exit_:
        serve.main(["--dir", str(tmp_path), *argv])
    assert exit_.value.code == serve.EXIT_USAGE
    assert said in capsys.readouterr().err


def test_ids_and_a_different_robot_count_are_refused(tmp_path, capsys):
    assert serve.main(["--dir", str(tmp_path), "--robots", "3", "--ids", "a,b"]) == 2
    assert "--robots 3 but --ids names 2" in capsys.readouterr().err
    assert not (tmp_path / "secret.key").exists()  # nothing was started
