"""Classes found, not set: a study's behaviours clustered without the paper's hand thresholds
(docs/studies.md, "Classes found by the data").

The paper classes a run by thresholds on its metrics (rotation c_o, mean cluster size, d_R, d_B,
the backward share; the grid world by its pattern scores). This module asks the data instead:
each run's features, standardised (zero mean, unit variance per feature), projected by PCA onto
the plane of the figure, and clustered by density in that plane (HDBSCAN, which needs no number
of clusters and leaves outliers as noise). The agreement with the hand-set classes is the
adjusted Rand index (1: the same partition, about 0: no better than chance) and the purity.
Runs of the Thymio arenas and of the grid world are clustered apart, each arena scenario on its
own: their features and the paper's classes differ.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

__all__ = [
    "ARENA_FEATURES",
    "MIN_RUNS",
    "SENSOR_FEATURES",
    "Clustering",
    "cluster_behaviours",
    "clusters_figure",
    "clusters_markdown",
    "clusters_table",
    "features",
]

#: The Thymio runs' features: the metrics the paper's classes are thresholds on, what the
#: safety layer did (a behaviour that leans on the layer looks different from one that does not),
#: and features of the post-evaluation's trace that no threshold uses: how fast the robots turn
#: and how often they stand still, how close their nearest neighbour is
#: (:mod:`simulator.metrics`), and what their sensors read on average (:data:`SENSOR_FEATURES`).
ARENA_FEATURES: Final = (
    "rotation",
    "mean_cluster_size",
    "distance_covered",
    "box_displacement",
    "backward_share",
    "safety_share",
    "turn_rate",
    "still_share",
    "neighbour_distance",
)
#: Sensor families whose mean reading over the post-evaluation (every robot, every sensor of the
#: family) is a feature, named ``<family>_mean``: near walls and robots the IR reads high, on the
#: rim the ground low, among boxes the force high, near the lamp the light high.
SENSOR_FEATURES: Final = ("ir", "ground", "force", "light")
#: HDBSCAN's smallest cluster, in runs: with three, a class of ten runs whose metrics vary only
#: by noise was split in two for 3 of 3 seeds (tests/studies/test_study_clusters.py's runs), with
#: five for none. Fewer runs than :data:`MIN_RUNS` in a family are not clustered: two clusters
#: need that many.
MIN_CLUSTER: Final = 5
MIN_RUNS: Final = 2 * MIN_CLUSTER
#: The principal components the clustering sees: the plane the figure shows. In more, the runs of
#: a family (40 in an object arena) are too thin for a density: with the components holding 90 %
#: of the variance the trace features took the object arenas' agreement down, not up
#: (docs/studies.md, "Classes found by the data").
CLUSTERED_COMPONENTS: Final = 2
#: HDBSCAN's smallest cluster is at least this fraction of the runs: a behaviour one run in ten
#: shows is a class; fewer is an outlier.
SMALLEST_SHARE: Final = 10
#: Noise, as HDBSCAN labels it.
NOISE: Final = -1


@dataclass(frozen=True)
class Clustering:
    """One family's clustering: its ``runs`` (names), the ``features`` used, each run's cluster
    (``labels``, -1 noise), its hand-set class (``classes``), the PCA projection (``points``,
    (n, 2)) and the share of variance each axis explains, and the adjusted Rand index between
    clusters and classes (None when there was too little to compare)."""

    family: str
    runs: list[str]
    features: list[str]
    labels: list[int]
    classes: list[str]
    points: np.ndarray
    explained: list[float]
    ari: float | None
    note: str = ""
    #: per cluster: how many runs of each hand-set class it holds
    composition: dict[int, dict[str, int]] = field(default_factory=dict)

    @property
    def clusters(self) -> int:
        """How many clusters were found (noise not counted)."""
        return len({label for label in self.labels if label != NOISE})

    @property
    def purity(self) -> float | None:
        """Of the runs in a cluster (noise not counted), the share whose hand-set class is their
        cluster's most common one; None when no run is in a cluster. Unlike the Rand index it
        does not count a class found as two clusters, or runs left as noise, against the
        thresholds: it says whether a threshold cuts through a cluster."""
        counts = [held for label, held in self.composition.items() if label != NOISE]
        clustered = sum(sum(held.values()) for held in counts)
        return sum(max(held.values()) for held in counts) / clustered if clustered else None


def features(done: Any) -> dict[str, tuple[Any, list[str]]]:
    """Per family (each arena scenario by its name, ``grid``), the finished runs' feature table
    and its columns.

    Arena runs, one family per scenario (the paper classes basic and object-manipulation
    behaviours apart): :data:`ARENA_FEATURES` and the :data:`SENSOR_FEATURES` means (a feature
    no run has, such as d_B without boxes, is left out; a missing value counts as the feature's
    median). Grid runs: their nine pattern scores.
    """
    import pandas as pd

    out: dict[str, tuple[Any, list[str]]] = {}
    if "rotation" in done:
        done = done.assign(**_sensor_means(done))
        measured = done[done["rotation"].notna()]
        scenarios = measured["scenario"] if "scenario" in measured else ["arena"] * len(measured)
        for scenario, arena in measured.groupby(list(scenarios), sort=True):
            names = [*ARENA_FEATURES, *(f"{family}_mean" for family in SENSOR_FEATURES)]
            columns = [c for c in names if c in arena and arena[c].notna().any()]
            if columns:
                table = arena[columns].astype(float)
                out[str(scenario)] = (table.fillna(table.median()), columns)
    scores = [
        row["_summary"].get("scores") if isinstance(row.get("_summary"), dict) else None
        for _, row in done.iterrows()
    ]
    grid = [(i, s) for i, s in zip(done.index, scores, strict=True) if isinstance(s, dict)]
    if grid:
        table = pd.DataFrame([s for _, s in grid], index=[i for i, _ in grid]).astype(float)
        out["grid"] = (table.fillna(0.0), list(table.columns))
    return out


def _sensor_means(done: Any) -> dict[str, list[float]]:
    # Each run's mean reading per sensor family, from its summary's post-evaluation means (NaN
    # where the run's robots have none of the family).
    columns: dict[str, list[float]] = {f"{family}_mean": [] for family in SENSOR_FEATURES}
    for summary in done.get("_summary", [None] * len(done)):
        summary = summary if isinstance(summary, dict) else {}
        names, means = summary.get("sensors") or [], summary.get("mean_sensors") or []
        # A summary whose lists disagree is not trusted for any family.
        pairs = list(zip(names, means, strict=True)) if len(names) == len(means) else []
        for family in SENSOR_FEATURES:
            values = [v for name, v in pairs if str(name).split(".")[0] == family]
            columns[f"{family}_mean"].append(float(np.mean(values)) if values else np.nan)
    return columns


def cluster_behaviours(done: Any, *, seed: int = 0) -> list[Clustering]:
    """Cluster each family of ``done`` (a study's finished runs, :func:`studies.report.load_runs`
    rows); deterministic for the same runs."""
    from sklearn.cluster import HDBSCAN
    from sklearn.decomposition import PCA
    from sklearn.metrics import adjusted_rand_score
    from sklearn.preprocessing import StandardScaler

    found = []
    done = done.reset_index(drop=True)  # one row per index: runs are looked up by it below
    for family, (table, columns) in features(done).items():
        rows = done.loc[table.index]
        runs = [str(r) for r in rows["run"]]
        classes = [str(c) for c in rows.get("behaviour", ["?"] * len(rows))]
        values = table.to_numpy(dtype=float)
        # A feature that does not vary carries nothing (and would divide by zero); a spread
        # below rounding's is none.
        varying = values.std(axis=0) > 1e-9 * (1.0 + np.abs(values).mean(axis=0))
        values, used = values[:, varying], [c for c, v in zip(columns, varying, strict=True) if v]
        if len(runs) < MIN_RUNS or values.shape[1] == 0:
            found.append(
                Clustering(
                    family,
                    runs,
                    used,
                    [NOISE] * len(runs),
                    classes,
                    np.zeros((len(runs), 2)),
                    [],
                    None,
                    note=f"{len(runs)} runs, {len(used)} varying features: too few "
                    f"to cluster (at least {MIN_RUNS} runs)",
                )
            )
            continue
        scaled = StandardScaler().fit_transform(values)
        components = min(CLUSTERED_COMPONENTS, scaled.shape[1])
        pca = PCA(n_components=components, random_state=seed).fit(scaled)
        kept = pca.transform(scaled)
        points = kept if components == 2 else np.column_stack([kept, np.zeros(len(kept))])
        smallest = max(MIN_CLUSTER, len(runs) // SMALLEST_SHARE)
        labels = HDBSCAN(min_cluster_size=smallest, copy=True).fit_predict(kept)
        composition: dict[int, dict[str, int]] = {}
        for label, name in zip(labels, classes, strict=True):
            counts = composition.setdefault(int(label), {})
            counts[name] = counts.get(name, 0) + 1
        ari = float(adjusted_rand_score(classes, labels)) if len(set(classes)) > 1 else None
        found.append(
            Clustering(
                family,
                runs,
                used,
                [int(x) for x in labels],
                classes,
                points,
                [float(x) for x in pca.explained_variance_ratio_],
                ari,
                composition=composition,
            )
        )
    return found


def clusters_table(found: list[Clustering]) -> Any:
    """One row per run: family, cluster, hand-set class and the projection's two coordinates."""
    import pandas as pd

    rows = [
        {
            "family": c.family,
            "run": run,
            "cluster": label,
            "class": name,
            "pc1": float(point[0]),
            "pc2": float(point[1]),
        }
        for c in found
        for run, label, name, point in zip(c.runs, c.labels, c.classes, c.points, strict=True)
    ]
    return pd.DataFrame(rows)


