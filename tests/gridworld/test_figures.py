"""The Sec. IV figures from a small table of run summaries (files written, nothing checked by
eye)."""

from __future__ import annotations

from gridworld import figures
from gridworld.tasks import run_task
from needs import require_module

pd = require_module("pandas")
require_module("matplotlib")


def test_every_figure_is_written(tmp_path):
    rows = []
    for size in (7, 8):
        for seed in (1, 2):
            run = tmp_path / f"run-{size}-{seed}"
            params = {"size": size, "agents": 12, "repetitions": 2, "steps": 20,
                      "population": 4, "generations": 2}  # fmt: skip
            summary = run_task("grid-evolved", params, seed, run)
            rows.append({**summary, "group": "evolved", "run_dir": str(run)})
            random = run_task("grid-random", {k: params[k] for k in ("size", "agents", "steps")},
                              seed, tmp_path / f"random-{size}-{seed}")  # fmt: skip
            rows.append({**random, "group": "random", "run_dir": str(tmp_path / "x")})
    frame = pd.DataFrame(rows)
    out = tmp_path / "figures"
    written = figures.fitness_over_generations(
        [r["run_dir"] + "/generations.csv" for r in rows if r["group"] == "evolved"],
        out / "fitness",
    )
    written += figures.fitness_and_quality_by(frame, out / "by_size")
    written += figures.pattern_distribution_by(frame, out / "patterns", group="evolved")
    written += figures.predictions_by_pattern(frame, out / "predictions")
    written += figures.example_grids(frame[frame["group"] == "evolved"], out / "examples")
    assert {p.suffix for p in written} == {".png", ".pdf"}
    assert all(p.stat().st_size > 0 for p in written)
