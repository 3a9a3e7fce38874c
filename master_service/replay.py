"""A stored genome driven again, without evolution: ``surprise-master replay`` (docs/runs.md).

A replay is a run that starts at its post-evaluation: its checkpoint holds the genome as the best
one and the phase ``post-evaluation``, so the one evolution loop runs it as it runs any
post-evaluation (traces, ``post_evaluation.json``, resume after a stop), on whatever evaluates
it: simulated robots, Aseba Playground's or real ones. ``replay.json`` names where the genome came
from, so that ``report`` puts the replay beside that run's own post-evaluation: the reality gap
(:mod:`reporting.reality_gap`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np

from master_service.rundir import RunDir, RunDirError
from minimize_surprise.config import ExperimentConfig
from minimize_surprise.errors import ConfigError
from minimize_surprise.network import GenomeLayout, NetworkSpec, spec_from_config
from runfiles import schema
from runfiles.schema import CONFIG_SNAPSHOT, BestGenome, Replay, Simulation

__all__ = [
    "ReplaySource",
    "check_spec",
    "load_replay_source",
    "replay_experiment",
    "write_replay_file",
]


@dataclass(frozen=True)
class ReplaySource:
    """The genome to replay, its network shape, and what is known of where it came from:
    ``run_dir`` (None for a bare genome file) and that run's ``experiment``."""

    genome: np.ndarray
    spec: NetworkSpec
    path: Path
    fitness: float | None
    run_dir: Path | None = None
    experiment: ExperimentConfig | None = None
    #: a simulated source's safety states when its post-evaluation began, robot by robot
    safety_before: list[list[int]] | None = None

    def safety_for(self, robots: int) -> list[list[int]] | None:
        """The source's safety states for a simulated replay of ``robots`` robots, so that the
        escape profile's random turns go on as in the source's post-evaluation; None when the
        source has none or another number of robots."""
        if self.safety_before is None or len(self.safety_before) != robots:
            return None
        return self.safety_before

    def to_file(self) -> Replay:
        """``replay.json`` of a replay of this source."""
        return Replay(
            source=str(self.path.resolve()),
            source_run=None if self.run_dir is None else str(self.run_dir.resolve()),
            genome_fitness=self.fitness,
        )


def load_replay_source(path: str | Path) -> ReplaySource:
    """The genome of a run directory (its ``best_genome.json``) or of a genome file in that
    format; :class:`RunDirError` naming the file when it holds none."""
    path = Path(path)
    run_dir = path if path.is_dir() else None
    genome_file = path / BestGenome.FILE if run_dir is not None else path
    try:
        best = schema.decode(BestGenome, genome_file.read_bytes(), name=str(genome_file))
    except FileNotFoundError:
        raise RunDirError(f"{genome_file} does not exist: no genome to replay") from None
    except OSError as exc:
        raise RunDirError(f"{genome_file} cannot be read: {exc}") from None
    except RunDirError as exc:
        raise RunDirError(f"no genome to replay: {exc}") from None
    spec = best.spec
    genome = np.array(best.genome, dtype=np.float64)
    fitness = best.fitness
    if genome.shape != (GenomeLayout(spec).size,):
        raise RunDirError(
            f"{genome_file}: {genome.size} genome values for a network of {GenomeLayout(spec).size}"
        )
    experiment = None
    safety = None
    if run_dir is not None and (run_dir / CONFIG_SNAPSHOT).exists():
        experiment = RunDir(run_dir).load_config().experiment
        simulation = schema.read(run_dir, Simulation)
        if simulation is not None:
            safety = simulation.post_evaluation_safety
    return ReplaySource(genome, spec, path, fitness, run_dir, experiment, safety)


def write_replay_file(run_dir: RunDir, source: ReplaySource) -> None:
    """Write ``replay.json`` into a new replay's directory."""
    schema.write(run_dir.path, source.to_file())


def check_spec(source: ReplaySource, experiment: ExperimentConfig) -> None:
    """Refuse a replay whose genome does not fit the experiment's networks (other sensors, other
    hidden layers): :class:`RunDirError` naming what differs."""
    spec = spec_from_config(experiment)
    if spec != source.spec:
        mine, theirs = msgspec.structs.asdict(source.spec), msgspec.structs.asdict(spec)
        differ = ", ".join(
            f"{key} {mine[key]!r} (genome) against {theirs[key]!r} (experiment)"
            for key in mine
            if mine[key] != theirs[key]
        )
        raise RunDirError(
            f"the genome of {source.path} does not fit the experiment's networks: {differ}"
        )


def replay_experiment(
    source: ReplaySource, experiment: ExperimentConfig | None, steps: int | None
) -> ExperimentConfig:
    """The experiment a replay runs: ``experiment`` (a lab's file) or the source run's, with
    ``steps`` post-evaluation steps (default: the experiment's own)."""
    chosen = experiment if experiment is not None else source.experiment
    if chosen is None:
        raise RunDirError(
            f"{source.path} is a genome without an experiment: name one (--config or --experiment)"
        )
    if steps is not None:
        data = msgspec.to_builtins(chosen) | {"post_evaluation_steps": steps}
        try:
            # Decoded again, so the experiment's own bounds hold for the new length too.
            chosen = msgspec.convert(data, ExperimentConfig)
        except msgspec.ValidationError as exc:
            raise ConfigError(f"{steps} steps cannot be replayed: {exc}", key="--steps") from None
    check_spec(source, chosen)
    return chosen
