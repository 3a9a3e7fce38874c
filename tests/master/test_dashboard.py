"""``surprise-master dashboard`` in a real headless browser (Debian's chromium through Selenium).

The page's numbers are read from its DOM (Bokeh draws each model in a shadow root; every value
stands in an element with a ``data-key``, see reporting/dashboard.py) and compared
with what ``evaluations.csv`` holds at that moment: while a simulated run (the agents engine, in
real time, so that it runs while the browser looks) goes on, and after it finished.
"""

from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Final

import numpy as np
import pytest
from run_files import write_checkpoint, write_live

from needs import end_process, require_binary, require_module

#: Seconds for the dashboard to print its URL: a Python start and Bokeh's import.
STARTUP: Final = 20.0
#: Seconds for the page to show what the files hold: a poll each second, then the websocket.
CATCH_UP: Final = 15.0
#: Seconds the simulated run may take: 16 evaluations of 0.8 s in real time, a 2 s
#: post-evaluation and the report's pictures, with room for a slow machine.
RUN_LIMIT: Final = 90.0
#: Seconds for a process to end after SIGTERM.
END: Final = 10.0

#: Collects every value the page shows, through the shadow roots: key (``robot/key`` in the
#: robots' table) -> [data-value, text shown].
READ_PAGE: Final = """
const out = {};
function walk(root) {
  for (const el of root.querySelectorAll('*')) {
    if (el.dataset && el.dataset.key !== undefined) {
      const row = el.closest('tr');
      const robot = row && row.dataset.robot !== undefined ? row.dataset.robot + '/' : '';
      out[robot + el.dataset.key] = [el.dataset.value, el.textContent];
    }
    if (el.shadowRoot) walk(el.shadowRoot);
  }
}
walk(document);
return out;
"""
#: What the trajectories' plot holds: whether it is shown, and each path's x values.
READ_PATHS: Final = """
const doc = window.Bokeh && Bokeh.documents[0];
const plot = doc && doc.get_model_by_name('trajectories');
if (!plot) return null;
const lines = plot.renderers.filter(r => r.glyph && r.glyph.type === 'MultiLine');
const data = lines.length ? lines[0].data_source.data : null;
const column = name => data ? (data instanceof Map ? data.get(name) : data[name]) : [];
const xs = Array.from(column('xs'), a => Array.from(a));
const robots = Array.from(column('robot'));
return {visible: plot.visible, xs: xs, robots: robots};
"""

#: An experiment short enough for a test, long enough (in real time) to watch.
EXPERIMENT: Final = "setting: paper\nevaluation_steps: 80\npost_evaluation_steps: 200\n"


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """A headless chromium driven by Selenium, through Debian's chromedriver (Selenium Manager
    would download a driver: no network in CI)."""
    require_module("bokeh", "master")
    require_module("selenium")
    chromium = require_binary("chromium")
    driver_path = require_binary("chromedriver", "chromium-driver")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for argument in (
        "--headless=new",
        "--no-sandbox",  # as root (CI, containers) chromium refuses to start otherwise
        "--disable-gpu",
        "--disable-dev-shm-usage",  # a container's /dev/shm is too small for a renderer
        "--window-size=1280,1400",
    ):
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(executable_path=driver_path), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "master_service", *args]


def _start_dashboard(run: Path, log: Path) -> tuple[subprocess.Popen[str], str]:
    process = subprocess.Popen(
        _command("dashboard", str(run), "--port", "0"),
        stdout=subprocess.PIPE,
        stderr=open(log, "w"),  # noqa: SIM115  # the child holds it
        text=True,
    )
    stdout = process.stdout
    assert stdout is not None
    lines: list[str] = []
    # A thread, so that a dashboard that hangs before printing fails the test instead of it.
    reader = threading.Thread(target=lambda: lines.append(stdout.readline()), daemon=True)
    reader.start()
    reader.join(STARTUP)
    first = lines[0] if lines else ""
    if not first.startswith("dashboard: http://127.0.0.1:"):
        end_process(process, END)
        pytest.fail(f"the dashboard printed {first!r}; its log: {log.read_text()}")
    return process, first.removeprefix("dashboard: ").strip()


def _page(driver: Any) -> dict[str, list[str]]:
    return driver.execute_script(READ_PAGE) or {}


def _rows(run: Path) -> list[dict[str, str]]:
    """The complete rows of the run's CSV now (a line still being written is left out)."""
    try:
        text = (run / "evaluations.csv").read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    return list(csv.DictReader(text[: text.rfind("\n") + 1].splitlines()))


