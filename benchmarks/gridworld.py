"""Speed of a paper-scale grid-world run against the authors' C code, and a check that both
simulate the same thing.

Ours: the GA and the compiled evaluation (no files written) for L = 15, N = 100, population 50,
10 runs of 500 steps per genome, ``--generations`` generations (default 100, the paper's), CPU
time of this process pinned to one core. The C code: the authors' ``Self-assembly-Torus``
repository, built with ``gcc -O2`` into a temporary directory at benchmark time (nothing of it is
kept) and run as ``EVOL 15 15 PRED NONE NONE`` on the same core for ``--c-generations``
generations; its CPU time per generation is extrapolated to a whole run. We are also timed on that
many generations. Prints ``name: value unit`` lines.

``--parts`` first times one generation of random genomes with the full network pair, without a
predictor (every prediction fixed) and with ten of its outputs (``line-partial``): the
predictor's share of the time.

``--check N`` also feeds N random genomes and start configurations to the C code's REPLAY mode
and to our simulator and compares, genome by genome: the fitness of the run, the mean prediction
per sensor, and the whole trajectory of the C code's second (logged) run, step by step.

``--qd N`` times N batches of MAP-Elites (:mod:`gridworld.qd`, the archive of the shipped study
``qd-grid``) against N generations of the GA on the same core: what the archive, the emitter and
the classification of every candidate's final grid add to the same evaluations.

The C sources: ``--c-source`` names a checkout or bare git directory of the repository
Minimize-Surprise/Self-assembly-Torus (e.g. ``git clone`` of it from GitHub). Without it only
ours is measured. Run:
``python benchmarks/gridworld.py --c-source PATH [--generations 100] [--c-generations 3]
[--check 20] [--parts] [--qd 100]``
"""

from __future__ import annotations

import os
import sys

# This script is named like the package it measures: keep its own folder off the import path.
sys.path = [p for p in sys.path if os.path.abspath(p or ".") != os.path.dirname(__file__)]

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from gridworld.config import GridRunConfig  # noqa: E402
from gridworld.evolve import evaluator_of, generation_noise_key, generation_starts  # noqa: E402
from gridworld.world import HEADINGS, Poses, Torus  # noqa: E402
from minimize_surprise.genetic import GeneticAlgorithm  # noqa: E402

AGENT_STEPS_PER_GENERATION = 50 * 10 * 500 * 100


def pin_to_one_core() -> int:
    """Run on the last CPU; return its number."""
    cpus = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpus[-1]})
    return cpus[-1]


def ours(generations: int, seed: int = 1) -> tuple[float, list[float]]:
    """CPU seconds of ``generations`` generations of a paper-scale run, and the best fitness of
    each generation."""
    config = GridRunConfig(generations=generations)
    evaluator = evaluator_of(config)
    evaluator.evaluate(
        np.zeros((1, evaluator.layout.size)), generation_starts(config, seed, 0)[:1]
    )  # compile (or load the cache) before timing
    ga = GeneticAlgorithm(config.genetic(), evaluator.layout.size, seed)
    best = []
    started = time.process_time()
    while not ga.done:
        g = ga.generation
        result = evaluator.evaluate(
            ga.ask(), generation_starts(config, seed, g), generation_noise_key(seed, g)
        )
        best.append(ga.tell(result.fitness).best_fitness)
    return time.process_time() - started, best


#: The archive of the shipped study qd-grid (studies/files/qd-grid.yaml).
QD_MEASURES = [
    {"name": "LN", "bins": 4}, {"name": "PR", "bins": 4}, {"name": "RD", "bins": 4},
    {"name": "AG", "bins": 3}, {"name": "LG", "bins": 3},
    {"name": "TL", "range": [0.0, 0.3], "bins": 3}, {"name": "SW", "range": [0.0, 0.3], "bins": 3},
]  # fmt: skip


def map_elites(batches: int, seed: int = 1) -> float:
    """CPU seconds of ``batches`` batches of 50 of a paper-scale MAP-Elites run (its loop, up to
    the last batch's checkpoint-free progress report; no plots)."""
    from gridworld.config import decode_run_config
    from gridworld.qd import run_map_elites

    with tempfile.TemporaryDirectory(prefix="qd-bench-") as tmp:
        tiny = {"optimizer": "map-elites", "size": 8, "agents": 16, "repetitions": 1,
                "steps": 5, "population": 4, "generations": 2, "measures": QD_MEASURES}  # fmt: skip
        run_map_elites(decode_run_config(tiny), seed, Path(tmp) / "warm", plots=False)
        config = decode_run_config(
            {"optimizer": "map-elites", "generations": batches, "measures": QD_MEASURES}
        )
        evaluator = evaluator_of(config)
        evaluator.evaluate(
            np.zeros((1, evaluator.layout.size)), generation_starts(config, seed, 0)[:1]
        )  # compile (or load the cache) before timing
        marks: list[float] = []
        started = time.process_time()
        run_map_elites(config, seed, Path(tmp) / "run", plots=False, checkpoint_seconds=1e9,
                       progress=lambda _: marks.append(time.process_time()))  # fmt: skip
        return marks[-1] - started


