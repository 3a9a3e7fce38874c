"""The safety layer: both profiles rule by rule, escape sequences step by step, and properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minimize_surprise.config import decode
from minimize_surprise.errors import ConfigError
from minimize_surprise.safety import (
    REASON_BACKWARD_LIMIT,
    REASON_CLAMP,
    REASON_ESCAPE,
    REASON_EXPERIMENTER,
    REASON_FORCE,
    REASON_FRONT,
    REASON_GROUND,
    REASON_INVALID,
    REASON_REAR,
    REASON_SENSOR,
    REASON_STALE,
    REASONS,
    STOP,
    Decision,
    SafetyConfig,
    SafetyLayer,
    SafetyState,
    apply_safety,
)
from minimize_surprise.sensors import ALL_SENSORS, GROUND_SENSORS, IR_SENSORS

BASIC = IR_SENSORS + GROUND_SENSORS  # the basic-behaviour robot
FULL = ALL_SENSORS  # the extended robot: + force + two light sensors
NAN = math.nan
INF = math.inf

STOP_LAYER = SafetyLayer(BASIC, SafetyConfig(profile="stop"))
ESCAPE_LAYER = SafetyLayer(FULL, SafetyConfig(profile="escape"))


def frame(sensors: tuple[str, ...] = BASIC, **by_name: float) -> np.ndarray:
    """Sensor values, all zero except the named ones (underscores stand for dots: ir_f0)."""
    values = np.zeros(len(sensors))
    for key, value in by_name.items():
        values[sensors.index(key.replace("_", "."))] = value
    return values


def full(**by_name: float) -> np.ndarray:
    return frame(FULL, **by_name)


# --------------------------------------------------------------------------- stop profile

STOP_CASES = [
    # id, command, sensors, expected command, expected reason
    ("forward-clear", (0.5, 0.5), {}, (0.5, 0.5), None),
    ("forward-front-f0", (0.5, 0.5), {"ir_f0": 0.8}, STOP, REASON_FRONT),
    ("forward-front-f4", (0.5, 0.5), {"ir_f4": 0.76}, STOP, REASON_FRONT),
    ("forward-front-at-threshold-passes", (0.5, 0.5), {"ir_f2": 0.75}, (0.5, 0.5), None),
    ("forward-ground-at-threshold", (0.5, 0.5), {"ground_0": 0.55}, STOP, REASON_GROUND),
    ("forward-ground-below", (0.5, 0.5), {"ground_1": 0.549}, (0.5, 0.5), None),
    ("forward-front-beats-ground", (1, 1), {"ir_f2": 0.9, "ground_0": 0.9}, STOP, REASON_FRONT),
    ("forward-rear-ignored", (0.5, 0.5), {"ir_b0": 0.9}, (0.5, 0.5), None),
    ("backward-clear", (-0.5, -0.5), {}, (-0.5, -0.5), None),
    ("backward-rear-b0", (-0.5, -0.5), {"ir_b0": 0.8}, STOP, REASON_REAR),
    ("backward-rear-b1", (-0.5, -0.5), {"ir_b1": 0.8}, STOP, REASON_REAR),
    ("backward-front-ignored", (-0.5, -0.5), {"ir_f2": 0.9}, (-0.5, -0.5), None),
    # The ground sensors sit at the front: a robot reversing away from the edge still sees it.
    ("backward-ground-passes", (-0.5, -0.5), {"ground_1": 0.6}, (-0.5, -0.5), None),
    ("spin-front-passes", (0.5, -0.5), {"ir_f2": 0.9}, (0.5, -0.5), None),
    ("spin-ground-passes", (-0.5, 0.5), {"ground_0": 0.9}, (-0.5, 0.5), None),
    ("pivot-ratio-1-is-straight", (1.0, 0.0), {"ir_f2": 0.9}, STOP, REASON_FRONT),
    ("wide-curve-is-straight", (1.0, 0.5), {"ir_f2": 0.9}, STOP, REASON_FRONT),
    ("tight-curve-passes", (1.0, -0.2), {"ir_f2": 0.9}, (1.0, -0.2), None),
    ("stopped-command-passes", (0.0, 0.0), {"ir_f2": 0.9}, (0.0, 0.0), None),
    ("clamp", (3.0, -7.0), {}, (1.0, -1.0), REASON_CLAMP),
    ("clamp-then-front", (3.0, 3.0), {"ir_f1": 0.9}, STOP, REASON_FRONT),
    ("nan-stops-both-wheels", (NAN, 0.5), {}, STOP, REASON_INVALID),
    ("inf-stops-both-wheels", (INF, INF), {"ir_f2": 0.9}, STOP, REASON_INVALID),
    ("minus-inf", (0.3, -INF), {}, STOP, REASON_INVALID),
    ("int-beyond-float", (10**400, 0.5), {}, STOP, REASON_INVALID),
    ("not-a-number", ("fast", 0.5), {}, STOP, REASON_INVALID),
    ("numpy-floats", (np.float32(0.25), np.float64(0.5)), {}, (0.25, 0.5), None),
]


@pytest.mark.parametrize(
    ("command", "sensors", "expected", "reason"),
    [case[1:] for case in STOP_CASES],
    ids=[case[0] for case in STOP_CASES],
)
def test_stop_profile(command, sensors, expected, reason):
    state = STOP_LAYER.initial_state()
    decision = STOP_LAYER.step(state, frame(**sensors), command)
    assert decision.command == expected
    assert decision.reason == reason
    assert decision.state == state  # the stop profile is stateless
    assert decision.intervened is (reason is not None)


def test_stop_profile_lets_a_robot_at_the_edge_back_away():
    # The paper keeps reversing robots in with the walls; stopping them too would trap a robot
    # that reached the edge for good (forward: stopped; backward: stopped as well).
    layer = SafetyLayer(BASIC, SafetyConfig())
    state = layer.initial_state()
    assert layer.step(state, frame(ground_0=0.9), (-1, -1)) == Decision((-1.0, -1.0), state, None)
    assert layer.step(state, frame(ground_0=0.9), (1, 1)).reason == REASON_GROUND


def test_stop_profile_ground_rule_can_cover_reversing_too():
    layer = SafetyLayer(BASIC, SafetyConfig(stop_ground_when_reversing=True))
    state = layer.initial_state()
    assert layer.step(state, frame(ground_1=0.6), (-0.5, -0.5)).reason == REASON_GROUND


def test_stop_profile_straight_ratio_is_configurable():
    strict = SafetyLayer(BASIC, SafetyConfig(straight_ratio=4.0))
    state = strict.initial_state()
    # (1.0, 0.5): |1.5 / -0.5| = 3 < 4, so with ratio 4 this curve is not straight.
    assert strict.step(state, frame(ir_f2=0.9), (1.0, 0.5)).reason is None
    assert strict.step(state, frame(ir_f2=0.9), (1.0, 0.8)).reason == REASON_FRONT


def test_stop_profile_ignores_force_and_has_no_backward_limit():
    layer = SafetyLayer(FULL, SafetyConfig(profile="stop"))
    assert REASON_FORCE not in layer.active_rules
    state = layer.initial_state()
    assert layer.step(state, full(force=1.0), (1, 1)).reason is None
    for _ in range(200):
        decision = layer.step(state, full(), (-1, -1))
        assert decision.command == (-1.0, -1.0)
        state = decision.state


# --------------------------------------------------------------------------- escape profile

ESCAPE_TRIGGERS = [
    # id, sensors, expected first command ("turn": on the spot, either direction), reason, phase
    ("clear-passes", {}, (0.4, 0.6), None, "idle"),
    ("front", {"ir_f2": 0.41}, (-1.0, -1.0), REASON_FRONT, "drive"),
    ("front-at-threshold-passes", {"ir_f0": 0.4}, (0.4, 0.6), None, "idle"),
    ("rear", {"ir_b1": 0.5}, (1.0, 1.0), REASON_REAR, "drive"),
    ("boxed-in-turns", {"ir_f2": 0.9, "ir_b0": 0.9}, "turn", REASON_FRONT, "turn"),
    (
        "rear-with-boundary-ahead-turns",
        {"ir_b0": 0.9, "ground_0": 0.6},
        "turn",
        REASON_REAR,
        "turn",
    ),
    ("rear-with-force-turns", {"ir_b0": 0.9, "force": 0.9}, "turn", REASON_REAR, "turn"),
    ("force", {"force": 0.46}, "turn", REASON_FORCE, "turn"),
    ("force-at-threshold-passes", {"force": 0.45}, (0.4, 0.6), None, "idle"),
    ("ground", {"ground_1": 0.55}, "turn", REASON_GROUND, "turn"),
    ("force-beats-ground", {"force": 0.9, "ground_1": 0.9}, "turn", REASON_FORCE, "turn"),
    ("light-is-ignored", {"light_0": 1.0, "light_1": 1.0}, (0.4, 0.6), None, "idle"),
]


@pytest.mark.parametrize(
    ("sensors", "expected", "reason", "phase"),
    [case[1:] for case in ESCAPE_TRIGGERS],
    ids=[case[0] for case in ESCAPE_TRIGGERS],
)
def test_escape_profile_triggers(sensors, expected, reason, phase):
    decision = ESCAPE_LAYER.step(ESCAPE_LAYER.initial_state(7), full(**sensors), (0.4, 0.6))
    if expected == "turn":
        left, right = decision.command
        assert abs(left) == 1.0 and right == -left
    else:
        assert decision.command == expected
    assert decision.reason == reason
    assert decision.state.phase == phase


def run(layer, state, steps, values, command=(0.3, 0.3)):
    """Run ``steps`` steps with the same inputs; return the decisions and the last state."""
    decisions = []
    for _ in range(steps):
        decision = layer.step(state, values, command)
        decisions.append(decision)
        state = decision.state
    return decisions, state


def turn_length(layer, state, values, command=(0.3, 0.3)):
    """Count the turn steps until the command passes again; check it is one steady spin."""
    first = None
    for n in range(1, 1000):
        decision = layer.step(state, values, command)
        state = decision.state
        if decision.reason is None:
            return n - 1, first, state
        assert decision.reason == REASON_ESCAPE
        first = first or decision.command
        assert decision.command == first and first[1] == -first[0] and abs(first[0]) == 1.0
    raise AssertionError("the turn never ended")


def test_front_escape_reverses_30_steps_then_turns_then_releases():
    layer, state = ESCAPE_LAYER, ESCAPE_LAYER.initial_state(1)
    first = layer.step(state, full(ir_f2=0.9), (1, 1))
    assert first.command == (-1.0, -1.0) and first.reason == REASON_FRONT
    # The obstacle is out of sight at once; the reverse still runs its full 30 steps.
    rest, state = run(layer, first.state, 29, full())
    assert [d.command for d in rest] == [(-1.0, -1.0)] * 29
    assert {d.reason for d in rest} == {REASON_ESCAPE}
    assert state.phase == "turn" and 25 <= state.steps_left <= 44
    n, spin, state = turn_length(layer, state, full())
    assert 25 <= n <= 44
    assert state == SafetyState(rng=state.rng)  # idle again, nothing left over
    # Pinned for seed 1, so that a change of the generator is noticed: traces replay exactly.
    assert (n, spin) == (PINNED_TURN_SEED_1, PINNED_SPIN_SEED_1)


def test_the_experimenter_starts_the_front_escape_whatever_the_network_commands():
    layer, state = ESCAPE_LAYER, ESCAPE_LAYER.initial_state(1)
    first = layer.step(state, full(), (1, 1), escape_now=True)
    assert first.command == (-1.0, -1.0) and first.reason == REASON_EXPERIMENTER
    rest, state = run(layer, first.state, 29, full())
    assert [d.command for d in rest] == [(-1.0, -1.0)] * 29
    assert {d.reason for d in rest} == {REASON_ESCAPE}
    # The same bounded manoeuvre as the layer's own: a turn of 25..44 steps, then idle.
    n, _, state = turn_length(layer, state, full())
    assert 25 <= n <= 44 and state == SafetyState(rng=state.rng)


def test_the_experimenter_restarts_a_running_manoeuvre_and_turns_when_boxed_in_behind():
    mid_turn = SafetyState(phase="turn", steps_left=3, direction=1, rng=5)
    again = ESCAPE_LAYER.step(mid_turn, full(), (0.2, 0.2), escape_now=True)
    assert again.reason == REASON_EXPERIMENTER and again.state.phase == "drive"
    assert again.state.steps_left == 29 and again.command == (-1.0, -1.0)
    # Something behind: reversing would hit it, so the escape only turns.
    behind = ESCAPE_LAYER.step(SafetyState(rng=5), full(ir_b0=0.9), (0, 0), escape_now=True)
    assert behind.reason == REASON_EXPERIMENTER and behind.state.phase == "turn"
    assert behind.command[0] == -behind.command[1] != 0


def test_the_experimenter_waits_for_usable_data_and_the_stop_profile_ignores_it():
    # Stale data stops the robot as always; the request is not used up (the caller asks again).
    stale = ESCAPE_LAYER.step(SafetyState(), full(), (1, 1), fresh=False, escape_now=True)
    assert stale == Decision(STOP, SafetyState(), REASON_STALE)
    # The stop profile has no escape behaviour to start.
    plain = STOP_LAYER.step(SafetyState(), frame(), (0.5, 0.5), escape_now=True)
    assert plain == Decision((0.5, 0.5), SafetyState(), None)


# Observed once for seed 1 and kept (see the test above).
PINNED_TURN_SEED_1 = 30
PINNED_SPIN_SEED_1 = (-1.0, 1.0)


def test_rear_escape_drives_forward_30_steps_then_turns():
    state = ESCAPE_LAYER.initial_state(3)
    decisions, state = run(ESCAPE_LAYER, state, 1, full(ir_b0=0.9), (-1, -1))
    decisions += run(ESCAPE_LAYER, state, 29, full(), (-1, -1))[0]
    state = decisions[-1].state
    assert [d.command for d in decisions] == [(1.0, 1.0)] * 30
    assert [d.reason for d in decisions] == [REASON_REAR] + [REASON_ESCAPE] * 29
    n, _, _ = turn_length(ESCAPE_LAYER, state, full())
    assert 25 <= n <= 44


def test_the_same_seed_gives_the_same_escape_and_seeds_differ():
    def escape(seed):
        state = ESCAPE_LAYER.initial_state(seed)
        state = ESCAPE_LAYER.step(state, full(force=0.9), (0, 0)).state
        return state.direction, state.steps_left

    assert escape(5) == escape(5)
    draws = {escape(seed) for seed in range(200)}
    assert {d for d, _ in draws} == {-1, 1}
    # The trigger step was the first of the turn: 25..44 drawn, 24..43 left.
    assert {n for _, n in draws} == set(range(24, 44))
    # The seed keeps flowing: two escapes in a row draw different turns (almost surely).
    state = ESCAPE_LAYER.initial_state(5)
    state = ESCAPE_LAYER.step(state, full(force=0.9), (0, 0)).state
    _, _, state = turn_length(ESCAPE_LAYER, state, full())
    again = ESCAPE_LAYER.step(state, full(force=0.9), (0, 0)).state
    assert again.rng != ESCAPE_LAYER.initial_state(5).rng


def test_force_turn_lasts_the_drawn_steps_then_releases():
    state = ESCAPE_LAYER.step(ESCAPE_LAYER.initial_state(11), full(force=0.9), (1, 1)).state
    drawn = state.steps_left + 1  # the trigger step was the first of the turn
    n, _, state = turn_length(ESCAPE_LAYER, state, full())
    assert n + 1 == drawn and state.phase == "idle"


def test_a_turn_is_not_interrupted_by_new_obstacles():
    state = ESCAPE_LAYER.step(ESCAPE_LAYER.initial_state(2), full(ground_0=0.9), (1, 1)).state
    spin = (state.direction * 1.0, -state.direction * 1.0)
    decision = ESCAPE_LAYER.step(state, full(ir_f2=1.0, ir_b0=1.0, force=1.0), (1, 1))
    assert decision.command == spin and decision.reason == REASON_ESCAPE


def test_reverse_that_meets_a_rear_obstacle_turns_at_once():
    _, state = run(ESCAPE_LAYER, ESCAPE_LAYER.initial_state(4), 10, full(ir_f2=0.9))
    assert state.phase == "drive"
    decision = ESCAPE_LAYER.step(state, full(ir_b1=0.9), (0, 0))
    assert decision.reason == REASON_REAR and decision.state.phase == "turn"
    assert decision.command[1] == -decision.command[0] != 0


@pytest.mark.parametrize("blocker", ["ir_f1", "force", "ground_0"])
def test_forward_escape_that_meets_something_ahead_turns_at_once(blocker):
    _, state = run(ESCAPE_LAYER, ESCAPE_LAYER.initial_state(4), 5, full(ir_b0=0.9))
    decision = ESCAPE_LAYER.step(state, full(**{blocker: 0.95}), (0, 0))
    assert decision.state.phase == "turn"
    assert decision.reason == {"ir_f1": REASON_FRONT, "force": REASON_FORCE}.get(
        blocker, REASON_GROUND
    )


def test_zero_drive_steps_turn_at_once():
    layer = SafetyLayer(FULL, SafetyConfig(profile="escape", escape_drive_steps=0))
    decision = layer.step(layer.initial_state(), full(ir_f2=0.9), (1, 1))
    assert decision.reason == REASON_FRONT and decision.state.phase == "turn"


def test_escape_speeds_and_lengths_come_from_the_configuration():
    cfg = SafetyConfig(
        profile="escape", escape_drive_steps=3, escape_speed=0.5, turn_speed=0.25,
        turn_steps_min=2, turn_steps_max=2,
    )  # fmt: skip
    layer = SafetyLayer(FULL, cfg)
    decisions, state = run(layer, layer.initial_state(), 1, full(ir_f2=0.9))
    decisions += run(layer, state, 5, full())[0]
    commands = [d.command for d in decisions]
    assert commands[:3] == [(-0.5, -0.5)] * 3
    assert commands[3] in [(0.25, -0.25), (-0.25, 0.25)] and commands[4] == commands[3]
    assert commands[5] == (0.3, 0.3) and decisions[5].reason is None


# --------------------------------------------------------------------------- backward limit


def test_backward_limit_stops_after_90_steps_until_a_positive_motor_value():
    layer, state = ESCAPE_LAYER, ESCAPE_LAYER.initial_state()
    decisions, state = run(layer, state, 90, full(), (-0.5, -1.0))
    assert all(d.command == (-0.5, -1.0) and d.reason is None for d in decisions)
    decisions, state = run(layer, state, 5, full(), (-0.5, -1.0))
    assert all(d.command == STOP and d.reason == REASON_BACKWARD_LIMIT for d in decisions)
    # A stop command neither extends nor resets the run of backward steps.
    decision = layer.step(state, full(), (0.0, 0.0))
    assert decision.reason is None and decision.state.backward_steps == state.backward_steps
    assert layer.step(decision.state, full(), (-0.1, 0.0)).reason == REASON_BACKWARD_LIMIT
    # One positive motor value, even on one wheel, resets it.
    decision = layer.step(state, full(), (0.2, -1.0))
    assert decision.command == (0.2, -1.0) and decision.state.backward_steps == 0
    assert layer.step(decision.state, full(), (-1, -1)).reason is None


def test_backward_limit_counts_the_intent_even_during_an_escape():
    layer = ESCAPE_LAYER
    _, state = run(layer, layer.initial_state(), 85, full(), (-1, -1))
    decisions, state = run(layer, state, 1, full(ir_b0=0.9), (-1, -1))
    decisions += run(layer, state, 70, full(), (-1, -1))[0]
    assert decisions[0].reason == REASON_REAR
    assert all(d.reason != REASON_BACKWARD_LIMIT for d in decisions if d.state.phase != "idle")
    assert decisions[-1].reason == REASON_BACKWARD_LIMIT  # at once when the manoeuvre ends


def test_backward_limit_can_be_switched_off():
    layer = SafetyLayer(FULL, SafetyConfig(profile="escape", backward_limit_steps=None))
    decisions, _ = run(layer, layer.initial_state(), 300, full(), (-1, -1))
    assert {d.reason for d in decisions} == {None}


# --------------------------------------------------------------------------- reset, stale, sensors


def test_a_new_genome_resets_the_escape_and_the_backward_count_but_not_the_random_stream():
    _, state = run(ESCAPE_LAYER, ESCAPE_LAYER.initial_state(9), 95, full(), (-1, -1))
    state = ESCAPE_LAYER.step(state, full(force=0.9), (-1, -1)).state
    assert state.phase == "turn" and state.backward_steps == 96
    fresh = ESCAPE_LAYER.reset(state)
    assert fresh == SafetyState(rng=state.rng)
    assert ESCAPE_LAYER.step(fresh, full(), (-1, -1)) == Decision(
        (-1.0, -1.0), SafetyState(backward_steps=1, rng=state.rng), None
    )


@pytest.mark.parametrize(
    ("fresh", "age"),
    [(False, None), (False, 0.0), (True, 0.26), (True, NAN), (True, INF)],
    ids=["not-fresh", "not-fresh-young", "too-old", "nan-age", "inf-age"],
)
@pytest.mark.parametrize("layer", [STOP_LAYER, ESCAPE_LAYER], ids=["stop", "escape"])
def test_stale_data_stops_and_freezes_the_state(layer, fresh, age):
    values = np.zeros(len(layer.sensors))
    mid_escape = SafetyState(phase="drive", steps_left=12, direction=-1, backward_steps=3, rng=5)
    decision = layer.step(mid_escape, values, (1, 1), fresh=fresh, age=age)
    assert decision == Decision(STOP, mid_escape, REASON_STALE)


@pytest.mark.parametrize("age", [None, 0.0, 0.25], ids=["unknown", "new", "at-limit"])
def test_fresh_enough_data_passes(age):
    assert STOP_LAYER.step(SafetyState(), frame(), (1, 1), age=age).reason is None


def test_max_frame_age_none_trusts_the_fresh_flag():
    layer = SafetyLayer(BASIC, SafetyConfig(max_frame_age=None))
    assert layer.step(SafetyState(), frame(), (1, 1), age=10.0).reason is None
    assert layer.step(SafetyState(), frame(), (1, 1), fresh=False).reason == REASON_STALE


@pytest.mark.parametrize("bad", [NAN, INF, -INF], ids=["nan", "inf", "-inf"])
def test_non_finite_sensor_values_stop_but_only_for_sensors_a_rule_reads(bad):
    assert ESCAPE_LAYER.step(SafetyState(), full(ground_1=bad), (1, 1)) == Decision(
        STOP, SafetyState(), REASON_SENSOR
    )
    assert ESCAPE_LAYER.step(SafetyState(), full(light_0=bad), (1, 1)).reason is None
    # The stop profile has no force rule, so a broken force sensor does not stop it.
    layer = SafetyLayer(FULL, SafetyConfig(profile="stop"))
    assert layer.step(SafetyState(), full(force=bad), (1, 1)).reason is None


MISSING = [
    # id, layout, profile, active rules
    ("basic-stop", BASIC, "stop", ("front", "rear", "ground")),
    ("basic-escape-no-force", BASIC, "escape", ("front", "rear", "ground")),
    ("full-escape", FULL, "escape", ("front", "rear", "force", "ground")),
    ("centre-ir-only", ("ir.f2",), "escape", ("front",)),
    ("no-ground", (*IR_SENSORS, "force"), "escape", ("front", "rear", "force")),
    ("lights-only", ("light.0", "light.1"), "escape", ()),
]


@pytest.mark.parametrize(
    ("sensors", "profile", "rules"), [m[1:] for m in MISSING], ids=[m[0] for m in MISSING]
)
def test_missing_sensors_switch_their_rules_off(sensors, profile, rules):
    layer = SafetyLayer(sensors, SafetyConfig(profile=profile))
    assert layer.active_rules == rules
    # Whatever the present sensors read, a rule without sensors never fires.
    everything = np.ones(len(sensors))
    decision = layer.step(layer.initial_state(), everything, (1, 1))
    assert (decision.reason in rules) if rules else decision.reason is None


def test_the_layout_is_checked():
    with pytest.raises(ValueError, match="unknown sensor"):
        SafetyLayer(("ir.f9",))
    with pytest.raises(ValueError, match="expected 9 sensor values"):
        STOP_LAYER.step(SafetyState(), np.zeros(8), (0, 0))


def test_apply_safety_is_the_same_function():
    cfg = SafetyConfig(profile="escape")
    state = SafetyState(rng=3)
    for values in (full(), full(ir_f2=0.9), full(force=0.9)):
        assert apply_safety(values, FULL, (0.5, 0.2), state, cfg) == ESCAPE_LAYER.step(
            state, values, (0.5, 0.2)
        )


def test_reasons_are_short_distinct_strings():
    assert len(set(REASONS)) == len(REASONS) == 11
    assert all(r == r.strip().lower() and len(r) <= 16 for r in REASONS)


# --------------------------------------------------------------------------- configuration


def test_defaults_are_the_authors():
    cfg = SafetyConfig()
    assert (cfg.profile, cfg.stop_ir_threshold, cfg.ground_threshold) == ("stop", 0.75, 0.55)
    assert (cfg.escape_front_threshold, cfg.escape_rear_threshold, cfg.force_threshold) == (
        0.4, 0.4, 0.45,
    )  # fmt: skip
    assert (cfg.escape_drive_steps, cfg.turn_steps_min, cfg.turn_steps_max) == (30, 25, 44)
    assert cfg.backward_limit_steps == 90


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"turn_steps_min": 30, "turn_steps_max": 20}, "turn_steps_max"),
        ({"profile": "bounce"}, "profile"),
        ({"stop_ir_threshold": 1.5}, "stop_ir_threshold"),
        ({"escape_speed": 0}, "escape_speed"),
        ({"force_treshold": 0.3}, "force_treshold"),
    ],
    ids=["turn-range", "profile", "threshold", "speed", "typo"],
)
def test_bad_configuration_names_the_key(data, key):
    with pytest.raises(ConfigError) as err:
        decode(data, SafetyConfig, file="agent.yaml")
    assert err.value.key == key


# --------------------------------------------------------------------------- properties

any_float = st.floats(allow_nan=True, allow_infinity=True)
unit = st.floats(min_value=0.0, max_value=1.0)
basic_frames = st.lists(unit, min_size=len(BASIC), max_size=len(BASIC)).map(np.array)
full_frames = st.lists(unit, min_size=len(FULL), max_size=len(FULL)).map(np.array)


@given(
    left=any_float, right=any_float, values=full_frames, profile=st.sampled_from(["stop", "escape"])
)
def test_output_is_always_finite_and_in_range(left, right, values, profile):
    layer = SafetyLayer(FULL, SafetyConfig(profile=profile))
    decision = layer.step(layer.initial_state(), values, (left, right))
    assert all(math.isfinite(x) and -1.0 <= x <= 1.0 for x in decision.command)
    assert decision.reason in (None, *REASONS)


forward_straight = st.tuples(
    st.floats(min_value=0.0, max_value=1e300), st.floats(min_value=0.0, max_value=1e300)
).filter(lambda c: c[0] + c[1] > 0)


@given(
    command=forward_straight,
    values=basic_frames,
    which=st.sampled_from(IR_SENSORS[:5]),
    level=st.floats(min_value=0.7500001, max_value=1.0),
)
def test_stop_profile_always_stops_a_forward_drive_at_a_front_obstacle(
    command, values, which, level
):
    values[BASIC.index(which)] = level
    decision = STOP_LAYER.step(SafetyState(), values, command)
    assert decision.command == STOP
    assert decision.reason in (REASON_FRONT, REASON_GROUND)


@given(
    left=st.floats(min_value=-1.0, max_value=1.0),
    right=st.floats(min_value=-1.0, max_value=1.0),
    profile=st.sampled_from(["stop", "escape"]),
)
def test_a_sane_command_in_a_clear_world_passes_unchanged(left, right, profile):
    layer = SafetyLayer(FULL, SafetyConfig(profile=profile))
    decision = layer.step(layer.initial_state(), full(), (left, right))
    assert decision.command == (left, right) and decision.reason is None


@settings(max_examples=60)
@given(
    steps=st.lists(st.tuples(full_frames, any_float, any_float), min_size=1, max_size=120),
    seed=st.integers(min_value=0, max_value=2**64 - 1),
)
def test_escape_state_stays_consistent_over_any_sequence(steps, seed):
    layer = ESCAPE_LAYER
    state = layer.initial_state(seed)
    for values, left, right in steps:
        decision = layer.step(state, values, (left, right))
        state = decision.state
        assert all(math.isfinite(x) and -1.0 <= x <= 1.0 for x in decision.command)
        assert state.backward_steps >= 0
        if state.phase == "idle":
            assert state.steps_left == 0 and state.direction == 0
        else:
            assert state.steps_left >= 1 and state.direction in (-1, 1)
        if decision.reason == REASON_ESCAPE:
            assert decision.command in [(-1.0, -1.0), (1.0, 1.0), (1.0, -1.0), (-1.0, 1.0)]
