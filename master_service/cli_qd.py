"""``surprise-master sim --optimizer map-elites`` and ``resume`` of such a run: the command
line's side of quality diversity (:mod:`master_service.experiments.qd_run`,
docs/quality-diversity.md), kept out of ``cli`` so that it stays one page of subcommands."""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path

from master_service.stopping import stop_flag
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import ConfigError
from minimize_surprise.text import plural
from runfiles import schema
from runfiles.schema import ARCHIVE, PLOTS, QD_ELITES, QD_PROGRESS, QDSummary

__all__ = ["is_qd_run", "report_qd", "simulate_qd", "summary_lines", "wants_map_elites"]

#: Seconds between two progress lines at the least.
_EVERY = 5.0


def wants_map_elites(experiment: ExperimentConfig, option: str | None) -> bool:
    """Whether ``sim`` runs MAP-Elites: ``--optimizer`` says so, or, without it, the
    experiment's ``optimizer.name``."""
    if option is not None:
        return option == "map-elites"
    return experiment.optimizer is not None and experiment.optimizer.name == "map-elites"


def is_qd_run(run_dir: str | Path) -> bool:
    """Whether ``run_dir`` is a MAP-Elites run's directory (it has ``qd.json``)."""
    return (Path(run_dir) / QDSummary.FILE).exists()


def simulate_qd(experiment: ExperimentConfig | None, out: Path, *, resume: bool) -> int:
    """Run (``experiment``) or resume (``experiment`` None: the one in ``out``'s ``qd.json``)
    a MAP-Elites run into ``out`` with progress lines; on SIGINT or SIGTERM stop after the
    batch, checkpointed, and say how to go on. The exit status."""
    from master_service.experiments.qd_run import QDRun

    if experiment is None:
        stored = schema.read(out, QDSummary)
        if stored is None:
            raise ConfigError(f"{out} holds no {QDSummary.FILE}: not a MAP-Elites run")
        if stored.done:
            print(f"run {out} is complete; nothing to resume")
            return 0
        experiment = stored.experiment
    last = [time.monotonic()]

    def progress(done: int, total: int) -> None:
        if time.monotonic() - last[0] >= _EVERY or done == total:
            last[0] = time.monotonic()
            print(f"  {done}/{total} evaluations", file=sys.stderr)

    run = QDRun(experiment, on_batch=progress)
    o = run.optimizer
    print(
        f"{'resuming' if resume else 'MAP-Elites in'} {experiment.place} ({experiment.setting} "
        f"setting): {experiment.robots} robots, {plural(run.batches * run.batch, 'evaluation')} "
        f"in batches of {run.batch}, {experiment.evaluation_steps} steps each, grid "
        + " x ".join(f"{m.name} {m.bins}" for m in o.measures)
        + f", seed {experiment.seed}"
    )
    received: list[int] = []
    began = time.perf_counter()
    with stop_flag(received):
        result = run.run(out, resume=resume, should_stop=lambda: bool(received))
    if result is None:
        name = signal.Signals(received[0]).name
        print(f"stopped by {name}; continue with `surprise-master resume {out}`", file=sys.stderr)
        return 128 + received[0]
    for line in summary_lines(result.summary, out, time.perf_counter() - began):
        print(line)
    return 0


def report_qd(run_dir: Path) -> int:
    """``surprise-master report`` of a MAP-Elites run: its figures drawn again from its
    checkpoint and its summary printed (a run not finished says how to go on)."""
    from master_service.experiments.qd_run import QDRun

    summary = schema.read(run_dir, QDSummary)
    if summary is None or not summary.done:
        print(f"run {run_dir} has not finished; continue with `surprise-master resume {run_dir}`")
        return 0
    drawn = QDRun(summary.experiment).redraw(run_dir)
    for line in summary_lines(summary, run_dir, summary.seconds):
        print(line)
    print(f"drew {', '.join(str(path) for path in drawn)}")
    return 0


def summary_lines(summary: QDSummary, out: Path, seconds: float) -> list[str]:
    """What a finished MAP-Elites run says: its archive, each class's best elite and its
    post-evaluation, and where its files are."""
    lines = [
        f"run {out} done in {seconds:.1f} s: {plural(summary.evaluations, 'evaluation')}, "
        f"{summary.cells} elites (coverage {summary.coverage:.3f}), QD score "
        f"{summary.qd_score:.2f}, {plural(len(summary.classes), 'class', 'classes')}:"
    ]
    for name, elite in summary.classes.items():
        post = ""
        if elite.post_fitness is not None:
            post = f"; post-evaluated {elite.post_fitness:.4f}, {elite.post_class}"
        lines.append(f"  {name}: best elite {elite.fitness:.4f}{post}")
    lines.append(
        f"files: {ARCHIVE}, {QD_PROGRESS}, {PLOTS}/qd_heatmap.png, {PLOTS}/qd_progress.png, "
        f"{QD_ELITES}/<class>/ (each a replay: `surprise-master report {out}/{QD_ELITES}/...`)"
    )
    return lines
