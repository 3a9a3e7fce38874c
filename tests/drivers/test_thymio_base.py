"""ThymioBase against the fake asebamedulla on a private D-Bus."""

from __future__ import annotations

import asyncio
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import drivers
import drivers.thymio as thymio_module
from drivers.config import ThymioConfig
from drivers.thymio import (
    EMPTY_PROGRAM,
    FAILSAFE_PROGRAM,
    FAILSAFE_TICK,
    HEARTBEAT,
    ThymioBase,
    end_process,
)
from minimize_surprise.errors import HardwareError, HardwareTimeoutError, RobotUnreachableError
from standins.fake_medulla import FakeMedulla, StaticThymioModel, serve_fake_medulla, vm_of

ConfigFactory = Callable[..., ThymioConfig]
# Long enough that a live fake medulla on a loaded CI machine always answers in time
# (0.05 s once failed an open in CI), short enough that the hang tests stay quick.
HANG_TIMEOUT = 0.25


async def test_read_normalises_ir_and_ground(medulla: FakeMedulla, thymio_config: ConfigFactory):
    async with _opened(thymio_config()) as thymio:
        ir = await thymio.read_ir()
        ground = await thymio.read_ground()
        both = await thymio.read()
    np.testing.assert_allclose(ir, [0, 0.25, 0.5, 1.0, 1.0, 0, 0.2])  # 6000 clips to 1
    np.testing.assert_allclose(ground, [1.0, 0.0])
    np.testing.assert_allclose(both, np.concatenate([ir, ground]))
    assert ("GetVariable", ("thymio-II", "prox.ground.reflected")) in medulla.calls


async def test_ground_variable_is_configurable(medulla: FakeMedulla, thymio_config: ConfigFactory):
    async with _opened(thymio_config(ground="prox.ground.delta")) as thymio:
        ground = await thymio.read_ground()
    np.testing.assert_allclose(ground, [512 / 1023, 100 / 1023])
    assert ("GetVariable", ("thymio-II", "prox.ground.delta")) in medulla.calls


async def test_ir_and_ground_are_requested_concurrently(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    async with _opened(thymio_config()) as thymio:
        medulla.latency = 0.02  # both requests are pending at the fake while it waits
        await thymio.read()
    assert medulla.max_in_flight == 2


@pytest.mark.parametrize(
    ("left", "right", "expected"),
    [
        (1.0, -1.0, (265, -265)),
        (0.5, 0.1, (132, 26)),  # round(132.5) == 132 (to even), round(26.5) == 26
        (3.0, -7.0, (265, -265)),
        (math.nan, math.inf, (0, 265)),
        (-math.inf, 0.0, (-265, 0)),
    ],
)
def test_targets_default_calibration(left: float, right: float, expected: tuple[int, int]):
    # 265 motor units: the paper's real robots drove at most 10.6 cm/s (0.04 cm/s per unit).
    assert ThymioBase(ThymioConfig()).targets(left, right) == expected


def test_a_calibrated_slow_wheel_gets_the_larger_target():
    # The right wheel drives at 95 % of its command (surprise-master calibrate): its target is
    # raised so that both wheels drive at the speed asked for; the clamp still holds.
    thymio = ThymioBase(ThymioConfig(wheel_right=0.95))
    assert thymio.targets(0.5, 0.5) == (132, round(0.5 * 265 / 0.95))
    assert thymio.targets(1.0, 1.0) == (265, round(265 / 0.95))
    assert ThymioBase(ThymioConfig(wheel_right=0.5 + 1e-9, max_target=400)).targets(1, 1)[1] == 400


def test_targets_clamp_to_max_target():
    thymio = ThymioBase(ThymioConfig(speed_scale=500, max_target=400))
    assert thymio.targets(1.0, -0.5) == (400, -250)


@given(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=1.0, max_value=500.0),
    st.integers(min_value=1, max_value=500),
)
def test_targets_always_within_limits(value: float, scale: float, limit: int):
    thymio = ThymioBase(ThymioConfig(speed_scale=scale, max_target=limit))
    left, right = thymio.targets(value, -value)
    assert -limit <= left <= limit and -limit <= right <= limit
    if math.isnan(value):
        assert (left, right) == (0, 0)
    else:
        assert left == -right
        assert left == 0 or (left > 0) == (value > 0)


