"""A simulated post-evaluation filmed by the synthetic overhead camera, shared by the tracking
tests (the fixture ``filmed`` in conftest.py): a short lab-setting run of the boxes scenario (4
robots, 271 boxes), its 30 s post-evaluation rendered at 1280x720 and 10 frames a second (one
frame per step), robot sim-1's marker covered from 3 s to 5 s, the LEDs flashing for 0.3 s at the
start after 1 s of standing."""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import msgspec
import numpy as np

from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulation_setup import simulation_experiment
from runfiles import schema
from runfiles.schema import BOX_TRACK, Simulation
from standins.overhead_camera import OverheadScene, OverheadVideo
from tracking.config import CameraSettings, RobotMarkers, TrackingConfig
from tracking.video import TrackResult, track_frames

ROBOTS = ("sim-0", "sim-1", "sim-2", "sim-3")
MARKERS = (10, 11, 12, 13)
STEPS = 300
HIDDEN = (1, 3.0, 5.0)
PRE_ROLL = 1.0


@dataclass(frozen=True)
class Filmed:
    """The simulated run, what the camera saw and what the tracker made of it."""

    run: Path
    poses: np.ndarray  # (steps, robots, 3): the simulator's
    boxes_start: np.ndarray
    boxes_end: np.ndarray
    video: OverheadVideo
    config: TrackingConfig
    result: TrackResult


def tracking_config(**robots: object) -> TrackingConfig:
    """The tracking configuration that matches the synthetic camera's scene."""
    markers = RobotMarkers(offset=(0.02, 0.0), ids=dict(zip(ROBOTS, MARKERS, strict=True)))
    return TrackingConfig(
        floor=(1.3, 1.3),
        robots=msgspec.structs.replace(markers, **robots),
        camera=CameraSettings(height=2.0),
    )


def scene(**changes: object) -> OverheadScene:
    """The synthetic camera's scene of the tests, with ``changes``."""
    base = OverheadScene(robots=ROBOTS, markers=MARKERS, marker_offset=(0.02, 0.0))
    return replace(base, **changes)  # type: ignore[arg-type]


def film(where: Path) -> Filmed:
    """Simulate the run in ``where``, film its post-evaluation and track the film (in memory)."""
    experiment = simulation_experiment("boxes", setting="lab", evaluations=3, seed=1)
    experiment = msgspec.structs.replace(
        experiment, evaluation_steps=20, post_evaluation_steps=STEPS
    )
    run = where / "simulated"
    FastRun(experiment).run(run, plots=False)
    poses = np.stack(
        [np.load(run / "traces" / f"{robot}.npz")["poses"] for robot in ROBOTS], axis=1
    )
    simulation = schema.read(run, Simulation)
    assert simulation is not None and simulation.post_evaluation_boxes is not None
    start = np.array(simulation.post_evaluation_boxes.start)
    end = np.array(simulation.post_evaluation_boxes.end)
    with np.load(run / BOX_TRACK) as track:
        frames, every = track["positions"], int(track["every"])
    video = OverheadVideo(
        scene(),
        poses,
        np.concatenate([frames, end[None]]),
        box_every=every,
        pre_roll=PRE_ROLL,
        hidden=[HIDDEN],
        seed=3,
    )
    config = tracking_config()
    result = track_frames(
        video.frames(), config, name="synthetic", duration=STEPS * 0.1, boxes=True
    )
    return Filmed(run, poses, start, end, video, config, result)


def as_real(run: Path, where: Path) -> Path:
    """The simulated run as a real one looks: no poses in its traces, no simulation files."""
    real = where / "real"
    shutil.copytree(run, real)
    for name in ("simulation.json", "box_track.npz", "metrics.json"):
        (real / name).unlink(missing_ok=True)
    shutil.rmtree(real / "plots", ignore_errors=True)
    for path in (real / "traces").iterdir():
        with np.load(path) as data:
            arrays = {key: data[key] for key in data.files if key != "poses"}
        np.savez_compressed(path, **arrays)
    return real
