"""What ``surprise-master calibrate`` computes and where it keeps it (docs/fleet.md,
"Calibration"): the safety layer's ground threshold between a robot's floor and rim readings,
each wheel's real speed per commanded speed from an overhead camera's poses, and the robot's
entry of the inventory rewritten with them, the rest of the file as it was.

The wheels' model is the Thymio's differential drive: a normalised command ``c`` on a wheel is
meant to drive it at ``c * max_speed``; a wheel that really drives at ``s * c * max_speed`` has
the scale ``s``. Driving both wheels at one command ``c``, the robot's forward speed is
``v = (s_l + s_r) / 2 * c * max_speed`` and its turn rate ``w = (s_r - s_l) * c * max_speed /
wheel_base``, so one straight drive filmed from above gives both scales:
``s_l = (v - w * wheel_base / 2) / (c * max_speed)``, ``s_r = (v + w * wheel_base / 2) / (c *
max_speed)``. The turn rate is the heading's slope over time, the forward speed the arc's
length between the drive's ends over the time (:func:`drive_speeds`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Final, Literal

import numpy as np
import yaml

from master_service.inventory import MAX_WHEEL_SCALE, Calibration, load_inventory
from minimize_surprise.errors import ConfigError
from minimize_surprise.files import write_atomic

__all__ = [
    "MIN_DRIVE_SECONDS",
    "MIN_GROUND_GAP",
    "CalibrationError",
    "drive_speeds",
    "ground_threshold",
    "wheel_scales",
    "write_calibration",
]

#: Floor and rim readings closer than this (normalised) cannot be told apart by a threshold:
#: the ground sensors' noise on a real carpet is a few hundredths.
MIN_GROUND_GAP: Final = 0.1
#: A drive shorter than this (seconds) gives too few camera frames for a scale within 1 %.
MIN_DRIVE_SECONDS: Final = 1.0
#: Frames averaged at each end of a drive for its start and end positions (the tracker's jitter
#: is a few millimetres per frame).
END_FRAMES: Final = 5


class CalibrationError(ValueError):
    """A measurement that cannot give a calibration: the message says what was measured."""


def ground_threshold(
    floor: tuple[float, ...], rim: tuple[float, ...], boundary: Literal["above", "below"]
) -> float:
    """The safety layer's ``ground_threshold`` for a robot whose ground sensors read ``floor``
    on the arena's floor and ``rim`` on its rim: midway between the floor's reading nearest the
    rim and the rim's nearest the floor, so that either sensor sees the rim and no sensor takes
    the floor for it. ``boundary``: ``above`` when the rim is the brighter (the ground rule
    fires at or above the threshold), ``below`` when it is the darker."""
    if boundary == "above":
        near_floor, near_rim = max(floor), min(rim)
    else:
        near_floor, near_rim = min(floor), max(rim)
    gap = near_rim - near_floor if boundary == "above" else near_floor - near_rim
    if gap < MIN_GROUND_GAP:
        side = "brighter" if boundary == "above" else "darker"
        raise CalibrationError(
            f"the floor reads {_values(floor)} and the rim {_values(rim)}: the rim must read "
            f"{side} than the floor by at least {MIN_GROUND_GAP} for a threshold between them "
            f"(ground_boundary: {boundary}); was the robot on the rim the second time?"
        )
    return round((near_floor + near_rim) / 2, 3)


def _span(times: np.ndarray) -> float:
    return float(times[-1] - times[0]) if len(times) > 1 else 0.0


def _values(values: tuple[float, ...]) -> str:
    return "/".join(f"{v:.2f}" for v in values)


def wheel_scales(
    times: np.ndarray,
    poses: np.ndarray,
    command: float,
    *,
    max_speed: float,
    wheel_base: float,
) -> tuple[float, float]:
    """Each wheel's real speed per commanded speed, (left, right), from ``poses`` (F, 3) tracked
    at ``times`` (F,) seconds while both wheels were commanded ``command`` (normalised, not 0);
    see the module docstring. Raises :class:`CalibrationError` for too short a drive or a scale
    beyond :data:`~master_service.inventory.MAX_WHEEL_SCALE`."""
    times = np.asarray(times, dtype=float)
    poses = np.asarray(poses, dtype=float)
    if len(times) < 2 or times[-1] - times[0] < MIN_DRIVE_SECONDS:
        raise CalibrationError(
            f"the camera followed the robot for {_span(times):.1f} s of its drive; at least "
            f"{MIN_DRIVE_SECONDS:g} s are needed"
        )
    if command == 0:
        raise CalibrationError("the wheels were commanded to stand still: nothing to measure")
    v, w = drive_speeds(times, poses)
    v = math.copysign(v, command)
    nominal = command * max_speed
    left = (v - w * wheel_base / 2) / nominal
    right = (v + w * wheel_base / 2) / nominal
    for name, scale in (("left", left), ("right", right)):
        if not 0 < scale <= MAX_WHEEL_SCALE:
            raise CalibrationError(
                f"the {name} wheel drove at {scale:.2f} of its command (forward {v * 100:.1f} "
                f"cm/s, turning {w:.2f} rad/s): a broken motor, a robot held, or another robot "
                "tracked"
            )
    return round(left, 4), round(right, 4)


def drive_speeds(times: np.ndarray, poses: np.ndarray) -> tuple[float, float]:
    """The forward speed (m/s, unsigned) and turn rate (rad/s) of a robot driving a constant
    arc, from its tracked ``poses`` (F, 3) at ``times`` (F,). The turn rate is the heading's
    least-squares slope; the speed the arc's length between the mean positions of the first and
    the last :data:`END_FRAMES` frames over the time between them (the chord, lengthened to the
    arc the turn rate gives). Summing frame-to-frame steps instead would count the tracker's
    jitter as distance."""
    times = np.asarray(times, dtype=float)
    poses = np.asarray(poses, dtype=float)
    heading = np.unwrap(poses[:, 2])
    w = float(np.polyfit(times, heading, 1)[0])
    k = max(1, min(END_FRAMES, len(times) // 4))
    start, end = poses[:k, :2].mean(axis=0), poses[-k:, :2].mean(axis=0)
    elapsed = float(times[-k:].mean() - times[:k].mean())
    chord = float(np.hypot(*(end - start)))
    half_turn = abs(w) * elapsed / 2
    arc = chord * half_turn / math.sin(half_turn) if half_turn > 1e-9 else chord
    return arc / elapsed, w


def write_calibration(
    path: str | Path,
    robot: str,
    *,
    ground_floor: tuple[float, float] | None = None,
    ground_rim: tuple[float, float] | None = None,
    wheels: tuple[float, float] | None = None,
) -> Calibration:
    """Write what was measured (the ground readings, the wheels' (left, right) scales) into
    ``robot``'s entry of the inventory at ``path``; what the entry held and was not measured
    again stays. Every other line of the file stays as it was
    (comments too): only the entry's ``calibration`` value is replaced, or added after its last
    key. Returns the entry's calibration as written."""
    path = Path(path)
    fleet = load_inventory(path)
    entry = fleet.robot(robot)
    if entry is None:
        raise ConfigError(f"no robot is named {robot!r}", file=str(path), key="robots")
    old = entry.calibration or Calibration()
    merged = Calibration(
        ground_floor=old.ground_floor if ground_floor is None else ground_floor,
        ground_rim=old.ground_rim if ground_rim is None else ground_rim,
        wheel_left=old.wheel_left if wheels is None else wheels[0],
        wheel_right=old.wheel_right if wheels is None else wheels[1],
    )
    text = path.read_text(encoding="utf-8")
    flow = _flow(merged)
    node = yaml.compose(text)
    robots = next(v for k, v in node.value if k.value == "robots")
    index = [r.name for r in fleet.robots].index(robot)
    item = robots.value[index]
    lines = text.splitlines(keepends=True)
    offsets = np.cumsum([0] + [len(line) for line in lines])
    existing = [(k, v) for k, v in item.value if k.value == "calibration"]
    if existing:
        value = existing[0][1]
        start, end = value.start_mark.index, value.end_mark.index
        if isinstance(value, yaml.MappingNode) and not value.flow_style and value.value:
            # A block mapping's mark ends where the next key starts: end at its last value.
            end = value.value[-1][1].end_mark.index
        text = text[:start] + flow + text[end:]
    elif item.flow_style:
        end = item.end_mark.index - 1  # the closing brace
        text = text[:end].rstrip() + f", calibration: {flow}" + text[end:]
    else:
        last = item.value[-1][1].end_mark
        column = item.value[0][0].start_mark.column
        # After the entry's last line (a block value ends at the start of the next line).
        line = last.line if last.column == 0 else last.line + 1
        at = int(offsets[min(line, len(lines))])
        before = "" if at == 0 or text[at - 1] == "\n" else "\n"
        text = text[:at] + before + " " * column + f"calibration: {flow}\n" + text[at:]
    # Checked before it replaces the file: an inventory this cannot edit stays as it was.
    check = path.with_name(f".{path.name}.calibrated")
    problem = None
    try:
        check.write_text(text, encoding="utf-8")
        written = load_inventory(check).robot(robot)
        if written is None or written.calibration != merged:
            problem = "it reads back otherwise"
    except ConfigError as exc:
        problem = str(exc)
    finally:
        check.unlink(missing_ok=True)
    if problem is not None:
        raise ConfigError(
            f"cannot write the calibration into this file's layout ({problem}); add it by "
            f"hand: calibration: {flow}",
            file=str(path),
            key=f"robots[{index}].calibration",
        )
    write_atomic(path, text.encode())
    return merged


def _flow(c: Calibration) -> str:
    parts = []
    if c.ground_floor is not None:
        parts.append(f"ground_floor: [{c.ground_floor[0]:.3f}, {c.ground_floor[1]:.3f}]")
    if c.ground_rim is not None:
        parts.append(f"ground_rim: [{c.ground_rim[0]:.3f}, {c.ground_rim[1]:.3f}]")
    parts.append(f"wheel_left: {c.wheel_left:.4f}")
    parts.append(f"wheel_right: {c.wheel_right:.4f}")
    return "{" + ", ".join(parts) + "}"
