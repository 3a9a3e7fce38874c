"""``surprise-master sim --optimizer map-elites``: quality diversity on the compiled engine.

MAP-Elites through pyribs (``ribs``: a grid archive, iso-line or Gaussian emitters, a scheduler
asked for a batch and told its results). Each batch of candidates is evaluated in one compiled
call (:func:`simulator.engine.evaluate_swarms`, one swarm a candidate), every candidate from an
arena freshly placed with a seed of its own (the run's seed and the evaluation's index), its
fitness the swarm's prediction accuracy as in the (1+1) and its measures computed from its
trace with the functions the paper's classification uses (:func:`trace_behaviour`). The archive
keeps, per cell, the fittest genome with its measures and its behaviour class.

The run directory (``runfiles.schema``: ``qd.json``, ``archive.csv``, ``qd_progress.csv``,
``qd_checkpoint.pkl``, ``plots/``, ``elites/<class>/``): the checkpoint is the pickled
scheduler (archive, emitters and their random numbers) after a whole batch, so a stopped run
resumes to the result it would have had. At the end each behaviour class's best elite is
post-evaluated as a run's best genome is (a replay run, :class:`~master_service.experiments.
engine_run.FastRun`, in ``elites/<class>/``). docs/quality-diversity.md says more.
"""

from __future__ import annotations

import csv
import io
import json
import math
import pickle
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import msgspec
import numpy as np

from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulation_setup import simulated_safety, world_config
from master_service.replay import ReplaySource
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import ConfigError
from minimize_surprise.network import GenomeLayout, spec_from_config
from minimize_surprise.optimizer import OptimizerConfig
from runfiles import schema
from runfiles.schema import (
    ARCHIVE,
    PLOTS,
    QD_CHECKPOINT,
    QD_ELITES,
    QD_PROGRESS,
    QD_PROGRESS_COLUMNS,
    QDElite,
    QDSummary,
)
from simulator import metrics as sm
from simulator.engine import EvaluationRecord, Swarm, evaluate_swarms

__all__ = [
    "CHECKPOINT_INTERVAL",
    "QDResult",
    "QDRun",
    "behaviour_class",
    "class_slug",
    "qd_experiment",
    "trace_behaviour",
]

#: Seconds between two checkpoints at most (and one after the last batch).
CHECKPOINT_INTERVAL: Final = 2.0
_CHECKPOINT_FORMAT: Final = 1
#: The trace's measures every elite keeps, whichever of them span the grid.
_KEPT: Final = ("rotation", "mean_cluster_size", "distance_covered", "backward_share")


def behaviour_class(behaviour: dict[str, Any]) -> str:
    """The paper's class of a behaviour (a run's ``behaviour`` metrics, or
    :func:`trace_behaviour`'s): the object-manipulation class with boxes, else
    ``motion/grouping`` (``stopped/grouped``, ...), as a study's tables name it."""
    if behaviour.get("manipulation") is not None:
        return str(behaviour["manipulation"])
    return f"{behaviour['motion']}/{behaviour['grouping']}"


def class_slug(name: str) -> str:
    """A class's name as a directory name: ``stopped/grouped`` is ``stopped-grouped``,
    ``reverse driving`` is ``reverse-driving``."""
    return "-".join(name.replace("/", " ").split())


