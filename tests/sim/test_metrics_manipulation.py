"""The paper's object-manipulation classes (Sec. V-C), one per run: pushing when the boxes moved
more than 0.1 m on average, else reverse driving when most moving steps went backwards, else
circling."""

from __future__ import annotations

import numpy as np
import pytest

from simulator.metrics import (
    backward_share,
    behaviour_label,
    behaviour_metrics,
    classify_manipulation,
)


def straight(steps: int, robots: int, speed: float, heading: float = 0.3) -> np.ndarray:
    """Robots driving straight at ``speed`` metres a step (negative: backwards)."""
    t = np.arange(steps + 1)[:, None]
    x = 0.1 * np.arange(robots)[None, :] + speed * np.cos(heading) * t
    y = speed * np.sin(heading) * t + np.zeros((1, robots))
    theta = np.full_like(x, heading)
    return np.stack([x, y, theta], axis=-1)


def test_backward_share_counts_the_moves_against_the_heading():
    forward, backward = straight(100, 3, 0.001), straight(100, 3, -0.001)
    assert backward_share(forward) == 0.0 and backward_share(backward) == 1.0
    # Steps that do not move a robot (held by the safety layer, turning on the spot) do not count.
    held = np.concatenate([backward, np.repeat(backward[-1:], 400, axis=0)])
    assert backward_share(held) == 1.0
    assert backward_share(np.zeros((5, 2, 3))) == 0.0


@pytest.mark.parametrize(
    ("d_b", "backward", "motion", "expected"),
    [
        (0.2, 0.9, "stopped", "pushing"),  # the boxes moved: pushing, whatever else
        (0.05, 0.8, "stopped", "reverse driving"),  # backwards until the layer stopped them
        (0.05, 0.8, "diverse", "reverse driving"),
        (0.05, 0.99, "circling", "circling"),  # small circles, driven backwards
        (0.05, 0.2, "stopped", "circling"),
        (0.1, 0.5, "stopped", "circling"),  # both thresholds are strict, as the paper's d_B
    ],
)
def test_one_class_per_run(d_b, backward, motion, expected):
    assert classify_manipulation(d_b, backward, motion) == expected


def test_a_run_with_boxes_gets_its_class_and_a_run_without_none():
    poses = straight(600, 4, -0.002)
    boxes = np.zeros((3, 2))
    with_boxes = behaviour_metrics(poses, boxes, boxes + 0.01)
    assert with_boxes.manipulation == "reverse driving"
    assert behaviour_label(with_boxes).startswith("reverse driving (")
    without = behaviour_metrics(poses)
    assert without.manipulation is None and behaviour_label(without) == (
        f"{without.motion}, {without.grouping}"
    )