def _mismatches(page: dict[str, list[str]], row: dict[str, str], robots: list[str]) -> list[str]:
    """What the page shows differently from ``row`` of the CSV (exact texts and shown texts)."""
    expected = {
        "last_evaluation": row["evaluation"],
        "best_fitness": row["best_fitness"],
        "last_fitness": row["fitness"],
        **{f"{r}/fitness": row[f"fitness_{r}"] for r in robots},
    }
    wrong = [
        f"{key}: page {page.get(key, [None])[0]!r}, csv {value!r}"
        for key, value in expected.items()
        if page.get(key, [None])[0] != value
    ]
    best = page.get("best_fitness", ["", ""])[1]
    if best != f"{float(row['best_fitness']):.4f}":
        wrong.append(f"best fitness shown as {best!r}")
    return wrong


def _robots(rows: list[dict[str, str]]) -> list[str]:
    return [c.removeprefix("fitness_") for c in rows[0] if c.startswith("fitness_")] if rows else []


def _listing(run: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(run.rglob("*"))}


@pytest.mark.slow
def test_the_page_follows_a_running_simulated_run_to_its_end(tmp_path: Path, browser: Any) -> None:
    run = tmp_path / "run"
    run.mkdir()  # the run starts in an empty directory; the dashboard is there before it
    config = tmp_path / "experiment.yaml"
    config.write_text(EXPERIMENT)
    dashboard, url = _start_dashboard(run, tmp_path / "dashboard.log")
    sim = None
    try:
        browser.get(url)
        deadline = time.monotonic() + CATCH_UP
        while _page(browser).get("state", [None])[0] != "not started":
            assert time.monotonic() < deadline, f"the page never loaded: {_page(browser)}"
            time.sleep(0.2)
        sim = subprocess.Popen(
            _command(
                *("sim", "--engine", "agents", "--realtime", "--robots", "3"),
                *("--evaluations", "16", "--seed", "7", "--config", str(config)),
                *("--out", str(run)),
            ),
            stdout=subprocess.DEVNULL,
            stderr=open(tmp_path / "sim.log", "w"),  # noqa: SIM115  # the child holds it
        )
        agreed: set[int] = set()
        seen: dict[str, set[str]] = {"state": set(), "connected": set(), "time_left": set()}
        deadline = time.monotonic() + RUN_LIMIT
        while sim.poll() is None:
            assert time.monotonic() < deadline, "the simulated run did not end"
            page = _page(browser)
            rows = _rows(run)
            shown = int(page.get("evaluations", ["0"])[0] or 0)
            if shown and page.get("phase", [""])[0] == "evolution":
                # The row the page claims to show holds exactly the numbers it shows, and the
                # CSV holds no fewer rows: the page never runs ahead of the file.
                assert shown <= len(rows), (shown, len(rows))
                assert not _mismatches(page, rows[shown - 1], _robots(rows))
                if shown == len(rows):
                    agreed.add(shown)
                seen["state"].add(page["state"][0])
                seen["connected"] |= {v[0] for k, v in page.items() if k.endswith("/connected")}
                if "time_left" in page:
                    seen["time_left"].add(page["time_left"][0])
            time.sleep(0.2)
        assert sim.returncode == 0, (tmp_path / "sim.log").read_text()
        # The page agreed with the CSV's last row at several moments: it follows the run.
        assert len(agreed) >= 3, agreed
        assert "running" in seen["state"] and "true" in seen["connected"], seen
        assert seen["time_left"], "a master that runs tells the time left"

        rows = _rows(run)
        robots = _robots(rows)
        assert len(rows) == 16 and robots == ["sim-0", "sim-1", "sim-2"]
        deadline = time.monotonic() + CATCH_UP
        while True:
            page = _page(browser)
            done = page.get("state", [None])[0] == "finished"
            wrong = _mismatches(page, rows[-1], robots)
            # The master stops (live.json: running false, no robot) after its last checkpoint.
            gone = all(page.get(f"{r}/connected", [None])[0] == "false" for r in robots)
            if done and gone and not wrong and page.get("trajectories", [None])[0] == "3":
                break
            assert time.monotonic() < deadline, f"finished page differs: {wrong}, {page}"
            time.sleep(0.2)
        assert page["evaluations"] == ["16", "16 / 16"]
        assert page["phase"][0] == "done"
        post = json.loads((run / "post_evaluation.json").read_text())
        assert float(page["post_fitness"][0]) == post["swarm_fitness"]
        for robot in robots:
            assert float(page[f"{robot}/post_fitness"][0]) == post["robots"][robot]["fitness"]
            assert page[f"{robot}/overruns"][0] == rows[-1][f"overruns_{robot}"]
        paths = browser.execute_script(READ_PATHS)
        assert paths is not None and paths["visible"] and paths["robots"] == robots
        for robot, xs in zip(robots, paths["xs"], strict=True):
            with np.load(run / "traces" / f"{robot}.npz") as trace:
                assert xs == pytest.approx(trace["poses"][:, 0].tolist(), abs=1e-12)

        # The dashboard only reads: more polls leave every file of the run as it was.
        before = _listing(run)
        time.sleep(2.5)
        assert _listing(run) == before
        assert dashboard.poll() is None, "the dashboard ended on its own"
    finally:
        end_process(sim, END)
        end_process(dashboard, END)
    assert dashboard.returncode == 0, (tmp_path / "dashboard.log").read_text()