def trace_behaviour(
    poses: np.ndarray,
    box_start: np.ndarray | None,
    box_end: np.ndarray | None,
    dt: float,
    *,
    wanted: tuple[str, ...] = ("distance_covered", "backward_share"),
) -> dict[str, Any]:
    """An evaluation's measures and class from its poses (steps, robots, 3) and boxes.

    c_o is summed over the paper's window (:func:`~simulator.metrics.default_window`: for an
    evaluation shorter than 100 s, its second half) and scaled to the paper's 50 s, so that
    its thresholds (5 and 55 rad) classify an evaluation of any length; the rest as the
    paper's classification computes them. d_R and the backward share are computed when
    ``wanted`` names them or with boxes (the manipulation classes need the backward share),
    else NaN: an arena without boxes classifies on c_o and the cluster size alone.
    """
    window = sm.default_window(poses, dt)
    seconds = max(window, 1) * dt
    c_o = sm.rotation(poses, window) * sm.WINDOW_SECONDS / seconds
    size = sm.mean_cluster_size(poses, window)
    boxes = box_start is not None and box_end is not None
    backward = sm.backward_share(poses) if boxes or "backward_share" in wanted else math.nan
    covered = sm.distance_covered(poses) if boxes or "distance_covered" in wanted else math.nan
    motion = sm.classify_motion(c_o)
    d_b = sm.box_displacement(box_start, box_end) if boxes else None  # type: ignore[arg-type]
    return {
        "rotation": c_o,
        "mean_cluster_size": size,
        "distance_covered": covered,
        "backward_share": backward,
        "box_displacement": d_b,
        "motion": motion,
        "grouping": sm.classify_grouping(size),
        "manipulation": None if d_b is None else sm.classify_manipulation(d_b, backward, motion),
    }


def qd_experiment(experiment: ExperimentConfig) -> tuple[ExperimentConfig, OptimizerConfig]:
    """The experiment of a MAP-Elites run and its optimizer section (the section's defaults
    when the experiment has none); a measure the arena cannot give (d_B without boxes) is a
    :class:`ConfigError` naming its key."""
    optimizer = experiment.optimizer or OptimizerConfig()
    optimizer = msgspec.structs.replace(optimizer, name="map-elites")
    if experiment.evolution.evaluations is None:
        raise ConfigError(
            "MAP-Elites needs a budget: give the number of evaluations",
            key="evolution.evaluations",
        )
    if experiment.events:
        raise ConfigError(
            "MAP-Elites evaluates every candidate in an arena of its own: an arena that changes "
            "is for the (1+1)'s online evolution (docs/changing-arenas.md)",
            key="events",
        )
    boxes = world_config(experiment).boxes
    for index, measure in enumerate(optimizer.measures):
        if measure.name == "box_displacement" and not boxes:
            raise ConfigError(
                f"d_B needs boxes; the {experiment.place} arena has none",
                key=f"optimizer.measures[{index}].name",
            )
    return msgspec.structs.replace(experiment, optimizer=optimizer), optimizer


@dataclass(frozen=True)
class QDResult:
    """What a finished MAP-Elites run leaves: its summary (``qd.json``) and run directory."""

    summary: QDSummary
    run_dir: Path


