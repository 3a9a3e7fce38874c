"""The fleet's commands over the agents' own protocol: ``surprise-master fleet status`` and
``fleet stop`` (docs/fleet.md).

How the laptop reaches the agents without a run: the agents already connect to the master's
address (their ``master`` setting) and retry with backoff while nobody listens. A fleet command
listens there as a master does (the master file's host, port, secret and TLS), as the preflight
does, and asks each agent that connects. No ssh and no second port on the robots: what the
agent answers is what the agent itself can say, and tests run it against real agents in-process.

``fleet status`` asks each agent a :class:`~minimize_surprise.wire.Check` (never drives) and
shows what its Hello and the report say: version, commit, firmware, battery, its clock against
the laptop's (the report's time against the exchange's midpoint), the Pi's ``vcgencmd
get_throttled`` flags. A robot whose agent does not connect within the timeout is *not
reachable*: its Pi is off, its agent stopped, or its ``master`` names another address; the
protocol cannot tell those apart (``fleet logs`` over ssh can).

``fleet stop`` without a run (:func:`fleet_stop`) serves the agents too and stops each as it
connects (:class:`~master_service.stopall.Stopper`): an agent connected to this command runs
nothing, and its Stopped is the confirmation. With a run going, the stop goes through its master
(:mod:`master_service.stopall`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

from master_service.agent_server import CHECK_TIMEOUT, CONNECT_TIMEOUT, AgentServer
from master_service.config import MasterConfig
from master_service.inventory import Inventory
from master_service.server import Session
from master_service.stopall import StopOutcome, Stopper

__all__ = [
    "CHECK_TIMEOUT",
    "StatusRow",
    "fleet_status",
    "fleet_stop",
    "format_status",
    "throttled_text",
]

#: Characters of a commit shown in the status table.
_SHORT_COMMIT: Final = 10
#: The Pi's ``get_throttled`` bits and what they say (the firmware's documentation).
_THROTTLED_BITS: Final = (
    (0x1, "under-voltage now"),
    (0x2, "frequency capped now"),
    (0x4, "throttled now"),
    (0x8, "soft temperature limit now"),
    (0x10000, "under-voltage has occurred"),
    (0x20000, "frequency capping has occurred"),
    (0x40000, "throttling has occurred"),
    (0x80000, "soft temperature limit has occurred"),
)


def throttled_text(flags: int | None) -> str:
    """The Pi's ``vcgencmd get_throttled`` flags for a person: ``n/a`` when unknown (no
    ``vcgencmd`` on the robot, or an agent older than the field), ``ok`` when none is set."""
    if flags is None:
        return "n/a"
    if flags == 0:
        return "ok"
    named = [text for bit, text in _THROTTLED_BITS if flags & bit]
    return ", ".join(named) or f"0x{flags:x}"


@dataclass
class StatusRow:
    """One robot of ``fleet status``."""

    robot: str
    address: str | None = None
    enabled: bool = True
    spare: bool = False
    reachable: bool = False
    peer: str | None = None
    software: str | None = None
    commit: str | None = None
    firmware: int | None = None
    battery_v: float | None = None
    clock_offset_s: float | None = None
    throttled: int | None = None
    #: the agent runs an evaluation for another master (it answered busy) or did not answer
    busy: bool = False
    problem: str | None = None

    def to_json(self) -> dict[str, Any]:
        """Plain data for ``--json``."""
        return {
            "robot": self.robot,
            "address": self.address,
            "enabled": self.enabled,
            "spare": self.spare,
            "reachable": self.reachable,
            "agent_active": self.reachable,
            "peer": self.peer,
            "software": self.software,
            "commit": self.commit,
            "firmware": self.firmware,
            "battery_v": self.battery_v,
            "clock_offset_s": None
            if self.clock_offset_s is None
            else round(self.clock_offset_s, 3),
            "throttled": self.throttled,
            "throttled_text": throttled_text(self.throttled),
            "problem": self.problem,
        }


def _admit(robots: Sequence[str]) -> Callable[[str], str | None]:
    """Admit ``robots`` (none: any robot)."""

    def admit(robot_id: str) -> str | None:
        if robots and robot_id not in robots:
            return f"{robot_id} is not an enabled robot of the fleet"
        return None

    return admit


def _fleet_robots(config: MasterConfig, fleet: Inventory | None) -> list[str]:
    """The robots a fleet command waits for: the inventory's enabled ones, else the master
    file's ``allowed_robots``; none: any that connects."""
    if fleet is not None:
        return fleet.enabled
    return list(config.allowed_robots)


