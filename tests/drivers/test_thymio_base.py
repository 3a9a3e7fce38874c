"""ThymioBase against the fake asebamedulla on a private D-Bus."""

from __future__ import annotations

import asyncio
import math
import os
import time
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.config import ThymioConfig
from drivers.thymio import HEARTBEAT, ThymioBase
from sim_stub.fake_medulla import FakeMedulla, StaticThymioModel, serve_fake_medulla
from surprise.errors import HardwareError, HardwareTimeoutError

ConfigFactory = Callable[..., ThymioConfig]
HANG_TIMEOUT = 0.05


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
        (1.0, -1.0, (315, -315)),
        (0.5, 0.1, (158, 32)),  # round(157.5) == 158, round(31.5) == 32
        (3.0, -7.0, (315, -315)),
        (math.nan, math.inf, (0, 315)),
        (-math.inf, 0.0, (-315, 0)),
    ],
)
def test_targets_default_calibration(left: float, right: float, expected: tuple[int, int]):
    assert ThymioBase(ThymioConfig()).targets(left, right) == expected


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
    async with _opened(thymio_config()) as thymio:
        assert await thymio.set_speeds(0.5, -0.25) == (158, -79)
        await thymio.is_connected()  # barrier: medulla has processed the writes
        assert model.targets == {"left": 158, "right": -79}
        assert thymio.last_targets == (158, -79)
        await thymio.stop()
        await thymio.is_connected()
        assert model.targets == {"left": 0, "right": 0}