class QDRun:
    """One MAP-Elites run on the engine, into a run directory (see the module docstring).

    ``on_batch`` sees (evaluations done, evaluations in all) after every batch.
    """

    def __init__(
        self,
        experiment: ExperimentConfig,
        *,
        on_batch: Callable[[int, int], None] | None = None,
    ) -> None:
        self.experiment, self.optimizer = qd_experiment(experiment)
        self.on_batch = on_batch
        self.spec = spec_from_config(experiment)
        self.size = GenomeLayout(self.spec).size
        self.batch = self.optimizer.batch * self.optimizer.emitters
        evaluations = self.experiment.evolution.evaluations
        assert evaluations is not None  # qd_experiment refuses an endless run
        self.batches = math.ceil(evaluations / self.batch)
        world, safety = world_config(experiment), simulated_safety(experiment)
        self.swarms = [Swarm(world, safety, self.spec, experiment.seed) for _ in range(self.batch)]
        self._safety = self.swarms[0].safety.copy()
        self.has_boxes = bool(world.boxes)
        self._wanted = tuple(m.name for m in self.optimizer.measures)
        #: seconds of the compiled calls alone, and the robot-steps they ran (the benchmark's)
        self.engine_seconds = 0.0
        self.robot_steps = 0

    # ------------------------------------------------------------------ the optimizer

    def _scheduler(self) -> Any:
        from ribs.archives import GridArchive
        from ribs.emitters import GaussianEmitter, IsoLineEmitter
        from ribs.schedulers import Scheduler

        o, seed = self.optimizer, self.experiment.seed
        fields: dict[str, Any] = {name: ((), np.float64) for name in _KEPT} | {
            "box_displacement": ((), np.float64),
            "arena_seed": ((), np.int64),
            "klass": ((), np.int64),
        }
        archive = GridArchive(
            solution_dim=self.size,
            dims=[m.bins for m in o.measures],
            ranges=[m.range for m in o.measures],
            seed=seed,
            extra_fields=fields,
        )
        initial = o.initial_range
        if initial is None:
            initial = self.experiment.evolution.initial_range
        rng = np.random.default_rng(seed)
        emitters: list[Any] = []
        for k in range(o.emitters):
            first = rng.uniform(-initial, initial, (o.batch, self.size))
            if o.emitter == "iso-line":
                emitter: Any = IsoLineEmitter(
                    archive, iso_sigma=o.sigma, line_sigma=o.line_sigma,
                    initial_solutions=first, batch_size=o.batch, seed=seed * 1009 + k,
                )  # fmt: skip
            else:
                emitter = GaussianEmitter(
                    archive, sigma=o.sigma, initial_solutions=first, batch_size=o.batch,
                    seed=seed * 1009 + k,
                )  # fmt: skip
            emitters.append(emitter)
        return Scheduler(archive, emitters)

    # ------------------------------------------------------------------ evaluation

    def arena_seed(self, evaluation: int) -> int:
        """The arena seed of the run's ``evaluation``-th candidate (0-based)."""
        return int(np.random.SeedSequence([self.experiment.seed, evaluation]).generate_state(1)[0])

    def evaluate(self, genomes: np.ndarray, first: int) -> tuple[np.ndarray, list[dict[str, Any]]]:
        """Evaluate ``genomes`` (the candidates ``first``, ``first + 1``, ...) in one compiled
        call, each in its own freshly placed arena; their fitness and behaviours."""
        swarms = self.swarms[: len(genomes)]
        seeds = [self.arena_seed(first + i) for i in range(len(genomes))]
        starts = []
        for swarm, seed in zip(swarms, seeds, strict=True):
            swarm.world.reset(seed=seed)
            swarm.safety[:] = self._safety
            starts.append(swarm.world.box_positions.copy())
        steps = self.experiment.evaluation_steps
        began = time.perf_counter()
        records: list[EvaluationRecord] = evaluate_swarms(
            swarms, list(genomes), steps, record="poses"
        )
        self.engine_seconds += time.perf_counter() - began
        self.robot_steps += steps * len(swarms) * len(swarms[0].ids)
        fitness = np.array([float(np.mean(r.fitness)) for r in records])
        behaviours = []
        for swarm, record, start, seed in zip(swarms, records, starts, seeds, strict=True):
            assert record.poses is not None
            end = swarm.world.box_positions.copy() if self.has_boxes else None
            b = trace_behaviour(
                record.poses,
                start if self.has_boxes else None,
                end,
                self.experiment.step_period,
                wanted=self._wanted,
            )
            b["arena_seed"] = seed
            behaviours.append(b)
        return fitness, behaviours

    # ------------------------------------------------------------------ the run

    def run(
        self,
        run_dir: str | Path,
        *,
        plots: bool = True,
        resume: bool = False,
        should_stop: Callable[[], bool] | None = None,
        post_evaluate: bool = True,
    ) -> QDResult | None:
        """Evolve the archive into ``run_dir`` (new or empty; with ``resume`` from its
        checkpoint), write its files and post-evaluate each class's best elite; None when
        ``should_stop`` answered true between two batches (resume it later)."""
        path = Path(run_dir)
        began = time.perf_counter()
        if resume:
            scheduler, done, progress, classes = self._load(path)
        else:
            if path.exists() and any(path.iterdir()):
                raise ConfigError(f"{path} is not empty: a new run needs a new directory")
            path.mkdir(parents=True, exist_ok=True)
            schema.write(path, QDSummary(experiment=self.experiment))
            scheduler, done, progress, classes = self._scheduler(), 0, [], []
        last = time.monotonic()
        while done < self.batches:
            if should_stop is not None and should_stop():
                self._checkpoint(path, scheduler, done, progress, classes)
                return None
            genomes = scheduler.ask()
            fitness, behaviours = self.evaluate(genomes, done * self.batch)
            klass = []
            for b in behaviours:
                name = behaviour_class(b)
                if name not in classes:
                    classes.append(name)
                klass.append(classes.index(name))
            scheduler.tell(
                fitness,
                np.array([[b[m.name] for m in self.optimizer.measures] for b in behaviours]),
                **{name: np.array([b[name] for b in behaviours]) for name in _KEPT},
                box_displacement=np.array([b["box_displacement"] or 0.0 for b in behaviours]),
                arena_seed=np.array([b["arena_seed"] for b in behaviours], dtype=np.int64),
                klass=np.array(klass, dtype=np.int64),
            )
            done += 1
            progress.append(self._progress_row(scheduler.archive, done * self.batch, classes))
            if self.on_batch is not None:
                self.on_batch(done * self.batch, self.batches * self.batch)
            if time.monotonic() - last >= CHECKPOINT_INTERVAL:
                self._checkpoint(path, scheduler, done, progress, classes)
                last = time.monotonic()
        self._checkpoint(path, scheduler, done, progress, classes)
        return self._finish(path, scheduler.archive, progress, classes, plots, post_evaluate,
                            time.perf_counter() - began)  # fmt: skip

    def _progress_row(self, archive: Any, evaluations: int, classes: list[str]) -> list[Any]:
        stats = archive.stats
        held = len(set(archive.data("klass").tolist())) if stats.num_elites else 0
        best = float(stats.obj_max) if stats.num_elites else float("nan")
        return [evaluations, float(stats.coverage), float(stats.qd_score), best, held]

    def _checkpoint(
        self, path: Path, scheduler: Any, done: int, progress: list[Any], classes: list[str]
    ) -> None:
        data = {
            "format": _CHECKPOINT_FORMAT,
            "batches": done,
            "scheduler": scheduler,
            "progress": progress,
            "classes": classes,
        }
        schema.write_atomic(path / QD_CHECKPOINT, pickle.dumps(data))

    def _load(self, path: Path) -> tuple[Any, int, list[Any], list[str]]:
        try:
            data = pickle.loads((path / QD_CHECKPOINT).read_bytes())
        except FileNotFoundError:
            if not (path / QDSummary.FILE).exists():
                raise ConfigError(f"{path} is not a MAP-Elites run: nothing to resume") from None
            # Stopped before its first checkpoint: nothing was done, so it starts afresh.
            return self._scheduler(), 0, [], []
        if data.get("format") != _CHECKPOINT_FORMAT:
            raise ConfigError(f"{path / QD_CHECKPOINT}: a checkpoint of another format")
        return data["scheduler"], data["batches"], data["progress"], data["classes"]

    # ------------------------------------------------------------------ outputs

    def _finish(
        self,
        path: Path,
        archive: Any,
        progress: list[Any],
        classes: list[str],
        plots: bool,
        post_evaluate: bool,
        seconds: float,
    ) -> QDResult:
        rows = archive_rows(archive, self.optimizer, classes)
        _write_csv(
            path / ARCHIVE, list(rows[0]) if rows else ["cell"], [list(r.values()) for r in rows]
        )
        _write_csv(path / QD_PROGRESS, list(QD_PROGRESS_COLUMNS), progress)
        best: dict[str, dict[str, Any]] = {}
        for row in rows:
            name = row["class"]
            if name not in best or row["fitness"] > best[name]["fitness"]:
                best[name] = row
        elites: dict[str, QDElite] = {}
        if post_evaluate:
            shutil.rmtree(path / QD_ELITES, ignore_errors=True)  # a killed run's half-done
        for name in sorted(best):
            row = best[name]
            # Those computed (trace_behaviour leaves what the arena's classes need not NaN).
            measures = {m: row[m] for m in (*_KEPT, "box_displacement") if not math.isnan(row[m])}
            elite = QDElite(fitness=float(row["fitness"]), measures=measures)
            if post_evaluate:
                elite = self._post_evaluate(path, name, row, elite)
            elites[name] = elite
        stats = archive.stats
        summary = QDSummary(
            experiment=self.experiment,
            done=True,
            evaluations=self.batches * self.batch,
            cells=int(stats.num_elites),
            coverage=float(stats.coverage),
            qd_score=float(stats.qd_score),
            seconds=seconds,
            classes=elites,
        )
        if plots:
            self._draw(path, archive, progress)
        schema.write(path, summary)
        return QDResult(summary, path)

    def redraw(self, run_dir: str | Path) -> list[Path]:
        """Draw a finished run's figures again from its checkpoint; the files written."""
        scheduler, _, progress, _ = self._load(Path(run_dir))
        return self._draw(Path(run_dir), scheduler.archive, progress)

    def _draw(self, path: Path, archive: Any, progress: list[Any]) -> list[Path]:
        from master_service.experiments.qd_figures import draw_heatmap, draw_progress

        (path / PLOTS).mkdir(exist_ok=True)
        drawn = draw_heatmap(path / PLOTS / "qd_heatmap", archive, self.optimizer)
        return drawn + draw_progress(path / PLOTS / "qd_progress", progress)

    def _post_evaluate(self, path: Path, name: str, row: dict[str, Any], elite: QDElite) -> QDElite:
        # As a run's best genome: a replay of the same experiment, from the arena the (1+1)'s
        # post-evaluation starts from.
        directory = path / QD_ELITES / class_slug(name)
        genome = np.array(json.loads(row["genome"]), dtype=np.float64)
        source = ReplaySource(genome, self.spec, path / ARCHIVE, float(row["fitness"]))
        plain = msgspec.structs.replace(self.experiment, optimizer=None)
        result = FastRun(plain).run(directory, plots=False, replay=source)
        assert result is not None
        post = result.metrics.get("post_evaluation") or {}
        behaviour = post.get("behaviour") or result.metrics.get("behaviour")
        return msgspec.structs.replace(
            elite,
            directory=str(directory.relative_to(path)),
            post_fitness=result.summary.post_evaluation_fitness,
            post_class=None if behaviour is None else behaviour_class(behaviour),
        )


def archive_rows(
    archive: Any, optimizer: OptimizerConfig, classes: list[str]
) -> list[dict[str, Any]]:
    """The archive's elites as rows: cell, fitness, the grid's measures, every kept measure,
    class, the arena seed it was evaluated in and its genome (a JSON list); by cell."""
    if not archive.stats.num_elites:
        return []
    data = archive.data()
    order = np.argsort(data["index"])
    rows = []
    for i in order:
        row: dict[str, Any] = {
            "cell": int(data["index"][i]),
            "fitness": float(data["objective"][i]),
        }
        for k, m in enumerate(optimizer.measures):
            row[f"grid.{m.name}"] = float(data["measures"][i][k])
        for name in (*_KEPT, "box_displacement"):
            row[name] = float(data[name][i])
        row["class"] = classes[int(data["klass"][i])]
        row["arena_seed"] = int(data["arena_seed"][i])
        row["genome"] = json.dumps([float(g) for g in data["solution"][i]])
        rows.append(row)
    return rows


def _write_csv(path: Path, header: list[str], rows: list[list[Any]]) -> None:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    schema.write_atomic(path, out.getvalue().encode())
