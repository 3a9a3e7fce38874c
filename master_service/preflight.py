"""``surprise-master check CONFIG``: is every robot fit for a run? (docs/preflight.md)

The check listens where the run will (the master configuration's address, secret and robots),
lets the robots' agents connect as they would for a run, and asks each of them, between
evaluations and without driving, for a :class:`~minimize_surprise.wire.CheckReport`: every part
of its body read on its own, its battery, and what its own safety layer would do to a forward
drive on that reading. From the connection it measures the link's round trip (three pings) and
the robot's clock offset. Then it says goodbye; the agents reconnect to the run that follows.

A robot is **unfit** (the exit status is 1) when it did not connect, lacks a sensor the experiment
uses, is busy with another master's evaluation, has a part that does not answer or answers out of
range, reads a battery below ``battery_min_v``, stands on a floor that its safety layer takes
for the arena's boundary (it would never drive forward: the lab's floor is too bright for the
ground rule's threshold), or runs other software than the master: another version, another
commit, or no commit to compare (an agent built before it reported one); its row then says the
command that updates it (docs/fleet.md). A slow link, a clock far off, an unknown battery,
something in front of the robot, a master whose own commit is unknown or has uncommitted changes,
and an inventory's spare that did not connect are **notes**: worth knowing, no reason to stop.

With an inventory (docs/fleet.md) the check waits for its swarm, admits its spares too, and gives
a spare that has not come with the swarm :data:`SPARE_GRACE` seconds more.
"""

from __future__ import annotations

import asyncio
import logging
import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import minimize_surprise
from master_service.agent_server import CHECK_TIMEOUT, CONNECT_TIMEOUT, AgentServer
from master_service.config import MasterConfig, inventory_of
from master_service.inventory import Inventory
from master_service.server import Session
from minimize_surprise.provenance import DIRTY, software_commit
from minimize_surprise.wire import CheckReport

__all__ = [
    "CHECK_TIMEOUT",
    "CLOCK_OFFSET_NOTE",
    "PINGS",
    "RTT_NOTE",
    "SPARE_GRACE",
    "RobotCheck",
    "format_table",
    "provision_command",
    "run_check",
    "update_command",
]

#: Pings per robot for the round trip; the median is reported.
PINGS: Final = 3
#: A round trip above this is noted: the control loop runs on the robot, but a run's rounds wait
#: for the slowest link, and Wi-Fi that slow tends to drop.
RTT_NOTE: Final = 0.1
#: A clock offset above this is noted: the robots' logs and the master's no longer line up.
CLOCK_OFFSET_NOTE: Final = 1.0
#: Seconds a spare that has not connected with the swarm gets: a spare is often switched off on
#: the shelf, which must not hold every check for the whole connect timeout.
SPARE_GRACE: Final = 3.0
#: Characters of a commit shown in the table (git accepts them as the commit's name).
SHORT_COMMIT: Final = 10


@dataclass
class RobotCheck:
    """One robot's row: what was measured, and what makes it unfit (``problems``) or is worth
    knowing (``notes``)."""

    robot: str
    connected: bool = False
    peer: str | None = None
    software: str | None = None
    commit: str | None = None
    firmware: int | None = None
    spare: bool = False
    rtt_s: float | None = None
    clock_offset_s: float | None = None
    battery_v: float | None = None
    readings: dict[str, float] = field(default_factory=dict)
    ground_rule: str = ""
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: the command that brings its software in step with the master's, when it is not
    fix: str | None = None

    @property
    def fit(self) -> bool:
        """Whether nothing stands in the way of a run."""
        return not self.problems

    def to_json(self) -> dict[str, Any]:
        """Plain data for ``--json``."""
        return {
            "robot": self.robot,
            "fit": self.fit,
            "connected": self.connected,
            "peer": self.peer,
            "software": self.software,
            "commit": self.commit,
            "firmware": self.firmware,
            "spare": self.spare,
            "rtt_ms": None if self.rtt_s is None else round(1000 * self.rtt_s, 1),
            "clock_offset_s": None
            if self.clock_offset_s is None
            else round(self.clock_offset_s, 3),
            "battery_v": self.battery_v,
            "readings": {k: round(v, 4) for k, v in self.readings.items()},
            "ground_rule": self.ground_rule,
            "problems": self.problems,
            "notes": self.notes,
            "fix": self.fix,
        }


