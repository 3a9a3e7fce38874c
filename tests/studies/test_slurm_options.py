"""The ``slurm:`` section of a study file and the ``--slurm-*`` options, without a Slurm cluster:
what they decode to, the job script dask-jobqueue writes from them, and the one-line errors of a
bad value, a missing ``sbatch`` and a Slurm that does not answer."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from study_helpers import TINY, write_study

from minimize_surprise.errors import ConfigError
from needs import require_binary, require_module
from studies.cli import main
from studies.slurm import (
    SlurmOptions,
    cluster_options,
    walltime_seconds,
    with_overrides,
)
from studies.slurm_jobs import renewal_line
from studies.spec import load_study


def _slurm_study(tmp_path: Path, section: str) -> Path:
    return write_study(tmp_path, TINY + f"slurm:\n{section}")


def test_the_study_file_s_slurm_section_decodes_and_options_override_it(tmp_path):
    path = _slurm_study(
        tmp_path,
        "  queue: short\n  jobs: 4\n  cores: 2\n  memory: 8GB\n  walltime: '02:00:00'\n"
        "  directives: ['--qos=quick']\n  prologue: ['module load gcc']\n",
    )
    file = load_study(path).slurm
    assert file == SlurmOptions(
        queue="short", jobs=4, cores=2, memory="8GB", walltime="02:00:00",
        directives=["--qos=quick"], prologue=["module load gcc"],
    )  # fmt: skip
    options = with_overrides(file, {"jobs": 10, "queue": None, "walltime": "30"}, file=path)
    assert (options.jobs, options.queue, options.walltime, options.cores) == (10, "short", "30", 2)
    assert load_study(write_study(tmp_path, TINY, "plain.yaml")).slurm is None
    assert with_overrides(None, {"cores": 3}).worker_processes == 3


@pytest.mark.parametrize(
    ("section", "key", "reason"),
    [
        ("  cpus: 4\n", "slurm.cpus", "unknown key"),
        ("  jobs: 0\n", "slurm.jobs", ">= 1"),
        ("  memory: lots\n", "slurm.memory", "an amount such as 4GB"),
        ("  walltime: 2h\n", "slurm.walltime", "Slurm's time"),
        ("  cores: 4\n  processes: 3\n", "slurm.processes", "divisor of `cores`"),
        ("  directives: [qos=x]\n", "slurm.directives", "an sbatch option"),
        ("  walltime: '10'\n  walltime_margin: 600\n", "slurm.walltime_margin", "nothing of"),
        ("  walltime_margin: 0\n", "slurm.walltime_margin", "> 0"),
    ],
)
def test_a_bad_slurm_key_is_one_line_naming_file_and_key(tmp_path, capsys, section, key, reason):
    path = _slurm_study(tmp_path, section)
    with pytest.raises(ConfigError) as caught:
        load_study(path)
    assert (caught.value.file, caught.value.key) == (str(path), key)
    assert reason in caught.value.reason
    # The command says it in one line, before anything starts.
    assert main(["run", str(path), "--out", str(tmp_path / "out"), "--slurm"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"surprise-study: {path}: key '{key}'")
    assert not (tmp_path / "out" / "runs").exists()


@pytest.mark.parametrize(
    ("walltime", "seconds"),
    [
        ("90", 5400), ("5:30", 330), ("04:00:00", 14400), ("2-0", 172800), ("1-2:03", 93780),
        ("1-02:03:04", 93784), ("0", 0),
    ],
)  # fmt: skip
def test_a_walltime_in_each_of_slurm_s_formats_is_its_seconds(walltime, seconds):
    assert walltime_seconds(walltime) == seconds


@pytest.mark.parametrize(
    ("walltime", "margin", "lifetime"),
    [
        ("08:00:00", None, 8 * 3600 - 300),  # 5 minutes before the walltime
        ("01:00:00", None, 3300),
        ("20", None, 20 * 60 - 120),  # a tenth of a short walltime
        ("1", 55, 5),  # as the tests ask
        ("02:00:00", 900, 6300),
        ("0", None, None),  # no walltime: the workers stay
    ],
)
def test_the_workers_leave_a_margin_before_the_walltime(tmp_path, walltime, margin, lifetime):
    options = SlurmOptions(walltime=walltime, walltime_margin=margin)
    assert options.lifetime == lifetime
    worker = _worker_command(options, tmp_path)
    if lifetime is None:
        assert "--lifetime" not in worker
    else:
        assert f" --lifetime {lifetime:g}s" in worker
    assert "--lifetime-stagger" not in worker


def test_the_line_that_says_jobs_were_replaced():
    line = renewal_line({"41": "walltime", "42": "walltime"}, ["43", "44"], wanted=2, runs_left=9)
    assert line == "slurm: 2 jobs ended (walltime: 41, 42); submitted 2 new ones (43, 44)"
    line = renewal_line({"41": "walltime", "42": "cancelled"}, ["43"], wanted=1, runs_left=1)
    assert line == (
        "slurm: 2 jobs ended (walltime: 41; cancelled: 42); submitted 1 new one (43), enough for "
        "the 1 run left"
    )
    line = renewal_line({"41": "node failure"}, [], wanted=0, runs_left=2)
    assert line == (
        "slurm: 1 job ended (node failure: 41); no new ones: the other jobs are enough for the "
        "2 runs left"
    )
    refused = "sbatch: error: Batch job submission failed: Job violates accounting/QOS policy"
    line = renewal_line({"41": "walltime"}, [], wanted=1, refused=refused, runs_left=5)
    assert line == (
        f"slurm: 1 job ended (walltime: 41); sbatch refused 1 new one ({refused}); "
        "trying again soon"
    )
    assert renewal_line({}, ["45"], wanted=1) == "slurm: submitted 1 new job (45)"


def _worker_command(options: SlurmOptions, logs: Path) -> str:
    """The line of the job script that starts the workers."""
    require_module("dask_jobqueue", "studies")
    from dask_jobqueue.slurm import SLURMJob

    kwargs = cluster_options(options, logs)
    kwargs.pop("scheduler_options")  # the scheduler's, not a job's
    return SLURMJob("tcp://127.0.0.1:1", name="w", **kwargs).job_script().splitlines()[-1]


def test_a_bad_slurm_option_is_named(tmp_path, capsys):
    study = str(write_study(tmp_path))
    out = str(tmp_path / "out")
    assert main(["run", study, "--out", out, "--slurm", "--slurm-jobs", "0"]) == 2
    assert capsys.readouterr().err.startswith("surprise-study: option '--slurm-jobs': ")
    assert main(["run", study, "--out", out, "--slurm", "--slurm-walltime", "soon"]) == 2
    assert "option '--slurm-walltime': expected Slurm's time" in capsys.readouterr().err
    assert main(["run", study, "--out", out, "--slurm-cores", "2"]) == 2
    assert capsys.readouterr().err == "surprise-study: option '--slurm-cores': only with --slurm\n"


def test_the_job_script_runs_this_python_with_the_asked_resources(tmp_path):
    require_module("dask_jobqueue", "studies")
    from dask_jobqueue.slurm import SLURMJob

    options = SlurmOptions(
        queue="short", account="lab", cores=4, memory="8GB", walltime="1-00:00:00",
        directives=["--qos=quick"], prologue=["module load gcc"], interface="lo",
    )  # fmt: skip
    kwargs = cluster_options(options, tmp_path / "logs")
    kwargs.pop("scheduler_options")  # the scheduler's, not a job's
    script = SLURMJob("tcp://127.0.0.1:1", name="w", **kwargs).job_script()
    for line in (
        "#SBATCH -J surprise-study", f"#SBATCH -e {tmp_path}/logs/surprise-study-%J.err",
        "#SBATCH -p short", "#SBATCH -A lab", "#SBATCH --cpus-per-task=4", "#SBATCH --mem=8G",
        "#SBATCH -t 1-00:00:00", "#SBATCH --qos=quick", "module load gcc",
    ):  # fmt: skip
        assert line in script.splitlines(), (line, script)
    worker = script.splitlines()[-1]
    assert worker.startswith(f"{sys.executable} -m distributed.cli.dask_worker tcp://127.0.0.1:1")
    # four single-threaded processes; the dashboard only on loopback
    assert "--nthreads 1 " in worker and "--nworkers 4 " in worker and "--interface lo" in worker
    assert "--dashboard-address 127.0.0.1:0" in worker
    # memory by default: 2 GiB per core
    assert SlurmOptions(cores=3).job_memory == "6144MiB"


def test_without_sbatch_the_study_says_so_in_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch on it
    assert main(["run", str(write_study(tmp_path)), "--out", str(tmp_path / "o"), "--slurm"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "surprise-study: --slurm: sbatch is not on PATH; run the study on a Slurm cluster's "
        "login node\n"
    )


def test_a_slurm_conf_that_is_not_there_is_named(tmp_path, capsys, monkeypatch):
    require_binary("sbatch", "slurm-client")
    monkeypatch.setenv("SLURM_CONF", str(tmp_path / "nowhere.conf"))
    assert main(["run", str(write_study(tmp_path)), "--out", str(tmp_path / "o"), "--slurm"]) == 2
    assert capsys.readouterr().err == (
        f"surprise-study: --slurm: SLURM_CONF names no file: {tmp_path / 'nowhere.conf'}\n"
    )


def test_a_slurm_controller_that_does_not_answer_is_one_line(tmp_path, capsys, monkeypatch):
    require_binary("sbatch", "slurm-client")
    require_module("dask_jobqueue", "studies")
    # A controller on a port where nothing listens (refused at once; MessageTimeout keeps
    # sbatch's retries short).
    conf = tmp_path / "slurm.conf"
    conf.write_text(
        "ClusterName=nowhere\nSlurmctldHost=nowhere(127.0.0.1)\nSlurmctldPort=1\n"
        "MessageTimeout=1\nAuthType=auth/munge\nNodeName=nowhere NodeAddr=127.0.0.1 CPUs=1\n"
        "PartitionName=p Nodes=nowhere Default=YES\n"
    )
    monkeypatch.setenv("SLURM_CONF", str(conf))
    study = _slurm_study(tmp_path, "  interface: lo\n")
    assert main(["run", str(study), "--out", str(tmp_path / "o"), "--slurm"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("surprise-study: Slurm's controller does not answer (SLURM_CONF?): ")
    assert "Unable to contact slurm controller" in line


def test_an_interface_this_machine_lacks_is_one_line(tmp_path, capsys, monkeypatch):
    require_module("dask_jobqueue", "studies")
    sbatch = tmp_path / "bin" / "sbatch"  # never run: the scheduler fails first
    sbatch.parent.mkdir()
    sbatch.write_text("#!/bin/sh\nexit 1\n")
    sbatch.chmod(0o755)
    monkeypatch.setenv("PATH", str(sbatch.parent))
    monkeypatch.delenv("SLURM_CONF", raising=False)
    study = _slurm_study(tmp_path, "  interface: no-such-nic\n")
    assert main(["run", str(study), "--out", str(tmp_path / "o"), "--slurm"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("surprise-study: --slurm: the Dask scheduler cannot start: ")
    assert "'no-such-nic' is not a valid network interface" in line