def clusters_markdown(found: list[Clustering]) -> str:
    """What a person reads: per family the clusters found, what each holds, the agreement."""
    lines = ["# Classes found by the data", ""]
    for c in found:
        lines.append(f"## {c.family}: {len(c.runs)} runs")
        lines.append("")
        if c.note:
            lines += [c.note, ""]
            continue
        ari = "n/a (one hand-set class)" if c.ari is None else f"{c.ari:.2f}"
        purity = "n/a" if c.purity is None else f"{c.purity:.0%}"
        lines.append(
            f"HDBSCAN found {c.clusters} clusters (and {c.labels.count(NOISE)} runs of noise) in "
            f"{len(c.features)} standardised features ({', '.join(c.features)}); the agreement "
            f"with the hand-set classes, adjusted Rand index: {ari}; of the runs in a cluster, "
            f"{purity} share their cluster's most common class. PCA's two axes explain "
            f"{', '.join(f'{x:.0%}' for x in c.explained)} of the variance."
        )
        lines += ["", "| cluster | runs | hand-set classes |", "| --- | --- | --- |"]
        for label in sorted(c.composition):
            counts = c.composition[label]
            held = ", ".join(f"{name} {n}" for name, n in sorted(counts.items(), key=_by_count))
            name = "noise" if label == NOISE else str(label)
            lines.append(f"| {name} | {sum(counts.values())} | {held} |")
        lines.append("")
    return "\n".join(lines)


