"""The world's rules: sensor models cell by cell, torus wrap, blocked moves, index-order
conflicts, vacated cells, turns, start configurations, and the compiled loop against a plain-loop
reference of the authors' simulation."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from grid_helpers import forced_genome, reference_run

from gridworld.evaluate import GridEvaluator, noise_threshold
from gridworld.world import HEADINGS, SENSOR_OFFSETS, Poses, Torus, draw_starts, heading_index
from minimize_surprise.gridnet import GridGenomeLayout, GridNetSpec

# Sensor cells written out for heading east (x right, y up: right of east is -y), from the
# authors' sensorModelSTDL, sensorModelSTD and sensorModelSTDSL.
EAST_14 = [(1, 0), (1, -1), (1, 1), (2, 0), (2, -1), (2, 1), (0, -1), (0, 1),
           (-1, 0), (-1, -1), (-1, 1), (-2, 0), (-2, -1), (-2, 1)]  # fmt: skip
EAST_8 = [(1, 0), (1, -1), (1, 1), (0, -1), (0, 1), (-1, 0), (-1, -1), (-1, 1)]


def rotate(dx: int, dy: int, heading: int) -> tuple[int, int]:
    for _ in range(heading):
        dx, dy = -dy, dx
    return dx, dy


@pytest.mark.parametrize("sensors,east", [(14, EAST_14), (6, EAST_14[:6]), (8, EAST_8)])
@pytest.mark.parametrize("heading", range(4))
def test_every_sensor_cell_in_every_heading(sensors, east, heading):
    torus = Torus(7, 9)
    nb = torus.neighbours(sensors)
    x, y = 3, 4
    for k, (dx, dy) in enumerate(east):
        rx, ry = rotate(dx, dy, heading)
        assert nb[torus.cell(x, y), heading, k] == torus.cell(x + rx, y + ry), (k, heading)


def test_sensor_cells_of_the_code_for_heading_north():
    # sensorModelSTDL, heading (0, 1): S1 = (x+1, y+1), S6 = (x+1, y), S9 = (x+1, y-1), S13 =
    # (x-1, y-2)
    torus = Torus(10, 10)
    nb = torus.neighbours(14)
    c = torus.cell(5, 5)
    north = heading_index(0, 1)
    assert nb[c, north, 1] == torus.cell(6, 6)
    assert nb[c, north, 6] == torus.cell(6, 5)
    assert nb[c, north, 9] == torus.cell(6, 4)
    assert nb[c, north, 13] == torus.cell(4, 3)


def test_sensors_wrap_around_the_torus():
    torus = Torus(5, 4)
    nb = torus.neighbours(14)
    east = heading_index(1, 0)
    c = torus.cell(4, 0)
    assert nb[c, east, 0] == torus.cell(0, 0)
    assert nb[c, east, 3] == torus.cell(1, 0)
    assert nb[c, east, 1] == torus.cell(0, 3)  # front-right of east is -y: wraps to y = 3
    assert set(SENSOR_OFFSETS) == {14, 6, 8}


def test_left_turn_is_counter_clockwise():
    assert HEADINGS[(heading_index(1, 0) + 1) % 4] == (0, 1)
    assert HEADINGS[(heading_index(0, 1) + 1) % 4] == (-1, 0)


def run(poses, action, steps=1, width=6, height=6, sensors=14):
    torus = Torus(width, height)
    spec = GridNetSpec(sensors)
    ev = GridEvaluator(torus, spec, steps)
    genome = forced_genome(ev.layout, action)
    start = Poses.from_rows(poses).to_cells(torus)
    out = ev.evaluate(genome[None], start[None], trace=(0, 0))
    return [Poses.from_cells(torus, frame).to_rows() for frame in out.trace]


def test_forward_move_and_torus_wrap():
    trace = run([[5, 2, 1, 0], [0, 4, 0, -1]], "move")
    assert trace[1] == [[0, 2, 1, 0], [0, 3, 0, -1]]


def test_blocked_move_keeps_cell_and_heading_even_when_the_blocker_leaves():
    # agent 0 faces agent 1, which moves away this step: the snapshot still blocks agent 0
    trace = run([[1, 1, 1, 0], [2, 1, 0, 1]], "move", steps=2)
    assert trace[1] == [[1, 1, 1, 0], [2, 2, 0, 1]]
    assert trace[2] == [[2, 1, 1, 0], [2, 3, 0, 1]]


def test_conflict_goes_to_the_lower_index():
    # both want (2, 1)
    assert run([[1, 1, 1, 0], [3, 1, -1, 0]], "move")[1] == [[2, 1, 1, 0], [3, 1, -1, 0]]
    assert run([[3, 1, -1, 0], [1, 1, 1, 0]], "move")[1] == [[2, 1, -1, 0], [1, 1, 1, 0]]


def test_a_queue_advances_one_agent_per_step():
    trace = run([[0, 0, 1, 0], [1, 0, 1, 0], [2, 0, 1, 0]], "move", steps=3, width=10)
    assert [row[0] for row in trace[1]] == [0, 1, 3]
    assert [row[0] for row in trace[2]] == [0, 2, 4]
    assert [row[0] for row in trace[3]] == [1, 3, 5]


def test_turns_never_conflict():
    assert run([[1, 1, 1, 0], [2, 1, -1, 0]], "left")[1] == [[1, 1, 0, 1], [2, 1, 0, -1]]
    assert run([[1, 1, 1, 0]], "right")[1] == [[1, 1, 0, -1]]


@pytest.mark.parametrize(
    "sensors,predefined", [(14, None), (6, None), (8, None), (14, "line-partial"), (14, "pair")]
)
@pytest.mark.parametrize("width,height", [(6, 5), (4, 7)])  # bit rows; cell by cell
def test_compiled_loop_matches_the_plain_reference(sensors, predefined, width, height):
    torus = Torus(width, height)
    spec = GridNetSpec(sensors, predefined)
    layout = GridGenomeLayout(spec)
    rng = np.random.default_rng(sensors)
    starts = draw_starts(rng, torus, 12, 2)
    genomes = rng.uniform(-1.5, 1.5, (2, layout.size))
    steps = 12
    ev = GridEvaluator(torus, spec, steps, exact=True)
    for g in range(2):
        for rep in range(2):
            out = ev.evaluate(genomes[g : g + 1], starts, trace=(0, rep))
            start = [(int(c) % width, int(c) // width, int(d)) for c, d in starts[rep]]
            trace, fitness, predsum = reference_run(layout, genomes[g], width, height, start, steps)
            ours = [[(int(c) % width, int(c) // width, int(d)) for c, d in f] for f in out.trace]
            assert ours == trace
            assert out.fitness[0, rep] == pytest.approx(fitness, abs=1e-12)
            np.testing.assert_allclose(out.predictions[0, rep], predsum, atol=1e-12)


def test_fast_tanh_changes_no_trajectory_and_hardly_the_fitness():
    torus = Torus(8, 8)
    spec = GridNetSpec(14)
    rng = np.random.default_rng(5)
    genomes = rng.uniform(-0.5, 0.5, (4, GridGenomeLayout(spec).size))
    starts = draw_starts(rng, torus, 30, 3)
    exact = GridEvaluator(torus, spec, 60, exact=True).evaluate(genomes, starts)
    fast = GridEvaluator(torus, spec, 60).evaluate(genomes, starts)
    np.testing.assert_array_equal(exact.final, fast.final)
    np.testing.assert_allclose(exact.fitness, fast.fitness, atol=1e-3)


def test_noise_flips_readings_but_never_the_blocking():
    torus = Torus(6, 6)
    spec = GridNetSpec(14)
    genome = forced_genome(GridGenomeLayout(spec), "move")
    start = Poses.from_rows([[1, 1, 1, 0], [2, 1, 1, 0], [4, 4, 0, 1]]).to_cells(torus)[None]
    clean = GridEvaluator(torus, spec, 5).evaluate(genome[None], start)
    noisy = GridEvaluator(torus, spec, 5, noise=1.0).evaluate(genome[None], start)
    # the actor ignores its inputs, so the moves are the same; every reading is inverted
    np.testing.assert_array_equal(clean.final, noisy.final)
    assert noisy.fitness[0, 0] == pytest.approx(1.0 - clean.fitness[0, 0])
    half = GridEvaluator(torus, spec, 50, noise=0.5)
    a = half.evaluate(genome[None], start, noise_key=1).fitness
    b = half.evaluate(genome[None], start, noise_key=1).fitness
    c = half.evaluate(genome[None], start, noise_key=2).fitness
    assert a[0, 0] == b[0, 0] != c[0, 0]
    assert 0.4 < a[0, 0] < 0.6
    assert noise_threshold(0.0) == 0
    with pytest.raises(ValueError, match="noise"):
        noise_threshold(1.5)


def test_starts_are_distinct_cells_with_uniform_headings():
    torus = Torus(11, 11)
    starts = draw_starts(np.random.default_rng(0), torus, 100, 10)
    assert starts.shape == (10, 100, 2)
    for rep in starts:
        assert np.unique(rep[:, 0]).size == 100
    counts = np.bincount(starts[:, :, 1].ravel(), minlength=4)
    assert counts.min() > 200
    again = draw_starts(np.random.default_rng(0), torus, 100, 10)
    np.testing.assert_array_equal(starts, again)
    with pytest.raises(ValueError, match="do not fit"):
        draw_starts(np.random.default_rng(0), torus, 122, 1)


def test_bad_starts_are_refused():
    torus = Torus(4, 4)
    ev = GridEvaluator(torus, GridNetSpec(14), 2)
    genome = np.zeros((1, ev.layout.size))
    with pytest.raises(ValueError, match="two agents"):
        ev.evaluate(genome, np.array([[[0, 0], [0, 1]]]))
    with pytest.raises(ValueError, match="outside"):
        ev.evaluate(genome, np.array([[[16, 0]]]))
    with pytest.raises(ValueError, match="heading"):
        Poses.from_rows([[0, 0, 1, 1]])


INTERPRETED = """
import numpy as np
from gridworld.evaluate import GridEvaluator
from gridworld.world import Torus, draw_starts
from minimize_surprise.gridnet import GridGenomeLayout, GridNetSpec
rows = []
for predefined in (None, "line-partial"):
    spec = GridNetSpec(14, predefined)
    rng = np.random.default_rng(1)
    torus = Torus(7, 6)
    starts = draw_starts(rng, torus, 10, 2)
    genomes = rng.uniform(-1, 1, (2, GridGenomeLayout(spec).size))
    out = GridEvaluator(torus, spec, 4).evaluate(genomes, starts)
    rows += [out.fitness.ravel(), out.predictions.ravel(), out.final.ravel()]
print(np.concatenate(rows).tobytes().hex())
"""


def test_interpreted_kernels_give_the_compiled_results():
    # without numba (SURPRISE_NO_JIT) every kernel runs as Python, the vector code as plain loops
    runs = []
    for no_jit in ("0", "1"):
        env = {**os.environ, "SURPRISE_NO_JIT": no_jit}
        command = [sys.executable, "-c", INTERPRETED]
        runs.append(subprocess.run(command, check=True, capture_output=True, text=True, env=env))
    assert runs[0].stdout == runs[1].stdout
