"""``surprise-sim-robots`` without the ``robot`` extra: ``--help`` works, serving says what to
install. A subprocess stands in for a machine without ``dbus-fast``: ``sys.modules["dbus_fast"]
= None`` makes every import of it fail, as if it were not installed."""

from __future__ import annotations

import subprocess
import sys

_WITHOUT_DBUS = (
    "import sys; sys.modules['dbus_fast'] = None; "
    "from standins.serve import main; sys.exit(main(sys.argv[1:]))"
)


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _WITHOUT_DBUS, *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_help_works_without_dbus_fast() -> None:
    done = _run("--help")
    assert done.returncode == 0, done.stderr
    assert "usage: surprise-sim-robots" in done.stdout
    assert "--scenario" in done.stdout


def test_serving_without_dbus_fast_names_the_pip_command(tmp_path) -> None:
    done = _run("--dir", str(tmp_path / "robots"))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "pip install -e '.[robot]'" in lines[0]
    assert "dbus-fast" in lines[0]
    assert not (tmp_path / "robots").exists()  # nothing was started
