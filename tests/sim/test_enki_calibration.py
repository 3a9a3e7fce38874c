"""The lab setting's IR and ground sensors against Enki's Thymio II model (simulator.physics).

The world's default sensor models (the "lab" setting, the real robots' calibration) follow Enki's
Thymio II: the horizontal IR's response ``c / (d^2 + c)`` with c = 73 cm^2 within 14 cm, and the
ground sensors over a grey carpet with a bright boundary. Here the same geometries are set up in
Enki itself (Debian's ``python3-enki2``, for the system python: one subprocess runs every probe
and prints JSON) and in our :class:`~simulator.world.World`, and the normalised values compared
(IR: raw / 4500, Enki's maximum is 4505; ground: raw / 1023).

What Enki computes (enki/interactions/IRSensor.cpp, GroundSensor.cpp): an IR sensor casts three
rays, on its axis and at +-15 degrees, and reads ``r(d-15) + r(d0) - 2 r(d0 / cos 15) + r(d+15)``
with ``r(x) = 4505 (c - x0^2) / (x^2 - 2 x0 x + c)`` (x0 = 0.3 mm, nothing beyond 14 cm) plus
Gaussian noise of 2.87 raw. Head-on to a flat surface the outer rays meet it at ``d0 / cos 15``
and the sum is exactly ``r(d0)``: our cone model's value. Elsewhere the models part, as measured
below. A ground sensor averages the floor's grey level over +-1 cm (Gaussian, sd 4 mm) and reads
``60 + 884 sigmoid(9 (grey - 0.44))`` plus noise of 10 raw.

Every Enki probe starts the world anew with a fixed random seed and averages a few steps of a
still scene, so the numbers are the same on every run; tolerances are set from the measured
differences, stated next to each assertion. A fresh world per probe also matters because
Debian's Enki (1.6.99, 2020) predates upstream's fix of its IR initialisation (commit 7dbaa0b,
2021, "Fixed IR sensor initialisation. Closes #68"): a ray that stops meeting anything keeps its
last value, so in a moving scene Enki's IR values stick after their target has gone. Still
scenes read the same either way.
"""

from __future__ import annotations

import json
import os
import subprocess

import numpy as np
import pytest

from minimize_surprise.safety import SafetyConfig
from needs import missing
from simulator.physics import GROUND_POSITIONS, IR_POSITIONS
from simulator.scenarios import scenario_config
from simulator.world import World

SYSTEM_PYTHON = "/usr/bin/python3"
LAB = scenario_config("basic")  # the lab setting: 1 m carpet, walls 10 cm beyond it
F1, F2, F3 = 1, 2, 3
G0, G1 = 7, 8  # the ground sensors' columns in the basic world's sensor order
IR_SENSOR_X = IR_POSITIONS[F2, 0] * 100  # the middle front sensor, cm ahead of the wheel axis
GROUND_SENSOR_X = GROUND_POSITIONS[0, 0] * 100

# Gaps (cm) from the middle front sensor F2 to the wall or robot ahead; 14.5 is out of range.
WALL_GAPS = [0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.5]
ROBOT_GAPS = [0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0]
# Positions (cm) of the ground sensors relative to the carpet's edge, negative on the carpet.
EDGE_OFFSETS = [-5.0, -3.0, -1.5, -1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0, 2.0, 3.0, 5.0]