def _by_count(item: tuple[str, int]) -> tuple[int, str]:
    return -item[1], item[0]


def clusters_figure(c: Clustering) -> Any:
    """The runs in the projection, coloured by cluster (left) and by hand-set class (right)."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4.5), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    for ax, values, title in (
        (axes[0], [("noise" if x == NOISE else f"cluster {x}") for x in c.labels], "found"),
        (axes[1], c.classes, "hand-set (the paper's thresholds)"),
    ):
        names = sorted(set(values))
        palette = colormaps["tab10"]
        for i, name in enumerate(names):
            mask = np.array([v == name for v in values])
            colour = (0.6, 0.6, 0.6, 1.0) if name == "noise" else palette(i % 10)
            ax.scatter(c.points[mask, 0], c.points[mask, 1], s=18, color=colour, label=name)
        ax.set_title(title)
        ax.set_xlabel("PC 1" + (f" ({c.explained[0]:.0%})" if c.explained else ""))
        ax.legend(fontsize=7, loc="best")
    axes[0].set_ylabel("PC 2" + (f" ({c.explained[1]:.0%})" if len(c.explained) > 1 else ""))
    ari = "n/a" if c.ari is None else f"{c.ari:.2f}"
    fig.suptitle(f"{c.family}: {len(c.runs)} runs, adjusted Rand index {ari}")
    return fig
