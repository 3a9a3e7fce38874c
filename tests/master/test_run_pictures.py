"""The pictures of a simulated run and the animation of its post-evaluation, and the report's
word when the safety layer did the driving."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import numpy as np
import pytest

from master_service.cli import main
from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulate import simulation_experiment
from needs import require_module
from reporting import pictures

require_module("matplotlib")
Image = require_module("PIL.Image")


def small(scenario: str, *, setting: str = "paper", evaluations: int = 6, **simulation):
    experiment = simulation_experiment(scenario, setting=setting, robots=3, seed=1)
    return msgspec.structs.replace(
        experiment,
        evolution=msgspec.structs.replace(experiment.evolution, evaluations=evaluations),
        evaluation_steps=50,
        post_evaluation_steps=300,
        simulation={**experiment.simulation, **simulation},
    )


@pytest.fixture(scope="module")
def boxes_run(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("pictures") / "boxes"
    FastRun(small("boxes")).run(run, plots=False)
    return run


def test_a_simulated_run_gets_every_picture_as_png_and_pdf(boxes_run: Path, capsys):
    assert main(["report", str(boxes_run)]) == 0
    names = ("fitness", "robot_fitness", "predictions", "trajectories")
    expected = {f"{name}.{fmt}" for name in names for fmt in ("png", "pdf")}
    assert {p.name for p in (boxes_run / "plots").iterdir()} == expected
    for name in expected:
        data = (boxes_run / "plots" / name).read_bytes()
        assert data[:4] == (b"\x89PNG" if name.endswith("png") else b"%PDF")
    with Image.open(boxes_run / "plots" / "trajectories.png") as image:
        assert image.size[0] >= 1200  # sharp enough for a slide
    assert "8 pictures" in capsys.readouterr().out


def test_the_boxes_track_follows_the_post_evaluation(boxes_run: Path):
    simulation = json.loads((boxes_run / "simulation.json").read_text())
    boxes = simulation["post_evaluation_boxes"]
    with np.load(boxes_run / "box_track.npz") as track:
        positions, every = track["positions"], int(track["every"])
    assert every == 10  # 0.1 s of the paper setting's 10 ms steps
    assert positions.shape == (30, len(boxes["start"]), 2)
    assert np.allclose(positions[0], boxes["start"])
    # The last frame is 10 steps before the end: the boxes are (nearly) where they ended.
    assert np.abs(positions[-1] - np.asarray(boxes["end"])).max() < 0.02


def test_report_animate_writes_a_gif_of_the_post_evaluation(boxes_run: Path, capsys):
    assert main(["report", str(boxes_run), "--animate"]) == 0
    gif = boxes_run / "plots" / "post_evaluation.gif"
    assert f"animation: {gif}" in capsys.readouterr().out
    assert gif.read_bytes()[:6] == b"GIF89a"
    with Image.open(gif) as image:
        # 300 steps, at most 200 frames (20 s at 10 frames a second): every second step drawn.
        assert image.n_frames == 150
        first = np.asarray(image.convert("RGB"))
        image.seek(image.n_frames - 1)
        last = np.asarray(image.convert("RGB"))
    assert first.shape == last.shape and (first != last).any()  # the robots moved


def test_animating_a_run_of_real_robots_is_refused_with_a_reason(tmp_path: Path, capsys):
    run = tmp_path / "run"
    FastRun(small("basic", evaluations=2)).run(run, plots=False)
    (run / "simulation.json").unlink()  # as a run of real robots: no simulated world
    for trace in (run / "traces").iterdir():
        with np.load(trace) as data:
            arrays = {k: data[k] for k in data.files if k != "poses"}
        np.savez(trace, **arrays)
    assert main(["report", str(run), "--animate"]) == 2
    assert "no simulated post-evaluation with poses to animate" in capsys.readouterr().err


def test_a_floor_as_light_as_the_edge_is_reported_as_the_safety_layer_driving(tmp_path, capsys):
    # The lab's robots stop at a ground reading above 0.55 (a white edge on a dark carpet): on a
    # light floor every reading trips the rule and the networks never drive.
    run = tmp_path / "run"
    result = FastRun(small("basic", setting="lab", ground_carpet=0.9)).run(run, plots=False)
    assert result is not None
    safety = result.metrics["safety"]
    assert safety["post_evaluation_share"] > 0.9
    assert max(safety["post_evaluation_reasons"], key=safety["post_evaluation_reasons"].get) == (
        "ground"
    )
    [post, _] = safety["warnings"]
    assert post.startswith("in the post-evaluation the safety layer overrode")
    assert "safety.ground_threshold" in post
    rows = (run / "evaluations.csv").read_text().splitlines()
    header = rows[0].split(",")
    shares = [float(r.split(",")[header.index("safety_share")]) for r in rows[1:]]
    assert min(shares) > 0.9

    from master_service.experiments.simulate import summary_text

    text = summary_text(result.metrics, run, 1.0)
    assert "warning: in the post-evaluation the safety layer overrode" in text


def test_twenty_one_robots_share_a_band_and_ten_get_a_panel_each(tmp_path: Path):
    rng = np.random.default_rng(0)

    def rows(robots: list[str]) -> list[dict]:
        return [
            {"evaluation": e, "fitness": 0.5, "robots": {r: float(rng.uniform()) for r in robots}}
            for e in range(1, 30)
        ]

    ten = [f"r{i}" for i in range(10)]
    [png, _] = pictures.robot_fitness_picture(tmp_path, rows(ten), ten, "ten")
    with Image.open(png) as image:
        wide, high = image.size
    assert wide > high  # two rows of five panels
    many = [f"r{i}" for i in range(21)]
    (tmp_path / "many").mkdir()
    [png, pdf] = pictures.robot_fitness_picture(tmp_path / "many", rows(many), many, "many")
    assert png.is_file() and pdf.read_bytes()[:4] == b"%PDF"
