"""``surprise-master dashboard RUN_DIR``: a live web page of one run, served by Bokeh.

::

    surprise-master dashboard RUN_DIR [--host 127.0.0.1] [--port 5006] [--open]
                                      [--broker mqtt://HOST[:PORT] [--prefix P]]

The page (docs/dashboard.md) shows where the run stands (phase, evaluations done of the planned,
time left, a pause and its reason), the best and each evaluation's fitness over the evaluations,
a table of the robots (connected, last fitness, battery, overruns, read failures, whatever
per-robot columns the run has) and, once the post-evaluation is written, the robots' paths.

It is a separate process that only reads the run directory (:mod:`.dashboard_data`), once every
:data:`POLL_INTERVAL` for all open pages together, so it serves a running, paused or finished run
of ``run``, ``resume`` or ``sim`` alike, and nothing it does, or fails to do, reaches the run.
With ``--broker`` it also follows the swarm's MQTT telemetry (docs/telemetry.md, as ``watch``
does): each robot's own view, online or not by its last will, its battery after its last
evaluation and how long ago it last spoke, which the robots publish whether or not the master
can reach them.
Every value the page shows stands in an element with a ``data-key`` (and, in the robots' table, its
row's ``data-robot``) whose ``data-value`` holds the text read from the file, for a test or a
script to read back.

Bokeh is imported inside the functions that serve the page: the rest of ``master_service`` (and a
robot's Pi) does without it. The HTML of the status and the table is built by plain functions
(:mod:`reporting.dashboard_html`), tested without a browser. While ``surprise-master track
--live`` watches the run, the trajectories' plot shows where the camera sees the robots now.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import signal
import socket
import sys
import time
import webbrowser
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from reporting.dashboard_data import RunReader, Snapshot, Trajectories
from reporting.dashboard_html import header_html, robots_html, status_html, trajectories_note
from runfiles.schema import RunDirError

if TYPE_CHECKING:
    from bokeh.document import Document

    from reporting.watch import SwarmState

__all__ = [
    "DEFAULT_PORT",
    "POLL_INTERVAL",
    "robots_html",
    "run_dashboard",
    "status_html",
]

_log = logging.getLogger(__name__)

#: Bokeh's own default port, so that a habit (and an ``ssh -L 5006:...``) carries over.
DEFAULT_PORT: Final = 5006
#: Seconds between two looks at the run directory: the master commits at most a few evaluations
#: a second with robots, and a person reads no faster.
POLL_INTERVAL: Final = 1.0

#: The loopback names a browser on this machine (or at the end of an ``ssh -L``) may use.
_LOOPBACK: Final = ("localhost", "127.0.0.1")
_CSS: Final = """
:host { font-family: sans-serif; font-size: 14px; }
.dash-grid { display: grid; grid-template-columns: repeat(3, max-content 16em); gap: 2px 12px; }
.dash-label { color: #555; }
.dash-pause { background: #fff3cd; border: 1px solid #e0b000; padding: 6px 10px; margin: 6px 0; }
.dash-bar { width: 100%; max-width: 60em; height: 8px; background: #eee; margin-top: 4px; }
.dash-bar > div { height: 8px; background: #1f77b4; }
.dash-robots { border-collapse: collapse; }
.dash-robots th, .dash-robots td { border-bottom: 1px solid #ddd; padding: 2px 8px; }
.dash-robots td { text-align: right; font-variant-numeric: tabular-nums; }
.dash-robots td[data-key=robot] { text-align: left; }
.dash-problem { color: #a00; }
"""


class _Poller:
    """One reader for every open page: a page asking within half a period of the last read gets
    that read's snapshot. Bokeh runs every session's callbacks on one thread, so no lock."""

    def __init__(self, reader: RunReader) -> None:
        self.reader = reader
        self._snapshot: Snapshot | None = None
        self._at = 0.0

    def snapshot(self) -> Snapshot:
        now = time.monotonic()
        if self._snapshot is None or now - self._at >= POLL_INTERVAL / 2:
            self._snapshot, self._at = self.reader.read(), now
        return self._snapshot


class _Page:
    """The models of one open page and their refresh from the poller's snapshot."""

    def __init__(
        self, doc: Document, poller: _Poller, run_dir: Path, telemetry: SwarmState | None = None
    ) -> None:
        from bokeh.layouts import column
        from bokeh.models import ColumnDataSource, HoverTool
        from bokeh.models.widgets.markups import Div
        from bokeh.plotting import figure

        self.poller, self.run_dir, self.telemetry = poller, run_dir, telemetry
        css: list[Any] = [_CSS]  # a string is an inline style sheet for Bokeh
        self.header = Div(name="header", stylesheets=css)
        self.status = Div(name="status", stylesheets=css)
        self.robots = Div(name="robots", stylesheets=css)
        self.note = Div(name="trajectories_note", stylesheets=css)
        self.curve = ColumnDataSource({"evaluation": [], "fitness": [], "best_fitness": []})
        self.paths = ColumnDataSource({"xs": [], "ys": [], "robot": [], "colour": []})
        self.ends = ColumnDataSource({"x": [], "y": [], "robot": [], "colour": []})
        self.arena = ColumnDataSource({"x": [], "y": [], "side": [], "height": []})
        self.seen = ColumnDataSource({"x": [], "y": [], "angle": [], "robot": []})
        fitness = figure(
            name="fitness",
            title="fitness over the evaluations",
            x_axis_label="evaluation",
            y_axis_label="fitness",
            height=320,
            sizing_mode="stretch_width",
            tools="pan,wheel_zoom,box_zoom,reset,save",
        )
        each = fitness.scatter(
            "evaluation", "fitness", source=self.curve, size=4, alpha=0.5,
            legend_label="fitness of the evaluation", color="#7f7f7f",
        )  # fmt: skip
        fitness.step(
            "evaluation", "best_fitness", source=self.curve, mode="after", line_width=2,
            legend_label="best fitness", color="#1f77b4",
        )  # fmt: skip
        tips = [("evaluation", "@evaluation"), ("fitness", "@fitness{0.0000}")]
        fitness.add_tools(HoverTool(renderers=[each], tooltips=tips))
        fitness.legend.location = "bottom_right"
        fitness.legend.click_policy = "hide"
        self.paths_plot = figure(
            name="trajectories",
            title="post-evaluation trajectories",
            x_axis_label="x (m)",
            y_axis_label="y (m)",
            width=460,
            height=460,
            match_aspect=True,
            visible=False,
        )
        plot = self.paths_plot
        plot.rect("x", "y", "side", "height", source=self.arena, fill_alpha=0, line_dash="dashed",
                  line_color="#555")  # fmt: skip
        plot.multi_line("xs", "ys", source=self.paths, line_color="colour", line_width=1.5)
        plot.scatter("x", "y", source=self.ends, color="colour", size=8)
        # The camera's live view: a triangle per robot pointing its heading (0 points up).
        plot.scatter("x", "y", source=self.seen, marker="triangle", angle="angle", size=14,
                     color="#d62728")  # fmt: skip
        plot.text("x", "y", text="robot", source=self.ends, text_font_size="9pt", x_offset=6,
                  text_baseline="middle", text_color="colour")  # fmt: skip
        plot.add_tools(HoverTool(tooltips=[("robot", "@robot")]))
        self._generation: int | None = None
        self._signature: tuple[Any, ...] | None = None
        self.doc = doc
        doc.title = f"run {run_dir.name}"
        doc.add_root(
            column(
                self.header,
                self.status,
                self.robots,
                fitness,
                self.note,
                plot,
                sizing_mode="stretch_width",
            )
        )
        self.refresh()
        doc.add_periodic_callback(self.refresh, int(POLL_INTERVAL * 1000))

    def refresh(self) -> None:
        """Show the run directory as it is now; an error shows on the page, which goes on."""
        # One message to the browser for all of a snapshot: sent change by change, a page read
        # between two of them showed the header of one evaluation over the robots' table of the
        # one before.
        self.doc.hold("combine")
        try:
            snapshot = self.poller.snapshot()
            self._show(snapshot)
        except Exception as exc:  # the page must outlive what it cannot show
            _log.exception("dashboard: cannot show %s", self.run_dir)
            _set(self.header, header_html(self.run_dir, None, f"cannot show the run: {exc}"))
        finally:
            self.doc.unhold()

    def _show(self, snapshot: Snapshot) -> None:
        _set(self.header, header_html(self.run_dir, snapshot, None))
        _set(self.status, status_html(snapshot, self.telemetry))
        _set(self.robots, robots_html(snapshot, self.telemetry))
        _set(self.note, trajectories_note(snapshot.trajectories))
        curve = snapshot.curve
        sent = len(self.curve.data["evaluation"])
        if curve.generation == self._generation and len(curve.evaluation) >= sent:
            if len(curve.evaluation) > sent:
                self.curve.stream(
                    {
                        "evaluation": curve.evaluation[sent:],
                        "fitness": curve.fitness[sent:],
                        "best_fitness": curve.best_fitness[sent:],
                    }
                )
        else:
            self.curve.data = {
                "evaluation": curve.evaluation,
                "fitness": curve.fitness,
                "best_fitness": curve.best_fitness,
            }
            self._generation = curve.generation
        self._show_trajectories(snapshot.trajectories)
        self._show_camera(snapshot)

    def _show_trajectories(self, trajectories: Trajectories | None) -> None:
        signature = None if trajectories is None else trajectories.signature
        if signature == self._signature:
            return
        self._signature = signature
        self.paths_plot.visible = trajectories is not None
        if trajectories is None:
            self.paths.data = {"xs": [], "ys": [], "robot": [], "colour": []}
            self.ends.data = {"x": [], "y": [], "robot": [], "colour": []}
            return
        robots = list(trajectories.xs)
        colours = _colours(len(robots))
        self.paths.data = {
            "xs": [trajectories.xs[r] for r in robots],
            "ys": [trajectories.ys[r] for r in robots],
            "robot": robots,
            "colour": colours,
        }
        self.ends.data = {
            "x": [trajectories.xs[r][-1] for r in robots],
            "y": [trajectories.ys[r][-1] for r in robots],
            "robot": robots,
            "colour": colours,
        }
        side = trajectories.arena_side
        height = trajectories.arena_height or side
        self.arena.data = (
            {"x": [0.0], "y": [0.0], "side": [side], "height": [height]}
            if side
            else {"x": [], "y": [], "side": [], "height": []}
        )

    def _show_camera(self, snapshot: Snapshot) -> None:
        view = snapshot.camera
        robots = [] if view is None else sorted(view.robots)
        poses = [] if view is None else [view.robots[r] for r in robots]
        self.seen.data = {
            "x": [p.x for p in poses],
            "y": [p.y for p in poses],
            "angle": [p.heading - math.pi / 2 for p in poses],
            "robot": robots,
        }
        self.paths_plot.visible = snapshot.trajectories is not None or view is not None
        if view is not None and snapshot.trajectories is None:
            width, height = view.floor
            self.arena.data = {"x": [0.0], "y": [0.0], "side": [width], "height": [height]}


def _set(div: Any, text: str) -> None:
    # Only a change goes over the websocket: most polls change nothing.
    if div.text != text:
        div.text = text


def _colours(count: int) -> list[str]:
    from bokeh.palettes import Category10_10, Category20_20

    palette = Category10_10 if count <= 10 else Category20_20
    return [palette[k % len(palette)] for k in range(count)]


# -- serving ---------------------------------------------------------------------------------------


def _origins(host: str, port: int) -> list[str]:
    """The ``host:port`` a browser's page may open the websocket from (Bokeh checks the origin)."""
    names = {*_LOOPBACK}
    if ":" not in host:  # Bokeh's allowlist cannot hold an IPv6 address
        names.add(host)
    if host in ("0.0.0.0", ""):
        names |= {socket.gethostname(), socket.getfqdn()}
    return sorted(f"{name}:{port}" for name in names if name)


def _url(host: str, port: int) -> str:
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
    return f"http://[{shown}]:{port}/" if ":" in shown else f"http://{shown}:{port}/"


def run_dashboard(
    run_dir: Path,
    host: str = "127.0.0.1",
    port: int = DEFAULT_PORT,
    open_browser: bool = False,
    broker: str | None = None,
    prefix: str | None = None,
) -> int:
    """Serve the dashboard of ``run_dir`` on ``host:port`` (port 0: any free one) until SIGINT
    or SIGTERM; prints ``dashboard: URL`` once it listens. With ``broker`` (``mqtt://host[:port]``)
    it also follows the telemetry under ``prefix``. Returns the exit status: 0, 1 when the port
    cannot be bound, 2 without Bokeh, with a bad broker URL or prefix, or with a broker but no
    MQTT client installed.

    Raises :class:`~runfiles.schema.RunDirError` when ``run_dir`` is not a directory; a
    port that cannot be bound is one line on stderr and exit status 1.
    """
    if not run_dir.is_dir():
        raise RunDirError(f"{run_dir} is not a run directory (no such directory)")
    try:
        import bokeh  # noqa: F401  # only this command needs it (the master extra)
    except ImportError:
        print(
            "surprise-master: the dashboard needs bokeh: pip install -e '.[master]'",
            file=sys.stderr,
        )
        return 2
    telemetry = None
    if broker is not None:
        telemetry = _telemetry(broker, prefix)
        if telemetry is None:
            return 2
    return asyncio.run(_serve(run_dir, host, port, open_browser, telemetry))


def _telemetry(broker: str, prefix: str | None) -> tuple[Any, SwarmState] | None:
    # The broker's address and an empty swarm state, or None after one line on stderr.
    from reporting.watch import SwarmState
    from telemetry.config import DEFAULT_PREFIX, check_prefix, parse_broker_url

    option = "--broker"
    try:
        address = parse_broker_url(broker)
        option = "--prefix"
        check_prefix(prefix or DEFAULT_PREFIX)
        import aiomqtt  # noqa: F401  # the telemetry extra
    except ValueError as exc:
        print(f"surprise-master dashboard: {option}: {exc}", file=sys.stderr)
        return None
    except ImportError:
        print(
            "surprise-master dashboard: --broker needs the MQTT client: "
            "pip install 'minimize-surprise[telemetry]'",
            file=sys.stderr,
        )
        return None
    return address, SwarmState(prefix=prefix or DEFAULT_PREFIX)


async def _follow(address: Any, state: SwarmState) -> None:
    # The telemetry, whatever happens to it, never takes the page down: an unexpected failure
    # is logged and shown as the broker's state, and following starts again.
    from reporting.watch import follow

    while True:
        try:
            await follow(address, state)
        except Exception as exc:  # follow handles the broker's own errors
            _log.exception("dashboard: following the telemetry failed")
            state.broker = f"telemetry failed ({exc}); trying again"
            await asyncio.sleep(POLL_INTERVAL * 5)


async def _serve(
    run_dir: Path,
    host: str,
    port: int,
    open_browser: bool,
    telemetry: tuple[Any, SwarmState] | None = None,
) -> int:
    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler
    from bokeh.server.server import BaseServer
    from bokeh.server.tornado import BokehTornado
    from bokeh.server.util import bind_sockets
    from tornado.httpserver import HTTPServer
    from tornado.ioloop import IOLoop

    poller = _Poller(RunReader(run_dir))
    state = None if telemetry is None else telemetry[1]

    def page(doc: Document) -> None:
        _Page(doc, poller, run_dir, state)

    application = Application(FunctionHandler(page))
    # Bound before the application: with port 0 the allowed origins need the port chosen.
    try:
        sockets, port = bind_sockets(host, port)
    except OSError as exc:
        print(
            f"surprise-master: cannot serve on {host}:{port}: {exc.strerror or exc}; choose "
            "another --port (0: any free one)",
            file=sys.stderr,
        )
        return 1
    tornado = BokehTornado({"/": application}, extra_websocket_origins=_origins(host, port))
    http = HTTPServer(tornado)
    http.add_sockets(sockets)
    server = BaseServer(IOLoop.current(), tornado, http)
    server.start()
    url = _url(host, port)
    print(f"dashboard: {url}", flush=True)
    if open_browser:
        webbrowser.open(url)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    following = None
    if telemetry is not None:
        following = asyncio.create_task(_follow(*telemetry), name="dashboard-telemetry")
    try:
        await stop.wait()
    finally:
        if following is not None:
            following.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await following
        server.stop()
    return 0
