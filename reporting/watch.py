"""``surprise-master watch``: a live terminal view of a swarm's MQTT telemetry.

::

    surprise-master watch --broker mqtt://localhost:1883 [--prefix surprise] [--once]

It subscribes to ``<prefix>/#`` and shows the run's progress (``run/status``), every robot seen
(online or not, its last evaluation's fitness, steps and safety interventions, its latest command)
and, per robot, the latest sensor readings against what the predictor forecast for them. It needs
nothing but the broker: not the master's machine, not the run directory. ``--once`` listens for
:data:`ONCE_COLLECT` seconds, prints one snapshot and exits (for scripts and tests); without it
the view refreshes until Ctrl-C and reconnects when the broker goes away.

The pieces are separate so they can be tested without a terminal or a broker:
:class:`SwarmState` is fed ``(topic, payload)`` pairs, :func:`render` turns it into a rich
renderable, :func:`collect` fills a state from a broker.

Exit status: 0 done (or Ctrl-C); 1 the broker could not be reached (``--once``); 2 bad arguments
or the MQTT client (``aiomqtt``) is not installed.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import IO, Any, Final

from rich.console import Console, Group, RenderableType
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from minimize_surprise.backoff import Backoff, BackoffConfig
from minimize_surprise.text import format_duration
from telemetry.config import (
    DEFAULT_PREFIX,
    BrokerAddress,
    check_prefix,
    parse_broker_url,
)
from telemetry.payloads import (
    ClientStatus,
    EvaluationSummary,
    RunStatus,
    StepSample,
    decode_payload,
    parse_topic,
)
from telemetry.publisher import BROKER_TIMEOUT

__all__ = [
    "ONCE_COLLECT",
    "PLAIN_WIDTH",
    "RobotView",
    "SwarmState",
    "collect",
    "follow",
    "render",
    "run_watch",
]

#: Seconds ``--once`` listens before printing: retained states (the run, each robot's status)
#: arrive right after subscribing; a second also brings a step sample or two at the default 2 Hz.
ONCE_COLLECT: Final = 1.0
#: Redraws per second of the live view: smooth enough for 2 Hz samples, cheap for a laptop.
REFRESH_PER_SECOND: Final = 4
#: Columns of the snapshot when the output is not a terminal (a pipe has no width): room for a
#: Thymio's nine sensors without wrapping.
PLAIN_WIDTH: Final = 160
#: Reconnection delays of the live view: a person is watching, so retry often, never slower
#: than every 5 s.
_RECONNECT = BackoffConfig(initial=0.5, max=5.0, jitter=0.25)
#: |reading - prediction| below which a sensor is shown as well predicted, and above which as
#: badly (a surprise); between them it is shown as middling.
GOOD_ERROR: Final = 0.1
BAD_ERROR: Final = 0.3

_EXIT_UNREACHABLE: Final = 1
_EXIT_USAGE: Final = 2


@dataclass
class RobotView:
    """What the watcher knows of one robot; every field None until its message arrives."""

    robot_id: str
    status: ClientStatus | None = None
    evaluation: EvaluationSummary | None = None
    sample: StepSample | None = None
    #: evaluations summarised since the watcher started
    evaluations_seen: int = 0
    #: wall-clock time of the last message from this robot
    last_seen: float | None = None
    #: why the last message could not be read (None: it could)
    problem: str | None = None

    @property
    def online(self) -> bool | None:
        """Online per its status topic (None: no status seen)."""
        return None if self.status is None else self.status.online


@dataclass
class SwarmState:
    """The swarm as seen from the messages under ``prefix``; feed it with :meth:`apply`."""

    prefix: str = DEFAULT_PREFIX
    run: RunStatus | None = None
    master: ClientStatus | None = None
    robots: dict[str, RobotView] = field(default_factory=dict)
    #: the watcher's own link to the broker, for the view's footer
    broker: str = "connecting"
    #: messages read, and messages ignored (not ours, or not readable)
    messages: int = 0
    ignored: int = 0

    def apply(self, topic: str, payload: bytes | bytearray, received: float | None = None) -> bool:
        """Take one message in; returns whether it was understood. Never raises."""
        info = parse_topic(self.prefix, topic)
        if info is None:
            self.ignored += 1
            return False
        received = time.time() if received is None else received
        robot = None
        if info.robot_id is not None:
            robot = self.robots.get(info.robot_id)
            if robot is None:
                robot = self.robots[info.robot_id] = RobotView(info.robot_id)
            robot.last_seen = received
        try:
            if info.source == "run":
                self.run = decode_payload(payload, RunStatus)
            elif info.source == "master":
                self.master = decode_payload(payload, ClientStatus)
            elif robot is not None and info.kind == "status":
                robot.status = decode_payload(payload, ClientStatus)
            elif robot is not None and info.kind == "evaluation":
                robot.evaluation = decode_payload(payload, EvaluationSummary)
                robot.evaluations_seen += 1
            elif robot is not None and info.kind == "sample":
                robot.sample = decode_payload(payload, StepSample)
        except ValueError as exc:
            self.ignored += 1
            if robot is not None:
                robot.problem = f"{info.kind}: {exc}"
            return False
        if robot is not None:
            robot.problem = None
        self.messages += 1
        return True


# --------------------------------------------------------------------------- rendering


def _number(value: float | None, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _interventions(counts: dict[str, int]) -> str:
    if not counts:
        return "none"
    return ", ".join(f"{reason} {n}" for reason, n in sorted(counts.items()))


def _run_panel(state: SwarmState) -> Panel:
    run = state.run
    if run is None:
        return Panel("no run status yet (is the master running with telemetry?)", title="run")
    if run.phase == "done":
        what = "done"
    elif run.waiting:
        what = "waiting for robots"
    else:
        what = run.phase
    grid = Table.grid(padding=(0, 2))
    grid.add_column(style="bold")
    grid.add_column()
    grid.add_row("phase", what + ("" if run.online else " (master stopped)"))
    if run.paused:
        grid.add_row("paused", Text(run.paused, style="yellow"))
    grid.add_row("evaluations", f"{run.evaluations}/{run.total or 'endless'}")
    grid.add_row("fitness", f"best {_number(run.best_fitness)}, last {_number(run.last_fitness)}")
    robots = f"{run.robots_connected}/{run.robots_expected}"
    if run.robots:
        robots += f" ({', '.join(run.robots)})"
    grid.add_row("robots", robots)
    left = "-" if run.time_left_s is None else f"~{format_duration(run.time_left_s)}"
    grid.add_row(
        "time",
        f"elapsed {format_duration(run.elapsed_s)}, left {left}, "
        f"failed attempts {run.failed_attempts}",
    )
    return Panel(grid, title=f"run {run.run_id}", expand=False)


def _state_text(robot: RobotView) -> Text:
    if robot.online is None:
        return Text("?", style="dim")
    return Text("online", style="green") if robot.online else Text("offline", style="red")


def _robots_table(state: SwarmState, now: float) -> Table:
    table = Table(title="robots", title_justify="left")
    for column in ("robot", "state", "seen", "evaluation", "fitness", "steps", "safety"):
        table.add_column(column)
    table.add_column("command")
    table.add_column("step safety")
    table.add_column("dropped", justify="right")
    for robot_id in sorted(state.robots):
        robot = state.robots[robot_id]
        seen = "-" if robot.last_seen is None else f"{format_duration(now - robot.last_seen)} ago"
        ev = robot.evaluation
        state_text = _state_text(robot)
        if ev is None:
            evaluation = fitness = steps = safety = "-"
        else:
            evaluation = str(ev.evaluation)
            fitness = _number(ev.fitness) if ev.failure is None else f"failed: {ev.failure}"
            # Late steps and failed reads only when there were any: the table stays narrow.
            steps = f"{ev.steps}/{ev.requested}" + "".join(
                f", {n} {what}"
                for n, what in ((ev.overruns, "late"), (ev.read_failures, "failed reads"))
                if n
            )
            if ev.battery_v is not None:
                state_text.append(f" {ev.battery_v:.2f} V")
            safety = _interventions(ev.interventions)
        sample = robot.sample
        command = "-" if sample is None else f"{sample.command[0]:+.2f} {sample.command[1]:+.2f}"
        reason = "-" if sample is None else (sample.reason or "none")
        status = robot.status
        dropped = "-" if status is None or status.dropped is None else str(status.dropped)
        table.add_row(
            robot_id,
            state_text,
            seen,
            evaluation,
            fitness,
            steps,
            safety,
            command,
            reason,
            dropped,
        )
        if robot.problem:
            table.add_row("", Text(f"unreadable message: {robot.problem}", style="yellow"))
    return table


def _sensor_cell(value: float, predicted: float | None) -> Text:
    if predicted is None:
        return Text(f"{value:.2f}/-")
    error = abs(value - predicted)
    style = "green" if error < GOOD_ERROR else "red" if error > BAD_ERROR else "yellow"
    return Text(f"{value:.2f}/{predicted:.2f}", style=style)


def _sensors_table(state: SwarmState) -> Table | None:
    samples = [(rid, state.robots[rid].sample) for rid in sorted(state.robots)]
    present = [(rid, s) for rid, s in samples if s is not None]
    if not present:
        return None
    names: list[str] = []
    for _, sample in present:
        names += [name for name in sample.names if name not in names]
    # Each cell: the reading s(t) / what the predictor forecast for it at t-1, coloured by the
    # gap between them (the surprise).
    table = Table(title="sensors: reading/prediction", title_justify="left")
    table.add_column("robot")
    table.add_column("step", justify="right")
    for name in names:
        table.add_column(name, justify="right")
    for robot_id, sample in present:
        where = dict(zip(sample.names, range(len(sample.names)), strict=False))
        predicted = sample.predictions
        cells: list[Any] = []
        for name in names:
            i = where.get(name)
            if i is None or i >= len(sample.sensors):
                cells.append("")
                continue
            p = predicted[i] if predicted is not None and i < len(predicted) else None
            cells.append(_sensor_cell(float(sample.sensors[i]), p))
        table.add_row(robot_id, f"{sample.evaluation}:{sample.step}", *cells)
    return table


def render(state: SwarmState, now: float | None = None) -> RenderableType:
    """The whole view of ``state``; ``now`` (wall-clock seconds) dates the "seen" column."""
    now = time.time() if now is None else now
    parts: list[RenderableType] = [_run_panel(state)]
    if state.robots:
        parts.append(_robots_table(state, now))
        sensors = _sensors_table(state)
        if sensors is not None:
            parts.append(sensors)
    else:
        parts.append(Text("no robot seen yet"))
    master = state.master
    master_text = "?" if master is None else "online" if master.online else "offline"
    parts.append(
        Text(
            f"broker {state.broker} | prefix {state.prefix} | master {master_text} | "
            f"{state.messages} messages, {state.ignored} ignored",
            style="dim",
        )
    )
    return Group(*parts)


# --------------------------------------------------------------------------- the broker


async def collect(
    address: BrokerAddress,
    state: SwarmState,
    *,
    duration: float | None = None,
    on_connect: Callable[[], None] | None = None,
) -> None:
    """Subscribe to ``<state.prefix>/#`` and feed ``state`` for ``duration`` seconds (None:
    until cancelled or the connection is lost). Raises ``aiomqtt.MqttError`` if the broker cannot
    be reached or goes away."""
    import aiomqtt  # the telemetry extra; checked by run_watch before it gets here

    client = aiomqtt.Client(
        address.host,
        address.port,
        identifier=f"surprise-watch-{uuid.uuid4().hex[:8]}",
        timeout=BROKER_TIMEOUT,
    )
    async with client:
        await client.subscribe(f"{state.prefix}/#")
        state.broker = f"connected to {address.url}"
        if on_connect is not None:
            on_connect()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(duration):
                async for message in client.messages:
                    payload = message.payload
                    if isinstance(payload, bytes | bytearray):
                        state.apply(str(message.topic), payload)
                    else:
                        state.ignored += 1


async def follow(address: BrokerAddress, state: SwarmState) -> None:
    """Feed ``state`` from the broker until cancelled, reconnecting with capped backoff whenever
    it cannot be reached or goes away (``state.broker`` says which)."""
    from aiomqtt import MqttError

    backoff = Backoff(_RECONNECT)
    while True:
        try:
            await collect(address, state, on_connect=backoff.reset)
        except MqttError as exc:
            delay = backoff.next_delay()
            state.broker = f"{address.url} unreachable ({exc}); retrying in {delay:.1f} s"
            await asyncio.sleep(delay)


async def _live(address: BrokerAddress, state: SwarmState, console: Console) -> None:
    from rich.live import Live

    with Live(
        get_renderable=lambda: render(state),
        console=console,
        refresh_per_second=REFRESH_PER_SECOND,
    ):
        await follow(address, state)


def run_watch(
    broker: str,
    *,
    prefix: str = DEFAULT_PREFIX,
    once: bool = False,
    collect_s: float = ONCE_COLLECT,
    stream: IO[str] | None = None,
) -> int:
    """The ``watch`` command; returns the exit status (see the module docstring)."""
    err = sys.stderr
    try:
        address = parse_broker_url(broker)
        check_prefix(prefix)
    except ValueError as exc:
        print(f"surprise-master watch: {exc}", file=err)
        return _EXIT_USAGE
    try:
        from aiomqtt import MqttError
    except ImportError:
        print(
            "surprise-master watch: the MQTT client is not installed: "
            "pip install 'minimize-surprise[telemetry]'",
            file=err,
        )
        return _EXIT_USAGE
    stream = stream if stream is not None else sys.stdout
    console = Console(file=stream, width=None if stream.isatty() else PLAIN_WIDTH)
    state = SwarmState(prefix=prefix)
    if once:
        try:
            asyncio.run(collect(address, state, duration=collect_s))
        except MqttError as exc:
            print(f"surprise-master watch: cannot reach the broker {address.url}: {exc}", file=err)
            return _EXIT_UNREACHABLE
        console.print(render(state))
        return 0
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(_live(address, state, console))
    return 0