async def run_check(
    config: MasterConfig,
    secret: bytes,
    *,
    timeout: float = CONNECT_TIMEOUT,
    log: logging.Logger | None = None,
    on_listening: Any = None,
) -> list[RobotCheck]:
    """Check every robot of ``config`` (see the module docstring); one row per robot, the
    expected ones first in the order the configuration names them.

    ``on_listening(port)`` (optional) is called once robots can connect.
    """
    assert config.experiment is not None, "the experiment must be loaded"
    log = log if log is not None else logging.getLogger("master_service.preflight")
    fleet = inventory_of(config)
    # Robots admitted besides ``allowed_robots``: the inventory's spares.
    spares = [] if fleet is None else fleet.spares

    def admit(robot_id: str) -> str | None:
        allowed = config.allowed_robots
        if allowed and robot_id not in allowed and robot_id not in spares:
            return f"{robot_id} is not among the allowed robots"
        return None

    checker = AgentServer(config, secret, log, admit=admit, purpose="check")
    expected: Sequence[str] | int = list(config.allowed_robots) or config.robot_count
    await checker.start()
    try:
        if on_listening is not None:
            on_listening(checker.server.port)
        await checker.wait_for_robots(expected, timeout)
        if spares:
            await checker.wait_for_robots(spares, SPARE_GRACE)
        sessions = dict(checker.server.sessions)
        rows = await asyncio.gather(
            *(_check_one(checker, config, fleet, session) for session in sessions.values())
        )
    finally:
        await checker.close("check done")
    by_robot = {row.robot: row for row in rows}
    for spare in spares:
        row = by_robot.setdefault(spare, RobotCheck(spare))
        row.spare = True
        if not row.connected:
            row.notes.append(
                "spare, not connected: it is checked when it comes (switch it on, check again)"
            )
    if isinstance(expected, int):
        ordered = sorted(by_robot.values(), key=lambda row: row.robot)
        missing = max(0, expected - len(ordered))
        for i in range(missing):
            ordered.append(_missing(f"(robot {len(by_robot) + i + 1})", timeout))
        return ordered
    ordered = [by_robot.get(robot) or _missing(robot, timeout) for robot in expected]
    return ordered + [row for robot, row in sorted(by_robot.items()) if robot not in expected]


def _missing(robot: str, timeout: float) -> RobotCheck:
    row = RobotCheck(robot)
    row.problems.append(
        f"not connected within {timeout:.0f} s: is its agent running (`systemctl status "
        "surprise-agent` on its Pi) and does its configuration name this master's address?"
    )
    return row


async def _check_one(
    checker: AgentServer, config: MasterConfig, fleet: Inventory | None, session: Session
) -> RobotCheck:
    assert config.experiment is not None
    hello = session.hello
    row = RobotCheck(
        session.robot_id,
        True,
        session.peer,
        hello.software_version,
        hello.software_commit,
        hello.thymio_firmware,
    )
    await _measure(checker, config, session, row)
    # Last: the body's findings come first in the row, as before robots reported their commit.
    _compare_software(row, fleet, config.inventory)
    return row


async def _measure(
    checker: AgentServer, config: MasterConfig, session: Session, row: RobotCheck
) -> None:
    assert config.experiment is not None
    lacking = [s for s in config.experiment.sensors if s not in session.hello.sensors]
    if lacking:
        row.problems.append(f"lacks sensors the experiment uses: {', '.join(lacking)}")
    trips = [await checker.round_trip(session, seq) for seq in range(1, PINGS + 1)]
    answered = [t for t in trips if t is not None]
    if answered:
        row.rtt_s = statistics.median(answered)
        if row.rtt_s > RTT_NOTE:
            row.notes.append(f"slow link: round trip {1000 * row.rtt_s:.0f} ms")
    if len(answered) < len(trips):
        row.notes.append(f"{len(trips) - len(answered)} of {len(trips)} pings lost")
    exchange = await checker.check(session, PINGS + 1)
    if exchange is None:
        row.problems.append(
            f"no answer to the check within {CHECK_TIMEOUT:.0f} s (an agent older than the "
            "check, or a hung robot: see its log)"
        )
        return
    report, midpoint = exchange
    _judge(row, report, midpoint, config)


def _compare_software(
    row: RobotCheck, fleet: Inventory | None, inventory_file: str | None = None
) -> None:
    """UNFIT when the robot runs other software than the master, with the command that fixes it
    (``inventory_file``: the fleet's file, for the playbook's command); a note when the master
    cannot tell (its own commit unknown)."""
    version, commit = minimize_surprise.__version__, software_commit()
    differs: list[str] = []
    if row.software != version:
        differs.append(f"version {row.software}, the master's {version}")
    if commit is None:
        row.notes.append(
            "the master's own commit is unknown (no git, no build stamp): robots' commits are "
            "not compared"
        )
    elif row.commit is None:
        differs.append("it reports no commit (an agent built before it reported one)")
    elif row.commit != commit:
        differs.append(f"commit {_short(row.commit)}, the master's {_short(commit)}")
    elif commit.endswith(DIRTY):
        row.notes.append(
            "the master's checkout has uncommitted changes: the robot's may differ although "
            "both name the same commit"
        )
    if not differs:
        return
    row.problems.append("other software than the master's: " + "; ".join(differs))
    entry = None if fleet is None else fleet.robot(row.robot)
    if entry is not None and inventory_file is not None:
        row.fix = provision_command(row.robot, inventory_file)
        return
    row.fix = update_command(row.robot, None if entry is None else entry.address, commit)


def provision_command(robot: str, inventory_file: str) -> str:
    """The command that brings ``robot`` of a fleet in step from the laptop (docs/fleet.md): the
    playbook, in the master's own checkout, which builds the wheels of exactly the software the
    master runs and installs them on that robot alone."""
    return f"in the master's checkout: deploy/ansible/provision {inventory_file} --limit {robot}"