async def test_open_stops_the_motors(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    model.targets = {"left": 200, "right": 200}  # left running by an earlier process
    async with _opened(thymio_config()) as thymio:
        await thymio.is_connected()
        assert model.targets == {"left": 0, "right": 0}


async def test_writes_are_sent_without_expecting_a_reply(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    # Like the real medulla's no-reply SetVariable: a rejected write does not raise.
    async with _opened(thymio_config()) as thymio:
        await thymio._set("no.such.variable", [1])
        await thymio.is_connected()
    assert medulla.rejected == ["SetVariable: variable no.such.variable does not exists"]


async def test_unknown_node_is_a_clear_error(medulla: FakeMedulla, thymio_config: ConfigFactory):
    thymio = ThymioBase(thymio_config(node="thymio-7"))
    with pytest.raises(HardwareError, match=r"no node 'thymio-7' \(nodes: 'thymio-II'\)"):
        await thymio.open()
    assert not thymio.is_open


async def test_missing_medulla_is_a_clear_error(thymio_config: ConfigFactory):
    thymio = ThymioBase(thymio_config())
    with pytest.raises(HardwareError, match=r"does not answer.*is it running") as info:
        await thymio.open()
    assert "ServiceUnknown" in str(info.value)


async def test_unreachable_bus_is_a_hardware_error(tmp_path):
    thymio = ThymioBase(ThymioConfig(bus=f"unix:path={tmp_path}/none"))
    with pytest.raises(HardwareError, match="connect to the D-Bus"):
        await thymio.open()


async def test_dbus_error_becomes_hardware_error(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    async with _opened(thymio_config()) as thymio:
        medulla.errors["prox.horizontal"] = "the robot is on fire"
        with pytest.raises(HardwareError, match="the robot is on fire") as info:
            await thymio.read()
    assert not isinstance(info.value, HardwareTimeoutError)


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


async def test_robot_gone_reads_time_out(medulla: FakeMedulla, thymio_config: ConfigFactory):
    async with _opened(thymio_config(timeout=HANG_TIMEOUT)) as thymio:
        medulla.disconnect_robot()
        assert not await thymio.is_connected()
        with pytest.raises(HardwareTimeoutError):
            await thymio.read_ir()


async def test_stop_that_does_not_reach_the_robot_is_an_error(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    # SetVariable is no-reply and medulla drops writes to a robot it lost: without a check, a
    # stop that went nowhere would look done and nobody would retry it.
    async with _opened(thymio_config(timeout=HANG_TIMEOUT)) as thymio:
        await thymio.set_speeds(0.5, 0.5)
        medulla.disconnect_robot()
        with pytest.raises(HardwareError, match="stop not confirmed"):
            await thymio.stop()
        medulla.reconnect_robot()
        await thymio.stop()  # a retry succeeds once the robot is reachable again
        assert model.targets == {"left": 0, "right": 0}


async def test_stop_without_medulla_is_an_error(
    dbus_address: str, model: StaticThymioModel, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config(timeout=HANG_TIMEOUT))
    async with serve_fake_medulla(dbus_address, model):
        await thymio.open()
    with pytest.raises(HardwareError):  # the writes went to nobody
        await thymio.stop()
    await thymio.close()


async def test_open_refuses_a_disconnected_robot(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    medulla.disconnect_robot()
    with pytest.raises(HardwareError, match="disconnected"):
        await ThymioBase(thymio_config()).open()


async def test_close_stops_the_motors_even_when_medulla_hangs(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    thymio = ThymioBase(thymio_config(timeout=HANG_TIMEOUT))
    await thymio.open()
    await thymio.set_speeds(1.0, 1.0)
    medulla.hang = True
    with pytest.raises(HardwareTimeoutError):
        await thymio.read()
    await thymio.close()
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
    from sim_stub.fake_medulla import private_bus

    async with private_bus() as address, serve_fake_medulla(address, model):
        thymio = ThymioBase(ThymioConfig(bus=address, timeout=HANG_TIMEOUT))
        await thymio.open()
    await asyncio.sleep(0.01)  # the daemon is gone; let the client notice the closed socket
    await thymio.close()
    await thymio.close()
    with pytest.raises(HardwareError, match="closed"):
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
    with pytest.raises(HardwareError, match="connection is closed"):
        await thymio.set_speeds(0.1, 0.1)


async def test_failsafe_is_loaded_and_heartbeat_refreshed(
    medulla: FakeMedulla, model: StaticThymioModel, thymio_config: ConfigFactory
):
    async with _opened(thymio_config(failsafe=True, failsafe_timeout=1.0)) as thymio:
        assert thymio.failsafe_active
        assert medulla.program is not None and "var heartbeat" in medulla.program
        (path,) = medulla.loaded_scripts
        assert not os.path.exists(path)  # the temporary copy is removed after loading
        model.variables[HEARTBEAT] = [0]  # as if the program had counted down
        medulla.calls.clear()
        await thymio.set_speeds(0.2, 0.2)
        await thymio.is_connected()
        assert model.variables[HEARTBEAT] == [10]  # 1 s in ticks of 100 ms
    writes = [args[1] for name, args in medulla.calls if name == "SetVariable"]
    # The heartbeat goes first, so fresh targets never meet an expired heartbeat.
    assert writes[:3] == [HEARTBEAT, "motor.left.target", "motor.right.target"]
    assert writes[3:6] == [HEARTBEAT, "motor.left.target", "motor.right.target"]  # close()


async def test_failsafe_uses_the_configured_node_name(
    dbus_address: str, model: StaticThymioModel, thymio_config: ConfigFactory
):
    async with serve_fake_medulla(dbus_address, model, node="thymio-7") as fake:
        async with _opened(thymio_config(node="thymio-7", failsafe=True)) as thymio:
            assert thymio.failsafe_active
        assert fake.loaded_scripts and not fake.rejected


async def test_failsafe_that_does_not_load_is_a_clear_error(
    medulla: FakeMedulla, thymio_config: ConfigFactory
):
    medulla.load_scripts = lambda path: None  # type: ignore[method-assign]  # silently ignored
    thymio = ThymioBase(thymio_config(failsafe=True))
    with pytest.raises(HardwareError, match=r"failsafe program did not load.*en_US\.UTF-8"):
        await thymio.open()
    assert not thymio.is_open


@pytest.mark.parametrize(("seconds", "ticks"), [(1.0, 10), (0.25, 3), (0.3, 3), (2.5, 25)])
def test_heartbeat_ticks(seconds: float, ticks: int):
    assert ThymioBase(ThymioConfig(failsafe_timeout=seconds)).heartbeat_ticks == ticks


def test_failsafe_heartbeat_not_written_without_failsafe():
    assert not ThymioBase(ThymioConfig()).failsafe_active


class _opened:
    """``async with _opened(config) as thymio``: open, then always close."""

    def __init__(self, config: ThymioConfig) -> None:
        self.thymio = ThymioBase(config)

    async def __aenter__(self) -> ThymioBase:
        await self.thymio.open()
        return self.thymio

    async def __aexit__(self, *exc: object) -> None:
        await self.thymio.close()
