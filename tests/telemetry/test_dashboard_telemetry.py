"""``surprise-master dashboard --broker``: the robots' own view over MQTT beside the run
directory's, from a real broker into the page's models (the browser's rendering of the same
models is tested in tests/master/test_dashboard.py)."""

from __future__ import annotations

import asyncio
import contextlib
import re
from pathlib import Path

import pytest
from telemetry_helpers import eventually

from master_service.cli import main
from minimize_surprise.backoff import BackoffConfig
from reporting.dashboard import _follow, _Page, _Poller, robots_html
from reporting.dashboard_data import RunReader
from reporting.watch import SwarmState
from telemetry.config import TelemetryConfig, parse_broker_url
from telemetry.payloads import EvaluationSummary
from telemetry.publisher import TelemetryPublisher

FAST = BackoffConfig(initial=0.02, max=0.1, jitter=0.5)


def _run(tmp_path: Path) -> Path:
    """A run directory whose evaluations.csv names robots r1 and r2."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("experiment:\n  evolution:\n    evaluations: 4\n")
    (run / "evaluations.csv").write_text(
        "evaluation,kind,fitness,best_fitness,accepted,attempts,duration_s,safety_share,"
        "fitness_r1,fitness_r2\n1,initial,0.5,0.5,true,1,0.1,0.0,0.4,0.6\n"
    )
    (run / "checkpoint.json").write_text(
        '{"phase": "evolution", "csv_rows": 1, "roster": null, "written_at": 0.0,'
        ' "optimizer": {"evaluations": 1, "best_fitness": 0.5}}'
    )
    return run


def cells(html: str, robot: str) -> dict[str, str]:
    """The data-key -> data-value of one robot's row."""
    row = re.search(rf'<tr data-robot="{robot}">(.*?)</tr>', html)
    assert row is not None, f"no row for {robot}"
    return dict(re.findall(r'data-key="([^"]+)" data-value="([^"]*)"', row.group(1)))


async def test_the_page_shows_each_robots_mqtt_view_beside_the_run(tmp_path, mosquitto):
    from bokeh.document import Document

    run = _run(tmp_path)
    state = SwarmState()
    following = asyncio.create_task(_follow(parse_broker_url(mosquitto.url), state))
    config = TelemetryConfig(broker=mosquitto.url, reconnect=FAST)
    try:
        await eventually(lambda: state.broker.startswith("connected"))
        # r1 reports its battery after an evaluation; r3, not (yet) in the run, is online; r2
        # says nothing. Then r3 goes away: its last will says it is offline.
        async with TelemetryPublisher(config, status_suffix="robot/r1/status") as r1:
            summary = EvaluationSummary(
                t=0.0, evaluation=1, requested=10, steps=10, fitness=0.4, battery_v=3.81
            )
            r1.publish_nowait("robot/r1/evaluation", summary)
            async with TelemetryPublisher(config, status_suffix="robot/r3/status"):
                await eventually(lambda: "r3" in state.robots and state.robots["r3"].online)
            await eventually(lambda: state.robots["r3"].online is False)
            await eventually(lambda: state.robots["r1"].evaluation is not None)
            page = _Page(Document(), _Poller(RunReader(run)), run, state)
            html = page.robots.text
    finally:
        following.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await following
    r1_cells, r2_cells, r3_cells = (cells(html, r) for r in ("r1", "r2", "r3"))
    assert r1_cells["fitness"] == "0.4" and r1_cells["mqtt_battery_v"] == "3.81"
    assert r1_cells["mqtt_online"] == "true" and float(r1_cells["mqtt_last_message"]) < 30
    assert r2_cells["fitness"] == "0.6"
    assert r2_cells["mqtt_online"] == r2_cells["mqtt_battery_v"] == ""  # never heard of
    assert r3_cells["mqtt_online"] == "false" and r3_cells["fitness"] == ""  # MQTT only
    assert 'data-key="telemetry" data-value="connected' in page.status.text


def test_without_a_broker_the_table_has_no_mqtt_columns(tmp_path):
    html = robots_html(RunReader(_run(tmp_path)).read())
    assert "mqtt_" not in html and cells(html, "r1")["fitness"] == "0.4"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--broker", "http://x"], "mqtt://"),
        (["--broker", "mqtt://localhost", "--prefix", "a/#"], "prefix"),
    ],
)
def test_a_bad_broker_or_prefix_is_a_usage_error(tmp_path, capsys, args, message):
    assert main(["dashboard", str(tmp_path), "--port", "0", *args]) == 2
    assert message in capsys.readouterr().err
