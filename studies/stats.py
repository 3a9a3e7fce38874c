"""The statistics the paper uses, on top of scipy.stats (docs/studies.md).

* Mann-Whitney U (two-sided) between two samples, e.g. evolved against random per arena;
* Kruskal-Wallis across several samples, e.g. across arena sizes;
* Fisher's exact test on a contingency table of behaviour counts (r x c tables included);
* Bonferroni correction of a family of p-values.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats

__all__ = ["bonferroni", "fisher", "kruskal_wallis", "mann_whitney"]

#: Tables drawn for Fisher's test on an r x c table (scipy's default): p within about 0.006.
_RESAMPLES = 9999


def mann_whitney(a: Sequence[float], b: Sequence[float]) -> dict[str, float]:
    """Two-sided Mann-Whitney U test of ``a`` against ``b``: ``U`` (of ``a``) and ``p``."""
    result = stats.mannwhitneyu(np.asarray(a, float), np.asarray(b, float), alternative="two-sided")
    return {"U": float(result.statistic), "p": float(result.pvalue)}


def kruskal_wallis(samples: Sequence[Sequence[float]]) -> dict[str, float]:
    """Kruskal-Wallis H test across ``samples``: ``H`` and ``p``."""
    result = stats.kruskal(*(np.asarray(s, float) for s in samples))
    return {"H": float(result.statistic), "p": float(result.pvalue)}


def fisher(table: Sequence[Sequence[int]]) -> dict[str, float]:
    """Fisher's exact test of a contingency table (rows: samples, columns: classes); columns
    counting nothing are dropped. ``p`` is 1 when fewer than two columns remain. Larger than
    2 x 2, ``p`` is drawn (Monte Carlo, 9999 tables) from a fixed seed."""
    counts = np.asarray(table, dtype=np.int64)
    counts = counts[:, counts.sum(axis=0) > 0]
    if counts.shape[1] < 2 or counts.shape[0] < 2:
        return {"p": 1.0}
    if counts.shape == (2, 2):
        result = stats.fisher_exact(counts)
    else:
        # scipy draws an r x c table's p-value by Monte Carlo, unseeded: another each report.
        # Seeded, the same runs give the same statistics.csv. (Exact permutations would cost
        # 0.5 s a test against 5 ms, and a grid study's report has hundreds.)
        method = stats.MonteCarloMethod(n_resamples=_RESAMPLES, rng=np.random.default_rng(0))
        result = stats.fisher_exact(counts, method=method)
    # scipy 1.17 gives an r x c table's p-value as an array of one when a row's counts are all
    # in other columns than the other row's (e.g. [[3, 0, 0], [0, 1, 1]]).
    out = {"p": float(np.ravel(result.pvalue)[0])}
    if counts.shape == (2, 2):
        out["odds_ratio"] = float(np.ravel(result.statistic)[0])
    return out


def bonferroni(p_values: Sequence[float]) -> list[float]:
    """Each p-value times the size of its family, capped at 1."""
    m = len(p_values)
    return [min(1.0, p * m) for p in p_values]
