"""What a test needs from the machine, and the processes it can see.

A test that needs a program from a Debian package calls :func:`require_binary`, one that needs an
optional Python package :func:`require_module`: outside CI a missing one skips the test with what
to install; in CI (``CI=true``) it fails the test, because ``.ci/run`` installs everything the
tests use and a skip there would hide a missing install step.

:func:`processes` lists processes from ``/proc`` (no ``pgrep``, so the tests need no procps).
"""

from __future__ import annotations

import importlib
import os
import shutil
import subprocess
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

#: Programs whose Debian package is not named after them, for the hint of a skipped test.
PACKAGES = {
    "asebamedulla": "aseba",
    "asebaplayground": "aseba",
    "dbus-daemon": "dbus-daemon",
    "dbus-monitor": "dbus-bin",
    "mosquitto": "mosquitto",
    "systemd-analyze": "systemd",
    "openssl": "openssl",
    "unshare": "util-linux",
    "setpriv": "util-linux",
}
#: Directories searched besides PATH: Debian puts daemons in sbin, not on every user's PATH.
SBIN = ("/usr/sbin", "/usr/local/sbin", "/sbin")


def in_ci() -> bool:
    """Whether the tests run in CI (``CI=true``), where nothing they need may be missing."""
    return os.environ.get("CI", "").lower() in ("true", "1")


def missing(reason: str) -> None:
    """Fail the test in CI, skip it elsewhere, saying ``reason`` (what is missing, what to do)."""
    if in_ci():
        pytest.fail(f"{reason}; CI must run this test: .ci/run has to install it")
    pytest.skip(reason, allow_module_level=True)


def find_binary(name: str) -> str | None:
    """The path of the program ``name`` on PATH or in an sbin directory, or None."""
    found = shutil.which(name)
    if found:
        return found
    return next((str(Path(d) / name) for d in SBIN if os.access(Path(d) / name, os.X_OK)), None)


def require_binary(name: str, package: str | None = None) -> str:
    """The path of the program ``name``; skip (fail in CI) when it is not installed."""
    found = find_binary(name)
    if found is None:
        package = package or PACKAGES.get(name, name)
        missing(f"{name} is not installed (apt-get install {package})")
    assert found is not None
    return found


def require_module(name: str, extra: str = "dev") -> ModuleType:
    """The imported module ``name``; skip (fail in CI) when it cannot be imported."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        missing(f"the Python module {name} cannot be imported ({exc}; pip install -e '.[{extra}]')")
        raise AssertionError("not reached") from None


def obeying_modes(directory: Path) -> tuple[str, ...]:
    """What to run a command under so that it obeys file modes in ``directory``: nothing for a
    user; for root, ``setpriv`` without the capabilities it writes and reads anywhere with.

    Both capability sets: root's exec keeps what the inheritable set holds, and a container
    (systemd-nspawn) hands its processes a full one."""
    probe = directory / ".probe"
    probe.mkdir()
    probe.chmod(0o500)
    try:
        if not os.access(probe, os.W_OK):
            return ()
    finally:
        probe.chmod(0o700)
        probe.rmdir()
    caps = "-dac_override,-dac_read_search"
    return (require_binary("setpriv"), f"--inh-caps={caps}", f"--bounding-set={caps}", "--")


def end_process(process: subprocess.Popen[Any] | None, timeout: float) -> None:
    """End ``process`` if it still runs: SIGTERM, then SIGKILL after ``timeout`` seconds."""
    if process is None or process.poll() is not None:
        return
    process.terminate()
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


@dataclass(frozen=True)
class Process:
    """One process as ``/proc`` shows it."""

    pid: int
    ppid: int
    name: str  #: the command name (``comm``), as ``pgrep NAME`` matches it
    cmdline: str  #: the arguments joined by spaces, as ``pgrep -f`` matches them


def processes() -> list[Process]:
    """Every process this test can see; ones that end while being read are left out."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:  # it ended meanwhile
            continue
        # The name is in parentheses and may itself hold spaces and parentheses.
        name = stat[stat.index("(") + 1 : stat.rindex(")")]
        ppid = int(stat[stat.rindex(")") + 2 :].split()[1])
        args = cmdline.rstrip(b"\0").replace(b"\0", b" ").decode(errors="replace")
        found.append(Process(int(entry.name), ppid, name, args))
    return found


def pids(
    name: str | None = None, *, parent: int | None = None, containing: str | None = None
) -> set[int]:
    """Process ids by command name, parent or a substring of the command line (like ``pgrep``,
    ``pgrep -P`` and ``pgrep -f``); every given condition must hold."""
    return {p.pid for p in _matching(processes(), name, parent, containing) if p.pid != os.getpid()}


def _matching(
    every: Iterable[Process], name: str | None, parent: int | None, containing: str | None
) -> Iterable[Process]:
    for p in every:
        if name is not None and p.name != name:
            continue
        if parent is not None and p.ppid != parent:
            continue
        if containing is not None and containing not in p.cmdline:
            continue
        yield p
