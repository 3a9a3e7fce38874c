"""A real Dask scheduler and workers, each a process of its own started with the ``dask``
command, on loopback only: for the tests that run studies on a cluster and break parts of it.

Everything listens on 127.0.0.1: the scheduler and the workers bind there (``--host``), and so
do their HTTP servers (``--dashboard-address 127.0.0.1:0``; ``--no-dashboard`` alone still
serves on 0.0.0.0:8787). :meth:`LoopbackCluster.listening` lists what the cluster's processes
listen on, read from ``/proc`` (no ``ss`` needed), so a test can check that.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType
from typing import Self

from needs import processes

#: Seconds for a Dask scheduler or worker process to come up (a loaded CI machine).
DASK_START_TIMEOUT = 60.0
#: The loopback address every process binds to.
LOOPBACK = "127.0.0.1"


def dask_command() -> str:
    """The ``dask`` command of this venv (it comes with distributed)."""
    found = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    assert found is not None, "the dask command comes with distributed (pip install -e '.[dev]')"
    return found


def start(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    """``args`` as a process of its own, its output into ``log``."""
    with open(log, "ab") as out:
        return subprocess.Popen(
            args, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip


def wait_until(condition, what: str, timeout: float, log: Path | None = None) -> None:
    """Poll ``condition()`` until true; fail saying ``what`` (and the end of ``log``) after
    ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            tail = log.read_text(errors="replace")[-3000:] if log and log.exists() else ""
            raise AssertionError(f"{what}: not within {timeout:.0f} s\n{tail}")
        time.sleep(0.05)


class LoopbackCluster:
    """A scheduler and workers on loopback below ``folder`` (their logs and scheduler file);
    use as a context manager, which stops whatever is still running."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.dask = dask_command()
        self.scheduler: subprocess.Popen[bytes] | None = None
        self.workers: list[subprocess.Popen[bytes]] = []
        self.address = ""
        self._schedulers = 0
        self._started: list[subprocess.Popen[bytes]] = []

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def start_scheduler(self, port: int = 0) -> str:
        """Start a scheduler on ``port`` (0: any free one); its address once it is up."""
        index = self._schedulers
        self._schedulers += 1
        scheduler_file = self.folder / f"scheduler-{index}.json"
        log = self.folder / f"scheduler-{index}.log"
        self.scheduler = start(
            [self.dask, "scheduler", "--host", LOOPBACK, "--port", str(port),
             "--dashboard-address", f"{LOOPBACK}:0", "--scheduler-file", str(scheduler_file)],
            log,
        )  # fmt: skip
        self._started.append(self.scheduler)
        wait_until(scheduler_file.exists, "the scheduler did not start", DASK_START_TIMEOUT, log)
        self.address = json.loads(scheduler_file.read_text())["address"]
        return self.address

    @property
    def port(self) -> int:
        """The scheduler's port."""
        return int(self.address.rsplit(":", 1)[1])

    def start_workers(self, count: int, *, nanny: bool = True) -> None:
        """Start ``count`` workers of one thread each and wait until the scheduler has them.
        Without a nanny, a worker killed stays dead (a nanny would start it again)."""
        for _ in range(count):
            index = len(self.workers)
            log = self.folder / f"worker-{index}.log"
            worker = start(
                [self.dask, "worker", self.address, "--host", LOOPBACK, "--nthreads", "1",
                 "--dashboard-address", f"{LOOPBACK}:0",
                 *(["--nanny-port", "0"] if nanny else ["--no-nanny"]),
                 "--worker-port", "0", "--name", f"worker-{index}"],
                log,
            )  # fmt: skip
            self.workers.append(worker)
            self._started.append(worker)
        self.wait_for_workers(count)

    def wait_for_workers(self, count: int) -> None:
        """Wait until the scheduler has ``count`` workers."""
        from distributed import Client

        with Client(self.address, timeout=DASK_START_TIMEOUT) as client:
            client.wait_for_workers(count, timeout=DASK_START_TIMEOUT)

    def kill(self, process: subprocess.Popen[bytes]) -> None:
        """SIGKILL ``process`` and every process it started (a nanny's worker): no clean-up
        of any kind."""
        for pid in [process.pid, *_descendants({process.pid})]:
            with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
                os.kill(pid, signal.SIGKILL)
        process.wait()

    def stop(self) -> None:
        """Stop every process started, at once: a worker asked to stop takes seconds to leave
        (longer without a scheduler), and nothing of theirs needs keeping."""
        for process in reversed(self._started):
            self.kill(process)

    def listening(self) -> list[tuple[int, str, bool]]:
        """Every TCP socket the cluster's processes (and their children) listen on: pid,
        ``address:port`` and whether it is loopback."""
        ours = {p.pid for p in self._started if p.poll() is None}
        ours |= _descendants(ours)  # the nannies' workers, and whatever they start
        return [(pid, *found) for pid in sorted(ours) for found in listening_addresses(pid)]


def listening_addresses(pid: int) -> list[tuple[str, bool]]:
    """The TCP sockets process ``pid`` listens on: ``address:port`` and whether it is
    loopback."""
    sockets = _listening_sockets()
    found = []
    for inode in _socket_inodes(pid):
        if inode in sockets:
            host, port = sockets[inode]
            found.append((f"{host}:{port}", _is_loopback(host)))
    return found


def _descendants(pids: set[int]) -> set[int]:
    # The processes started by ``pids``, by their children, and so on.
    every = processes()
    found: set[int] = set()
    while True:
        more = {p.pid for p in every if p.ppid in pids | found} - found
        if not more:
            return found
        found |= more


def _listening_sockets() -> dict[int, tuple[str, int]]:
    # Socket inode -> (address, port) of every listening TCP socket, from /proc/net/tcp{,6}.
    found = {}
    for table in ("tcp", "tcp6"):
        try:
            lines = Path(f"/proc/net/{table}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if fields[3] != "0A":  # TCP_LISTEN
                continue
            host, port = fields[1].split(":")
            raw = bytes.fromhex(host)
            # Each 32-bit word is in the kernel's (little-endian) byte order.
            raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
            found[int(fields[9])] = (str(ipaddress.ip_address(raw)), int(port, 16))
    return found


def _socket_inodes(pid: int) -> set[int]:
    inodes = set()
    try:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(int(target[8:-1]))
    except OSError:  # it ended meanwhile
        pass
    return inodes


def _is_loopback(host: str) -> bool:
    address = ipaddress.ip_address(host)
    mapped = getattr(address, "ipv4_mapped", None)
    return address.is_loopback or (mapped is not None and mapped.is_loopback)
