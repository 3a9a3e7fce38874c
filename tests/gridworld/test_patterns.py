"""The nine patterns on hand-made grids whose answer is known, with ties and near misses."""

from __future__ import annotations

import pytest

from gridworld.patterns import PATTERNS, Grid, classify, clusters, poses_of, scores

E, W, N, S = (1, 0), (-1, 0), (0, 1), (0, -1)


def grid_scores(cells, size=15):
    return scores(Grid(size, size, poses_of([(x, y, *h) for x, y, h in cells])))


def classified(cells, size=15):
    return classify(size, size, poses_of([(x, y, *h) for x, y, h in cells]))


def block(x0, y0, w, h, heading=N):
    return [(x, y, heading) for x in range(x0, x0 + w) for y in range(y0, y0 + h)]


def test_a_line_with_ends_facing_in():
    line = [(3, 5, E), (4, 5, E), (5, 5, W), (6, 5, E), (7, 5, W)]
    c = classified(line)
    assert (c.pattern, c.quality) == ("LN", 1.0)


def test_a_line_one_agent_short_is_a_pair():
    # the left end faces out and is dropped; two agents are not a line, but they are a pair
    s = grid_scores([(3, 5, W), (4, 5, E), (5, 5, W)])
    assert s["LN"] == 0.0
    assert s["PR"] == pytest.approx(2 / 3)


def test_ends_must_face_opposite_ways_after_trimming():
    # both ends face east: the right end does not face into the run, trimming eats the line
    assert grid_scores([(3, 5, E), (4, 5, E), (5, 5, E), (6, 5, E)])["LN"] == 0.0


def test_a_line_with_two_adjacent_agents_beside_it_is_rejected():
    line = [(3, 5, E), (4, 5, E), (5, 5, W), (6, 5, W)]
    apart = grid_scores([*line, (3, 6, N), (5, 6, N)])
    assert apart["LN"] == pytest.approx(4 / 6)
    adjacent = grid_scores([*line, (3, 6, N), (4, 6, N)])
    assert adjacent["LN"] == 0.0


def test_a_full_row_is_a_line_whatever_its_ends():
    row = [(x, 2, E if x % 3 else W) for x in range(15)]
    assert classified(row).pattern == "LN"
    assert grid_scores(row)["LN"] == 1.0


def test_a_column_wrapping_around_the_torus():
    column = [(4, 13, N), (4, 14, N), (4, 0, S), (4, 1, S)]
    assert grid_scores(column)["LN"] == 1.0


def test_pairs_and_their_flanks():
    pair = [(5, 5, E), (6, 5, W)]
    assert classified(pair).pattern == "PR"
    same_side = grid_scores([*pair, (5, 6, N), (6, 6, N)])
    assert same_side["PR"] == 0.0
    opposite_sides = grid_scores([*pair, (5, 6, N), (6, 4, S)])
    assert opposite_sides["PR"] == 0.5
    not_facing = grid_scores([(5, 5, E), (6, 5, N)])
    assert not_facing["PR"] == 0.0


def test_squares_and_a_near_miss():
    square = [(2, 2, N), (4, 2, E), (2, 4, S), (4, 4, W)]
    assert classified(square).pattern == "SQ"
    assert grid_scores(square)["SQ"] == 1.0
    assert grid_scores([*square, (1, 1, N)])["SQ"] == 0.0  # a corner of the box is occupied
    assert grid_scores([*square, (10, 10, N)])["SQ"] == pytest.approx(0.8)


def test_triangular_lattice_and_a_near_miss():
    offsets = [(0, 0), (2, 0), (-2, 0), (0, 2), (0, -2), (1, 1), (1, -1), (-1, 1), (-1, -1)]
    lattice = [(7 + dx, 7 + dy, N) for dx, dy in offsets]
    assert classified(lattice).pattern == "TL"
    assert grid_scores(lattice)["TL"] == 1.0
    assert grid_scores(lattice[:-1])["TL"] == 0.0
    assert grid_scores([*lattice, (8, 7, N)])["TL"] == 0.0  # (1, 0) must be empty


def test_a_swirl_and_a_block_that_is_not_one():
    swirl = [(5, 5, E), (6, 5, N), (6, 6, W), (5, 6, S)]
    assert classified(swirl).pattern == "SW"
    assert grid_scores(swirl)["SW"] == 1.0
    other_way = [(5, 5, N), (5, 6, E), (6, 6, S), (6, 5, W)]
    assert grid_scores(other_way)["SW"] == 1.0
    same_heading = block(5, 5, 2, 2, E)
    s = grid_scores(same_heading)
    assert s["SW"] == 0.0
    # nothing else either: every score is 0, and the tie goes to the first pattern (CL)
    assert all(v == 0.0 for v in s.values())
    assert classified(same_heading).pattern == PATTERNS[0] == "CL"
    crowded = grid_scores([*swirl, (4, 4, N), (7, 7, N)])
    assert crowded["SW"] == 0.0
    one_neighbour = grid_scores([*swirl, (4, 4, N)])
    assert one_neighbour["SW"] == pytest.approx(0.8)


def test_random_dispersion_excludes_structures():
    apart = [(0, 0, N), (5, 0, E), (10, 5, S), (3, 9, W)]
    assert classified(apart).pattern == "RD"
    assert grid_scores(apart)["RD"] == 1.0
    # a pair has one Moore neighbour each, but belongs to a pair
    assert grid_scores([(5, 5, E), (6, 5, W), (0, 0, N)])["RD"] == pytest.approx(1 / 3)
    # one diagonal neighbour: still dispersed (0 von Neumann neighbours)
    assert grid_scores([(1, 1, N), (2, 2, N), (3, 3, N)])["RD"] == 1.0


def test_aggregation_clustering_and_loose_grouping():
    one = block(0, 0, 5, 5)
    c = classified(one)
    assert (c.pattern, c.quality) == ("AG", 1.0)
    two_apart = block(0, 0, 5, 5) + block(8, 8, 5, 5)
    c = classified(two_apart, size=20)
    assert (c.pattern, c.quality) == ("CL", 1.0)
    # two blocks touching at one corner: two clusters (no two cores adjacent), linked
    touching = block(0, 0, 5, 5) + block(5, 4, 5, 5)
    grid = Grid(20, 20, poses_of([(x, y, *h) for x, y, h in touching]))
    assert len(clusters(grid)) == 2
    c = classified(touching, size=20)
    assert (c.pattern, c.quality) == ("LG", 1.0)
    # grouping's fraction counts the cluster members only
    s = grid_scores([*one, (10, 10, N)])
    assert s["AG"] == pytest.approx(25 / 26) and s["RD"] == pytest.approx(1 / 26)


def test_ties_go_to_the_earlier_pattern():
    # four agents in a line, four in two pairs: LN and PR tie at 0.5, LN comes first
    line = [(1, 1, E), (2, 1, E), (3, 1, W), (4, 1, W)]
    pairs = [(1, 8, E), (2, 8, W), (8, 12, N), (8, 13, S)]
    c = classified(line + pairs)
    assert c.scores["LN"] == c.scores["PR"] == 0.5
    assert c.pattern == "LN"


def test_two_agents_on_one_cell_are_refused():
    with pytest.raises(ValueError, match="share cell"):
        classified([(1, 1, E), (16, 1, N)])
