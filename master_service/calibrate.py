"""``surprise-master calibrate ROBOT`` (docs/fleet.md, "Calibration"): one robot's floor, rim and
wheels measured through its agent, and written into its entry of the inventory.

The command listens where the master would (:class:`~master_service.agent_server.AgentServer`)
and
waits for the robot's agent. Then, each step started by the person (``ask`` returns when they
are ready; the terminal's Enter):

1. **ground**: the robot on the arena's floor, then on its rim; each time the median of
   :data:`GROUND_READS` check reports' ground readings. The safety layer's threshold goes
   midway between them (:func:`~master_service.calibration.ground_threshold`), on the side the
   agent's own ground rule says.
2. **wheels**: the person starts filming; the robot drives straight for :data:`DRIVE_SECONDS`
   at :data:`DRIVE_COMMAND` of its top speed (its top LED flashes at the start, as in a
   post-evaluation, for the tracker to find); the person saves the video; the tracker follows
   the robot's marker, and the wheels' scales come from its path
   (:func:`~master_service.calibration.wheel_scales`). The drive is an evaluation of a genome
   whose network outputs the same speed on both wheels whatever it senses, so the agent's
   safety layer is in charge as in any run; a drive the layer changed is refused.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np

from master_service.agent_server import CONNECT_TIMEOUT, AgentServer
from master_service.calibration import (
    CalibrationError,
    drive_speeds,
    ground_threshold,
    wheel_scales,
)
from master_service.config import MasterConfig
from master_service.inventory import Inventory
from master_service.server import Session
from minimize_surprise.errors import ConfigError
from minimize_surprise.network import GenomeLayout, NetworkSpec
from minimize_surprise.wire import Evaluate, Failed, genome_to_bytes

__all__ = [
    "DRIVE_COMMAND",
    "DRIVE_SECONDS",
    "GROUND_READS",
    "Measured",
    "calibrate_robot",
    "drive_genome",
    "format_measured",
]

#: Check reports whose ground readings make one measurement (their median): the ground sensors
#: read a carpet's texture, which varies by a few hundredths from one spot to the next.
GROUND_READS: Final = 5
#: The drive's normalised speed on both wheels: half the top speed, where a real Thymio's
#: motors are steady and the robot covers about 25 cm in the drive.
DRIVE_COMMAND: Final = 0.5
#: The drive's length in seconds: 50 frames of a 10 Hz camera, enough for a scale within 1 %.
DRIVE_SECONDS: Final = 5.0
#: The drive's control period, the real robots' 10 Hz.
DRIVE_PERIOD: Final = 0.1
#: Seconds the agent gets beyond the drive to answer (a slow Wi-Fi, the trace's bytes).
ANSWER_MARGIN: Final = 15.0

#: What the command asks the person, one step at a time; returns when they are ready.
Ask = Callable[[str], Awaitable[None]]


@dataclass
class Measured:
    """What one calibration measured (None: that step was not run) and the threshold."""

    robot: str
    ground_floor: tuple[float, float] | None = None
    ground_rim: tuple[float, float] | None = None
    boundary: Literal["above", "below"] | None = None
    threshold: float | None = None
    wheels: tuple[float, float] | None = None
    drive: dict[str, float] = field(default_factory=dict)


def drive_genome(spec: NetworkSpec, command: float) -> np.ndarray:
    """A genome of ``spec`` whose actor outputs ``command`` on both wheels whatever the robot
    senses: every weight zero but the actor's output biases, atanh(command)."""
    if not -1 < command < 1:
        raise ValueError(f"the drive's command must lie in (-1, 1), not {command}")
    layout = GenomeLayout(spec)
    genome = np.zeros(layout.size)
    layout.unpack(genome)["actor.output"][:, -1] = math.atanh(command)
    return genome


async def calibrate_robot(
    config: MasterConfig,
    secret: bytes,
    fleet: Inventory,
    robot: str,
    *,
    ask: Ask,
    ground: bool = True,
    wheels: Callable[[], Any] | None = None,
    timeout: float = CONNECT_TIMEOUT,
    log: logging.Logger | None = None,
    on_listening: Any = None,
) -> Measured:
    """Calibrate ``robot`` of ``fleet`` (see the module docstring). ``wheels``: None to skip the
    wheels; else returns the tracker's result for the drive (a :class:`tracking.video.
    TrackResult`) once the person saved the video. Raises :class:`CalibrationError` for a
    measurement that gives no calibration, ``ConfigError`` for a robot not in the fleet and
    ``TimeoutError`` when its agent does not come."""
    entry = fleet.robot(robot)
    if entry is None:
        raise ConfigError(
            f"no robot of the inventory is named {robot!r}; it lists "
            + ", ".join(r.name for r in fleet.robots),
            file="<inventory>",
            key="robots",
        )
    log = log if log is not None else logging.getLogger("master_service.calibrate")
    measured = Measured(robot)
    failure: list[BaseException] = []
    finished: list[bool] = []

    async def work(session: Session) -> None:
        try:
            if ground:
                await ask(f"place {robot} on the arena's floor, away from its rim")
                measured.ground_floor, rule = await _ground(server, session)
                await ask(f"place {robot} with both ground sensors over the rim")
                measured.ground_rim, _ = await _ground(server, session)
                measured.boundary = "below" if "<" in rule else "above"
                measured.threshold = ground_threshold(
                    measured.ground_floor, measured.ground_rim, measured.boundary
                )
            if wheels is not None:
                await _drive(server, session, measured, ask, wheels)
        except BaseException as exc:
            failure.append(exc)
        finally:
            finished.append(True)

    def admit(robot_id: str) -> str | None:
        return None if robot_id == robot else f"only {robot} is being calibrated"

    server = AgentServer(config, secret, log, admit=admit, purpose="calibrate", on_session=work)
    await server.serve(lambda: bool(finished), timeout, on_listening)
    if failure:
        raise failure[0]
    if not finished:
        raise TimeoutError(
            f"{robot}'s agent did not connect within {timeout:.0f} s: is it running "
            "(`systemctl status surprise-agent`) and does its `master` name this laptop?"
        )
    return measured