def parts(seed: int = 1, repeats: int = 3) -> dict[str, float]:
    """Nanoseconds per agent-step of one generation of random genomes (L = 15, N = 100, 50
    genomes, 10 x 500 steps; best CPU time of ``repeats``) for the full network pair, without a
    predictor (every prediction fixed) and with the predictor partly fixed: where the time goes."""
    from gridworld.evaluate import GridEvaluator
    from gridworld.world import Torus, draw_starts
    from minimize_surprise.gridnet import GridGenomeLayout, GridNetSpec

    torus = Torus(15, 15)
    rng = np.random.default_rng(seed)
    starts = draw_starts(rng, torus, 100, 10)
    out = {}
    for name, predefined in (
        ("full", None),
        ("actor_only", "line"),
        ("line_partial", "line-partial"),
    ):
        spec = GridNetSpec(14, predefined)
        evaluator = GridEvaluator(torus, spec, 500)
        genomes = rng.uniform(-0.5, 0.5, (50, GridGenomeLayout(spec).size))
        evaluator.evaluate(genomes[:1], starts[:1])  # compile (or load the cache) before timing
        best = float("inf")
        for _ in range(repeats):
            started = time.process_time()
            evaluator.evaluate(genomes, starts)
            best = min(best, time.process_time() - started)
        out[name] = best / AGENT_STEPS_PER_GENERATION * 1e9
    return out