def update_command(robot: str, address: str | None, commit: str | None) -> str:
    """The command that installs the master's software on ``robot`` without a fleet file
    (docs/fleet.md): its checkout on the Pi at the master's commit, then
    ``deploy/install-pi.sh``."""
    where = f"ssh {address}" if address else f"on {robot}'s Pi"
    checkout = "git pull"
    if commit is not None:
        # A dirty master's changes are nowhere to fetch: its commit is the nearest the robot gets.
        checkout = f"git fetch && git checkout {commit.removesuffix(DIRTY)}"
    return f"{where}, in its checkout: {checkout} && sudo deploy/install-pi.sh {robot}"


def _short(commit: str) -> str:
    dirty = commit.endswith(DIRTY)
    return commit.removesuffix(DIRTY)[:SHORT_COMMIT] + (DIRTY if dirty else "")


def _judge(row: RobotCheck, report: CheckReport, midpoint: float, config: MasterConfig) -> None:
    row.clock_offset_s = report.time - midpoint
    if abs(row.clock_offset_s) > CLOCK_OFFSET_NOTE:
        row.notes.append(
            f"clock {row.clock_offset_s:+.1f} s off the master's (logs will not line up; "
            "enable NTP on the Pi)"
        )
    if report.busy:
        row.problems.append("busy: still finishing an evaluation or a check; check again")
        return
    row.ground_rule = report.ground_rule
    for part in report.parts:
        if part.error is not None:
            row.problems.append(f"{part.part} does not answer: {part.error}")
            continue
        bad = [
            f"{name} {value}"
            for name, value in zip(part.sensors, part.values, strict=False)
            if not (math.isfinite(value) and 0.0 <= value <= 1.0)
        ]
        if len(part.values) != len(part.sensors):
            bad.append(f"{len(part.values)} values for {len(part.sensors)} sensors")
        if bad:
            row.problems.append(f"{part.part} reads out of range: {', '.join(bad)}")
    row.readings.update(report.readings())
    row.battery_v = report.battery_v
    threshold = config.battery_min_v
    if report.battery_v is None:
        row.notes.append("battery unknown (this robot does not report one)")
    elif threshold is not None and report.battery_v < threshold:
        row.problems.append(
            f"battery {report.battery_v:.2f} V, below {threshold:.2f} V: swap it before the run"
        )
    reason = report.forward_safety
    if reason == "ground":
        ground = ", ".join(
            f"{row.readings[g]:.2f}" for g in ("ground.0", "ground.1") if g in row.readings
        )
        row.problems.append(
            f"the ground sensors read {ground}, which the safety layer ({report.ground_rule} is "
            "the arena's boundary) takes for an edge: it will not drive forward here. If it "
            "stands on the arena's floor, that floor is too bright for the threshold: set "
            "safety.ground_threshold / ground_boundary in the agents' configuration, or darken "
            "the floor"
        )
    elif reason in ("front", "rear"):
        row.notes.append(f"something is close to its {reason} IR: move it free before the run")
    elif reason is not None:
        row.problems.append(f"the safety layer stops a forward drive on this reading ({reason})")


def format_table(rows: Sequence[RobotCheck]) -> str:
    """The rows as a table for a person, then each robot's problems and notes."""
    header = (
        "robot", "verdict", "software", "firmware", "link", "clock", "battery", "IR max",
        "ground", "light", "force",
    )  # fmt: skip
    lines = [header]
    for row in rows:
        r = row.readings
        ir = [v for k, v in r.items() if k.startswith("ir.")]
        lines.append(
            (
                row.robot + (" (spare)" if row.spare else ""),
                "fit" if row.fit else "UNFIT",
                _software(row),
                "-" if row.firmware is None else str(row.firmware),
                "-" if row.rtt_s is None else f"{1000 * row.rtt_s:.1f} ms",
                "-" if row.clock_offset_s is None else f"{row.clock_offset_s:+.2f} s",
                "?" if row.battery_v is None else f"{row.battery_v:.2f} V",
                f"{max(ir):.2f}" if ir else "-",
                _values(r, ("ground.0", "ground.1")),
                _values(r, ("light.0", "light.1")),
                _values(r, ("force",)),
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    text = ["  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip()
            for line in lines]  # fmt: skip
    for row in rows:
        text += [f"{row.robot}: {problem}" for problem in row.problems]
        text += [f"{row.robot}: note: {note}" for note in row.notes]
        if row.fix is not None:
            text.append(f"{row.robot}: fix: {row.fix}")
    fit = sum(row.fit for row in rows)
    text.append(
        f"{fit} of {len(rows)} robots fit" + ("" if fit == len(rows) else ": fix the above")
    )
    return "\n".join(text)


def _software(row: RobotCheck) -> str:
    if row.software is None:
        return "-"
    return row.software + ("" if row.commit is None else f" {_short(row.commit)}")


def _values(readings: dict[str, float], names: tuple[str, ...]) -> str:
    present = [f"{readings[n]:.2f}" for n in names if n in readings]
    return "/".join(present) if present else "-"
