"""The robot's side of a preflight check (``surprise-master check``, docs/preflight.md).

Between evaluations the master may ask a :class:`~minimize_surprise.wire.Check`: the agent reads
every part of its body on its own (one broken part must not hide the others), its battery, and
asks its own safety layer what it would do to a forward drive on that reading, with its own
thresholds. That last answer is what tells a floor too bright for the ground rule from a robot
standing at an edge: only the agent knows the thresholds it runs with. Nothing drives.

On a Raspberry Pi it also reads ``vcgencmd get_throttled`` (under-voltage and throttling flags,
for ``surprise-master fleet status``); where there is no ``vcgencmd`` the report says unknown.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import shutil
import time
from typing import Final

import numpy as np

from drivers.body import Body, PartReading
from minimize_surprise.safety import SafetyLayer, SafetyState
from minimize_surprise.wire import MAX_BATTERY_V, MAX_THROTTLED, CheckReport, PartCheck

__all__ = [
    "BATTERY_CHECK_TIMEOUT",
    "FORWARD",
    "THROTTLED_TIMEOUT",
    "VCGENCMD",
    "check_body",
    "ground_rule",
    "read_throttled",
]

log = logging.getLogger(__name__)

#: Seconds the battery read of a check may take: one ``GetVariable``, answered within a sensor
#: period by a robot that is there.
BATTERY_CHECK_TIMEOUT: Final = 2.0
#: The drive the safety layer is asked about: straight ahead at full speed, where the ground rule
#: and the front IR apply.
FORWARD: Final = (1.0, 1.0)
#: Seconds ``vcgencmd get_throttled`` may take: it answers in milliseconds from the firmware's
#: mailbox; one that hangs (a firmware in trouble) must not hold the check.
THROTTLED_TIMEOUT: Final = 2.0
#: The Pi's firmware tool, looked up on ``PATH`` (absent off a Pi: the flags are unknown).
VCGENCMD: Final = "vcgencmd"
_THROTTLED = re.compile(rb"throttled=(0x[0-9a-fA-F]+|\d+)")
#: The longest error text a report carries per part (the wire's bound is larger; a person reads
#: one line).
_ERROR_CHARS: Final = 300


def ground_rule(layer: SafetyLayer) -> str:
    """What the layer's ground rule takes for the arena's boundary, e.g. ``ground >= 0.55``."""
    if not layer.ground.size:
        return "no ground sensors"
    sign = "<" if layer.params.ground_below else ">="
    return f"ground {sign} {layer.params.ground_threshold:g}"


async def check_body(body: Body, layer: SafetyLayer, state: SafetyState, seq: int) -> CheckReport:
    """Read ``body`` for check ``seq`` (see the module docstring); never raises for the body."""
    parts = await body.read_parts()
    battery = await _battery(body)
    reason = _forward_safety(body, layer, state, parts)
    throttled = await read_throttled()
    return CheckReport(
        seq=seq,
        time=time.time(),
        battery_v=battery,
        parts=tuple(
            PartCheck(
                part=p.part,
                sensors=p.sensors,
                values=p.values,
                error=None if p.error is None else p.error[:_ERROR_CHARS],
            )
            for p in parts
        ),
        forward_safety=reason,
        ground_rule=ground_rule(layer),
        throttled=throttled,
    )


async def read_throttled() -> int | None:
    """The Pi's ``vcgencmd get_throttled`` flags, None where there is no ``vcgencmd`` or it
    does not answer within :data:`THROTTLED_TIMEOUT` (never raises: a report is still worth
    sending without them)."""
    program = shutil.which(VCGENCMD)
    if program is None:
        return None
    process = None
    try:
        process = await asyncio.create_subprocess_exec(
            program,
            "get_throttled",
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.DEVNULL,
        )
        async with asyncio.timeout(THROTTLED_TIMEOUT):
            out, _ = await process.communicate()
    except (OSError, TimeoutError) as exc:
        log.info("check: vcgencmd get_throttled failed: %r", exc)
        if process is not None and process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            await process.wait()
        return None
    match = _THROTTLED.search(out)
    if process.returncode != 0 or match is None:
        return None
    value = int(match.group(1), 0)
    return value if 0 <= value <= MAX_THROTTLED else None


async def _battery(body: Body) -> float | None:
    try:
        async with asyncio.timeout(BATTERY_CHECK_TIMEOUT):
            volts = await body.read_battery()
    except Exception as exc:  # unknown, and the Thymio part's own reading says why
        log.info("check: the battery could not be read: %r", exc)
        return None
    if volts is None or not 0.0 <= volts <= MAX_BATTERY_V:
        return None
    return float(volts)


def _forward_safety(
    body: Body, layer: SafetyLayer, state: SafetyState, parts: list[PartReading]
) -> str | None:
    """The layer's reason to change a forward drive on this reading; None when it lets it pass
    or when a part did not answer (then there is no whole reading to judge)."""
    if any(p.error is not None for p in parts):
        return None
    values = {name: v for p in parts for name, v in zip(p.sensors, p.values, strict=False)}
    if set(values) != set(body.sensors):  # a part answered fewer values than it names
        return None
    frame = np.array([values[name] for name in body.sensors])
    decision = layer.step(layer.reset(state), frame, np.array(FORWARD))
    return decision.reason
