"""A person's request to a running master, through its run directory (docs/runs.md): the one
mechanism behind ``surprise-master escape``, ``swap`` and ``fleet stop --run``.

The command drops a typed request (``EscapeRequest``, ``SwapRequest``, ``StopRequest``, each
with a fresh ``token``) into ``requests/`` and waits for the master's answer, an event naming the
same token in ``events.jsonl`` (:func:`ask_master`); a request not answered in time is taken back,
so that it never acts late. The master's desk for each kind takes the requests, oldest first,
hands each to its handler and appends the event it returns (:func:`serve_requests`). A request
the master cannot read is logged and dropped; the run's state is never touched by it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Final, TypeVar

from runfiles import schema
from runfiles.schema import (
    REQUESTS,
    EscapeRequest,
    Event,
    Live,
    MarkRequest,
    RunDirError,
    StopRequest,
    SwapRequest,
    append_event,
    master_alive,
    read_events,
)

__all__ = [
    "ANSWER_POLL",
    "ask_master",
    "drop_request",
    "new_token",
    "pending_requests",
    "request_path",
    "serve_requests",
]

#: Seconds between two looks of a command into ``events.jsonl`` for its answer.
ANSWER_POLL: Final = 0.1

#: The kinds of request a person's command drops for the running master.
Request = TypeVar("Request", EscapeRequest, SwapRequest, StopRequest, MarkRequest)


def new_token() -> str:
    """A request's token: unique per request, the key its answer names."""
    return secrets.token_hex(8)


def request_path(run_dir: Path, kind: type[Request], token: str) -> Path:
    """Where a person's request of ``kind`` with ``token`` lies for the running master:
    ``requests/<stem>-<token>.json``, the stem ``kind.FILE``'s (``escape-request``)."""
    stem = kind.FILE.removesuffix(".json")
    return run_dir / REQUESTS / f"{stem}-{token}.json"


def pending_requests(folder: Path, kind: type[Request]) -> list[Path]:
    """The requests of ``kind`` waiting in ``folder``, oldest first (none when it does not
    exist; a file being written has a ``.tmp`` name until it is whole; each desk takes only its
    own kind's, named by :func:`request_path`)."""
    prefix = kind.FILE.removesuffix(".json") + "-"
    try:
        paths = [p for p in folder.iterdir() if p.suffix == ".json" and p.name.startswith(prefix)]
    except FileNotFoundError:
        return []

    def written(path: Path) -> tuple[float, str]:
        try:
            return path.stat().st_mtime, path.name
        except OSError:  # taken back meanwhile: the desk finds it gone
            return 0.0, path.name

    return sorted(paths, key=written)


def drop_request(run_dir: Path, request: Request) -> Path:
    """Write ``request`` into ``run_dir``'s ``requests/`` for the master's desk; its file."""
    target = request_path(run_dir, type(request), request.token)
    with schema.writing(target):
        target.parent.mkdir(exist_ok=True)
    schema.write_atomic(target, schema.encode(request), durable=False)
    return target


def ask_master(
    run_dir: Path, request: Request, answer: str, *, timeout: float, not_running: str
) -> Event:
    """Drop ``request`` for the master running ``run_dir`` and wait for its answer, the event of
    kind ``answer`` naming the request's token.

    Raises :class:`RunDirError` with ``not_running`` when no master runs the run
    (``master_alive``), and when none answers within ``timeout`` (the request is then taken back
    when it was not taken yet, so that it never acts late).
    """
    if not master_alive(schema.read_if_readable(run_dir, Live), time.time()):
        raise RunDirError(not_running)
    target = drop_request(run_dir, request)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for event in read_events(run_dir):
            if event.kind == answer and event.request == request.token:
                return event
        time.sleep(ANSWER_POLL)
    with contextlib.suppress(FileNotFoundError):
        target.unlink()  # not taken: it must not act later; taken: its event comes anyway
    raise RunDirError(f"the master running {run_dir} did not answer within {timeout:.0f} s")


async def serve_requests(
    run_dir: Path,
    kind: type[Request],
    handle: Callable[[Request], Awaitable[Event]],
    log: logging.Logger,
    what: str,
    interval: Callable[[], float],
) -> None:
    """Answer the requests of ``kind`` in ``run_dir`` until cancelled, one after the other in
    the order they came, looking again every ``interval()`` seconds; ``what`` names them in the
    log (``the experimenter's escape``)."""
    folder = run_dir / REQUESTS
    while True:
        try:
            for path in await asyncio.to_thread(pending_requests, folder, kind):
                await _take(run_dir, path, kind, handle, log, what)
        except Exception:  # a bug must cost one request, never the desk or the run
            log.exception("%s: a request failed", what)
        await asyncio.sleep(interval())


async def _take(
    run_dir: Path,
    path: Path,
    kind: type[Request],
    handle: Callable[[Request], Awaitable[Event]],
    log: logging.Logger,
    what: str,
) -> None:
    try:
        raw = await asyncio.to_thread(path.read_bytes)
        path.unlink()
    except FileNotFoundError:
        return  # taken back by its command, which gave up waiting
    except OSError as exc:
        log.warning("cannot take the request %s: %s", path, exc)
        return
    try:
        request = schema.decode(kind, raw, name=str(path))
    except RunDirError as exc:
        log.warning("ignored a request this master cannot read: %s", exc)
        return
    event = await handle(request)
    try:
        await asyncio.to_thread(append_event, run_dir, event)
    except OSError as exc:
        log.error("%s could not be logged: %s", what, exc)
