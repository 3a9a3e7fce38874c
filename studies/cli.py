"""``surprise-study``: many runs from one file, on this machine or a Dask cluster.

::

    surprise-study run STUDY.yaml --out DIR [--workers N | --scheduler ADDRESS | --slurm]
    surprise-study report DIR
    surprise-study status DIR
    surprise-study list

``run`` runs every run of the study that has not finished yet (a killed study run again goes
on where it stopped), on local worker processes (one per core, or ``--workers``) or on the Dask
cluster whose scheduler is at ``ADDRESS`` (``tcp://host:8786``; see the README for starting
``dask scheduler`` and ``dask worker`` on lab machines), or on workers in Slurm batch jobs
(``--slurm``, :mod:`studies.slurm`). ``report`` writes the tables, statistics and figures
(docs/studies.md). ``status`` tells where a study stands.

Exit codes: 0 done, 1 some runs failed (recorded; run again to retry them), 2 bad input (or no
scheduler at the address, or Slurm cannot start the workers), 3 stopped by a lost Dask
scheduler or a full disk (the runs not finished stay pending: run the same command again).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from minimize_surprise.errors import ClusterError, ConfigError
from minimize_surprise.text import plural

__all__ = ["main"]


def _positive(text: str) -> int:
    # argparse's type: a whole number of at least 1, or its own one-line error.
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, got {value}")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="surprise-study", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run (or go on with) a study")
    run.add_argument("study", help="the study file (YAML), or a shipped study's name (see `list`)")
    run.add_argument("--out", type=Path, required=True, help="the study's directory")
    run.add_argument(
        "--batch",
        type=_positive,
        default=None,
        metavar="N",
        help="evolved runs of one shape stepped together per worker, at most N (default 4; "
        "1: each run alone; docs/studies.md)",
    )
    where = run.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="local worker processes (default: one per core)")
    where.add_argument(
        "--scheduler", metavar="ADDRESS", help="a Dask scheduler's address, e.g. tcp://host:8786"
    )
    where.add_argument(
        "--local-cluster",
        action="store_true",
        help="a Dask LocalCluster on this machine (one worker process per core)",
    )
    where.add_argument(
        "--slurm",
        action="store_true",
        help="workers in Slurm batch jobs, as the study file's slurm: section and the "
        "--slurm-* options say (docs/studies.md)",
    )
    _slurm_arguments(run)
    run.set_defaults(handler=_run)
    report = sub.add_parser("report", help="tables, statistics and figures of a study")
    report.add_argument("dir", type=Path)
    report.set_defaults(handler=_report)
    shipped = sub.add_parser("list", help="the study files that come with the project")
    shipped.set_defaults(handler=_list)
    status = sub.add_parser("status", help="where a study stands")
    status.add_argument("dir", type=Path)
    status.set_defaults(handler=_status)
    return parser


#: The ``--slurm-*`` options: each overrides the study file's ``slurm:`` key of the same name.
_SLURM_OPTIONS = {
    "queue": ("PARTITION", str, "the partition the jobs go to"),
    "account": ("ACCOUNT", str, "the account the jobs are charged to"),
    "jobs": ("N", int, "how many batch jobs to submit"),
    "cores": ("N", int, "cores per job (a one-thread worker process on each)"),
    "memory": ("SIZE", str, "memory per job, e.g. 8GB"),
    "walltime": ("TIME", str, "the longest a job may run, e.g. 04:00:00"),
}


def _slurm_arguments(run: argparse.ArgumentParser) -> None:
    group = run.add_argument_group(
        "Slurm", "with --slurm; each overrides the key of the study file's slurm: section"
    )
    for name, (metavar, type_, text) in _SLURM_OPTIONS.items():
        group.add_argument(f"--slurm-{name}", metavar=metavar, type=type_, help=text)


def _slurm_executor(args: argparse.Namespace):
    from studies.runner import find_study
    from studies.slurm import start_slurm, with_overrides
    from studies.spec import load_study

    given = {name: getattr(args, f"slurm_{name}") for name in _SLURM_OPTIONS}
    if not args.slurm:
        for name, value in given.items():
            if value is not None:
                raise ConfigError("only with --slurm", key=f"--slurm-{name}")
        return None
    path = find_study(args.study)
    options = with_overrides(load_study(path).slurm, given, file=path)
    try:
        # Flushed: a study's output often goes to a file (nohup, tmux logs), where a line about
        # its jobs would otherwise wait in a buffer for hours.
        return start_slurm(options, args.out, say=lambda line: print(line, flush=True))
    except KeyboardInterrupt:  # start_slurm has cancelled the jobs
        raise ClusterError("stopped while waiting for the workers' jobs (cancelled)") from None


def _executor(args: argparse.Namespace):
    from studies.executors import DaskCluster, LocalPool

    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"expected a positive number, got {args.workers}", key="--workers")
    slurm = _slurm_executor(args)
    if slurm is not None:
        return slurm
    if args.scheduler:
        return DaskCluster(args.scheduler)
    if args.local_cluster:
        return DaskCluster(None, workers=args.workers)
    return LocalPool(args.workers)


def _run(args: argparse.Namespace) -> int:
    from studies.batches import BATCH_RUNS
    from studies.executors import SchedulerLostError
    from studies.progress import StudyProgress
    from studies.runner import prepare, run_study, study_status
    from studies.tasks import DiskFullError

    tasks = prepare(args.study, args.out)  # a bad study fails before any worker starts
    executor = _executor(args)
    print(f"study {args.out}: {plural(len(tasks), 'run')} on {plural(executor.workers, 'worker')}")
    started = time.monotonic()
    try:
        with StudyProgress() as progress:
            counts = run_study(
                args.study,
                args.out,
                executor,
                on_update=progress.update,
                on_notice=print,
                batch=args.batch or BATCH_RUNS,
            )
    except KeyboardInterrupt:
        print(f"stopped: run `surprise-study run {args.study} --out {args.out}` to go on")
        return 130
    except (SchedulerLostError, DiskFullError) as exc:
        status = study_status(args.out)
        left = status["runs"] - status["done"]
        print(f"surprise-study: {exc} ({left} of {status['runs']} runs pending)", file=sys.stderr)
        return 3
    finally:
        executor.close()
    print(
        f"study {args.out}: {counts.done}/{plural(counts.total, 'run')} done "
        f"({counts.skipped} from before), "
        f"{counts.failed} failed, {time.monotonic() - started:.0f} s; "
        f"see `surprise-study report {args.out}`"
    )
    for failure in counts.failures[:10]:
        print(f"  failed: {failure.get('run')}: {failure.get('error')}")
    return 1 if counts.failed else 0


def _report(args: argparse.Namespace) -> int:
    from studies.report import write_study_report

    result = write_study_report(args.dir)
    print(
        f"wrote {result['report']}: {result['done']} of {result['runs']} runs, "
        f"{result['groups']} groups, {result['tests']} tests, {len(result['figures'])} figure files"
    )
    for line in result["problems"]:  # also in the report's problems.txt
        print(f"  left out: {line}")
    for row in result["recovery"]:  # also in the report's recovery.md
        drop = "-" if row["median_drop"] is None else f"{row['median_drop']:.4f}"
        back = "-" if row["median_recovery"] is None else f"{row['median_recovery']:g}"
        print(
            f"  {row['group']}, {row['detail']}: median drop {drop}, recovered "
            f"{row['recovered']}/{row['runs']}, median recovery {back} evaluations"
        )
    return 0


def _list(args: argparse.Namespace) -> int:
    from studies.runner import shipped_studies
    from studies.spec import load_study

    for name, path in shipped_studies().items():
        print(f"{name}: {load_study(path).description} ({path})")
    return 0


def _status(args: argparse.Namespace) -> int:
    from studies.runner import study_status

    status = study_status(args.dir)
    runs = plural(status["runs"], "run")
    print(f"{args.dir}: {status['done']}/{runs} done, {status['failed']} failed")
    for name, group in status["groups"].items():
        left = group["runs"] - group["done"] - group["failed"]
        print(
            f"  {name} ({group['kind']}): {group['done']}/{plural(group['runs'], 'run')} done, "
            f"{group['failed']} failed, {left} not run"
        )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``surprise-study``; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        return args.handler(args)
    except (ConfigError, OSError) as exc:
        print(f"surprise-study: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
