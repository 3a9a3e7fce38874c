"""The handlers of ``surprise-master``'s commands around a run: ``report``, ``status``,
``check`` (the preflight), ``continue`` (after a pause), ``escape`` (the experimenter's hand),
``swap`` (a spare for a robot gone for good), ``mark`` (a change a person made),
``watch``, ``dashboard`` and ``track`` (the overhead camera, with its options here), and the
parsers of a person's actions on a running run (:func:`add_hand_commands`); the rest of the
parser and the commands that run experiments are in :mod:`master_service.cli`."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
from pathlib import Path
from typing import Any

from master_service.cli_args import add_timeout
from master_service.config import load_master_config, required_secret
from master_service.rundir import RunDir, RunDirError
from minimize_surprise.text import plural

__all__ = [
    "add_hand_commands",
    "add_track_parser",
    "check_command",
    "continue_command",
    "dashboard_command",
    "escape_command",
    "mark_command",
    "report_command",
    "secret_command",
    "status_command",
    "swap_command",
    "track_command",
    "watch_command",
]


def report_command(args: argparse.Namespace) -> int:
    """``surprise-master report``."""
    from reporting.reality_gap import gap_lines
    from reporting.report import (
        baseline_text,
        behaviour_line,
        safety_lines,
        write_report,
    )
    from reporting.robot_stats import robot_lines

    metrics = write_report(
        args.dir,
        baseline=args.baseline,
        animate=args.animate,
        positions=args.positions,
        positions_offset=args.positions_offset,
    )
    best = metrics.get("best_fitness")
    post = (metrics.get("post_evaluation") or {}).get("swarm_fitness")
    drawn = metrics.get("pictures", [])
    print(
        f"wrote {Path(args.dir) / 'metrics.json'} and {plural(len(drawn), 'picture')} in "
        f"{Path(args.dir) / 'plots'}: {plural(metrics['evaluations'], 'evaluation')}, best "
        "fitness "
        + ("-" if best is None else f"{best:.4f}")
        + ("" if post is None else f", post-evaluation fitness {post:.4f}")
    )
    behaviour = behaviour_line(metrics)
    if behaviour is not None:
        print(behaviour)
    for line in safety_lines(metrics):
        print(line)
    for line in robot_lines(metrics.get("robot_stats")):
        print(line)
    for line in gap_lines(metrics.get("reality_gap")):
        print(line)
    for change in metrics.get("recovery") or []:
        back = change["recovery"]
        drop = "-" if change["drop"] is None else f"{change['drop']:.4f}"
        print(
            f"after evaluation {change['evaluation']}, {change['detail']}: fitness drop {drop}, "
            + ("not recovered" if back is None else f"recovered after {back} evaluations")
        )
    comparison = metrics.get("baseline")
    if comparison:
        print(baseline_text(comparison))
    if args.animate:
        print(f"animation: {Path(args.dir) / 'plots' / 'post_evaluation.gif'}")
    return 0


def check_command(args: argparse.Namespace) -> int:
    """``surprise-master check``."""
    from master_service.preflight import format_table, run_check

    config = load_master_config(args.config)
    secret = required_secret(config, args.config)
    timeout = args.timeout
    if not args.json:
        print(f"checking the robots of {args.config} (waiting up to {timeout:.0f} s for them)")
    rows = asyncio.run(run_check(config, secret, timeout=timeout))
    if args.json:
        print(json.dumps([row.to_json() for row in rows], indent=2))
    else:
        print(format_table(rows))
    return 0 if all(row.fit for row in rows) else 1


def continue_command(args: argparse.Namespace) -> int:
    """``surprise-master continue``."""
    from master_service.pause import request_continue
    from reporting.status import running_master

    run = RunDir(args.dir)
    if running_master(run.path) is None:
        # Nothing waits: removing the file would only hide why the run stopped where it did.
        raise RunDirError(
            f"no master is running {args.dir}: continue it with `surprise-master resume "
            f"{args.dir}` (a pause ends with the master that waited in it)"
        )
    pause = request_continue(run)
    reason = "no reason given" if pause is None else pause.reason
    print(f"continuing {args.dir} (it was paused: {reason})")
    return 0


def escape_command(args: argparse.Namespace) -> int:
    """``surprise-master escape``: 0 when the robot's safety layer starts its escape, 1 with one
    line when the master or the robot refused it (a RunDirError, exit 2, when no master runs)."""
    from master_service.escape import request_escape

    event = request_escape(RunDir(args.dir), args.robot, timeout=args.timeout)
    if not event.accepted:
        print(f"surprise-master: escape of {args.robot}: {event.detail}", file=sys.stderr)
        return 1
    print(
        f"{args.robot} escapes now: its safety layer starts the escape at its next step of "
        f"evaluation {event.evaluation_id} (logged in {args.dir}/events.jsonl)"
    )
    return 0


def swap_command(args: argparse.Namespace) -> int:
    """``surprise-master swap``: 0 when the spare took the gone robot's place, 1 with one line
    when the master refused (a RunDirError, exit 2, when no master runs or none answered)."""
    from master_service.swap import request_swap

    event = request_swap(RunDir(args.dir), args.gone, args.spare, timeout=args.timeout)
    if not event.accepted:
        print(
            f"surprise-master: swap of {args.gone} for {args.spare}: {event.detail}",
            file=sys.stderr,
        )
        return 1
    print(
        f"{args.spare} takes the place of {args.gone} from evaluation {event.evaluation_id} on "
        f"(logged in {args.dir}/events.jsonl)"
    )
    return 0


def mark_command(args: argparse.Namespace) -> int:
    """``surprise-master mark``: 0 once the running master logged the mark."""
    from master_service.mark import request_mark

    event = request_mark(RunDir(args.dir), " ".join(args.text), timeout=args.timeout)
    print(
        f"marked after evaluation {event.evaluation}: {event.detail} "
        f"(logged in {args.dir}/events.jsonl)"
    )
    return 0


def add_hand_commands(sub: argparse._SubParsersAction) -> None:
    """Add the commands by which a person acts on a running run: ``continue``, ``escape``,
    ``swap`` and ``mark``."""
    from master_service.escape import ANSWER_TIMEOUT
    from master_service.mark import MARK_TIMEOUT
    from master_service.swap import ANSWER_TIMEOUT as SWAP_TIMEOUT

    go_on = sub.add_parser(
        "continue", help="let a paused run go on (after a battery swap, or the robots placed)"
    )
    go_on.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    go_on.set_defaults(handler=continue_command)

    escape = sub.add_parser(
        "escape",
        help="make a robot of a running run escape now (paper Sec. V-C: force it back into the "
        "arena)",
    )
    escape.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    escape.add_argument("robot", metavar="ROBOT", help="the robot's id")
    add_timeout(escape, ANSWER_TIMEOUT, "the master's answer")
    escape.set_defaults(handler=escape_command)

    swap = sub.add_parser(
        "swap", help="bring a spare into a running run in place of a robot gone for good"
    )
    swap.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    swap.add_argument("gone", metavar="GONE", help="the robot gone for good")
    swap.add_argument("spare", metavar="SPARE", help="the spare robot taking its place")
    add_timeout(swap, SWAP_TIMEOUT, "the master's answer")
    swap.set_defaults(handler=swap_command)

    mark = sub.add_parser(
        "mark",
        help="mark a change you made to a running run (moved the light): the report shows the "
        "fitness around it",
    )
    mark.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    mark.add_argument("text", nargs="+", metavar="TEXT", help="what you changed")
    add_timeout(mark, MARK_TIMEOUT, "the master's answer")
    mark.set_defaults(handler=mark_command)


def status_command(args: argparse.Namespace) -> int:
    """``surprise-master status``."""
    from reporting.status import status_text

    print(status_text(args.dir))
    return 0


def watch_command(args: argparse.Namespace) -> int:
    """``surprise-master watch``."""
    from reporting.watch import run_watch  # rich and aiomqtt only for this command

    return run_watch(args.broker, prefix=args.prefix, once=args.once)


def dashboard_command(args: argparse.Namespace) -> int:
    """``surprise-master dashboard``."""
    from reporting.dashboard import run_dashboard  # bokeh only for this command

    return run_dashboard(
        args.dir, args.host, args.port, open_browser=args.open, broker=args.broker,
        prefix=args.prefix,
    )  # fmt: skip


def secret_command(args: argparse.Namespace) -> int:
    """``surprise-master secret``."""
    from minimize_surprise.files import write_new_secret

    try:
        path = write_new_secret(args.file)
    except FileExistsError:
        print(
            f"surprise-master: {args.file} exists: keep it (the robots may hold it) or remove it "
            "first",
            file=sys.stderr,
        )
        return 1
    print(
        f"wrote a new shared secret to {path} (only you may read it); copy it to every robot: "
        f"sudo deploy/install-pi.sh ROBOT_ID {path}"
    )
    return 0


def add_track_parser(sub: Any) -> None:
    """The ``track`` command's options, on the subcommands' parser ``sub``."""
    track = sub.add_parser(
        "track", help="robots' poses and the boxes of a post-evaluation from an overhead camera"
    )
    track.add_argument("video", nargs="?", type=Path, metavar="VIDEO", help="a video file")
    track.add_argument("--camera", type=int, metavar="N", help="or the camera N (V4L2), live")
    track.add_argument(
        "--run", type=Path, metavar="DIR", help="the run: its robots, boxes and post-evaluation"
    )
    track.add_argument("--out", type=Path, metavar="CSV", help="default: DIR/tracked_positions.csv")
    track.add_argument("--config", type=Path, help="a tracking file (YAML; docs/tracking.md)")
    track.add_argument("--floor", metavar="WxH", help="metres between the corner markers")
    track.add_argument("--markers", metavar="ROBOT=ID,...", help="each robot's marker id")
    track.add_argument(
        "--inventory",
        type=Path,
        metavar="FILE",
        help="take the markers from this fleet inventory (default: the run's, if its master file "
        "names one; docs/fleet.md)",
    )
    track.add_argument(
        "--camera-height", type=float, metavar="M", help="the lens's height above the floor"
    )
    track.add_argument(
        "--start", type=float, metavar="S", help="the post-evaluation's start in the video "
        "(default: the robots' LED flash)",
    )  # fmt: skip
    track.add_argument(
        "--duration", type=float, metavar="S", help="its length (default: the run's)"
    )
    track.add_argument("--boxes", action="store_true", help="find boxes (default: the run's)")
    track.add_argument(
        "--live", action="store_true", help="write where the camera sees the robots to "
        "DIR/camera.json while it tracks, for the dashboard (needs --run)",
    )  # fmt: skip
    track.set_defaults(handler=track_command)


def track_command(args: argparse.Namespace) -> int:
    """``surprise-master track``."""
    import msgspec

    from minimize_surprise.errors import ConfigError
    from runfiles import schema
    from simulator.experiment import world_config
    from tracking.config import load_tracking_config, parse_floor, parse_markers
    from tracking.live import CameraWriter
    from tracking.video import track_video, write_boxes, write_positions

    if (args.video is None) == (args.camera is None):
        raise ConfigError("give a video file or --camera N (one of them)", key="VIDEO")
    config = load_tracking_config(args.config)
    robots = config.robots
    if args.markers is not None:
        robots = msgspec.structs.replace(robots, ids=parse_markers(args.markers))
    else:
        inventory = _marker_inventory(args, has_ids=bool(robots.ids))
        if inventory is not None:
            robots = msgspec.structs.replace(robots, ids=inventory)
    updates: dict[str, Any] = {"robots": robots}
    if args.floor is not None:
        updates["floor"] = parse_floor(args.floor)
    if args.camera_height is not None:
        updates["camera"] = msgspec.structs.replace(config.camera, height=args.camera_height)
    duration, boxes = args.duration, args.boxes
    if args.run is not None:
        run = schema.read_config(args.run).experiment
        assert run is not None
        post = schema.read(args.run, schema.PostEvaluation)
        ids = list(post.robots) if post is not None else []
        stray = [r for r in robots.ids if ids and r not in ids]
        if stray:
            raise ConfigError(
                f"no robot '{stray[0]}' in the run's post-evaluation (it has {', '.join(ids)})",
                key="--markers",
            )
        steps = post.steps if post is not None else run.post_evaluation_steps
        duration = steps * run.step_period if duration is None else duration
        world = world_config(run)
        if args.floor is None and config.floor is None:
            # The corner markers lie in the walls' inner corners, off the carpet the boxes and
            # robots cover: the run's arena gives where.
            updates["floor"] = (2 * world.wall_hx, 2 * world.wall_hy)
        boxes = boxes or world.boxes
        if world.boxes:
            updates["boxes"] = msgspec.structs.replace(config.boxes, size=world.box_size)
    try:
        config = msgspec.structs.replace(config, **updates)
    except ValueError as exc:  # the checks of TrackingConfig, e.g. a marker used twice
        raise ConfigError(str(exc), file=str(args.config) if args.config else None) from None
    out = args.out
    if out is None:
        if args.run is None:
            raise ConfigError("name the positions' file, or the run it belongs to", key="--out")
        out = args.run / "tracked_positions.csv"
    if args.camera is not None and duration is None:
        # A camera has no last frame: the post-evaluation's length says when to stop.
        raise ConfigError("a live camera needs the post-evaluation's length", key="--duration")
    source = args.camera if args.camera is not None else str(args.video)
    live = None
    if args.live:
        if args.run is None or config.floor is None:
            raise ConfigError("a live view is written into its run: give --run", key="--live")
        name = f"camera {source}" if isinstance(source, int) else source
        live = CameraWriter(args.run, name, config.floor)
    result = track_video(
        source, config, duration=duration, start=args.start, boxes=boxes, on_frame=live
    )
    camera = result.camera
    how = "the LED flash" if result.flash else "--start"
    print(
        f"tracked {result.source}: {plural(result.frames, 'frame')}; the post-evaluation from "
        f"{result.start:.2f} s ({how}), {plural(len(result.times), 'frame')} over "
        f"{result.times[-1]:.1f} s"
        + ("" if result.end_reached else f" (the video ended before its {duration:g} s)")
    )
    print(
        f"camera {camera.height:g} m above ({camera.nadir[0]:.3f}, {camera.nadir[1]:.3f}) m, "
        f"{math.degrees(camera.tilt):.1f} degrees off the vertical; the corner markers fit to "
        f"{camera.residual_px:.2f} px"
    )
    for robot, summary in result.robots.items():
        line = f"{robot} (marker {summary.marker}): seen in {summary.seen} of {summary.frames}"
        if summary.seen < summary.frames:
            line += (
                f", {summary.frames - summary.seen} filled in (interpolated, or held at an end), "
                f"longest gap {summary.longest_gap_s:.1f} s"
            )
        print(line)
    if result.unknown:
        print(
            "ignored stray markers: " + ", ".join(f"{m} ({n}x)" for m, n in result.unknown.items())
        )
    write_positions(out, result)
    written = [str(out)]
    boxes_file = write_boxes(out, result)
    if boxes_file is not None and result.boxes is not None:
        found = result.boxes
        print(
            f"boxes: {len(found.boxes.start) + len(found.unpaired_start)} at the start, "
            f"{len(found.boxes.end) + len(found.unpaired_end)} at the end, "
            f"{len(found.boxes.start)} paired"
        )
        written.append(str(boxes_file))
    print(f"wrote {' and '.join(written)}")
    if args.run is not None:
        print(f"next: surprise-master report {args.run} --positions {out}")
    return 0


def _marker_inventory(args: argparse.Namespace, *, has_ids: bool) -> dict[str, int] | None:
    """The robots' markers from an inventory: ``--inventory``, or else, when the tracking file
    gives none, the one the run's master file names; only the run's robots when it has a
    post-evaluation (a spare's marker is not expected in its video). None: no inventory."""
    from master_service.inventory import load_inventory
    from runfiles import schema

    path = args.inventory
    if path is None and not has_ids and args.run is not None:
        named = schema.read_config(args.run).inventory
        path = None if named is None else Path(named)
    if path is None:
        return None
    markers = load_inventory(path).markers()
    post = None if args.run is None else schema.read_if_readable(args.run, schema.PostEvaluation)
    if post is not None:
        markers = {robot: marker for robot, marker in markers.items() if robot in post.robots}
    return markers
