"""The statistics against values computed by hand on small samples."""

from __future__ import annotations

import math

import pytest

from studies.stats import bonferroni, fisher, kruskal_wallis, mann_whitney


def test_mann_whitney_u_counts_the_pairs_won():
    # a = [1, 2, 3], b = [4, 5]: a wins no pair, U(a) = 0; exact two-sided p = 2 / C(5, 2) = 0.2.
    result = mann_whitney([1, 2, 3], [4, 5])
    assert result["U"] == 0.0
    assert result["p"] == pytest.approx(0.2)
    # One tie counts a half: a = [1, 4], b = [4, 5] -> pairs won by a: (4 vs 4) half = 0.5.
    assert mann_whitney([1, 4], [4, 5])["U"] == 0.5


def test_kruskal_wallis_h_by_hand():
    # Ranks 1..6 over groups [1, 2], [3, 4], [5, 6]: R = 3, 7, 11, n = 2 each, N = 6.
    # H = 12 / (N (N + 1)) * sum(R^2 / n) - 3 (N + 1) = 12/42 * (9 + 49 + 121) / 2 - 21 = 4.5714
    result = kruskal_wallis([[1, 2], [3, 4], [5, 6]])
    assert result["H"] == pytest.approx(12 / 42 * (9 + 49 + 121) / 2 - 21)
    assert result["p"] == pytest.approx(math.exp(-result["H"] / 2))  # chi2 with 2 dof


def test_fisher_exact_on_a_two_by_two_table_by_hand():
    # [[3, 0], [0, 3]]: the only table as extreme with these margins; P = 1 / C(6, 3) = 0.05,
    # two-sided: the other extreme [[0, 3], [3, 0]] too: 0.1.
    assert fisher([[3, 0], [0, 3]])["p"] == pytest.approx(0.1)
    assert fisher([[2, 1], [1, 2]])["p"] == pytest.approx(1.0)


def test_fisher_drops_empty_columns_and_handles_one_class():
    assert fisher([[3, 0, 0], [0, 0, 3]])["p"] == pytest.approx(0.1)
    assert fisher([[4], [5]])["p"] == 1.0


def test_fisher_on_a_two_by_three_table_gives_a_number():
    # [[3, 0, 0], [0, 1, 1]]: the rows share no class, the most extreme table with these
    # margins: P = 1 / C(5, 3) = 0.1 (the tables as probable or less: this one only). scipy 1.17
    # answers an array of one here, drawn by Monte Carlo (9999 tables: within 0.01 here at 3
    # standard errors), from a fixed seed: the same each time.
    result = fisher([[3, 0, 0], [0, 1, 1]])
    assert isinstance(result["p"], float) and result["p"] == pytest.approx(0.1, abs=0.01)
    assert fisher([[3, 0, 0], [0, 1, 1]]) == result


def test_bonferroni_multiplies_by_the_family_size_and_caps_at_one():
    assert bonferroni([0.01, 0.2, 0.5]) == pytest.approx([0.03, 0.6, 1.0])
    assert bonferroni([]) == []
