"""Classes found, not set (studies.clusters): runs whose metrics fall into well-separated groups
are clustered into those groups, and the agreement with the hand-set classes says so; too few
runs are not clustered; the grid world's runs are clustered by their pattern scores."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from studies.clusters import MIN_RUNS, NOISE, cluster_behaviours, clusters_markdown


def _arena_runs(seed: int = 3) -> pd.DataFrame:
    # Three behaviours as the paper's metrics tell them apart: circling (high rotation, short
    # paths), aggregation (large clusters), dispersion (long paths, small clusters).
    rng = np.random.default_rng(seed)
    rows = []
    for name, centre in (
        ("circling", (40.0, 1.2, 1.0)),
        ("aggregation", (5.0, 8.0, 3.0)),
        ("dispersion", (5.0, 1.1, 12.0)),
    ):
        for i in range(10):
            rotation, cluster, distance = np.array(centre) * rng.normal(1.0, 0.05, 3)
            rows.append(
                {
                    "run": f"{name}/seed-{i}",
                    "scenario": "basic",
                    "behaviour": name,
                    "rotation": rotation,
                    "mean_cluster_size": cluster,
                    "distance_covered": distance,
                    "box_displacement": np.nan,  # no boxes in this arena
                    "backward_share": 0.1,  # the same for all: carries nothing
                    "safety_share": rng.uniform(0.0, 0.02),
                    "_summary": {},
                }
            )
    return pd.DataFrame(rows)


def test_separate_behaviours_are_found_and_agree_with_the_hand_set_classes() -> None:
    (found,) = cluster_behaviours(_arena_runs())
    assert found.family == "basic" and len(found.runs) == 30
    assert "box_displacement" not in found.features  # no run has it
    assert "backward_share" not in found.features  # it does not vary
    assert found.clusters == 3 and found.ari == pytest.approx(1.0)
    assert found.points.shape == (30, 2) and sum(found.explained) <= 1.0
    text = clusters_markdown([found])
    assert "HDBSCAN found 3 clusters" in text and "adjusted Rand index: 1.00" in text
    assert found.purity == 1.0 and "100% share their cluster's most common class" in text


def test_the_same_runs_give_the_same_clusters() -> None:
    first, second = cluster_behaviours(_arena_runs()), cluster_behaviours(_arena_runs())
    assert first[0].labels == second[0].labels
    assert np.array_equal(first[0].points, second[0].points)


def test_runs_mislabelled_by_a_threshold_lower_the_agreement() -> None:
    runs = _arena_runs()
    runs.loc[runs.index[:5], "behaviour"] = "dispersion"  # a threshold that cut circling in two
    (found,) = cluster_behaviours(runs)
    assert found.clusters == 3 and found.ari is not None and found.ari < 0.9
    # The cut class's five runs sit in the circling cluster: it is no longer pure.
    assert found.purity == pytest.approx(25 / 30)


def test_too_few_runs_are_not_clustered() -> None:
    (found,) = cluster_behaviours(_arena_runs().head(MIN_RUNS - 1))
    assert found.note and set(found.labels) == {NOISE} and found.ari is None
    assert "too few to cluster" in clusters_markdown([found])


def test_grid_runs_are_clustered_by_their_pattern_scores() -> None:
    rng = np.random.default_rng(1)
    rows = []
    for pattern in ("line", "pair", "square"):
        for i in range(10):
            scores = {p: rng.uniform(0.0, 0.1) for p in ("line", "pair", "square", "cluster")}
            scores[pattern] = rng.uniform(0.8, 1.0)
            rows.append(
                {"run": f"{pattern}-{i}", "behaviour": pattern, "_summary": {"scores": scores}}
            )
    (found,) = cluster_behaviours(pd.DataFrame(rows))
    assert found.family == "grid" and found.ari == pytest.approx(1.0)


def test_each_arena_scenario_is_its_own_family() -> None:
    basic, boxes = _arena_runs(3), _arena_runs(4)
    boxes["scenario"] = "boxes"
    boxes["box_displacement"] = np.linspace(0.0, 0.3, len(boxes))
    found = {c.family: c for c in cluster_behaviours(pd.concat([basic, boxes]))}
    assert set(found) == {"basic", "boxes"}
    assert "box_displacement" in found["boxes"].features
    assert "box_displacement" not in found["basic"].features


def test_the_post_evaluation_s_trace_parts_what_the_thresholds_metrics_do_not() -> None:
    # Two behaviours alike in every metric a threshold uses: one keeps to the walls (its IR reads
    # high, it turns more), one to the open floor. Only the trace's features tell them apart.
    rng = np.random.default_rng(5)
    rows = []
    for name, ir, turn in (("wall-following", 0.6, 0.8), ("open-floor", 0.05, 0.3)):
        for i in range(20):
            rows.append(
                {
                    "run": f"{name}/seed-{i}",
                    "scenario": "basic",
                    "behaviour": name,
                    "rotation": rng.normal(30.0, 1.0),
                    "mean_cluster_size": rng.normal(1.2, 0.02),
                    "distance_covered": rng.normal(8.0, 0.2),
                    "turn_rate": rng.normal(turn, 0.02),
                    "_summary": {
                        "sensors": ["ir.f0", "ir.f1", "ground.0"],
                        "mean_sensors": [rng.normal(ir, 0.01), rng.normal(ir, 0.01), 0.4],
                    },
                }
            )
    (found,) = cluster_behaviours(pd.DataFrame(rows))
    assert {"ir_mean", "turn_rate"} <= set(found.features)
    assert "ground_mean" not in found.features  # the same for all: carries nothing
    # Two clusters, each of one behaviour (HDBSCAN leaves the runs at their edges as noise).
    pure = [held for label, held in found.composition.items() if label != NOISE]
    assert found.clusters == 2 and all(len(held) == 1 for held in pure)
    assert found.ari is not None and found.ari > 0.8
    blind = pd.DataFrame(rows).drop(columns="turn_rate").assign(_summary=[{}] * len(rows))
    (metrics_only,) = cluster_behaviours(blind)
    assert (metrics_only.ari or 0.0) < 0.1
