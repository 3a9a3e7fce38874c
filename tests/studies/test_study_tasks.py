"""One run's task: a kind this installation does not know is refused by name, when the task is
checked and when it is run (it is not taken for a grid-world run)."""

from __future__ import annotations

import json

import pytest

from minimize_surprise.errors import ConfigError
from studies.tasks import FAILED, KINDS, SUMMARY, check_task, run_dir, run_task

FLYING = {
    "group": "a",
    "kind": "flying",
    "seed": 1,
    "sweep": {},
    "run": "a/seed-1",
    "params": {"size": 10},
}


def test_checking_a_task_of_an_unknown_kind_names_it_and_the_known_kinds():
    with pytest.raises(ConfigError, match="unknown run kind 'flying'") as caught:
        check_task(FLYING)
    assert caught.value.key == "kind"
    assert all(kind in caught.value.reason for kind in KINDS)


def test_running_a_task_of_an_unknown_kind_fails_the_run_naming_it(tmp_path):
    summary = run_task(FLYING, str(tmp_path))
    assert summary["status"] == "failed"
    assert summary["error"].startswith("ConfigError: ")
    assert "unknown run kind 'flying'" in summary["error"]
    assert ", ".join(KINDS) in summary["error"]
    directory = run_dir(tmp_path, FLYING)
    assert (directory / FAILED).is_file() and not (directory / SUMMARY).exists()
    assert json.loads((directory / FAILED).read_text())["error"] == summary["error"]


def test_a_file_system_without_locks_runs_the_run_unlocked(tmp_path, monkeypatch, caplog):
    # Lustre without its flock mount option, NFS without lockd: flock fails with ENOLCK there.
    import errno
    import fcntl

    from studies import tasks

    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    monkeypatch.setattr(tasks, "_warned_no_locks", False)
    with tasks.run_lock(tmp_path / "run") as held:
        assert held
    assert not tasks.run_busy(tmp_path / "run")
    with tasks.run_lock(tmp_path / "run", wait=False) as held:
        assert held
    assert caplog.text.count("offers no locks (No locks available)") == 1


def evolved(**options) -> dict:
    params = {
        "setting": "lab", "scenario": "basic", "robots": 2, "evaluation_steps": 8,
        "post_evaluation_steps": 12, "evolution": {"evaluations": 3}, **options,
    }  # fmt: skip
    return {"group": "e", "kind": "evolved", "seed": 1, "sweep": {}, "run": "e/seed-1",
            "params": params}  # fmt: skip


def test_an_evolved_run_without_traces_keeps_its_summary_and_report_data(tmp_path):
    # traces: false drops the post-evaluation's traces once the run's summary holds what the
    # study's report needs: the same figures as a run that keeps them.
    kept = run_task(evolved(), str(tmp_path / "kept"))
    dropped = run_task(evolved(traces=False), str(tmp_path / "dropped"))
    assert (run_dir(tmp_path / "kept", evolved()) / "traces").is_dir()
    directory = run_dir(tmp_path / "dropped", evolved())
    assert not (directory / "traces").exists() and (directory / SUMMARY).is_file()
    for key in ("best_fitness", "post_fitness", "behaviour", "mean_sensors"):
        assert dropped[key] == kept[key]


@pytest.mark.parametrize("key", ["traces", "plots"])
def test_a_run_option_that_is_not_true_or_false_is_refused_by_name(key):
    with pytest.raises(ConfigError, match="expected true or false") as caught:
        check_task(evolved(**{key: "no"}))
    assert caught.value.key == key


def test_batches_group_runs_of_one_shape_and_keep_every_worker_busy():
    from studies.batches import plan_batches

    def task(group, kind, seed, **params):
        params = {"setting": "paper", "scenario": "basic", **params}
        return {
            "group": group,
            "kind": kind,
            "seed": seed,
            "params": params,
            "run": f"{group}/{seed}",
        }

    tasks = [
        *(
            task("basic", "evolved", s, simulation={"arena_side": 0.7 + 0.1 * (s % 2)})
            for s in range(1, 8)
        ),
        *(task("random", "random", s) for s in (101, 102)),
        *(task("boxes", "evolved", s, scenario="boxes") for s in (1, 2, 3)),
        task("longer", "evolved", 1, evaluation_steps=500),
    ]
    batches = plan_batches(tasks, workers=2)
    runs = [[t["run"] for t in batch] for batch in batches]
    # Seven basic runs (two arena sides, one shape) on two workers: batches of four and three;
    # three boxes runs: two and one; a run of another length and the random pairs alone, last.
    assert runs[:3] == [
        ["basic/1", "basic/2", "basic/3", "basic/4"],
        ["basic/5", "basic/6", "basic/7"],
        ["boxes/1", "boxes/2"],
    ]
    assert sorted(map(tuple, runs[3:])) == [
        ("boxes/3",),
        ("longer/1",),
        ("random/101",),
        ("random/102",),
    ]
    assert [len(b) for b in plan_batches(tasks, workers=8)][:2] == [1, 1]  # one run per worker
    # Five batches of four on two workers: the last two go as runs alone, so that the workers
    # end together.
    many = [task("basic", "evolved", s) for s in range(1, 21)]
    assert [len(b) for b in plan_batches(many, workers=2)] == [4, 4, 4] + [1] * 8
    assert all(len(b) == 1 for b in plan_batches(tasks, workers=1, size=1))


def test_a_batch_run_again_keeps_its_finished_runs_and_runs_the_rest(tmp_path):
    # As Dask does when a worker dies under a batch: the runs that finished are not run again,
    # the one killed half-way is, and a batch of finished runs only returns their summaries.
    from studies.batches import run_tasks

    tasks = [{**evolved(), "seed": s, "run": f"e/seed-{s}"} for s in (1, 2)]
    first = run_tasks(tasks, str(tmp_path))
    assert [s["status"] for s in first] == ["done", "done"] and first[0]["batch"] == 2
    (run_dir(tmp_path, tasks[1]) / SUMMARY).unlink()  # killed before its summary
    kept = (run_dir(tmp_path, tasks[0]) / SUMMARY).stat().st_mtime_ns
    again = run_tasks(tasks, str(tmp_path))
    assert again[0] == first[0] and again[1]["best_fitness"] == first[1]["best_fitness"]
    assert (run_dir(tmp_path, tasks[0]) / SUMMARY).stat().st_mtime_ns == kept
    assert run_tasks(tasks, str(tmp_path)) == again  # all finished: nothing runs
