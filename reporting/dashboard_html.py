"""The dashboard's text: the status and the robots' table as HTML, built by plain functions from a
:class:`~reporting.dashboard_data.Snapshot` (tested without a browser; docs/dashboard.md).

Every value stands in an element with a ``data-key`` (and, in the robots' table, its row's
``data-robot``) whose ``data-value`` holds the text read from the file, for a test or a script to
read back.
"""

from __future__ import annotations

import html
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from reporting.dashboard_data import RobotRow, Snapshot, Trajectories, parse_value

if TYPE_CHECKING:
    from reporting.watch import SwarmState

__all__ = ["header_html", "robots_html", "status_html", "trajectories_note"]

#: Column titles of the robots' table for the keys known today; another key shows as it is named.
_LABELS: Final = {
    "fitness": "last fitness",
    "safety_share": "safety share",
    "battery_v": "battery (V)",
    "overruns": "overruns",
    "read_failures": "read failures",
}
#: A yes/no/unknown value's data-value and shown text.
_YES_NO: Final = {None: ("", "–"), True: ("true", "yes"), False: ("false", "no")}
#: Keys whose values are shares of steps, shown as percentages.
_SHARES: Final = frozenset({"safety_share", "post_safety_share"})


def _duration(seconds: float) -> str:
    seconds = max(0, round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, seconds = divmod(rest, 60)
    if hours:
        return f"{hours} h {minutes:02d} min"
    return f"{minutes} min {seconds:02d} s" if minutes else f"{seconds} s"


def _shown(key: str, text: str | None) -> str:
    """How the page shows the value ``text`` (read from a file) of ``key``."""
    value = None if text is None else parse_value(text)
    if value is None:
        return "–"
    if isinstance(value, str):
        return value
    if key in _SHARES:
        return f"{value:.1%}"
    if key == "battery_v":
        return f"{value:.2f}"
    return str(value) if isinstance(value, int) else f"{value:.4f}"


def _value(key: str, text: str | None, shown: str | None = None) -> str:
    raw = "" if text is None else text
    return (
        f'<span class="dash-value" data-key="{html.escape(key)}" data-value="{html.escape(raw)}">'
        f"{html.escape(_shown(key, text) if shown is None else shown)}</span>"
    )


def _item(label: str, key: str, text: str | None, shown: str | None = None) -> str:
    return f'<span class="dash-label">{html.escape(label)}</span>' + _value(key, text, shown)


def status_html(snapshot: Snapshot, telemetry: SwarmState | None = None) -> str:
    """Where the run stands: state, progress, fitness, time left, a pause and its reason; with
    ``telemetry``, the link to the broker and the messages read."""
    last = snapshot.last_row or {}
    planned = snapshot.planned
    done = f"{snapshot.evaluations} / {'?' if planned is None else planned}"
    items = [
        _item("state", "state", snapshot.state, snapshot.state),
        _item("phase", "phase", snapshot.phase, snapshot.phase),
        _item("evaluations", "evaluations", str(snapshot.evaluations), done),
        _item("best fitness", "best_fitness", snapshot.best_fitness),
        _item(
            "last evaluation",
            "last_evaluation",
            last.get("evaluation"),
            f"{last['evaluation']} ({last.get('kind', '?')})" if "evaluation" in last else "–",
        ),
        _item("its fitness", "last_fitness", last.get("fitness")),
        _item("accepted", "accepted", last.get("accepted")),
        _item("its safety share", "safety_share", last.get("safety_share")),
    ]
    if snapshot.time_left_s is not None:
        left = snapshot.time_left_s
        items.append(_item("time left", "time_left", repr(left), f"~{_duration(left)}"))
    if snapshot.master is not None:
        items.append(_item("master", "master", snapshot.master, snapshot.master))
    if snapshot.post_fitness is not None:
        items.append(_item("post-evaluation fitness", "post_fitness", repr(snapshot.post_fitness)))
    if telemetry is not None:
        link = f"{telemetry.broker}, {telemetry.messages} messages"
        items.append(_item("telemetry", "telemetry", telemetry.broker, link))
    parts = [f'<div class="dash-grid">{"".join(items)}</div>']
    if planned:
        share = min(1.0, snapshot.evaluations / planned)
        parts.append(f'<div class="dash-bar"><div style="width: {share:.1%}"></div></div>')
    if snapshot.pause is not None:
        pause = snapshot.pause
        robots = f" (robots: {', '.join(pause.robots)})" if pause.robots else ""
        since = f", since {time.strftime('%H:%M:%S', time.localtime(pause.since))}"
        parts.append(
            f'<div class="dash-pause">paused: {_value("pause", pause.reason, pause.reason)}'
            f"{html.escape(robots)}{since if pause.since is not None else ''}</div>"
        )
    return "".join(parts)


def _robot_cells(
    robot: RobotRow, keys: list[str], post: dict[str, Any] | None, extra: str = ""
) -> str:
    connected = _YES_NO[robot.connected]
    cells = [
        f'<td data-key="robot" data-value="{html.escape(robot.robot)}">'
        f"{html.escape(robot.robot)}</td>",
        f'<td data-key="connected" data-value="{connected[0]}">{connected[1]}</td>',
    ]
    values = dict(robot.values)
    if post is not None:
        for key in ("fitness", "safety_share"):
            number = post.get(robot.robot, {}).get(key)
            values[f"post_{key}"] = "" if number is None else repr(number)
    for key in [*keys, *(("post_fitness", "post_safety_share") if post is not None else ())]:
        text = values.get(key)
        cells.append(
            f'<td data-key="{html.escape(key)}" data-value="{html.escape(text or "")}">'
            f"{html.escape(_shown(key, text))}</td>"
        )
    return f'<tr data-robot="{html.escape(robot.robot)}">{"".join(cells)}{extra}</tr>'


def robots_html(
    snapshot: Snapshot, telemetry: SwarmState | None = None, now: float | None = None
) -> str:
    """The robots' table: connected, the last row's per-robot columns (fitness, battery, ...),
    the newer ``robot_state`` of a running master, and the post-evaluation's fitness; with
    ``telemetry``, each robot's MQTT view too (a robot only MQTT knows gets a row of its own)."""
    robots = list(snapshot.robots)
    if telemetry is not None:
        known = {r.robot for r in robots}
        robots += [RobotRow(name, None) for name in sorted(telemetry.robots) if name not in known]
    if not robots:
        return '<p data-key="robots" data-value="0">no robots yet</p>'
    post = snapshot.post_robots or None
    titles = ["robot", "connected", *(_LABELS.get(k, k.replace("_", " ")) for k in snapshot.keys)]
    if post is not None:
        titles += ["post-eval. fitness", "post-eval. safety share"]
    if telemetry is not None:
        titles += ["online (MQTT)", "battery (MQTT, V)", "last message"]
    head = "".join(f"<th>{html.escape(t)}</th>" for t in titles)
    now = time.time() if now is None else now
    body = "".join(
        _robot_cells(r, snapshot.keys, post, _mqtt_cells(telemetry, r.robot, now)) for r in robots
    )
    return f'<table class="dash-robots"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _mqtt_cells(telemetry: SwarmState | None, robot: str, now: float) -> str:
    # A robot's own view over MQTT: online by its status (and last will), the battery it read
    # after its last evaluation, seconds since its last message.
    if telemetry is None:
        return ""
    view = telemetry.robots.get(robot)
    online = None if view is None else view.online
    state = _YES_NO[online]
    battery = None if view is None or view.evaluation is None else view.evaluation.battery_v
    seen = None if view is None or view.last_seen is None else max(0.0, now - view.last_seen)
    volts = ("", "–") if battery is None else (repr(battery), f"{battery:.2f}")
    ago = ("", "–") if seen is None else (f"{seen:.1f}", f"{_duration(seen)} ago")
    return "".join(
        f'<td data-key="{key}" data-value="{value}">{shown}</td>'
        for key, (value, shown) in (
            ("mqtt_online", state), ("mqtt_battery_v", volts), ("mqtt_last_message", ago)
        )
    )  # fmt: skip


def header_html(run_dir: Path, snapshot: Snapshot | None, error: str | None) -> str:
    name = snapshot.name if snapshot is not None else run_dir.name
    lines = [f"<h2>run {html.escape(name)}</h2><div>{html.escape(str(run_dir))}</div>"]
    problems = ([] if snapshot is None else snapshot.problems) + ([error] if error else [])
    lines += [f'<div class="dash-problem">{html.escape(p)}</div>' for p in problems]
    return "".join(lines)


def trajectories_note(trajectories: Trajectories | None) -> str:
    if trajectories is None:
        return '<p data-key="trajectories" data-value="0">no post-evaluation trajectories yet</p>'
    count = len(trajectories.xs)
    return (
        f'<p data-key="trajectories" data-value="{count}">post-evaluation: paths of {count} '
        f"robots over {trajectories.steps} steps (the dot: where each ended)</p>"
    )


# -- the Bokeh document --------------------------------------------------------------------------