def test_a_pause_batteries_and_a_half_written_row_show_on_the_page(
    tmp_path: Path, browser: Any
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("experiment:\n  evolution:\n    evaluations: 40\n")
    header = (
        "evaluation,kind,fitness,best_fitness,accepted,attempts,duration_s,safety_share,"
        "fitness_t1,fitness_t2,battery_v_t1,battery_v_t2,overruns_t1,overruns_t2,"
        "read_failures_t1,read_failures_t2\n"
    )
    first = "1,initial,0.5,0.5,true,1,9.000,0.1000,0.4,0.6,3.912,,0,3,0,1\n"
    (run / "evaluations.csv").write_text(header + first + "2,offspring,0.7,0.7,true,1,9.0")
    write_checkpoint(run, 1, best_fitness=None)
    paused = {"kind": "battery", "reason": "battery low: t2 <3.5 V", "robots": ["t2"]}
    write_live(
        run,
        robots=["t1"],
        time_left_s=3600.0,
        paused=paused,
        robot_state={"t2": {"battery_v": 3.4, "overruns": 3, "read_failures": 1}},
    )
    dashboard, url = _start_dashboard(run, tmp_path / "dashboard.log")
    try:
        browser.get(url)
        deadline = time.monotonic() + CATCH_UP
        while "pause" not in (page := _page(browser)):
            assert time.monotonic() < deadline, f"no pause on the page: {page}"
            time.sleep(0.2)
        assert page["state"][0] == "paused"
        assert page["pause"] == ["battery low: t2 <3.5 V"] * 2
        assert page["evaluations"] == ["1", "1 / 40"]  # the half-written row is not counted
        assert page["t1/connected"][0] == "true" and page["t2/connected"][0] == "false"
        assert page["t1/battery_v"] == ["3.912", "3.91"]
        assert page["t2/battery_v"] == ["3.4", "3.40"]  # the running master's newer reading
        assert page["t2/read_failures"][0] == "1"
        assert page["time_left"][1] == "~1 h 00 min"

        # The row completed and counted, the pause over: the page follows.
        with open(run / "evaluations.csv", "a", encoding="utf-8") as file:
            file.write("00,0.2000,0.7,0.7,3.9,3.8,0,0,0,0\n")
        write_checkpoint(run, 2, best_fitness=None)
        write_live(run, robots=["t1"], time_left_s=3600.0)
        deadline = time.monotonic() + CATCH_UP
        while (page := _page(browser)).get("evaluations", [None])[0] != "2" or "pause" in page:
            assert time.monotonic() < deadline, f"the page did not follow: {page}"
            time.sleep(0.2)
        assert page["state"][0] == "running"
        assert page["t2/battery_v"] == ["3.8", "3.80"] and page["last_fitness"][0] == "0.7"
    finally:
        end_process(dashboard, END)


def test_a_missing_directory_is_refused_before_serving(tmp_path: Path) -> None:
    result = subprocess.run(
        _command("dashboard", str(tmp_path / "nothing"), "--port", "0"),
        capture_output=True,
        text=True,
        timeout=STARTUP,
    )
    assert result.returncode == 2
    assert "nothing is not a run directory" in result.stderr and not result.stdout


def test_a_busy_port_is_one_line_and_exit_status_1(tmp_path: Path) -> None:
    require_module("bokeh", "master")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run(
            _command("dashboard", str(tmp_path), "--port", str(port)),
            capture_output=True,
            text=True,
            timeout=STARTUP,
        )
    assert result.returncode == 1 and not result.stdout
    assert result.stderr.startswith(f"surprise-master: cannot serve on 127.0.0.1:{port}: ")
    assert len(result.stderr.splitlines()) == 1