# Run by the system python (no numpy there). Enki's units are cm; each probe is a fresh world
# stepped with the wheels still (the robot only moves if a collision pushes it: at gap 0 Enki's
# hull, 0.5 mm ahead of F2, touches), and reports the poses after the step with the values.
ENKI_PROBES = r"""
import json, math, os, sys, tempfile
import pyenki

args = json.loads(sys.argv[1])
IR_X, GROUND_X, STEPS, GROUND_STEPS = args["ir_x"], args["ground_x"], 5, 20
out = {"wall": [], "robot_away": [], "robot_towards": [], "ground": []}

def pose(r):
    return [r.pos[0], r.pos[1], r.angle]

def read_ir(world, robot):
    total = [0.0] * 7
    for _ in range(STEPS):
        world.step(0.1)
        total = [t + v for t, v in zip(total, robot.proximitySensorValues)]
    return [t / STEPS / 4500.0 for t in total]

for gap in args["wall_gaps"]:
    world = pyenki.World()
    world.setRandomSeed(1)
    robot = pyenki.Thymio2()
    world.addObject(robot)
    # A static block 10 cm deep and 2 m long, its near face `gap` ahead of F2.
    wall = pyenki.RectangularObject(10.0, 200.0, 10.0, -1, pyenki.Color(0.5, 0.5, 0.5))
    wall.pos = (IR_X + gap + 5.0, 0.0)
    world.addObject(wall)
    ir = read_ir(world, robot)
    out["wall"].append({"gap": gap, "face": IR_X + gap, "pose": pose(robot), "ir": ir})

# Another Thymio ahead: its flat rear (3 cm behind its wheel axis) or its front arc (8 cm ahead)
# `gap` ahead of F2.
for key, heading, reach in (("robot_away", 0.0, 3.0), ("robot_towards", math.pi, 8.0)):
    for gap in args["robot_gaps"]:
        world = pyenki.World()
        world.setRandomSeed(1)
        robot = pyenki.Thymio2()
        world.addObject(robot)
        other = pyenki.Thymio2()
        other.pos = (IR_X + gap + reach, 0.0)
        other.angle = heading
        world.addObject(other)
        ir = read_ir(world, robot)
        out[key].append({"gap": gap, "pose": pose(robot), "other": pose(other), "ir": ir})

# Ground: a square world as big as our arena within its walls, 1 mm pixels: the carpet grey 0.4
# in the middle, white around it. A robot facing +x with its ground sensors at the right edge.
side, carpet, ppcm = args["side"], args["carpet"], 10
n = side * ppcm
lo, hi = (side - carpet) // 2 * ppcm, (side + carpet) // 2 * ppcm
grey, white = bytes([102, 102, 102]), bytes([255, 255, 255])
inside = white * lo + grey * (hi - lo) + white * (n - hi)
rows = [inside if lo <= j < hi else white * n for j in range(n)]
with tempfile.TemporaryDirectory() as tmp:
    path = os.path.join(tmp, "floor.ppm")
    with open(path, "wb") as f:
        f.write(b"P6\n%d %d\n255\n" % (n, n))
        f.write(b"".join(rows))
    world = pyenki.WorldWithTexturedGround(float(side), float(side), path)
world.setRandomSeed(1)
robot = pyenki.Thymio2()
world.addObject(robot)
edge = (side + carpet) / 2
for offset in args["edge_offsets"]:
    robot.pos = (edge + offset - GROUND_X, side / 2)
    robot.angle = 0.0
    total = [0.0, 0.0]
    for _ in range(GROUND_STEPS):
        world.step(0.1)
        total = [t + v for t, v in zip(total, robot.groundSensorValues)]
    out["ground"].append({"offset": offset, "pose": pose(robot),
                          "ground": [t / GROUND_STEPS / 1023.0 for t in total]})
print(json.dumps(out))
"""


def enki_python() -> str:
    """The system python, which has Enki's bindings (python3-enki2); skip the test without
    them, except in CI (``CI=true``), where ``.ci/run`` installs them."""
    found = os.path.exists(SYSTEM_PYTHON) and (
        subprocess.run(
            [SYSTEM_PYTHON, "-I", "-c", "import pyenki"], capture_output=True, timeout=60
        ).returncode
        == 0
    )
    if not found:
        missing(f"{SYSTEM_PYTHON} cannot import pyenki (apt-get install python3-enki2)")
    return SYSTEM_PYTHON


