"""When the safety layer drove most of a run: a note when that is the evolved behaviour (robots
held against each other or a wall), a warning when a person should fix the set-up."""

from __future__ import annotations

from minimize_surprise.dominance import dominance


def test_below_half_the_steps_nothing_is_said() -> None:
    assert dominance(0.5, [{"front": 50}]) is None


def test_robots_held_against_neighbours_are_a_note_in_the_papers_terms() -> None:
    found = dominance(0.78, [{"front": 70, "ground": 2}, {"front": 6}])
    assert found is not None and not found.actionable
    assert "78 %" in found.text and "stopped robots" in found.text
    assert "not a fault" in found.text


def test_a_floor_that_trips_the_ground_rule_is_a_warning_naming_what_to_check() -> None:
    found = dominance(0.95, [{"ground": 90, "front": 5}])
    assert found is not None and found.actionable
    assert "safety.ground_threshold" in found.text


def test_an_unknown_reason_is_worth_a_look() -> None:
    found = dominance(1.0, [])
    assert found is not None and found.actionable


def test_robots_held_at_the_arenas_edge_are_told_from_a_floor_taken_for_the_edge() -> None:
    # Robots start on the floor, away from its edge: a wrong floor stops them at once, an
    # evolved approach to the edge only later.
    from minimize_surprise.dominance import START_STEPS, ground_at_start

    counts = [{"ground": 90, "front": 5}]
    later = [[""] * START_STEPS + ["ground"] * 20, ["", "front"] * 3 + ["ground"] * 20]
    at_once = [["ground"] * 25, ["", "ground"] + ["ground"] * 20, [""] * 30]
    assert ground_at_start(later) == 0.0 and ground_at_start(at_once) == 2 / 3
    assert ground_at_start([]) is None
    edge = dominance(0.95, counts, at_start=ground_at_start(later))
    assert edge is not None and not edge.actionable
    assert "edge of the arena" in edge.text and "not a fault" in edge.text
    floor = dominance(0.95, counts, at_start=ground_at_start(at_once))
    assert floor is not None and floor.actionable and "safety.ground_threshold" in floor.text
    # Other reasons are judged as before, whatever the start.
    assert dominance(0.95, [{"force": 9}], at_start=0.0).actionable
