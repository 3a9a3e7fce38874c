"""Shared helpers of the grid-world tests: genomes with known behaviour and a plain-loop
reference of the authors' simulation loop."""

from __future__ import annotations

import numpy as np

from gridworld.world import HEADINGS, SENSOR_OFFSETS, sensor_cell_offset
from minimize_surprise.gridnet import GridGenomeLayout, actor_reference, predictor_reference


def forced_genome(layout: GridGenomeLayout, action: str) -> np.ndarray:
    """A genome whose actor always does ``action`` (move, left or right) whatever it senses:
    every input unit is tanh(1), every hidden unit positive, and the output weights' signs pick
    the decision (o0 < 0 moves; o1 < 0 turns left)."""
    w = layout.unpack(np.zeros(layout.size))
    genome = np.zeros(layout.size)
    views = {name: genome[s : s + int(np.prod(shape))].reshape(shape)
             for name, (s, shape) in layout.blocks.items()}  # fmt: skip
    views["actor.input"][:, 1] = -1.0
    views["actor.hidden"][:] = 0.1
    views["actor.output"][0] = -1.0 if action == "move" else 1.0
    views["actor.output"][1] = -1.0 if action == "left" else 1.0
    assert w  # the layout fits
    return genome


def reference_run(layout: GridGenomeLayout, genome, width, height, start, steps):
    """The code's doRun, literally: poses (x, y, heading) per step, fitness, mean predictions."""
    spec = layout.spec
    r = spec.sensors
    offsets = SENSOR_OFFSETS[r]
    poses = [tuple(p) for p in start]
    n = len(poses)
    predictions = [[int(v) for v in spec.fixed] for _ in range(n)]
    hidden = [[0.0] * spec.predictor_hidden for _ in range(n)]
    last_action = [0] * n
    trace = [list(poses)]
    correct = 0
    predsum = np.zeros(r)
    for _ in range(steps):
        grid = {(x, y) for x, y, _ in poses}
        nxt = []
        for i, (x, y, d) in enumerate(poses):
            sensors = []
            for f, rr in offsets:
                dx, dy = sensor_cell_offset(d, f, rr)
                sensors.append(int(((x + dx) % width, (y + dy) % height) in grid))
            correct += sum(int(s == p) for s, p in zip(sensors, predictions[i], strict=True))
            predsum += predictions[i]
            a0, turn = actor_reference(layout, genome, [*sensors, last_action[i]])
            last_action[i] = a0
            if layout.has_predictor:
                predictions[i], hidden[i] = predictor_reference(
                    layout, genome, [*sensors, a0], hidden[i]
                )
            new = (x, y, d)
            if a0 == 0:
                if sensors[0] == 0:
                    hx, hy = HEADINGS[d]
                    target = ((x + hx) % width, (y + hy) % height)
                    if all((px, py) != target for px, py, _ in nxt):
                        new = (*target, d)
            else:
                new = (x, y, (d + (1 if turn == 1 else 3)) % 4)
            nxt.append(new)
        poses = nxt
        trace.append(list(poses))
    return trace, correct / (steps * n * r), predsum / (steps * n)
