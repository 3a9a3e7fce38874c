"""The fake asebamedulla answers like the real one, seen from a raw dbus-fast client."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from dbus_fast import Message, MessageFlag, MessageType
from dbus_fast.aio import MessageBus

from drivers.thymio import ASEBA_INTERFACE, ASEBA_PATH, ASEBA_SERVICE, FAILSAFE_TICK
from needs import pids, require_binary
from standins.fake_medulla import FakeMedulla, StaticThymioModel, serve_fake_medulla


@pytest.fixture
async def client(dbus_address: str) -> AsyncIterator[MessageBus]:
    bus = await MessageBus(bus_address=dbus_address).connect()
    yield bus
    bus.disconnect()
    await bus.wait_for_disconnect()


def _message(member: str, signature: str = "", body: list[Any] | None = None, **kw) -> Message:
    return Message(
        destination=ASEBA_SERVICE,
        path=ASEBA_PATH,
        interface=ASEBA_INTERFACE,
        member=member,
        signature=signature,
        body=body or [],
        **kw,
    )


async def test_nodes_and_variables(medulla: FakeMedulla, client: MessageBus):
    reply = await client.call(_message("GetNodesList"))
    assert reply.body == [["thymio-II"]]
    reply = await client.call(_message("GetVariable", "ss", ["thymio-II", "prox.horizontal"]))
    assert reply.body == [[0, 1125, 2250, 4500, 6000, 0, 900]]
    reply = await client.call(_message("IsConnected", "s", ["thymio-II"]))
    assert reply.body == [True]


@pytest.mark.parametrize(
    ("node", "variable", "text"),
    [
        ("thymio-II", "no.such", "variable no.such does not exists in node thymio-II"),
        ("other", "prox.horizontal", "node other does not exists"),
    ],
)
async def test_unknown_names_are_invalid_args(
    medulla: FakeMedulla, client: MessageBus, node: str, variable: str, text: str
):
    reply = await client.call(_message("GetVariable", "ss", [node, variable]))
    assert reply.message_type == MessageType.ERROR
    assert reply.error_name == "org.freedesktop.DBus.Error.InvalidArgs"
    assert reply.body == [text]


async def test_set_variable_without_reply_when_asked(
    medulla: FakeMedulla, model: StaticThymioModel, client: MessageBus
):
    replies: list[Message] = []
    client.add_message_handler(
        lambda m: replies.append(m) if m.message_type != MessageType.SIGNAL else None
    )
    body = ["thymio-II", "motor.left.target", [123]]
    message = _message("SetVariable", "ssan", body, flags=MessageFlag.NO_REPLY_EXPECTED)
    message.serial = client.next_serial()
    await client.send(message)
    await client.call(_message("IsConnected", "s", ["thymio-II"]))  # barrier
    assert model.targets["left"] == 123
    assert [m for m in replies if m.reply_serial == message.serial] == []
    reply = await client.call(_message("SetVariable", "ssan", body))
    assert reply.message_type == MessageType.METHOD_RETURN and reply.body == []


async def test_hung_call_is_released_when_the_fake_stops(dbus_address: str, client: MessageBus):
    async with serve_fake_medulla(dbus_address, StaticThymioModel()) as fake:
        fake.hang = True
        pending = asyncio.ensure_future(
            client.call(_message("GetVariable", "ss", ["thymio-II", "prox.horizontal"]))
        )
        await asyncio.sleep(0.02)
        assert not pending.done()
    reply = await asyncio.wait_for(pending, 1.0)
    assert reply.error_name == "org.freedesktop.DBus.Error.NoReply"


async def test_load_scripts_declares_the_program_variables(
    medulla: FakeMedulla, model: StaticThymioModel, client: MessageBus, tmp_path: Path
):
    program = tmp_path / "p.aesl"
    program.write_text(
        '<!DOCTYPE aesl-source>\n<network>\n<node name="thymio-II" nodeId="1">'
        "var a = 3\nvar b[4]\nvar c\n</node>\n</network>\n"
    )
    await client.call(_message("LoadScripts", "s", [str(program)]))
    assert model.variables["a"] == [3] and model.variables["b"] == [0] * 4
    reply = await client.call(_message("GetVariable", "ss", ["thymio-II", "c"]))
    assert reply.body == [[0]]
    await client.call(_message("LoadScripts", "s", [str(tmp_path / "missing.aesl")]))
    assert len(medulla.rejected) == 1 and medulla.loaded_scripts == [str(program)]


async def test_load_scripts_answers_errors_only_to_a_caller_expecting_a_reply(
    medulla: FakeMedulla, client: MessageBus, tmp_path: Path
):
    missing = str(tmp_path / "missing.aesl")
    reply = await client.call(_message("LoadScripts", "s", [missing]))
    assert reply.error_name == "org.freedesktop.DBus.Error.InvalidArgs"
    assert reply.body == [f"file {missing} does not exists"]  # the real medulla's words
    broken = tmp_path / "broken.aesl"
    broken.write_text("<network><node")
    reply = await client.call(_message("LoadScripts", "s", [str(broken)]))
    assert reply.message_type == MessageType.ERROR
    message = _message("LoadScripts", "s", [missing], flags=MessageFlag.NO_REPLY_EXPECTED)
    message.serial = client.next_serial()
    replies: list[Message] = []
    client.add_message_handler(lambda m: replies.append(m) if m.reply_serial else None)
    await client.send(message)
    await client.call(_message("IsConnected", "s", ["thymio-II"]))  # barrier
    assert [m for m in replies if m.reply_serial == message.serial] == []


def _failsafe(tmp_path: Path) -> Path:
    from importlib import resources

    path = tmp_path / "failsafe.aesl"
    path.write_text(resources.files("drivers").joinpath("failsafe.aesl").read_text())
    return path


async def test_loading_a_program_resets_the_vm(
    medulla: FakeMedulla, model: StaticThymioModel, client: MessageBus, tmp_path: Path
):
    program = str(_failsafe(tmp_path))
    await client.call(_message("LoadScripts", "s", [program]))
    await client.call(_message("SetVariable", "ssan", ["thymio-II", "heartbeat", [40]]))
    assert model.variables["heartbeat"] == [40]
    await client.call(_message("LoadScripts", "s", [program]))
    assert model.variables["heartbeat"] == [0]


async def test_a_restarted_medulla_does_not_know_the_running_program(
    dbus_address: str, client: MessageBus, tmp_path: Path
):
    model = StaticThymioModel()
    program = str(_failsafe(tmp_path))
    async with serve_fake_medulla(dbus_address, model, keep_vm=True):
        await client.call(_message("LoadScripts", "s", [program]))
    async with serve_fake_medulla(dbus_address, model) as second:
        reply = await client.call(_message("GetVariable", "ss", ["thymio-II", "heartbeat"]))
        assert reply.body == ["variable heartbeat does not exists in node thymio-II"]
        # ...while the program still runs on the robot: its heartbeat is 0, so every tick of
        # its timer sets the targets back to 0, whatever the host writes.
        for _ in range(3):
            await client.call(_message("SetVariable", "ssan", ["thymio-II", "heartbeat", [50]]))
            await client.call(
                _message("SetVariable", "ssan", ["thymio-II", "motor.left.target", [90]])
            )
        assert "SetVariable: variable heartbeat does not exists" in second.rejected
        await asyncio.sleep(2.5 * FAILSAFE_TICK)
        assert model.targets["left"] == 0 and second.vm.ticks >= 2


async def test_is_connected_lags_behind_a_robot_that_went_away(
    medulla: FakeMedulla, client: MessageBus
):
    medulla.connected_lag = 0.2
    medulla.disconnect_robot()
    reply = await client.call(_message("IsConnected", "s", ["thymio-II"]))
    assert reply.body == [True]  # as the real medulla for about 3.8 s
    await asyncio.sleep(0.25)
    reply = await client.call(_message("IsConnected", "s", ["thymio-II"]))
    assert reply.body == [False]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_private_bus_dies_with_a_killed_parent(tmp_path):
    """``surprise-sim-robots`` killed with SIGKILL must not leave its dbus-daemons behind."""
    require_binary("dbus-daemon")
    code = (
        "import asyncio\n"
        "from standins.fake_medulla import private_bus\n"
        "async def main():\n"
        "    async with private_bus() as address:\n"
        "        print(address, flush=True)\n"
        "        await asyncio.sleep(60)\n"
        "asyncio.run(main())\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        address = parent.stdout.readline().strip()
        socket_dir = address.split("path=")[1].split(",")[0].rsplit("/", 1)[0]
        assert pids("dbus-daemon", containing=socket_dir)
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=5)
        for _ in range(50):  # the kernel signals the daemon at once; it exits within moments
            if not pids("dbus-daemon", containing=socket_dir):
                break
            time.sleep(0.05)
        assert not pids("dbus-daemon", containing=socket_dir)
    finally:
        parent.kill()
        parent.wait()
