"""The agent's configuration and ``surprise-agent``: bad configuration exits with 2 and one message
naming file and key; a robot that cannot be reached at start is recovered, a bug opening the body
exits with 1; SIGTERM, SIGINT and SIGHUP stop the motors and exit 0."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
from pathlib import Path

import msgspec
import pytest
from agent_fakes import SECRET, FakeBody, FakeClock, ScriptedMaster, genome, spec

from minimize_surprise.errors import ConfigError, ConnectionClosedError, HardwareError
from minimize_surprise.wire import DEFAULT_PORT, Bye, Evaluate, Failed, Result, genome_to_bytes
from robot_agent import cli
from robot_agent.config import (
    AgentConfig,
    load_agent_config,
    make_ssl_context,
    read_secret,
)
from standins.fake_medulla import StaticThymioModel, serve_fake_medulla

MINIMAL = """
robot_id: thymio-01
master: {host: 192.168.1.10, secret_file: secret.key}
"""


def write(tmp_path: Path, text: str, secret: bytes | None = b"s3cret\n") -> Path:
    path = tmp_path / "agent.yaml"
    path.write_text(text)
    if secret is not None:
        (tmp_path / "secret.key").write_bytes(secret)
    return path


# --------------------------------------------------------------------------- configuration


def test_a_minimal_file_gets_the_defaults_and_relative_paths_are_resolved(tmp_path):
    config = load_agent_config(write(tmp_path, MINIMAL))
    assert isinstance(config, AgentConfig)
    assert config.robot_id == "thymio-01" and config.master.port == DEFAULT_PORT
    assert config.master.secret_file == str(tmp_path / "secret.key")
    assert config.loop.min_period == 0.1 and config.loop.max_read_failures == 3
    assert config.reconnect.initial == 0.5 and config.reconnect.max == 30.0
    assert config.safety.profile == "stop" and config.master.tls is None
    assert read_secret(config) == b"s3cret"  # the final newline is not part of the secret
    assert make_ssl_context(config) is None


def test_a_full_file_decodes(tmp_path):
    config = load_agent_config(
        write(
            tmp_path,
            """
robot_id: thymio-02
master:
  host: master.lab
  port: 9000
  secret_file: /etc/surprise/secret
  tls: {ca_file: ca.pem, server_hostname: master}
body: {thymio: {speed_scale: 300, failsafe: true}, force: {address: 0x49}}
safety: {profile: escape, force_threshold: 0.3}
loop: {min_period: 0.1, max_steps: 600, read_timeout: 0.12, max_read_failures: 5}
reconnect: {initial: 1, max: 10, jitter: 0.1}
""",
        )
    )
    assert config.master.port == 9000 and config.master.secret_file == "/etc/surprise/secret"
    assert config.master.tls.ca_file == str(tmp_path / "ca.pem")
    assert config.body.thymio.failsafe and config.body.force.address == 0x49
    assert config.safety.profile == "escape" and config.loop.max_read_failures == 5


@pytest.mark.parametrize(
    "text, key, words",
    [
        ("robot_id: r1", "master", "required key is missing"),
        ("robot_id: 'bad id'\nmaster: {host: h, secret_file: s}", "robot_id", "letters, digits"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s, prot: 1}", "master.prot", "unknown"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s, port: 0}", "master.port", ">= 1"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s}\nloop: {read_timeout: 0.5}",
         "loop.read_timeout", "watchdog"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s}\nloop: {min_period: 0.5}",
         "loop.min_period", "watchdog"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s}\nloop: {period: 0.1}",
         "loop.period", "unknown key"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s}\nloop: {max_steps: 0}",
         "loop.max_steps", ">= 1"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s}\nreconnect: {initial: 5, max: 1}",
         "reconnect.max", "at least initial"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s, tls: {key_file: k}}",
         "master.tls.key_file", "certificate"),
        ("robot_id: r1\nmaster: {host: h, secret_file: s}\nsafety: {profile: wild}",
         "safety.profile", "Invalid enum value"),
    ],
)  # fmt: skip
def test_bad_configuration_names_the_key(tmp_path, text, key, words):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_agent_config(path)
    assert info.value.file == str(path) and words in info.value.reason
    assert info.value.key == key


def run_main(argv, capsys) -> tuple[int, str]:
    code = cli.main(argv)
    return code, capsys.readouterr().err


def test_cli_exits_2_for_a_missing_config_file(tmp_path, capsys):
    code, err = run_main(["--config", str(tmp_path / "nowhere.yaml")], capsys)
    assert code == 2
    assert "nowhere.yaml" in err and "cannot read" in err and err.count("\n") == 1


def test_cli_exits_2_naming_file_and_key_for_a_bad_key(tmp_path, capsys):
    path = write(tmp_path, MINIMAL + "loop: {perod: 0.1}\n")
    code, err = run_main(["--config", str(path)], capsys)
    assert code == 2 and str(path) in err and "loop.perod" in err and "unknown key" in err


@pytest.mark.parametrize(
    "secret, words", [(None, "cannot read the secret file"), (b" \n", "empty")]
)
def test_cli_exits_2_for_a_missing_or_empty_secret(tmp_path, capsys, secret, words):
    path = write(tmp_path, MINIMAL, secret=secret)
    code, err = run_main(["--config", str(path)], capsys)
    assert code == 2 and str(path) in err and "master.secret_file" in err and words in err
    assert "secret.key" in err


def test_cli_exits_2_for_an_unreadable_tls_file(tmp_path, capsys):
    path = write(tmp_path, MINIMAL.replace("secret.key}", "secret.key, tls: {ca_file: no.pem}}"))
    code, err = run_main(["--config", str(path)], capsys)
    assert code == 2 and "master.tls.ca_file" in err and "no.pem" in err


class BrokenBody(FakeBody):
    """A robot that cannot be reached at start: open() fails, recover() once ``back`` is set."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.back = asyncio.Event()
        self.recover_calls = 0

    async def open(self) -> None:
        raise HardwareError("asebamedulla has no node 'thymio-II'")

    async def recover(self) -> None:
        self.recover_calls += 1
        if not self.back.is_set():
            raise HardwareError("asebamedulla has no node 'thymio-II'")
        self.opened = True