def build_c(source: Path, into: Path) -> Path:
    """Copy the C sources of ``source`` (checkout or git directory) into ``into`` and build."""
    if (source / "main.c").exists():
        for name in os.listdir(source):
            if name.endswith((".c", ".h")):
                shutil.copy(source / name, into / name)
    else:
        archive = subprocess.run(
            ["git", "--git-dir", str(source), "archive", "HEAD", "main.c", "STD.h", "STD14.h"],
            check=True,
            capture_output=True,
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    binary = into / "minimize-surprise"
    subprocess.run(
        ["gcc", "-O2", "-o", str(binary), str(into / "main.c"), "-lm"],
        check=True,
        capture_output=True,
    )
    return binary


def c_generations(binary: Path, generations: int, core: int) -> tuple[float, list[float]]:
    """CPU seconds the C code takes for ``generations`` generations (then it is stopped), and
    the best fitness it printed for each."""
    workdir = binary.parent
    proc = subprocess.Popen(
        ["stdbuf", "-oL", str(binary), "EVOL", "15", "15", "PRED", "NONE", "NONE"],
        cwd=workdir,
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: os.sched_setaffinity(0, {core}),
    )
    best = []
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("#"):
            best.append(float(line.split()[1]))
            if len(best) >= generations:
                break
    proc.kill()
    _, _, usage = os.wait4(proc.pid, 0)
    return usage.ru_utime + usage.ru_stime, best


def _c_genome_lines(layout, genome: np.ndarray) -> tuple[list[str], list[str]]:
    # The code's 3 x 224 layer arrays per network: each of our blocks is a layer's used prefix.
    w = layout.unpack(genome)
    connections = 224

    def layers(prefix: str) -> list[str]:
        out = []
        for block in ("input", "hidden", "output"):
            values = np.zeros(connections)
            flat = w[f"{prefix}.{block}"].ravel()
            values[: flat.size] = flat
            out.append(" ".join(f"{v:f}" for v in values))
        return out

    return layers("actor"), layers("predictor")


def check_against_c(binary: Path, count: int, seed: int) -> dict[str, float]:
    """Feed ``count`` random genomes and starts to the C code's REPLAY mode and to ours."""
    config = GridRunConfig()
    torus = Torus(15, 15)
    exact = evaluator_of(config, exact=True)
    fast = evaluator_of(config)
    layout = exact.layout
    rng = np.random.default_rng(seed)
    fit_diff_exact, fit_diff_fast, pred_diff, frames, frames_equal, genomes_equal = (
        [], [], [], 0, 0, 0
    )  # fmt: skip
    workdir = binary.parent
    for i in range(count):
        # genomes written as the code writes them (%f), so both sides use the same numbers
        genome = np.round(rng.uniform(-0.5, 0.5, layout.size), 6)
        start = generation_starts(config, seed, 1000 + i)[0]
        actor_lines, predictor_lines = _c_genome_lines(layout, genome)
        (workdir / "act").write_text("\n" * 396 + "\n".join(actor_lines) + "\n")
        (workdir / "pred").write_text("\n" * 396 + "\n".join(predictor_lines) + "\n")
        rows = Poses.from_cells(torus, start).to_rows()
        traj = "Gen: 0\nGrid: 15, 15\nAgents: 100\n" + "".join(
            f"0: {x}, {y}, {hx}, {hy}\n" for x, y, hx, hy in rows
        )
        (workdir / "traj").write_text(traj)
        for name in ("replay_fitness", "agent_trajectory-1_0_100_15_15"):
            (workdir / name).unlink(missing_ok=True)
        args = ["REPLAY", "traj", "pred", "act", "PRED", "NONE", "NONE", "0", "0", "100", "100"]
        subprocess.run([str(binary), *args, "0", "0", "0", "0", "0", "0"],
                       cwd=workdir, check=True, capture_output=True)  # fmt: skip
        lines = (workdir / "replay_fitness").read_text().splitlines()
        c_fit = float(lines[0].split(":")[1])
        c_pred = np.array([float(v) for v in lines[1].split()])
        e = exact.evaluate(genome[None], start[None])
        f = fast.evaluate(genome[None], start[None])
        fit_diff_exact.append(abs(e.fitness[0, 0] - c_fit))
        fit_diff_fast.append(abs(f.fitness[0, 0] - c_fit))
        pred_diff.append(float(np.abs(e.predictions[0, 0] - c_pred).max()))
        # the second, logged run starts from the first run's final poses in another order
        log = (workdir / "agent_trajectory-1_0_100_15_15").read_text().splitlines()[3:]
        c_frames = np.array([[int(v) for v in ln.split(":")[1].split(",")] for ln in log])
        c_frames = c_frames.reshape(501, 100, 4)
        second = np.array([[torus.cell(x, y), HEADINGS.index((hx, hy))]
                           for x, y, hx, hy in c_frames[0]], dtype=np.int32)  # fmt: skip
        run = fast.evaluate(genome[None], second[None], trace=(0, 0))
        ours_frames = np.zeros_like(c_frames)
        for t in range(501):
            p = Poses.from_cells(torus, run.trace[t])
            hx, hy = p.vectors()
            ours_frames[t] = np.stack([p.x, p.y, hx, hy], axis=1)
        same = (ours_frames == c_frames).all(axis=(1, 2))
        frames += same.size
        frames_equal += int(same.sum())
        genomes_equal += int(same.all())
    return {
        "check_genomes": count,
        "check_trajectories_identical": genomes_equal,
        "check_frames_identical_share": frames_equal / frames,
        "check_fitness_max_abs_diff_exact": max(fit_diff_exact),
        "check_fitness_max_abs_diff_fast": max(fit_diff_fast),
        "check_prediction_max_abs_diff": max(pred_diff),
    }


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generations", type=int, default=100)
    parser.add_argument("--c-generations", type=int, default=3)
    parser.add_argument("--c-source", type=Path)
    parser.add_argument("--check", type=int, default=0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--qd", type=int, default=0, metavar="N",
                        help="time N batches of MAP-Elites against N GA generations")  # fmt: skip
    parser.add_argument(
        "--parts",
        action="store_true",
        help="also time a generation without the predictor and with it partly fixed",
    )
    args = parser.parse_args()
    core = pin_to_one_core()
    if args.qd:
        qd_seconds = map_elites(args.qd, args.seed)
        ga_seconds, _ = ours(args.qd, args.seed)
        print(f"qd_seconds_{args.qd}_batches: {qd_seconds:.2f} s (map-elites, batches of 50)")
        print(f"ga_seconds_{args.qd}_generations: {ga_seconds:.2f} s (the GA, population 50)")
        print(f"qd_time_per_ga_time: {qd_seconds / ga_seconds:.2f} x")
        return
    if args.parts:
        for name, ns in parts(args.seed).items():
            print(f"ours_ns_per_agent_step_{name}: {ns:.1f} ns")
    seconds, best = ours(args.generations, args.seed)
    agent_steps = AGENT_STEPS_PER_GENERATION * args.generations
    print(f"ours_run_seconds: {seconds:.1f} s ({args.generations} generations, one core)")
    print(f"ours_agent_steps_per_second: {agent_steps / seconds:.3e} agent-steps/s")
    print(f"ours_best_fitness_last: {best[-1]:.4f}")
    if args.c_source is None:
        print("c_code: not measured (no --c-source)")
        return
    k = args.c_generations
    ours_k, ours_best_k = ours(k, args.seed)
    with tempfile.TemporaryDirectory(prefix="c-self-assembly-") as tmp:
        binary = build_c(args.c_source, Path(tmp))
        c_seconds, c_best = c_generations(binary, k, core)
        c_run = c_seconds / k * 100
        print(f"ours_seconds_{k}_generations: {ours_k:.2f} s")
        print(f"c_seconds_{k}_generations: {c_seconds:.2f} s")
        print(f"c_run_seconds_extrapolated: {c_run:.0f} s (100 generations)")
        print(f"c_agent_steps_per_second: {AGENT_STEPS_PER_GENERATION * k / c_seconds:.3e} "
              "agent-steps/s")  # fmt: skip
        print(f"speedup_same_generations: {c_seconds / ours_k:.1f} x")
        print(f"speedup_whole_run: {c_run / seconds * args.generations / 100:.1f} x")
        print(f"best_fitness_per_generation_ours: {' '.join(f'{b:.4f}' for b in ours_best_k)}")
        print(f"best_fitness_per_generation_c: {' '.join(f'{b:.4f}' for b in c_best)}")
        if args.check:
            for name, value in check_against_c(binary, args.check, args.seed).items():
                print(f"{name}: {value:.3g}" if isinstance(value, float) else f"{name}: {value}")


if __name__ == "__main__":
    main()
