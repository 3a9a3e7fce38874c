"""Helpers of the telemetry tests: a real ``mosquitto`` broker on a free loopback port, a
subscriber that records what arrives, and a polling wait.

The broker is Debian's ``mosquitto`` (``.ci/run`` installs it). The helpers of the agent's and the
master's tests (``agent_fakes``, ``master_helpers``) become importable too.
"""

from __future__ import annotations

import asyncio
import contextlib
import getpass
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final

_TESTS = Path(__file__).resolve().parent.parent
for helpers in (_TESTS / "agent", _TESTS / "master"):
    if str(helpers) not in sys.path:
        sys.path.insert(0, str(helpers))

#: Where Debian puts the broker; /usr/sbin is not on every user's PATH.
_MOSQUITTO_PATHS: Final = ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto")
#: Seconds a starting broker may take to accept connections (it takes a few milliseconds; the
#: margin is for a loaded CI machine).
START_TIMEOUT: Final = 10.0
#: Seconds a broker may take to exit after SIGTERM before it is killed.
STOP_TIMEOUT: Final = 5.0
#: Seconds a test waits for a message that should arrive (milliseconds on loopback).
WAIT: Final = 10.0


def mosquitto_binary() -> str | None:
    """The broker's executable, or None if it is not installed."""
    found = shutil.which("mosquitto")
    if found:
        return found
    return next((p for p in _MOSQUITTO_PATHS if os.access(p, os.X_OK)), None)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Broker:
    """A ``mosquitto`` process on ``127.0.0.1:port`` that a test can stop and start again (on the
    same port, without persistence: a restarted broker has forgotten every retained message)."""

    def __init__(self, binary: str, directory: Path, port: int) -> None:
        self.binary = binary
        self.directory = directory
        self.port = port
        self.process: subprocess.Popen[bytes] | None = None
        self.starts = 0
        self.config_file = directory / "mosquitto.conf"
        lines = [
            f"listener {port} 127.0.0.1",
            "allow_anonymous true",
            "persistence false",
            "log_dest stderr",
        ]
        if os.geteuid() == 0:
            # As root, mosquitto drops to the user "mosquitto", which a container may lack.
            lines.append(f"user {getpass.getuser()}")
        self.config_file.write_text("\n".join(lines) + "\n", encoding="utf-8")

    @property
    def url(self) -> str:
        """The broker's URL as the configuration takes it."""
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> None:
        """Start the broker and wait until it accepts connections."""
        assert self.process is None, "the broker is running"
        self.starts += 1
        log = open(self.directory / f"mosquitto-{self.starts}.log", "wb")  # noqa: SIM115
        with log:
            self.process = subprocess.Popen(
                [self.binary, "-c", str(self.config_file)],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            if self.process.poll() is not None:
                output = (self.directory / f"mosquitto-{self.starts}.log").read_text()
                self.process = None
                raise RuntimeError(f"mosquitto exited at start:\n{output}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError(
                        f"mosquitto did not listen within {START_TIMEOUT} s"
                    ) from None
                time.sleep(0.01)

    def stop(self) -> None:
        """Stop the broker (SIGTERM, then SIGKILL) and wait until it has exited."""
        process, self.process = self.process, None
        if process is None:
            return
        process.terminate()
        try:
            process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


class Subscriber:
    """An MQTT client subscribed to ``<prefix>/#`` that records (topic, payload, retain)."""

    def __init__(self, port: int, prefix: str = "surprise") -> None:
        self.port = port
        self.prefix = prefix
        self.messages: list[tuple[str, bytes, bool]] = []
        self._changed = asyncio.Event()
        self._stack = contextlib.AsyncExitStack()

    async def __aenter__(self) -> Subscriber:
        import aiomqtt

        client = aiomqtt.Client(
            "127.0.0.1", self.port, identifier=f"test-{uuid.uuid4().hex[:8]}", timeout=WAIT
        )
        await self._stack.enter_async_context(client)
        await client.subscribe(f"{self.prefix}/#", qos=1)
        task = asyncio.create_task(self._read(client))

        async def stop() -> None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task

        self._stack.push_async_callback(stop)
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        with contextlib.suppress(Exception):  # the broker may be gone by now
            await self._stack.aclose()

    async def _read(self, client: Any) -> None:
        with contextlib.suppress(Exception):  # a stopped broker ends the subscription
            async for message in client.messages:
                self.messages.append((str(message.topic), bytes(message.payload), message.retain))
                self._changed.set()

    def topic(self, suffix: str) -> str:
        """The full topic of ``suffix``."""
        return f"{self.prefix}/{suffix}"

    def payloads(self, suffix: str) -> list[dict[str, Any]]:
        """The decoded payloads that arrived on ``<prefix>/<suffix>``, in order."""
        return [json.loads(p) for t, p, _ in self.messages if t == self.topic(suffix)]

    async def wait_for(
        self, suffix: str, predicate: Callable[[dict[str, Any]], bool] = lambda p: True
    ) -> dict[str, Any]:
        """The first payload on ``<prefix>/<suffix>`` satisfying ``predicate`` (waiting for it
        up to :data:`WAIT` seconds)."""
        async with asyncio.timeout(WAIT):
            seen = 0
            while True:
                for topic, payload, _ in self.messages[seen:]:
                    if topic == self.topic(suffix):
                        data = json.loads(payload)
                        if predicate(data):
                            return data
                seen = len(self.messages)
                self._changed.clear()
                await self._changed.wait()


async def eventually(predicate: Callable[[], bool], timeout: float = WAIT) -> None:
    """Wait until ``predicate()`` holds, polling; fail the test after ``timeout`` seconds."""
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(0.01)