@pytest.fixture(scope="module")
def enki() -> dict:
    """Every Enki probe's readings, from one run of the system python."""
    args = {
        "ir_x": IR_SENSOR_X,
        "ground_x": GROUND_SENSOR_X,
        "wall_gaps": WALL_GAPS,
        "robot_gaps": ROBOT_GAPS,
        "edge_offsets": EDGE_OFFSETS,
        "side": round(2 * LAB.wall_half * 100),
        "carpet": round(LAB.arena_side * 100),
    }
    done = subprocess.run(
        [enki_python(), "-I", "-c", ENKI_PROBES, json.dumps(args)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def lab_world(robots: int, **overrides) -> World:
    """The lab setting (the defaults) with ``robots`` robots, no noise."""
    return World(scenario_config("basic", {"robots": robots, **overrides}), seed=0)


def enki_pose(pose: list[float], dx: float = 0.0, dy: float = 0.0) -> tuple[float, float, float]:
    """An Enki pose (cm, rad) in metres, shifted by ``(dx, dy)`` m."""
    return pose[0] / 100 + dx, pose[1] / 100 + dy, pose[2]


def ours_facing_wall(probes: list[dict]) -> np.ndarray:
    """Our IR values (len(probes), 7) with the robot as far from our wall as Enki's from its."""
    world = lab_world(1, walls_visible_to_ir=True)
    rows = []
    for p in probes:
        # Our wall stands at x = wall_half: shift Enki's frame so that its wall face lands there.
        world.set_pose(0, *enki_pose(p["pose"], world.config.wall_half - p["face"] / 100))
        rows.append(world.sensor_matrix()[0, :7].copy())
    return np.array(rows)


def ours_behind_robot(probes: list[dict]) -> np.ndarray:
    """Our IR values (len(probes), 7) of robot 0 with both robots at Enki's poses."""
    world = lab_world(2)
    rows = []
    for p in probes:
        world.set_pose(0, *enki_pose(p["pose"]))
        world.set_pose(1, *enki_pose(p["other"]))
        rows.append(world.sensor_matrix()[0, :7].copy())
    return np.array(rows)


def enki_ir(probes: list[dict]) -> np.ndarray:
    return np.array([p["ir"] for p in probes])


def table(gaps: list[float], ours: np.ndarray, theirs: np.ndarray, cols: list[int]) -> str:
    """Ours / Enki per gap, for assertion messages."""
    lines = [
        f"{g:5.1f} cm: " + "  ".join(f"{ours[i, c]:.3f}/{theirs[i, c]:.3f}" for c in cols)
        for i, g in enumerate(gaps)
    ]
    return "ours/enki\n" + "\n".join(lines)


# --- IR: a flat wall ahead -----------------------------------------------------------------------
#
# Measured (ours / Enki, normalised) with the robot facing the wall, by gap from F2:
#
#   gap cm    F2             F1 (F3 within 0.001)   F0 (F4 the same; not compared)
#    0        1.000 / 1.001  0.997 / 0.997          0.949 / 0.912
#    1        0.986 / 0.989  0.972 / 0.969          0.888 / 0.820
#    2        0.948 / 0.951  0.923 / 0.913          0.810 / 0.717
#    3        0.890 / 0.894  0.859 / 0.841          0.727 / 0.622
#    5        0.745 / 0.747  0.709 / 0.681          0.568 / 0.466
#    7        0.598 / 0.601  0.566 / 0.534          0.439 / 0.113 (*)
#    9        0.474 / 0.476  0.448 / 0.418          0.342 / 0.343
#   11        0.376 / 0.378  0.356 / 0.330          0.000 / 0.000
#   12        0.336 / 0.338  0.319 / 0.054 (*)      0.000 / 0.000
#   13        0.302 / 0.303  0.286 / 0.287          0.000 / 0.000
#   14.5      0.000 / 0.000  0.000 / 0.000          0.000 / 0.000
#
# (*) Enki's artefact: its axis ray meets the target but an outer ray does not (it passes beside
# the target or ends at 14 cm), and the correction term meant to cancel that outer ray pulls the
# sum down to about 0.1. Not anything the real sensor does; such points are not compared.
#
# F0 and F4 (+-40 degrees) read 0.04 to 0.11 more than Enki's wherever all three of Enki's rays
# reach the wall (the cone's nearest point against Enki's sum, as for F1 below but at twice the
# incidence), and Enki's drop to 0.1 at 7 and 8 cm: too different to compare with a tolerance
# that would mean anything.


def test_middle_front_sensor_facing_a_wall_reads_as_enki(enki):
    ours, theirs = ours_facing_wall(enki["wall"]), enki_ir(enki["wall"])
    # Head-on to a flat surface both models are r(d) (see the module docstring): measured at most
    # 0.0033 apart, Enki higher (its maximum 4505 over our 4500, its x0 = 0.3 mm; its noise,
    # averaged over 5 steps, has an sd of 0.0003). 0.01 is three times that, and no more than
    # 1.3 mm of distance at the response's steepest (0.076 per cm, at d = 4.9 cm).
    assert np.abs(ours[:, F2] - theirs[:, F2]).max() <= 0.01, table(WALL_GAPS, ours, theirs, [F2])


def test_oblique_front_sensors_facing_a_wall_read_a_little_more_than_enki(enki):
    ours, theirs = ours_facing_wall(enki["wall"]), enki_ir(enki["wall"])
    # F1 and F3 meet the wall at 20 degrees. Our cone reads its nearest point, along the cone's
    # inner edge (5 degrees off the wall's normal); Enki sums its three rays with a correction
    # that is exact head-on only, and reads less: measured -0.001 to +0.032 (gap 7). Hence
    # ours - Enki in [-0.005, 0.04].
    # Compared only while Enki's outer ray (35 degrees off the normal, 14 cm long) reaches the
    # wall, up to a gap of 11 cm: beyond, Enki's correction term is left without the outer ray it
    # cancels and F1 collapses (0.054 at 12 cm, where ours reads 0.319), an artefact of Enki's
    # model rather than anything the real sensor does.
    rows = [i for i, g in enumerate(WALL_GAPS) if g <= 11.0]
    for col in (F1, F3):
        diff = ours[rows, col] - theirs[rows, col]
        assert diff.min() >= -0.005 and diff.max() <= 0.04, table(WALL_GAPS, ours, theirs, [col])


# --- IR: another robot ahead --------------------------------------------------------------------
#
# Our robot's body is a circle of radius 5.8 cm whose centre is 2.5 cm ahead of the wheel axis:
# it reaches 8.3 cm ahead and 3.3 cm behind the axis, where Enki's Thymio hull (a front arc of
# radius 8 cm around the axis, a flat rear 3 cm behind it, 11 cm wide) reaches 8.0 and 3.0 cm.
# Both robots sit at the same poses in both simulators, so that difference is part of what is
# measured. Ours / Enki, normalised, by gap from F2 to Enki's hull:
#
#   gap cm   facing away (its flat rear ahead)    facing us (its front arc ahead)
#            F2             F1 (F3 the same)      F2             F1 (F3 the same)
#    0       1.000 / 1.001  0.991 / 0.997         1.000 / 1.001  0.991 / 0.977
#    1       0.993 / 0.988  0.956 / 0.969         0.993 / 0.987  0.956 / 0.887
#    2       0.962 / 0.950  0.898 / 0.914         0.962 / 0.947  0.898 / 0.063 (*)
#    3       0.909 / 0.893  0.825 / 0.841         0.909 / 0.885  0.825 / 0.100 (*)
#    5       0.768 / 0.748  0.666 / 0.055 (*)     0.768 / 0.728  0.666 / 0.159 (*)
#    8       0.552 / 0.535  0.460 / 0.507         0.552 / 0.495  0.460 / 0.463
#   10       0.437 / 0.424  0.360 / 0.401         0.437 / 0.374  0.360 / 0.365
#   12       0.348 / 0.338  0.284 / 0.320         0.348 / 0.284  0.284 / 0.289
#   13       0.312 / 0.303  0.000 / 0.287         0.312 / 0.000 (*)  0.000 / 0.000
#
# (*) Enki's artefact, as for the wall.


def test_middle_front_sensor_behind_a_robot_reads_as_enki(enki):
    probes = enki["robot_away"]
    ours, theirs = ours_behind_robot(probes), enki_ir(probes)
    # Its flat rear is 11 cm wide, so all three of Enki's rays meet it head-on (r(d) exactly) at
    # every gap up to 13 cm. Ours reads more because our body circle reaches 3 mm nearer, 3.3 cm
    # behind the wheel axis: 3 mm at the response's steepest (0.076 per cm) is 0.023; measured
    # -0.001 to +0.020 (gap 5). Hence ours - Enki in [-0.005, 0.03].
    diff = ours[:, F2] - theirs[:, F2]
    assert diff.min() >= -0.005 and diff.max() <= 0.03, table(ROBOT_GAPS, ours, theirs, [F2])


def test_oblique_front_sensors_behind_a_robot_read_about_as_enki(enki):
    probes = enki["robot_away"]
    ours, theirs = ours_behind_robot(probes), enki_ir(probes)
    # Near (up to 3 cm) Enki's rays meet the flat rear, ours the circle's nearest point in the
    # cone: ours 0.007 to 0.016 less. From 8 cm on, Enki's axis ray passes beside the robot and
    # only its inner ray meets the rear face, where our circle has already curved away: ours
    # 0.036 to 0.047 less (gap 8). Hence |ours - Enki| <= 0.05. Not compared: 4 to 7 cm (Enki's
    # artefact, marked (*) above) and 13 cm (our cone's nearest point is beyond 14 cm, Enki's inner
    # ray still meets the flat rear at 13.5 cm).
    rows = [i for i, g in enumerate(ROBOT_GAPS) if g <= 3.0 or 8.0 <= g <= 12.0]
    for col in (F1, F3):
        diff = np.abs(ours[rows, col] - theirs[rows, col])
        assert diff.max() <= 0.05, table(ROBOT_GAPS, ours, theirs, [col])


def test_middle_front_sensor_facing_a_robot_reads_no_less_than_enki(enki):
    probes = enki["robot_towards"]
    ours, theirs = ours_behind_robot(probes), enki_ir(probes)
    # Nose to nose, two effects add up: our body circle reaches 3 mm nearer (8.3 cm ahead of the
    # other's wheel axis, Enki's arc 8.0 cm), and Enki's outer rays meet the convex front farther
    # than d / cos 15, so its correction term outweighs them and it reads less than r(d). Measured
    # ours - Enki: -0.001 at contact, growing to 0.040 at 5 cm and 0.064 at 11 cm. Hence
    # ours - Enki in [-0.005, 0.07] up to 12 cm; at 13 cm Enki's outer rays pass 14 cm and it
    # reads 0 (its artefact), not compared.
    rows = [i for i, g in enumerate(ROBOT_GAPS) if g <= 12.0]
    diff = ours[rows, F2] - theirs[rows, F2]
    assert diff.min() >= -0.005 and diff.max() <= 0.07, table(ROBOT_GAPS, ours, theirs, [F2])


# --- ground: the carpet's edge -------------------------------------------------------------------
#
# Measured, by the ground sensors' distance from the carpet's edge (negative: on the carpet), the
# mean of both sensors over 20 steps, Enki / ours:
#
#   -5 to -1.5 cm   0.412 to 0.416 / 0.400
#   -1 cm           0.424 / 0.400
#   -0.75           0.479 / 0.400
#   -0.5            0.608 / 0.400
#   -0.25           0.783 / 0.400
#    0              0.882 / 0.400 (ours switches just beyond the edge)
#   +0.25           0.911 / 0.950
#   +0.5 to +5 cm   0.915 to 0.919 / 0.950
#
# Enki's sigmoid turns grey 0.4 into 0.414, and saturates on white at (60 + 884 * 0.9936) / 1023 =
# 0.917: our 0.95 (the real robots on their bright boundary) is above anything Enki's Thymio reads.
# Enki's +-1 cm footprint blurs the edge, and its sigmoid's threshold (grey 0.44) lies so near the
# carpet's grey that the reading rises before the sensors reach the edge.


def ground_sweep(enki: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge offsets (cm) and ours and Enki's ground values (mean of the two sensors)."""
    world = lab_world(1)
    offsets, ours, theirs = [], [], []
    for p in enki["ground"]:
        # Enki's world has its corner at the origin, ours its centre.
        half = world.config.wall_half
        world.set_pose(0, *enki_pose(p["pose"], -half, -half))
        offsets.append(p["offset"])
        ours.append(world.sensor_matrix()[0, [G0, G1]].mean())
        theirs.append(np.mean(p["ground"]))
    return np.array(offsets), np.array(ours), np.array(theirs)


def test_ground_sensors_read_the_carpet_and_beyond_as_enki(enki):
    offsets, ours, theirs = ground_sweep(enki)
    rows = zip(offsets, ours, theirs, strict=True)
    message = "ours/enki\n" + "\n".join(f"{o:+.2f} cm: {a:.3f}/{b:.3f}" for o, a, b in rows)
    # Away from the edge by more than Enki's footprint (1 cm, 1.5 on the carpet side, where the
    # reading rises early): on the carpet Enki reads 0.412 to 0.416, ours 0.400 (the real carpet):
    # within 0.025 (the 0.016 measured plus Enki's noise, sd 0.002 over 20 steps).
    carpet = offsets <= -1.5
    assert np.abs(ours[carpet] - theirs[carpet]).max() <= 0.025, message
    # Beyond the edge Enki's white saturates at 0.917 (measured 0.916 to 0.919), ours reads 0.950
    # (the real robots over their boundary): within 0.04. Ours is the brighter.
    outside = offsets >= 1.0
    assert np.abs(ours[outside] - theirs[outside]).max() <= 0.04, message
    # What the difference matters for: the safety layer's boundary rule reads both alike there.
    threshold = SafetyConfig().ground_threshold
    assert (ours[carpet] < threshold).all() and (theirs[carpet] < threshold).all(), message
    assert (ours[outside] >= threshold).all() and (theirs[outside] >= threshold).all(), message


def test_enki_sees_the_carpet_edge_at_most_a_centimetre_before_ours(enki):
    offsets, ours, theirs = ground_sweep(enki)
    threshold = SafetyConfig().ground_threshold

    def crossing(values: np.ndarray) -> float:
        # Where the values first reach the threshold, interpolated between the sweep's points.
        k = int(np.argmax(values >= threshold))
        assert k > 0 and (values[k:] >= threshold).all()
        f = (threshold - values[k - 1]) / (values[k] - values[k - 1])
        return float(offsets[k - 1] + f * (offsets[k] - offsets[k - 1]))

    # Ours switches at the edge (to the sweep's resolution, 0.25 cm); Enki's reading crosses the
    # safety threshold 0.55 about 6 mm before the sensors reach the edge (measured -0.61 cm; its
    # footprint and sigmoid, see above). So its boundary rule fires at most a centimetre earlier
    # than ours, 0.08 s at full speed. Enki's transition rises steadily across its footprint.
    ours_at, enki_at = crossing(ours), crossing(theirs)
    assert abs(ours_at) <= 0.25
    assert -1.0 <= enki_at <= 0.0, f"Enki crosses {threshold} at {enki_at:+.2f} cm"
    blur = (offsets >= -1.5) & (offsets <= 1.0)
    assert (np.diff(theirs[blur]) > -0.01).all(), theirs[blur]
