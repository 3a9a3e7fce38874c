"""The master's overhead per round with 4, 100 and 1,000 connected scripted robots.

Overhead per round: from the last Result of a round arriving at the master to the next round's
Evaluate written to every robot. It covers telling the optimizer, the CSV row and the checkpoint
(fsynced, in a worker thread), asking for the next genome, encoding it once and writing it to every
connection. The robots run in a separate process so they do not share the master's event loop.
Target: <= 5 ms at 100 robots.

The scripted robots answer 10 ms after each Evaluate. A real round lasts 10 s, during which the
previous round's commit reaches the disk; robots answering instantly would make a round shorter
than one fsync and the figure would measure the disk, not the master (the last line gives the
commit's own cost).

Prints one figure a line as ``name: value unit`` (median and 95th percentile over the rounds).
Run: ``python benchmarks/master.py``
"""

from __future__ import annotations

import asyncio
import multiprocessing
import statistics
import tempfile
import time
from pathlib import Path

from master_service import Master, MasterConfig
from master_service.config import DEFAULT_MAX_PENDING_CONNECTIONS
from master_service.rundir import RunDir, format_row
from minimize_surprise.config import EvolutionConfig, ExperimentConfig
from standins.scripted_robots import ScriptedRobot

SECRET = b"benchmark-secret"
#: Rounds per swarm size: enough for a stable median, few enough for 1,000 robots to stay quick.
ROUNDS = {4: 300, 100: 150, 1000: 40}
#: Seconds the scripted robots take to "evaluate" (see the module docstring).
ANSWER_DELAY = 0.01


def _robots_process(port: int, count: int) -> None:
    """Child process: ``count`` scripted robots answering at once, until the master says Bye."""

    async def main() -> None:
        robots = [
            ScriptedRobot(f"r{i:04d}", SECRET, port, index=i, delay=ANSWER_DELAY)
            for i in range(count)
        ]
        # Connect in batches no larger than the master's limit of handshakes at once (real robots
        # beyond it retry with backoff; these scripted ones do not retry).
        batch = DEFAULT_MAX_PENDING_CONNECTIONS
        for start in range(0, count, batch):
            await asyncio.gather(*(r.connect() for r in robots[start : start + batch]))
        await asyncio.gather(*(r.closed.wait() for r in robots))

    asyncio.run(main())


async def _measure(robots: int, rounds: int) -> list[float]:
    experiment = ExperimentConfig(
        robots=robots,
        evaluation_steps=1,
        post_evaluation_steps=0,
        evolution=EvolutionConfig(evaluations=rounds),
    )
    # A generous margin: a round must never time out here, whatever the machine's load.
    config = MasterConfig(experiment=experiment, port=0, round_margin=60.0, heartbeat_interval=5.0)
    with tempfile.TemporaryDirectory() as tmp:
        async with Master(config, Path(tmp) / "run", secret=SECRET) as master:
            child = multiprocessing.get_context("spawn").Process(
                target=_robots_process, args=(master.port, robots)
            )
            child.start()
            try:
                await master.run()
            finally:
                await master.close()
                child.join(timeout=30)
                if child.is_alive():
                    child.kill()
            return master.overheads


def _commit_time(repeats: int = 200) -> float:
    """Median time of one commit (CSV row + checkpoint, both fsynced) of a 100-robot run."""
    from master_service.rundir import RunState
    from minimize_surprise.evolution import OnePlusOne

    with tempfile.TemporaryDirectory() as tmp:
        run = RunDir(tmp)
        state = RunState(run_id="bench", optimizer=OnePlusOne(EvolutionConfig(), 353, 0))
        header = ["evaluation", *(f"fitness_r{i}" for i in range(100))]
        times = []
        for i in range(repeats):
            row = format_row(i + 1, "offspring", 0.5, 0.5, True, 1, 10.0, 0.0, [0.5] * 100)
            start = time.perf_counter()
            run.commit(state.to_checkpoint(), row, header)
            times.append(time.perf_counter() - start)
        run.close()
    return statistics.median(times)


def _p95(values: list[float]) -> float:
    return statistics.quantiles(values, n=20)[-1]


def main() -> None:
    """Print the figures."""
    for robots, rounds in ROUNDS.items():
        overheads = asyncio.run(_measure(robots, rounds))
        print(f"master_round_overhead_{robots}_robots: {statistics.median(overheads) * 1e3:.2f} ms")
        print(f"master_round_overhead_{robots}_robots_p95: {_p95(overheads) * 1e3:.2f} ms")
    print(f"master_commit_row_and_checkpoint: {_commit_time() * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