async def fleet_status(
    config: MasterConfig,
    secret: bytes,
    fleet: Inventory | None,
    *,
    timeout: float = CONNECT_TIMEOUT,
    log: logging.Logger | None = None,
    on_listening: Any = None,
) -> list[StatusRow]:
    """``fleet status``: one row per robot of the inventory (its order, disabled ones too,
    not asked), then any other robot that connected."""
    log = log if log is not None else logging.getLogger("master_service.fleet")
    robots = _fleet_robots(config, fleet)
    rows: dict[str, StatusRow] = {}
    answered: set[str] = set()

    async def ask(session: Session) -> None:
        hello = session.hello
        row = rows.setdefault(session.robot_id, StatusRow(session.robot_id))
        row.reachable, row.peer = True, session.peer
        row.software, row.commit, row.firmware = (
            hello.software_version,
            hello.software_commit,
            hello.thymio_firmware,
        )
        try:
            exchange = await fleet_server.check(session)
            if exchange is None:
                row.problem = f"no answer to the status check within {CHECK_TIMEOUT:g} s"
                return
            report, midpoint = exchange
            row.clock_offset_s = report.time - midpoint
            row.battery_v, row.throttled, row.busy = (
                report.battery_v,
                report.throttled,
                report.busy,
            )
        finally:
            answered.add(session.robot_id)

    fleet_server = AgentServer(
        config, secret, log, admit=_admit(robots), purpose="fleet-status", on_session=ask
    )
    for robot in fleet.robots if fleet is not None else ():
        rows[robot.name] = StatusRow(
            robot.name, robot.address, enabled=robot.enabled, spare=robot.spare
        )
    await fleet_server.serve(
        lambda: bool(robots) and set(robots) <= answered, timeout, on_listening
    )
    for name in robots:
        row = rows.setdefault(name, StatusRow(name))
        if not row.reachable:
            row.problem = (
                f"not reachable within {timeout:.0f} s: its Pi off, its agent stopped "
                "(`systemctl status surprise-agent`), or its `master` names another address"
            )
    return list(rows.values())


async def fleet_stop(
    config: MasterConfig,
    secret: bytes,
    fleet: Inventory | None,
    *,
    timeout: float = CONNECT_TIMEOUT,
    log: logging.Logger | None = None,
    on_listening: Any = None,
) -> StopOutcome:
    """``fleet stop`` without a run: serve the agents and stop each as it connects."""
    log = log if log is not None else logging.getLogger("master_service.fleet")
    robots = _fleet_robots(config, fleet)
    outcome = StopOutcome()

    async def stop(session: Session) -> None:
        assert fleet_server.stopper is not None
        why = await fleet_server.stopper.stop(session)
        if why is None:
            outcome.confirmed.append(session.robot_id)
            outcome.unanswered.pop(session.robot_id, None)
        elif session.robot_id not in outcome.confirmed:
            outcome.unanswered[session.robot_id] = why

    fleet_server = AgentServer(
        config, secret, log, admit=_admit(robots), purpose="fleet-stop", on_session=stop
    )
    fleet_server.stopper = Stopper(fleet_server.server, log, "surprise-master fleet stop")

    def done() -> bool:
        return bool(robots) and set(robots) <= set(outcome.confirmed) | set(outcome.unanswered)

    await fleet_server.serve(done, timeout, on_listening)
    for robot in robots:
        if robot not in outcome.confirmed and robot not in outcome.unanswered:
            outcome.unanswered[robot] = f"did not connect within {timeout:.0f} s"
    order = {robot: i for i, robot in enumerate(robots)}
    outcome.confirmed.sort(key=lambda r: (order.get(r, len(order)), r))
    outcome.unanswered = dict(
        sorted(outcome.unanswered.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0]))
    )
    return outcome


# ---------------------------------------------------------------------------------------------
# The table


def format_status(rows: Sequence[StatusRow]) -> str:
    """The rows as a table for a person, then each robot's problem."""
    header = ("robot", "address", "reachable", "agent", "software", "firmware", "battery",
              "clock", "pi flags")  # fmt: skip
    lines = [header]
    for row in rows:
        lines.append(
            (
                row.robot + (" (spare)" if row.spare else ""),
                row.address or "-",
                "disabled" if not row.enabled else ("yes" if row.reachable else "no"),
                ("busy" if row.busy else "active") if row.reachable else "-",
                _software(row),
                "-" if row.firmware is None else str(row.firmware),
                _battery(row),
                "-" if row.clock_offset_s is None else f"{row.clock_offset_s:+.3f} s",
                throttled_text(row.throttled) if row.reachable else "-",
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    text = ["  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
            for line in lines]  # fmt: skip
    text += [f"{row.robot}: {row.problem}" for row in rows if row.problem and row.enabled]
    enabled = [row for row in rows if row.enabled]
    reachable = sum(row.reachable for row in enabled)
    text.append(f"{reachable} of {len(enabled)} enabled robots reachable")
    return "\n".join(text)


def _battery(row: StatusRow) -> str:
    if row.battery_v is not None:
        return f"{row.battery_v:.2f} V"
    return "?" if row.reachable else "-"  # ?: it answered, without a battery to report


def _software(row: StatusRow) -> str:
    if row.software is None:
        return "-"
    commit = "commit ?" if row.commit is None else row.commit[:_SHORT_COMMIT]
    return f"{row.software} {commit}" + ("-dirty" if (row.commit or "").endswith("-dirty") else "")