async def test_set_speeds_writes_motor_targets(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    async with _opened(thymio_config(speed_scale=315)) as thymio:
        assert await thymio.set_speeds(0.5, -0.25) == (158, -79)
        await thymio.is_connected()  # barrier: medulla has processed the writes
        assert model.targets == {"left": 158, "right": -79}
        assert thymio.last_targets == (158, -79)
        await thymio.stop()
        assert model.targets == {"left": 0, "right": 0}
        assert thymio.last_targets == (0, 0)


async def test_open_stops_the_motors(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    model.targets = {"left": 200, "right": 200}  # left running by an earlier process
    async with _opened(thymio_config()):
        assert model.targets == {"left": 0, "right": 0}


async def test_writes_are_sent_without_expecting_a_reply(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    # Like the real medulla's no-reply SetVariable: a rejected write does not raise.
    async with _opened(thymio_config()) as thymio:
        await thymio._set("no.such.variable", [1])
        await thymio.is_connected()
    assert medulla.rejected == ["SetVariable: variable no.such.variable does not exists"]


async def test_unknown_node_is_a_clear_error(dbus_address: str, model: StaticThymioModel):
    async with serve_fake_medulla(dbus_address, model):
        thymio = ThymioBase(ThymioConfig(bus=dbus_address, node="thymio-7", program_dir="."))
        with pytest.raises(
            RobotUnreachableError, match=r"no node 'thymio-7' \(nodes: 'thymio-II'\)"
        ):
            await thymio.open()
    assert not thymio.is_open


async def test_missing_medulla_is_a_clear_error(thymio_config: ConfigFactory):
    thymio = ThymioBase(thymio_config())
    with pytest.raises(RobotUnreachableError, match=r"asebamedulla is not running on the D-Bus"):
        await thymio.open()


async def test_a_bus_that_is_not_there_is_one_error_naming_the_key(tmp_path):
    thymio = ThymioBase(ThymioConfig(bus=f"unix:path={tmp_path}/none"))
    with pytest.raises(HardwareError) as info:
        await thymio.open()
    text = str(info.value)
    assert f"no D-Bus to reach at unix:path={tmp_path}/none (No such file or directory)" in text
    assert "check body.thymio.bus" in text


async def test_dbus_error_becomes_hardware_error(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    async with _opened(thymio_config()) as thymio:
        medulla.errors["prox.horizontal"] = "the robot is on fire"
        with pytest.raises(HardwareError, match="the robot is on fire") as info:
            await thymio.read()
    assert not isinstance(info.value, HardwareTimeoutError | RobotUnreachableError)


async def test_wrong_number_of_values_is_a_hardware_error(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    model.prox = [0] * 5
    async with _opened(thymio_config()) as thymio:
        with pytest.raises(HardwareError, match="5 values, expected 7"):
            await thymio.read_ir()


async def test_hung_get_variable_times_out(medulla: FakeMedulla, thymio_config: ConfigFactory):
    async with _opened(thymio_config(timeout=HANG_TIMEOUT)) as thymio:
        medulla.hang = True
        start = time.monotonic()
        with pytest.raises(HardwareTimeoutError) as info:
            await thymio.read()
        elapsed = time.monotonic() - start
        medulla.hang = False
        assert (await thymio.read_ground()).shape == (2,)  # answers again once released
    assert info.value.timeout == HANG_TIMEOUT
    assert "GetVariable" in info.value.operation
    assert HANG_TIMEOUT <= elapsed < HANG_TIMEOUT + 0.5


async def test_robot_gone_reads_time_out_while_medulla_still_says_connected(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    async with _opened(thymio_config(timeout=HANG_TIMEOUT)) as thymio:
        medulla.disconnect_robot()
        assert await thymio.is_connected()  # the real medulla lags by seconds
        with pytest.raises(HardwareTimeoutError):
            await thymio.read_ir()
        medulla.connected_lag = 0.0
        assert not await thymio.is_connected()


async def test_stop_is_confirmed_by_reading_the_targets_back(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    # SetVariable is no-reply, medulla drops writes to a robot it lost, and IsConnected stays
    # true for seconds: only the robot's own answer shows that the stop arrived.
    async with _opened(thymio_config(timeout=HANG_TIMEOUT)) as thymio:
        await thymio.set_speeds(0.5, 0.5)
        await thymio.is_connected()  # barrier: the writes arrived before the robot left
        medulla.disconnect_robot()
        with pytest.raises(RobotUnreachableError, match=r"stop not confirmed.*does not answer"):
            await thymio.stop()
        assert model.targets == {"left": 132, "right": 132}  # the robot never got it
        medulla.reconnect_robot()
        await thymio.stop()  # a retry succeeds once the robot is reachable again
        assert model.targets == {"left": 0, "right": 0}
    reads = [args[1] for name, args in medulla.calls if name == "GetVariable"]
    assert reads.count("motor.left.target") >= 2 and reads.count("motor.right.target") >= 2


async def test_stop_that_a_program_overrides_is_not_confirmed(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    async with _opened(thymio_config()) as thymio:
        original = medulla.set_variable

        def stuck(node: str, variable: str, values: list[int]) -> None:
            original(node, variable, [77] if variable.startswith("motor.") else values)

        medulla.set_variable = stuck  # type: ignore[method-assign]
        with pytest.raises(HardwareError, match=r"read back as \(77, 77\)"):
            await thymio.stop()
        medulla.set_variable = original  # type: ignore[method-assign]


async def test_stop_without_medulla_is_an_error(
    dbus_address: str, model: StaticThymioModel, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config(timeout=HANG_TIMEOUT))
    async with serve_fake_medulla(dbus_address, model):
        await thymio.open()
    with pytest.raises(RobotUnreachableError, match="not running"):  # the writes went nowhere
        await thymio.stop()
    await thymio.close()


async def test_open_refuses_a_robot_that_does_not_answer(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    medulla.disconnect_robot()  # IsConnected still says true: the read-back finds out
    with pytest.raises(RobotUnreachableError, match="does not answer"):
        await ThymioBase(thymio_config(timeout=HANG_TIMEOUT)).open()
    medulla.connected_lag = 0.0
    with pytest.raises(RobotUnreachableError, match="disconnected"):
        await ThymioBase(thymio_config(timeout=HANG_TIMEOUT)).open()


async def test_close_stops_the_motors_even_when_medulla_hangs(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config(timeout=HANG_TIMEOUT))
    await thymio.open()
    await thymio.set_speeds(1.0, 1.0)
    medulla.hang = True
    with pytest.raises(HardwareTimeoutError):
        await thymio.read()
    await thymio.close()  # the read-back hangs too: logged, not raised
    assert model.targets == {"left": 0, "right": 0}
    assert model.target_log[-2:] == [("left", 0), ("right", 0)]
    assert not thymio.is_open


async def test_close_never_raises_when_medulla_is_gone(
    dbus_address: str, model: StaticThymioModel, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config(timeout=HANG_TIMEOUT))
    async with serve_fake_medulla(dbus_address, model):
        await thymio.open()
        await thymio.set_speeds(0.3, 0.3)
    await thymio.close()  # the stop goes nowhere; logged, not raised
    assert not thymio.is_open


async def test_close_never_raises_when_the_bus_is_gone(model: StaticThymioModel):
    from standins.fake_medulla import private_bus

    async with private_bus() as address, serve_fake_medulla(address, model):
        thymio = ThymioBase(ThymioConfig(bus=address, timeout=HANG_TIMEOUT))
        await thymio.open()
    await asyncio.sleep(0.01)  # the daemon is gone; let the client notice the closed socket
    await thymio.close()
    await thymio.close()
    with pytest.raises(RobotUnreachableError, match="not attached"):
        await thymio.read()


async def test_close_is_idempotent_and_calls_after_close_fail(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config())
    await thymio.close()  # never opened: nothing to do
    await thymio.open()
    await thymio.open()  # already open: nothing to do
    await thymio.close()
    await thymio.close()
    with pytest.raises(RobotUnreachableError, match="not attached"):
        await thymio.set_speeds(0.1, 0.1)


# -- the programs -------------------------------------------------------------------------------


async def test_failsafe_is_loaded_from_the_installed_file_expecting_a_reply(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    async with _opened(thymio_config(failsafe=True, failsafe_timeout=1.0)) as thymio:
        assert thymio.failsafe_active
        assert medulla.program is not None and "var heartbeat" in medulla.program
        (path,) = medulla.loaded_scripts
        # The packaged file, not a copy in the agent's /tmp: under systemd's PrivateTmp=yes
        # medulla (another unit) would not see a file there.
        assert Path(path) == Path(drivers.__file__).parent / FAILSAFE_PROGRAM
        assert os.stat(path).st_mode & 0o004  # readable by medulla's user
        model.variables[HEARTBEAT] = [0]  # as if the program had counted down
        medulla.calls.clear()
        await thymio.set_speeds(0.2, 0.2)
        await thymio.is_connected()
        assert model.variables[HEARTBEAT] == [10]  # 1 s in ticks of 100 ms
    writes = [args[1] for name, args in medulla.calls if name == "SetVariable"]
    # The heartbeat goes first, so fresh targets never meet an expired heartbeat.
    assert writes[:3] == [HEARTBEAT, "motor.left.target", "motor.right.target"]


async def test_without_failsafe_an_empty_program_replaces_a_left_over_one(
    dbus_address: str, model: StaticThymioModel, thymio_config: ConfigFactory
):
    # An earlier run left the failsafe on the Thymio, and medulla has restarted since: the new
    # medulla does not know `heartbeat`, and the program keeps zeroing the motor targets.
    async with (
        serve_fake_medulla(dbus_address, model, keep_vm=True),
        _opened(thymio_config(failsafe=True)),
    ):
        pass
    async with serve_fake_medulla(dbus_address, model) as fake:
        async with _opened(thymio_config(failsafe=False)) as thymio:
            assert not thymio.failsafe_active
            (path,) = fake.loaded_scripts
            assert Path(path).name == EMPTY_PROGRAM
            await thymio.set_speeds(0.5, 0.5)
            await asyncio.sleep(3 * FAILSAFE_TICK)
            assert model.targets == {"left": 132, "right": 132}  # nothing zeroes them now
        assert vm_of(model).program is not None and "heartbeat" not in vm_of(model).program


async def test_a_program_medulla_cannot_find_is_reported_with_its_reason(
    medulla: FakeMedulla, thymio_config: ConfigFactory, tmp_path: Path
):
    (tmp_path / "programs").write_text("a file where a directory should be")
    thymio = ThymioBase(
        thymio_config(node="thymio-II", program_dir=str(tmp_path / "programs"), failsafe=True)
    )
    with pytest.raises(HardwareError, match="cannot write the Aseba program"):
        await thymio.open()
    original = medulla.load_scripts

    def missing(path: str) -> None:
        original(path + ".gone")

    medulla.load_scripts = missing  # type: ignore[method-assign]
    thymio = ThymioBase(thymio_config(failsafe=True))
    with pytest.raises(HardwareError, match=r"could not load the failsafe.*does not exists"):
        await thymio.open()
    assert not thymio.is_open


async def test_failsafe_uses_the_configured_node_name(
    dbus_address: str, model: StaticThymioModel, thymio_config: ConfigFactory, tmp_path: Path
):
    async with serve_fake_medulla(dbus_address, model, node="thymio-7") as fake:
        config = thymio_config(node="thymio-7", failsafe=True, program_dir=str(tmp_path))
        async with _opened(config) as thymio:
            assert thymio.failsafe_active
        (path,) = fake.loaded_scripts
        assert Path(path).parent == tmp_path and 'name="thymio-7"' in Path(path).read_text()
        assert not fake.rejected


def test_a_node_of_another_name_needs_a_program_dir():
    with pytest.raises(ValueError, match="program_dir"):
        ThymioConfig(node="thymio-7")


async def test_failsafe_that_does_not_load_is_a_clear_error(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    medulla.load_scripts = lambda path: None  # type: ignore[method-assign]  # silently ignored
    thymio = ThymioBase(thymio_config(failsafe=True))
    with pytest.raises(HardwareError, match=r"failsafe program .* did not load into node"):
        await thymio.open()
    assert not thymio.is_open


@pytest.mark.parametrize(("seconds", "ticks"), [(1.0, 10), (0.25, 3), (0.3, 3), (2.5, 25)])
def test_heartbeat_ticks(seconds: float, ticks: int):
    assert ThymioBase(ThymioConfig(failsafe_timeout=seconds)).heartbeat_ticks == ticks


def test_failsafe_heartbeat_not_written_without_failsafe():
    assert not ThymioBase(ThymioConfig()).failsafe_active


# -- a medulla restarted, a robot lost ---------------------------------------------------------


async def test_a_restarted_medulla_is_detected_and_the_failsafe_reloaded(
    dbus_address: str, model: StaticThymioModel, thymio_config: ConfigFactory
):
    config = thymio_config(failsafe=True, timeout=HANG_TIMEOUT)
    thymio = ThymioBase(config)
    try:
        async with serve_fake_medulla(dbus_address, model, keep_vm=True) as first:
            await thymio.open()
            old = thymio.attached
            await thymio.set_speeds(0.5, 0.5)
            await first.wait_idle()
        async with serve_fake_medulla(dbus_address, model) as second:
            # The old medulla is gone: reads fail at once (no timeout), and nothing drives
            # through the new one before the program is loaded there.
            start = time.monotonic()
            with pytest.raises(RobotUnreachableError, match="has ended"):
                await thymio.read()
            assert time.monotonic() - start < HANG_TIMEOUT
            with pytest.raises(RobotUnreachableError, match="not attached"):
                await thymio.set_speeds(0.5, 0.5)
            assert HEARTBEAT not in second.known  # it would drop every heartbeat write
            await thymio.recover()
            assert thymio.attached not in (None, old)
            assert second.loaded_scripts and HEARTBEAT in second.known
            await thymio.set_speeds(0.5, 0.5)
            await asyncio.sleep(4 * FAILSAFE_TICK)  # the program runs, the heartbeat holds
            assert model.targets == {"left": 132, "right": 132}
            await thymio.close()
    finally:
        await thymio.close()


async def test_recover_ends_a_medulla_that_lost_the_robot(
    medulla: FakeMedulla, thymio_config: ConfigFactory, monkeypatch: pytest.MonkeyPatch
):
    ended: list[tuple[str, int]] = []

    async def end(name: str, pid: int) -> None:
        ended.append((name, pid))

    thymio = ThymioBase(thymio_config(timeout=HANG_TIMEOUT), end_medulla=end)
    await thymio.open()
    medulla.disconnect_robot()
    with pytest.raises(RobotUnreachableError):
        await thymio.recover()
    assert ended == []  # a medulla gets MEDULLA_GRACE seconds to find its robot
    monkeypatch.setattr(thymio_module, "MEDULLA_GRACE", 0.0)
    with pytest.raises(RobotUnreachableError):
        await thymio.recover()
    assert ended == [(thymio._first_seen and next(iter(thymio._first_seen)), os.getpid())]
    medulla.reconnect_robot()
    await thymio.recover()
    assert thymio.attached is not None
    await thymio.close()


async def test_a_medulla_in_this_process_is_never_signalled():
    with pytest.raises(HardwareError, match="runs in this process"):
        await end_process(":1.7", os.getpid())


class _opened:
    """``async with _opened(config) as thymio``: open, then always close."""

    def __init__(self, config: ThymioConfig) -> None:
        self.thymio = ThymioBase(config)

    async def __aenter__(self) -> ThymioBase:
        await self.thymio.open()
        return self.thymio

    async def __aexit__(self, *exc: object) -> None:
        await self.thymio.close()
