"""Asking for more robots than fit at the start is one line naming the limit and what to change,
before anything is written."""

from __future__ import annotations

import re

import pytest

from master_service.cli import main
from master_service.experiments.simulation_setup import simulation_experiment
from minimize_surprise.errors import ConfigError

LIMIT = re.compile(r"at most about (\d+) robots fit on a ([\d.]+) m carpet \((\d+) asked for\)")


def one_line_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_sim_names_how_many_robots_fit_and_the_option(tmp_path, capsys):
    out = tmp_path / "run"
    line = one_line_error(
        capsys, ["sim", "--robots", "500", "--evaluations", "2", "--out", str(out)]
    )
    assert line.startswith("surprise-master: option '--robots': at most about ")
    assert line.endswith("; ask for fewer with --robots or a larger --arena")
    limit, side, asked = LIMIT.search(line).groups()
    assert (side, asked) == ("1.0", "500")
    # The paper's basic arena keeps bodies 16.4 cm apart: a few dozen fit on 1 m, not 500.
    assert 15 <= int(limit) <= 40
    assert not out.exists()
    # The limit is the one the run meets: that many start, one more does not.
    assert simulation_experiment("basic", robots=int(limit)).robots == int(limit)
    with pytest.raises(ConfigError, match=f"at most about {limit} robots"):
        simulation_experiment("basic", robots=int(limit) + 1)


def test_a_small_arena_names_its_side(tmp_path, capsys):
    line = one_line_error(
        capsys, ["sim", "--arena", "0.3", "--robots", "20", "--out", str(tmp_path / "r")]
    )
    assert "option '--robots'" in line
    limit, side, asked = LIMIT.search(line).groups()
    assert (side, asked) == ("0.3", "20") and 1 <= int(limit) <= 4
    # The scenario's ten robots on a carpet made too small by --arena: that option is named.
    line = one_line_error(capsys, ["sim", "--arena", "0.3", "--out", str(tmp_path / "r")])
    assert "option '--arena'" in line and "(10 asked for)" in line


def test_baseline_names_the_limit_before_creating_its_directory(tmp_path, capsys):
    out = tmp_path / "random"
    line = one_line_error(
        capsys, ["baseline", "--random", "2", "--robots", "500", "--out", str(out)]
    )
    assert "option '--robots': at most about" in line and "(500 asked for)" in line
    assert not out.exists()


def test_a_file_names_its_robots_key(tmp_path, capsys):
    experiment = tmp_path / "experiment.yaml"
    experiment.write_text("setting: paper\nrobots: 500\n", encoding="utf-8")
    line = one_line_error(
        capsys, ["sim", "--config", str(experiment), "--out", str(tmp_path / "r")]
    )
    assert line.startswith(f"surprise-master: {experiment}: key 'robots': at most about ")
    assert line.endswith("ask for fewer robots or a larger carpet (simulation.arena_side)")


def test_the_start_ring_names_how_many_robots_it_takes(tmp_path, capsys):
    # The paper's boxes arena starts its robots on a ring 10 cm from the centre: bodies 11.6 cm
    # wide leave room for 6 (the paper's 4 fit), not for 50 piled on each other.
    line = one_line_error(
        capsys, ["sim", "--scenario", "boxes", "--robots", "50", "--out", str(tmp_path / "r")]
    )
    assert line == (
        "surprise-master: option '--robots': at most 6 robots fit on the start ring "
        "0.1 m around the centre (50 asked for); ask for fewer with --robots or a wider start "
        "ring (simulation.start_ring)"
    )
    assert simulation_experiment("boxes", robots=6).robots == 6
    assert simulation_experiment("boxes").robots == 4
