"""``surprise-master track VIDEO --run DIR`` then ``report DIR --positions``: a real run's
behaviour and d_B from an overhead camera's video; and every bad input named in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from filmed_run import MARKERS, ROBOTS, Filmed, as_real, scene, tracking_config

from master_service.cli import main
from minimize_surprise.errors import ConfigError
from reporting.report import compute_metrics
from standins.overhead_camera import OverheadVideo
from tracking.camera import TrackingError
from tracking.config import parse_floor, parse_markers
from tracking.video import track_frames


def _tracking_file(path: Path) -> Path:
    path.write_text(
        yaml.safe_dump(
            {
                "floor": [1.3, 1.3],
                "robots": {"offset": [0.02, 0.0], "ids": dict(zip(ROBOTS, MARKERS, strict=True))},
                "camera": {"height": 2.0},
            }
        )
    )
    return path


def test_track_then_report_gives_the_simulators_class_and_d_b(filmed, tmp_path, capsys):
    video = filmed.video.write(tmp_path / "post.mp4")
    real = as_real(filmed.run, tmp_path)
    config = _tracking_file(tmp_path / "tracking.yaml")
    assert main(["track", str(video), "--run", str(real), "--config", str(config)]) == 0
    out = capsys.readouterr().out
    csv = real / "tracked_positions.csv"
    assert f"wrote {csv} and {real / 'tracked_positions.boxes.json'}" in out
    assert "sim-1 (marker 11): seen in 281 of 301, 20 filled in" in out
    assert csv.read_text().splitlines()[0] == "time,robot,x,y,heading,seen"
    assert main(["report", str(real), "--positions", str(csv)]) == 0
    out = capsys.readouterr().out
    assert "d_B from the boxes in" in out
    got = json.loads((real / "metrics.json").read_text())["post_evaluation"]
    want = compute_metrics(filmed.run)["post_evaluation"]["behaviour"]
    behaviour = got["behaviour"]
    for key in ("motion", "grouping", "pushing", "manipulation"):
        assert behaviour[key] == want[key], key
    assert behaviour["box_displacement"] == pytest.approx(want["box_displacement"], abs=0.01)
    assert behaviour["rotation"] == pytest.approx(want["rotation"], abs=0.5)
    assert behaviour["distance_covered"] == pytest.approx(want["distance_covered"], rel=0.1)
    assert got["positions"]["robots"]["sim-1"]["largest_gap_s"] == pytest.approx(2.1)
    assert got["positions"]["boxes"]["pairs"] > 250


def _short(tmp_path: Path, filmed: Filmed, **changes: object) -> OverheadVideo:
    # Two seconds of the run at 960x540: enough to see markers and a flash.
    return OverheadVideo(
        scene(image_size=(960, 540), **changes), filmed.poses[:15], pre_roll=0.5, seed=2
    )


def _one_line(error: BaseException, *words: str) -> None:
    text = str(error)
    assert "\n" not in text
    for word in words:
        assert word in text, text


def test_an_unreadable_video_is_named(tmp_path, capsys):
    bad = tmp_path / "bad.mp4"
    bad.write_text("not a video")
    args = ["--floor", "1x1", "--markers", "a=5", "--camera-height", "2"]
    assert main(["track", str(bad), "--out", str(tmp_path / "p.csv"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"surprise-master: {bad}: OpenCV") and "\n" not in err
    missing = tmp_path / "none.mp4"
    assert main(["track", str(missing), "--out", str(tmp_path / "p.csv"), *args]) == 2
    assert f"{missing}: no such video file" in capsys.readouterr().err


def test_corner_markers_not_found_are_named(filmed, tmp_path):
    video = _short(tmp_path, filmed, corner_ids=(0, 1, 2, 30))
    with pytest.raises(TrackingError) as caught:
        track_frames(video.frames(), tracking_config(), name="cornerless.mp4", duration=0.5)
    _one_line(caught.value, "cornerless.mp4", "3 top-left", "never seen together", "DICT_4X4_50")


def test_a_robot_left_out_of_the_markers_is_named(filmed, tmp_path):
    video = _short(tmp_path, filmed)
    config = tracking_config(ids={"sim-0": 10, "sim-1": 11, "sim-2": 12})
    with pytest.raises(TrackingError) as caught:
        track_frames(video.frames(), config, name="v.mp4", duration=0.5)
    _one_line(caught.value, "v.mp4", "marker 13", "neither a corner's nor a robot's")


def test_a_robot_whose_marker_is_never_seen_is_named(filmed, tmp_path):
    video = _short(tmp_path, filmed)
    config = tracking_config(ids={**dict(zip(ROBOTS, MARKERS, strict=True)), "sim-9": 20})
    with pytest.raises(TrackingError) as caught:
        track_frames(video.frames(), config, name="v.mp4", duration=0.5)
    _one_line(caught.value, "robot 'sim-9' (marker 20) was not seen")


def test_no_flash_and_no_start_is_named_and_a_start_does_without(filmed, tmp_path):
    video = _short(tmp_path, filmed, **{})
    video.flash = 0.0
    with pytest.raises(TrackingError) as caught:
        track_frames(video.frames(), tracking_config(), name="dark.mp4", duration=0.5)
    _one_line(caught.value, "dark.mp4", "no LED flash", "--start")
    result = track_frames(video.frames(), tracking_config(), name="dark", start=0.5, duration=0.5)
    assert not result.flash and result.start == 0.5


def test_markers_of_robots_not_in_the_run_are_refused(filmed, tmp_path, capsys):
    real = as_real(filmed.run, tmp_path)
    args = ["track", str(tmp_path / "v.mp4"), "--run", str(real), "--floor", "1.3x1.3"]
    assert main([*args, "--markers", "thymio-9=10", "--camera-height", "2"]) == 2
    err = capsys.readouterr().err
    assert "option '--markers': no robot 'thymio-9' in the run's post-evaluation" in err


@pytest.mark.parametrize(
    ("text", "message"),
    [("1.3", "expected WIDTHxHEIGHT"), ("0x2", "expected WIDTHxHEIGHT"), ("ax2", "got 'ax2'")],
)
def test_a_bad_floor_is_named(text, message):
    with pytest.raises(ConfigError, match=f"option '--floor': .*{message}"):
        parse_floor(text)


@pytest.mark.parametrize(
    ("text", "message"),
    [("a=1,b", "got 'b'"), ("a=x", "got 'a=x'"), ("a=1,a=2", "robot 'a' is given twice")],
)
def test_bad_markers_are_named(text, message):
    with pytest.raises(ConfigError, match=f"option '--markers': .*{message}"):
        parse_markers(text)


def test_a_marker_used_twice_in_a_tracking_file_is_named(tmp_path, capsys):
    config = tmp_path / "t.yaml"
    config.write_text("robots:\n  ids: {a: 1}\n")
    assert main(["track", "v.mp4", "--out", "p.csv", "--config", str(config)]) == 2
    assert (
        f"{config}: key 'robots.ids.a': marker 1 is already a corner's" in capsys.readouterr().err
    )
    assert parse_floor("2.2x2.9") == (2.2, 2.9)


def test_a_video_or_a_camera_is_needed(capsys):
    assert main(["track"]) == 2
    assert "give a video file or --camera N" in capsys.readouterr().err


def test_without_floor_the_runs_arena_gives_it(filmed, tmp_path, capsys):
    # The corner markers lie in the walls' inner corners: a run in the boxes arena (1.1 m, the
    # walls 10 cm out) needs no --floor for its 1.3 m between the markers.
    boxes = filmed.video.boxes
    assert boxes is not None
    video = OverheadVideo(
        scene(image_size=(960, 540)),
        filmed.poses[:15],
        boxes[: 15 // filmed.video.box_every + 1],
        box_every=filmed.video.box_every,
        pre_roll=0.5,
        seed=2,
    )
    path = video.write(tmp_path / "short.mp4")
    real = as_real(filmed.run, tmp_path)
    config_file = real / "config.yaml"
    config = yaml.safe_load(config_file.read_text())
    markers = ",".join(f"{r}={m}" for r, m in zip(ROBOTS, MARKERS, strict=True))
    args = ["track", str(path), "--run", str(real), "--markers", markers, "--camera-height", "2"]
    assert main([*args, "--duration", "0.5"]) == 0, capsys.readouterr().err
    assert _fit(capsys.readouterr().out) < 1.0  # pixels
    config["experiment"]["simulation"] = {"arena_side": 1.4}  # the wrong floor: a poor fit
    config_file.write_text(yaml.safe_dump(config))
    assert main([*args, "--duration", "0.5"]) == 0
    assert _fit(capsys.readouterr().out) > 3.0


def _fit(out: str) -> float:
    # The corner markers' residual the command prints, in pixels.
    return float(out.split("the corner markers fit to ")[1].split(" px")[0])
