"""Writing a file all at once, with the permissions a plain ``open()`` would give it.

Every package that replaces a file readers may look at while it is written (the run directory,
a study's summaries, the simulated robots' configuration files, the Aseba programs) uses
:func:`write_atomic`, so that a reader sees the old or the new content, never a mix, and the file
is as readable as any other the process creates: mode ``0666`` less the umask (``0644`` under
the usual ``022``). Secrets ask for :data:`PRIVATE_MODE` instead.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import secrets
from pathlib import Path
from typing import Final

__all__ = ["PRIVATE_MODE", "SECRET_BYTES", "write_atomic", "write_json", "write_new_secret"]

#: The mode of a file only its owner may read or write: for secrets.
PRIVATE_MODE: Final = 0o600

# Creating a temporary name: flags as tempfile.mkstemp's (the file must be new, not a link
# planted there), and as many tries before giving up.
_CREATE_FLAGS: Final = (
    os.O_WRONLY
    | os.O_CREAT
    | os.O_EXCL
    | getattr(os, "O_NOFOLLOW", 0)
    | getattr(os, "O_CLOEXEC", 0)
    | getattr(os, "O_BINARY", 0)
)
_NAME_TRIES: Final = 100


def write_atomic(
    path: str | Path, data: bytes, *, durable: bool = True, mode: int | None = None
) -> None:
    """Replace ``path`` by ``data`` all at once: temp file, (fsync), rename, (fsync directory).

    Readers see the old or the new content, never a mix. ``durable=False`` skips the fsyncs for
    files that can be rebuilt or only describe a running process. ``mode=None`` gives the file
    the permissions ``open()`` would (``0666`` less the umask); an explicit ``mode`` is applied
    whatever the umask, e.g. :data:`PRIVATE_MODE` for a secret (the file is never readable by
    others, not even while it is written).
    """
    path = Path(path)
    fd, tmp = _create_temp(path, 0o666 if mode is None else PRIVATE_MODE)
    try:
        with os.fdopen(fd, "wb") as file:
            if mode is not None and mode != PRIVATE_MODE:
                # chmod, unlike creation, ignores the umask: the caller asked for this mode.
                os.fchmod(file.fileno(), mode)
            file.write(data)
            if durable:
                file.flush()
                os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    if durable:
        _fsync_dir(path.parent)


def write_json(path: Path, data: object) -> None:
    """Write ``data`` as indented JSON with :func:`write_atomic` (a crash or a power cut leaves
    the old file or the new one, never an empty one)."""
    write_atomic(path, json.dumps(data, indent=1).encode("utf-8"))


#: Random bytes of a new shared secret: 256 bits, written as 64 hex digits.
SECRET_BYTES: Final = 32


def write_new_secret(path: str | Path) -> Path:
    """Write a new random shared secret of the master and the robots to ``path``: one line of
    hex digits in a file only its owner may read (:data:`PRIVATE_MODE`). Never overwrites:
    :class:`FileExistsError` when ``path`` exists, since robots may hold that secret already.
    The path written is returned."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(errno.EEXIST, "exists already: the robots may hold it", str(path))
    # Written whole, so that a stop half-way leaves no empty secret file behind.
    write_atomic(path, (secrets.token_hex(SECRET_BYTES) + "\n").encode("ascii"), mode=PRIVATE_MODE)
    return path


def _create_temp(path: Path, mode: int) -> tuple[int, Path]:
    # tempfile.mkstemp always creates 0600. Instead the creation mode goes to open(2), so the
    # kernel applies the umask (or the directory's default ACL) exactly as for any file open()
    # creates. Reading the umask ourselves would mean os.umask(x) and setting it back: the umask
    # is process-wide, and a file another thread creates in between would get the wrong mode.
    for _ in range(_NAME_TRIES):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            return os.open(tmp, _CREATE_FLAGS, mode), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no unused temporary name for {path} after {_NAME_TRIES} tries")


def _fsync_dir(path: Path) -> None:
    # A rename is durable only once the directory entry is on disk.
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