async def _ground(server: AgentServer, session: Session) -> tuple[tuple[float, float], str]:
    # The median of GROUND_READS reports' ground readings, and the agent's ground rule.
    readings: list[list[float]] = []
    rule = ""
    for _ in range(GROUND_READS):
        exchange = await server.check(session)
        if exchange is None:
            raise CalibrationError(f"{session.robot_id} did not answer a check")
        report, _ = exchange
        rule = report.ground_rule
        values = report.readings()
        if "ground.0" not in values or "ground.1" not in values:
            raise CalibrationError(
                f"{session.robot_id} reports no ground readings ({rule or 'no ground rule'})"
            )
        readings.append([values["ground.0"], values["ground.1"]])
    median = np.median(np.array(readings), axis=0)
    return (round(float(median[0]), 3), round(float(median[1]), 3)), rule


async def _drive(
    server: AgentServer,
    session: Session,
    measured: Measured,
    ask: Ask,
    wheels: Callable[[], Any],
) -> None:
    robot = session.robot_id
    await ask(
        f"start filming the arena; place {robot} with at least 40 cm of free floor ahead of it"
    )
    # The robot's own sensors (the network ignores them): a spec any agent accepts.
    spec = NetworkSpec(sensors=tuple(session.hello.sensors), actor_hidden=2, predictor_hidden=2)
    steps = round(DRIVE_SECONDS / DRIVE_PERIOD)
    message = Evaluate(
        evaluation_id=1,
        genome=genome_to_bytes(drive_genome(spec, DRIVE_COMMAND)),
        spec=spec,
        steps=steps,
        step_period=DRIVE_PERIOD,
        record=True,
        post_evaluation=True,  # the start flash, for the tracker
    )
    answer = await server.evaluate(session, message, DRIVE_SECONDS + ANSWER_MARGIN)
    if answer is None:
        raise CalibrationError(
            f"{robot}'s drive got no answer within {DRIVE_SECONDS + ANSWER_MARGIN:g} s"
        )
    if isinstance(answer, Failed):
        raise CalibrationError(f"{robot}'s drive failed: {answer.reason}")
    held = [] if answer.trace is None else [i for i, r in enumerate(answer.trace.safety) if r]
    if held:
        raise CalibrationError(
            f"{robot}'s safety layer changed the drive's command at {len(held)} of {steps} "
            f"steps (from step {held[0]}): give it more free floor and calibrate again"
        )
    await ask("stop filming and save the video")
    tracked = wheels()
    if robot not in tracked.poses:
        raise CalibrationError(f"the tracker did not follow {robot}'s marker")
    seen = np.asarray(tracked.seen[robot], dtype=bool)
    inside = (tracked.times >= 0) & (tracked.times <= steps * DRIVE_PERIOD) & seen
    times, poses = tracked.times[inside], tracked.poses[robot][inside]
    from simulator.world import WorldConfig  # the lab's Thymio II: its top speed, its wheels

    lab = WorldConfig()
    measured.wheels = wheel_scales(
        times, poses, DRIVE_COMMAND, max_speed=lab.max_speed, wheel_base=lab.wheel_base
    )
    speed, turn = drive_speeds(times, poses)
    measured.drive = {
        "seconds": round(float(times[-1] - times[0]), 2),
        "frames": int(inside.sum()),
        "speed_cm_s": round(100 * speed, 2),
        "turn_rad_s": round(turn, 4),
    }


def format_measured(measured: Measured, path: Path | None = None) -> str:
    """What was measured, for a person, and where it went."""
    lines = [f"{measured.robot}:"]
    if measured.ground_floor is not None and measured.ground_rim is not None:
        floor = "/".join(f"{v:.2f}" for v in measured.ground_floor)
        rim = "/".join(f"{v:.2f}" for v in measured.ground_rim)
        sign = ">=" if measured.boundary == "above" else "<"
        lines += [
            f"  ground on the floor {floor}, on the rim {rim}",
            f"  safety.ground_threshold: {measured.threshold} (the rim: ground {sign} it)",
        ]
    if measured.wheels is not None:
        drive = measured.drive
        lines += [
            f"  drove {drive['seconds']:.1f} s ({drive['frames']} frames) at "
            f"{drive['speed_cm_s']:.1f} cm/s, turning {drive['turn_rad_s']:+.3f} rad/s",
            f"  wheels: left {measured.wheels[0]:.3f}, right {measured.wheels[1]:.3f} "
            "of their commanded speed",
        ]
    if path is not None:
        lines.append(f"  written to {path}")
    agent = []
    if measured.threshold is not None:
        agent.append(f"safety.ground_threshold: {measured.threshold}")
    if measured.wheels is not None:
        agent.append(f"body.thymio.wheel_left: {measured.wheels[0]:.4f}")
        agent.append(f"body.thymio.wheel_right: {measured.wheels[1]:.4f}")
    if agent:
        lines.append(
            f"  for its agent (/etc/minimize-surprise/agent.yaml on {measured.robot}'s Pi, then "
            "`sudo systemctl restart surprise-agent`):"
        )
        lines += [f"    {line}" for line in agent]
    return "\n".join(lines)
