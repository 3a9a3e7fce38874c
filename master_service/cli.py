"""``surprise-master``: run, resume, report on and inspect experiments with real robots.

Subcommands::

    surprise-master run --config FILE [--out DIR] [--pause-before-post]
                                                    start a run (DIR: runs/<time>-<scenario>)
    surprise-master resume DIR [--pause-before-post]
                                                    continue a run from its checkpoint
    surprise-master report DIR [--positions CSV]   write metrics.json and plots/
    surprise-master track VIDEO --run DIR --floor WxH --markers R=ID,... --camera-height M
                                                    poses and boxes from an overhead camera
    surprise-master status DIR                      where a run stands
    surprise-master check CONFIG [--json]           preflight: is every robot fit for a run?
    surprise-master continue DIR                    let a paused run go on (a battery swapped,
                                                    the robots placed: --pause-before-post)
    surprise-master escape DIR ROBOT                make a robot of a running run escape now
    surprise-master swap DIR GONE SPARE             a spare in place of a robot gone for good
    surprise-master fleet status|stop|logs|inventory  the whole fleet at once (docs/fleet.md)
    surprise-master sim [--scenario S] [--robots N] [--evaluations N] [--seed S] [--out DIR]
                        [--realtime] [--config FILE] [--optimizer map-elites]
                                                    a whole experiment on a simulated swarm
    surprise-master replay SOURCE [--steps N] [--config FILE] [--out DIR]
                                                    drive a stored genome again (simulated
                                                    robots, or the configuration's robots)
    surprise-master baseline --scenario S --random N [--out DIR] [--seed S] [--config FILE]
                                                    random network pairs in the same arena
    surprise-master report DIR --baseline BASE      ... and evolved against random
    surprise-master watch --broker URL [--prefix P] [--once]
                                                    live view of a run's MQTT telemetry
    surprise-master dashboard DIR [--host H] [--port P] [--open] [--broker URL [--prefix P]]
                                                    live web page of a run (only reads DIR)

Exit status: 0 done; 1 the run stopped on an error (a busy port, a full disk: one line naming the
file and what to do, the run can be resumed); 2 bad configuration or run directory (one message
naming the file and key; nothing was started); 128 + N stopped by signal N (SIGINT, SIGTERM), the
run can be resumed.

Why one file of over 600 lines: it is the command line's one page, every subcommand's options
beside the handler that reads them; the fleet's, the lab's and quality diversity's own handlers
are in ``cli_fleet``, ``cli_lab`` and ``cli_qd``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import logging
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Final, TypeVar

import msgspec

from master_service import cli_fleet, cli_lab, cli_qd
from master_service.agent_server import CONNECT_TIMEOUT
from master_service.cli_args import add_timeout
from master_service.config import load_master_config, required_secret
from master_service.console import Console
from master_service.mark import hand_console
from master_service.master import Master
from master_service.progress import ProgressDisplay, planned_text
from master_service.rundir import RunDir, RunDirError
from master_service.stopping import cancelled_by_signal, stop_flag, until_signal
from minimize_surprise.config import ExperimentConfig, load_experiment
from minimize_surprise.errors import ConfigError, FileWriteError
from minimize_surprise.text import plural
from runfiles import schema
from runfiles.schema import CONFIG_SNAPSHOT, Replay, Simulation

if TYPE_CHECKING:
    from master_service.experiments.simulation_setup import SimulatedRun
    from master_service.replay import ReplaySource

__all__ = ["main"]

_log = logging.getLogger("master_service.cli")

#: Reasons a file cannot be written that space, or a writable directory, puts right.
_NO_SPACE: Final = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
_NOT_WRITABLE: Final = frozenset({errno.EACCES, errno.EPERM, errno.EROFS})

T = TypeVar("T")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="surprise-master",
        description="Online evolution by minimizing surprise on a swarm of Thymio II robots.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages too")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="start an experiment with real robots")
    run.add_argument("--config", required=True, type=Path, help="master configuration (YAML)")
    run.add_argument("--out", type=Path, help="run directory (must not exist or be empty)")
    _pause_option(run)
    run.set_defaults(handler=_run)

    resume = sub.add_parser("resume", help="continue a run from its checkpoint")
    resume.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    _pause_option(resume)
    resume.set_defaults(handler=_resume)

    check = sub.add_parser("check", help="preflight: is every robot fit for a run?")
    check.add_argument("config", type=Path, metavar="CONFIG", help="master configuration (YAML)")
    add_timeout(check, CONNECT_TIMEOUT, "the robots to connect")
    check.add_argument("--json", action="store_true", help="print the rows as JSON")
    check.set_defaults(handler=cli_lab.check_command)

    cli_lab.add_hand_commands(sub)  # continue, escape, swap
    cli_fleet.add_fleet_parser(sub)  # fleet status, stop, logs
    cli_lab.add_track_parser(sub)

    report = sub.add_parser("report", help="write metrics.json and plots of a run")
    report.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    report.set_defaults(handler=_report)

    report.add_argument(
        "--baseline",
        type=Path,
        metavar="BASE",
        help="a `surprise-master baseline` directory: compare evolved against random pairs",
    )
    report.add_argument(
        "--animate",
        action="store_true",
        help="also animate the post-evaluation of a simulated run (plots/post_evaluation.gif)",
    )
    report.add_argument(
        "--positions", type=Path, metavar="CSV", help="a tracker's time,robot,x,y,heading file"
    )
    report.add_argument(
        "--positions-offset", type=float, metavar="SECONDS", help="its time at the first step"
    )

    sim = sub.add_parser("sim", help="run an experiment on a simulated swarm (no robots needed)")
    _experiment_options(sim)
    sim.add_argument("--evaluations", type=int, help="evaluations to count (default: 1000)")
    sim.add_argument("--out", type=Path, help="run directory (default: runs/<time>-sim-<scenario>)")
    sim.add_argument(
        "--engine",
        choices=("fast", "agents"),
        default="fast",
        help="fast: the compiled engine (default); agents: the master and one real agent per "
        "robot over loopback TCP, as in a lab",
    )
    sim.add_argument(
        "--realtime", action="store_true", help="pace the world in real time (--engine agents)"
    )
    sim.add_argument(
        "--optimizer",
        choices=("one-plus-one", "map-elites"),
        help="one-plus-one: the paper's (1+1) (default); map-elites: quality diversity "
        "(docs/quality-diversity.md); default: the experiment file's optimizer.name",
    )
    sim.set_defaults(handler=_sim)

    replay = sub.add_parser(
        "replay", help="drive a stored genome (no evolution) and compare with its source run"
    )
    replay.add_argument(
        "source", type=Path, metavar="SOURCE", help="a run directory, or a best_genome.json"
    )
    replay.add_argument("--steps", type=int, help="steps to run (default: the experiment's)")
    replay.add_argument("--out", type=Path, help="its directory (default: runs/<time>-replay-...)")
    replay.add_argument(
        "--config",
        type=Path,
        help="a master configuration: replay on its robots (real ones, or Aseba Playground's); "
        "without it, on simulated robots in the source run's arena",
    )
    replay.add_argument(
        "--experiment", type=Path, help="the experiment, for a genome file on simulated robots"
    )
    replay.add_argument(
        "--engine", choices=("fast", "agents"), default="fast", help="simulated robots' engine"
    )
    _pause_option(replay)
    replay.set_defaults(handler=_replay)

    baseline = sub.add_parser("baseline", help="evaluate random network pairs in an arena")
    _experiment_options(baseline)
    baseline.add_argument(
        "--random", type=int, required=True, metavar="N", help="number of random pairs"
    )
    baseline.add_argument(
        "--out", type=Path, help="output directory (default: runs/<time>-baseline-<scenario>)"
    )
    baseline.set_defaults(handler=_baseline)

    secret = sub.add_parser(
        "secret",
        help="write a new shared secret of the master and the robots (only you may read it)",
    )
    secret.add_argument("file", type=Path, metavar="FILE", help="where (never replaced)")
    secret.set_defaults(handler=cli_lab.secret_command)

    status = sub.add_parser("status", help="show where a run stands")
    status.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    status.set_defaults(handler=cli_lab.status_command)
    watch = sub.add_parser("watch", help="live view of a swarm's MQTT telemetry")
    watch.add_argument("--broker", required=True, metavar="URL", help="mqtt://host[:port]")
    watch.add_argument("--prefix", default="surprise", help="topic prefix (default: surprise)")
    watch.add_argument("--once", action="store_true", help="print one snapshot and exit")
    watch.set_defaults(handler=cli_lab.watch_command)

    dashboard = sub.add_parser("dashboard", help="live web page of a run (only reads its files)")
    dashboard.add_argument("dir", type=Path, metavar="DIR", help="the run directory")
    dashboard.add_argument(
        "--host", default="127.0.0.1", help="address to serve on (default: 127.0.0.1, this machine)"
    )
    dashboard.add_argument(
        "--port", type=int, default=5006, help="port to serve on (default: 5006; 0: any free one)"
    )
    dashboard.add_argument("--open", action="store_true", help="open the page in a browser")
    dashboard.add_argument(
        "--broker",
        metavar="URL",
        help="also follow the swarm's MQTT telemetry (mqtt://host[:port])",
    )
    dashboard.add_argument("--prefix", help="the telemetry's topic prefix (default: surprise)")
    dashboard.set_defaults(handler=cli_lab.dashboard_command)
    return parser


def _pause_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--pause-before-post",
        action="store_true",
        help="after the evolution, wait (motors stopped, checkpoint written) for `surprise-master "
        "continue DIR` or Enter before the post-evaluation, so the robots can be placed",
    )


def _experiment_options(parser: argparse.ArgumentParser) -> None:
    from minimize_surprise.settings import SETTINGS
    from simulator.scenarios import SCENARIOS

    parser.add_argument(
        "--scenario", choices=SCENARIOS, help="arena and robots (default: basic, or the file's)"
    )
    parser.add_argument(
        "--setting",
        choices=SETTINGS,
        help="paper: the authors' Webots simulation; lab: the real robots (default: the "
        "experiment file's, lab if it names none, as for the robots; without --config: paper)",
    )
    parser.add_argument(
        "--arena", type=float, metavar="SIDE", help="side of the carpet in metres (basic: 0.7-1.5)"
    )
    parser.add_argument("--robots", type=int, help="number of robots (default: the scenario's)")
    parser.add_argument("--seed", type=int, help="seed of every random draw (default: 0)")
    parser.add_argument(
        "--config", type=Path, help="an experiment file (YAML) overriding the scenario's defaults"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``surprise-master``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        return args.handler(args)
    except (ConfigError, RunDirError) as exc:
        print(f"surprise-master: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        # A directory that cannot be written, a full disk: one line, no traceback. A run that
        # had started keeps its checkpoint and can be resumed.
        print(f"surprise-master: {_os_error_text(exc)}", file=sys.stderr)
        return 1


def _os_error_text(exc: OSError) -> str:
    if isinstance(exc, FileWriteError):
        return str(exc)
    if exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def _run(args: argparse.Namespace) -> int:
    config = load_master_config(args.config)
    assert config.experiment is not None
    secret = required_secret(config, args.config)
    out = args.out
    if out is None:
        out = Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{config.experiment.scenario}"
    RunDir(out).check_new()
    return _serve(Master(config, out, secret=secret), args)


def _report(args: argparse.Namespace) -> int:
    if cli_qd.is_qd_run(args.dir):
        return cli_qd.report_qd(args.dir)
    return cli_lab.report_command(args)


def _resume(args: argparse.Namespace) -> int:
    from master_service.experiments.simulation_setup import read_simulation_file

    if cli_qd.is_qd_run(args.dir):
        return cli_qd.simulate_qd(None, args.dir, resume=True)
    run = RunDir(args.dir)
    config = run.load_config()
    checkpoint = run.read_checkpoint()
    if checkpoint is not None and checkpoint.phase == "done":
        print(f"run {args.dir} is complete; nothing to resume")
        return 0
    simulation = read_simulation_file(args.dir)
    replay = _replay_of(run)
    if simulation is not None:
        if args.pause_before_post:
            raise ConfigError(
                "a simulated run places its robots itself; the pause is for a lab's robots",
                key="--pause-before-post",
            )
        # A simulated run restarts its own simulated robots: no secret, no lab.
        assert config.experiment is not None
        return _simulate(
            config.experiment,
            args.dir,
            simulation.engine,
            simulation.realtime,
            args.verbose,
            resume=True,
            replay=replay,
        )
    secret = required_secret(config, run.file("config.yaml"))
    return _serve(Master(config, args.dir, secret=secret, resume=True), args)


def _replay_of(run: RunDir) -> ReplaySource | None:
    """The source of a replay being resumed (its simulated robots start where the source's
    did), None for an evolution or a source that is gone."""
    from master_service.replay import load_replay_source

    with contextlib.suppress(RunDirError):
        info = schema.read(run.path, Replay)
        if info is not None and info.source:
            return load_replay_source(info.source)
    return None


def _serve(master: Master, args: argparse.Namespace) -> int:
    level = logging.DEBUG if args.verbose else logging.INFO
    master.evolution.pause_before_post = args.pause_before_post
    console = hand_console(master.run_dir, master.log)
    master.evolution.pauses.console = True
    master.evolution.pauses.terminal = console
    try:
        with ProgressDisplay(level=level) as display:
            master.add_progress_listener(display.update)
            try:
                return asyncio.run(_serve_async(master, console))
            except FileWriteError:
                raise
            except OSError as exc:
                # Typically a busy port: nothing was created (the port is bound before the run
                # directory is touched).
                _log.error("surprise-master: %s", exc)
                return 1
    except FileWriteError as exc:
        return _write_failed(exc, master.run_dir.path, simulated=False)


def _write_failed(exc: FileWriteError, run_dir: Path, *, simulated: bool) -> int:
    """Say in one line (after the progress display is gone) which file could not be written,
    why, and how to go on; the exit status."""
    print(f"surprise-master: {exc}; {_next_step(exc, run_dir, simulated)}", file=sys.stderr)
    return 1


def _next_step(exc: FileWriteError, run_dir: Path, simulated: bool) -> str:
    if exc.errno in _NO_SPACE:
        remedy = "free some space"
    elif exc.errno in _NOT_WRITABLE:
        remedy = f"make {run_dir} writable"
    else:
        remedy = "put that right"
    run = RunDir(run_dir)
    needed = (CONFIG_SNAPSHOT, Simulation.FILE) if simulated else (CONFIG_SNAPSHOT,)
    if not all(run.file(name).is_file() for name in needed):
        # It stopped before it could be resumed.
        return f"{remedy} and start the run again (its --out must be empty)"
    with contextlib.suppress(OSError, RunDirError):
        checkpoint = run.read_checkpoint()
        if checkpoint is not None and checkpoint.phase == "done":
            # Every evaluation is in; what failed was the report at the end.
            return f"{remedy} and run `surprise-master report {run_dir}`"
    return f"{remedy} and run `surprise-master resume {run_dir}`"


async def _serve_async(master: Master, console: Console | None = None) -> int:
    task = asyncio.current_task()
    assert task is not None
    received: list[int] = []
    summary = None
    # The first signal stops the run cleanly (Bye to the robots, files closed); the checkpoint
    # is always current, so nothing is lost.
    reading = console.reading() if console is not None else contextlib.nullcontext()
    with cancelled_by_signal(task, received), reading:
        async with master:
            try:
                summary = await master.run()
            except asyncio.CancelledError:
                if not received:
                    raise
                task.uncancel()
                # Logged before the master closes, so that it lands in the run's log file too.
                master.log.warning(
                    "stopped by %s; continue with `surprise-master resume %s`",
                    signal.Signals(received[0]).name,
                    master.run_dir.path,
                )
    if summary is None:
        return 128 + received[0]
    best = "-" if summary.best_fitness is None else f"{summary.best_fitness:.4f}"
    print(
        f"run {summary.run_dir} done: {plural(summary.evaluations, 'evaluation')}, best fitness "
        f"{best}; "
        f"see `surprise-master report {summary.run_dir}`"
    )
    return 0


def _sim_experiment(args: argparse.Namespace, evaluations: int | None = None):
    from master_service.experiments.simulation_setup import setting_note, simulation_experiment

    for name in ("robots", "evaluations", "random"):
        value = getattr(args, name, None)
        if value is not None and value < 1:
            raise ConfigError(f"expected a positive number, got {value}", key=f"--{name}")
    if args.config is not None and args.setting is None and (note := setting_note(args.config)):
        print(note, file=sys.stderr)
    return simulation_experiment(
        args.scenario,
        setting=args.setting,
        arena=args.arena,
        config_file=args.config,
        robots=args.robots,
        evaluations=evaluations,
        seed=args.seed,
    )


def _default_out(kind: str, scenario: str) -> Path:
    return Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{kind}-{scenario}"


def _sim(args: argparse.Namespace) -> int:
    experiment = _sim_experiment(args, args.evaluations)
    if cli_qd.wants_map_elites(experiment, args.optimizer):
        if args.engine != "fast" or args.realtime:
            raise ConfigError("MAP-Elites runs on the compiled engine only", key="--engine")
        out = args.out or _default_out("qd", experiment.scenario)
        RunDir(out).check_new()
        return cli_qd.simulate_qd(experiment, out, resume=False)
    if args.realtime and args.engine != "agents":
        raise ConfigError("real time needs the agents: add --engine agents", key="--realtime")
    out = args.out or _default_out("sim", experiment.scenario)
    RunDir(out).check_new()
    return _simulate(experiment, out, args.engine, args.realtime, args.verbose, resume=False)


def _simulate(
    experiment: ExperimentConfig,
    out: Path,
    engine: str,
    realtime: bool,
    verbose: bool,
    *,
    resume: bool,
    replay: ReplaySource | None = None,
) -> int:
    """Run (or resume) a simulated experiment with its progress display; on SIGINT or SIGTERM
    stop at the next commit and say in one line where the run stands and how to go on."""
    from master_service.experiments.simulate import summary_text
    from reporting.reality_gap import gap_lines

    display = ProgressDisplay(level=logging.DEBUG if verbose else logging.INFO)
    if display.live and not verbose:
        # A simulated run counts dozens of evaluations a second: the panel shows the progress,
        # master.log keeps every line, the console only what needs a look.
        display.level = logging.WARNING
    received: list[int] = []
    try:
        result, started = _run_simulation(
            experiment, out, engine, realtime, display, received, resume=resume, replay=replay
        )
    except FileWriteError as exc:
        return _write_failed(exc, out, simulated=True)
    if result is None:
        print(_stopped_text(out, experiment, received[0]), file=sys.stderr)
        return 128 + received[0]
    print(summary_text(result.metrics, out, time.perf_counter() - started, resumed=resume))
    for line in gap_lines(result.metrics.get("reality_gap")):
        print(line)
    return 0


def _run_simulation(
    experiment: ExperimentConfig,
    out: Path,
    engine: str,
    realtime: bool,
    display: ProgressDisplay,
    received: list[int],
    *,
    resume: bool,
    replay: ReplaySource | None = None,
) -> tuple[SimulatedRun | None, float]:
    """The simulated run behind :func:`_simulate` with its display; the run (None when stopped
    by a signal, which ``received`` names) and when it started (``time.perf_counter``)."""
    from master_service.experiments.simulate import SimulatedSwarm, print_if_compiling, quiet_agents

    mode = "real time" if realtime else "lockstep"
    what = f"replaying {replay.path} for" if replay is not None else "simulating"
    print(
        f"{'resuming' if resume else what} {experiment.place} "
        f"({experiment.setting} setting, {engine} engine): {experiment.robots} robots, "
        f"{planned_text(experiment.evolution.evaluations)}"
        f" of {experiment.evaluation_steps} steps of {experiment.step_period:g} s, seed "
        f"{experiment.seed}" + (f", {mode}" if engine == "agents" else "")
    )
    compiling = print_if_compiling(engine)
    started = time.perf_counter()
    fast = None
    if engine == "fast":
        from master_service.experiments.engine_run import FastRun

        fast = FastRun(experiment, on_progress=display.update)
        if compiling:
            # Before the display starts a thread (it forks); a signal meanwhile stops the run
            # at its first evaluation's end, as it did while the first evaluation compiled.
            with stop_flag(received):
                fast.compile_ahead()
    with display, quiet_agents():
        if fast is not None:
            with stop_flag(received):
                result = fast.run(
                    out, resume=resume, should_stop=lambda: bool(received), replay=replay
                )
        else:
            swarm = SimulatedSwarm(experiment, realtime=realtime, on_progress=display.update)
            work = swarm.run(out, resume=resume, replay=replay)
            result = asyncio.run(until_signal(work, received))
    return result, started


def _stopped_text(out: Path, experiment: ExperimentConfig, signum: int) -> str:
    run = RunDir(out)
    state = run.read_state(run.load_config())
    done = 0 if state is None else state.optimizer.evaluations
    total = experiment.evolution.evaluations
    where = (
        f"stopped by {signal.Signals(signum).name} at evaluation {done}/{total or 'endless'}"
        if state is None or state.phase == "evolution"
        else f"stopped by {signal.Signals(signum).name} in the post-evaluation"
    )
    return f"{where}; continue with `surprise-master resume {out}`"


def _replay(args: argparse.Namespace) -> int:
    from master_service.replay import load_replay_source, replay_experiment

    if args.steps is not None and args.steps < 1:
        raise ConfigError(f"expected a positive number, got {args.steps}", key="--steps")
    source = load_replay_source(args.source)
    if args.config is not None:
        config = load_master_config(args.config)
        experiment = replay_experiment(source, config.experiment, args.steps)
        out = args.out or _default_out("replay", experiment.scenario)
        RunDir(out).check_new()
        config = msgspec.structs.replace(config, experiment=experiment)
        master = Master(config, out, secret=required_secret(config, args.config), replay=source)
        code = _serve(master, args)
        if code == 0:
            # The gap is what a replay is for: reported at once, as a simulated one is.
            from reporting.reality_gap import gap_lines
            from reporting.report import write_report

            for line in gap_lines(write_report(out).get("reality_gap")):
                print(line)
        return code
    if args.pause_before_post:
        raise ConfigError(
            "a simulated replay places its robots itself; the pause is for a lab's robots "
            "(with --config)",
            key="--pause-before-post",
        )
    chosen = load_experiment(args.experiment) if args.experiment is not None else None
    experiment = replay_experiment(source, chosen, args.steps)
    out = args.out or _default_out("replay", experiment.scenario)
    RunDir(out).check_new()
    return _simulate(experiment, out, args.engine, False, args.verbose, resume=False, replay=source)


def _baseline(args: argparse.Namespace) -> int:
    from master_service.experiments.baseline import run_baseline

    experiment = _sim_experiment(args)
    out = args.out or _default_out("baseline", experiment.scenario)
    steps = max(experiment.post_evaluation_steps, experiment.evaluation_steps)
    print(
        f"evaluating {plural(args.random, 'random pair')} in the {experiment.scenario} arena "
        f"({experiment.setting} setting, {experiment.robots} robots, {steps} steps each)"
    )
    data = run_baseline(experiment, args.random, out)
    counts = data["behaviour_counts"]
    print(
        f"fitness of the random pairs: best {data['best_fitness']:.4f}, median "
        f"{data['median_fitness']:.4f}"
    )
    print(
        "behaviour counts: "
        + "; ".join(
            f"{key} " + ", ".join(f"{n} {name}" for name, n in counts[key].items())
            for key in counts
        )
    )
    print(f"wrote {Path(out) / 'baseline.json'}")
    print(f"next: compare an evolved run with `surprise-master report RUN_DIR --baseline {out}`")
    return 0