class BuggyBody(FakeBody):
    async def open(self) -> None:
        raise RuntimeError("a bug in a driver")


def test_cli_exits_1_when_opening_the_body_hits_a_bug(tmp_path, capsys):
    path = write(tmp_path, MINIMAL)
    body = BuggyBody()
    code = asyncio.run(cli.amain(["--config", str(path)], body_factory=lambda config: body))
    err = capsys.readouterr().err
    assert code == 1 and "cannot open the robot's body" in err and "a bug in a driver" in err
    assert body.closed  # closed anyway: open() may have got part of the way


async def test_a_robot_switched_on_later_is_served_once_it_is_there(tmp_path, caplog):
    """The Thymio is off when the Pi boots: the agent does not exit (systemd would restart it
    against a medulla that never finds the robot); it tells the master why each evaluation
    fails, recovers the robot in the background and then evaluates."""
    caplog.set_level(logging.INFO)
    master = ScriptedMaster()
    await master.start()
    clock = FakeClock()
    body = BrokenBody(clock=clock)
    path = write(tmp_path, MINIMAL.replace("192.168.1.10", f"127.0.0.1, port: {master.port}"))
    config = load_agent_config(path)
    network = spec()
    try:
        task = asyncio.create_task(
            cli.run_agent(config, SECRET, body_factory=lambda c: body, clock=clock)
        )
        stream = await master.next()
        await master.welcome(stream)
        evaluate = Evaluate(
            evaluation_id=1,
            genome=genome_to_bytes(genome(network)),
            spec=network,
            steps=5,
            step_period=0.1,
        )
        await stream.send(evaluate)
        failed = await asyncio.wait_for(stream.receive(), 5)
        assert isinstance(failed, Failed) and failed.evaluation_id == 1
        assert failed.reason.startswith("robot-unreachable: ") and "no node" in failed.reason
        assert body.reads == 0 and body.drives == []  # nothing was driven
        assert "robot unreachable" in caplog.text
        body.back.set()
        for attempt in range(2, 40):
            await stream.send(msgspec.structs.replace(evaluate, evaluation_id=attempt))
            outcome = await asyncio.wait_for(stream.receive(), 5)
            if isinstance(outcome, Result):
                break
            await asyncio.sleep(0.25)
        assert isinstance(outcome, Result) and body.reads == 5
        assert "robot reachable again after" in caplog.text
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
    finally:
        await master.close()


def test_cli_exits_2_when_the_body_configuration_is_refused(tmp_path, capsys):
    path = write(tmp_path, MINIMAL)

    def refuse(config):
        raise ConfigError("no such bus", key="body.light[0].bus")

    code = asyncio.run(cli.amain(["--config", str(path)], body_factory=refuse))
    assert code == 2 and "body.light[0].bus" in capsys.readouterr().err


# --------------------------------------------------------------------------- signals


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP])
async def test_a_signal_stops_the_motors_and_exits_0(tmp_path, signum):
    master = ScriptedMaster()
    await master.start()
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    path = write(tmp_path, MINIMAL.replace("192.168.1.10", f"127.0.0.1, port: {master.port}"))
    config = load_agent_config(path)
    (tmp_path / "secret.key").write_bytes(SECRET)
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        task = asyncio.create_task(
            cli.run_agent(config, read_secret(config), body_factory=lambda c: body, clock=clock)
        )
        stream = await master.next()
        await master.welcome(stream)
        network = spec()
        await stream.send(
            Evaluate(
                evaluation_id=1,
                genome=genome_to_bytes(genome(network, speed_bias=2.0)),
                spec=network,
                steps=30_000,  # long: it only ends when stopped
                step_period=0.1,
            )
        )
        await asyncio.wait_for(body.moved.wait(), 5)
        os.kill(os.getpid(), signum)
        assert await asyncio.wait_for(task, 5) == cli.EXIT_OK
        assert body.motors == (0.0, 0.0) and body.opened and body.closed
        assert await stream.receive() == Bye(reason="agent stopping")
        with pytest.raises(ConnectionClosedError):
            await stream.receive()
    finally:
        await master.close()
    assert {sig: signal.getsignal(sig) for sig in before} == before


# --------------------------------------------------------------------------- --stop-motors


async def test_stop_motors_zeroes_a_running_robot_without_needing_the_secret(
    tmp_path, capsys, dbus_address
):
    """systemd's ExecStopPost: after the agent ended in any way (even SIGKILL), the motors are
    set to zero from the robot's configuration alone, through whichever medulla runs, loading
    no program; the stop is confirmed by the robot."""
    text = MINIMAL + f"body: {{thymio: {{bus: '{dbus_address}', failsafe: true}}}}\n"
    path = write(tmp_path, text, secret=None)
    model = StaticThymioModel()
    model.targets = {"left": 200, "right": -120}  # what a killed agent may have left behind
    async with serve_fake_medulla(dbus_address, model) as fake:
        code = await cli.amain(["--config", str(path), "--stop-motors"])
    assert code == cli.EXIT_OK and model.targets == {"left": 0, "right": 0}
    assert fake.loaded_scripts == []


async def test_stop_motors_exits_1_when_the_robot_is_unreachable(tmp_path, capsys, dbus_address):
    text = MINIMAL + f"body: {{thymio: {{bus: '{dbus_address}', timeout: 0.05}}}}\n"
    path = write(tmp_path, text, secret=None)
    async with serve_fake_medulla(dbus_address, StaticThymioModel()) as fake:
        fake.disconnect_robot()  # medulla still says "connected", as the real one does
        code = await cli.amain(["--config", str(path), "--stop-motors"])
    assert code == cli.EXIT_FAILURE
    assert "stop was not confirmed" in capsys.readouterr().err
    code = await cli.amain(["--config", str(path), "--stop-motors"])  # no medulla at all
    assert code == cli.EXIT_FAILURE and "not running" in capsys.readouterr().err


async def test_stop_motors_reads_only_the_thymio_section(tmp_path, dbus_address):
    """A mistake elsewhere in the file (made while the agent ran) must not keep ExecStopPost from
    stopping the robot."""
    text = f"safety: {{profile: wild}}\nbody: {{thymio: {{bus: '{dbus_address}'}}, lidar: 1}}\n"
    path = write(tmp_path, text, secret=None)
    model = StaticThymioModel()
    model.targets = {"left": 200, "right": 200}
    async with serve_fake_medulla(dbus_address, model):
        code = await cli.amain(["--config", str(path), "--stop-motors"])
    assert code == cli.EXIT_OK and model.targets == {"left": 0, "right": 0}


def test_stop_motors_names_a_bad_thymio_key(tmp_path, capsys):
    path = write(tmp_path, MINIMAL + "body: {thymio: {bus: nowhere}}\n", secret=None)
    assert asyncio.run(cli.amain(["--config", str(path), "--stop-motors"])) == cli.EXIT_CONFIG
    assert "body.thymio" in capsys.readouterr().err
