"""Run-directory files for the readers' tests, written through the schema as a master writes
them (runfiles.schema), with only what a test cares about given."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from runfiles import schema
from runfiles.schema import Checkpoint, Live, Phase

__all__ = ["write_checkpoint", "write_live"]


def write_checkpoint(
    run: Path,
    rows: int,
    phase: Phase = "evolution",
    written_at: float = 0.0,
    best_fitness: float | None = 0.5,
) -> None:
    """A checkpoint that counts ``rows`` rows and as many evaluations."""
    schema.write(
        run,
        Checkpoint(
            run_id=run.name,
            phase=phase,
            next_evaluation_id=rows,
            attempts=0,
            failed_attempts=0,
            csv_rows=rows,
            roster=None,
            written_at=written_at,
            optimizer={"evaluations": rows, "best_fitness": best_fitness},
        ),
    )


def write_live(run: Path, **fields: Any) -> Live:
    """``live.json`` of a master of this process serving the run now; ``fields`` override."""
    live: dict[str, Any] = {
        "pid": os.getpid(),
        "running": True,
        "host": "127.0.0.1",
        "port": 1,
        "robots": [],
        "phase": "evolution",
        "waiting": False,
        "evaluations": 0,
        "time_left_s": None,
        "paused": None,
        "robot_state": {},
        "updated_at": time.time(),
    }
    data = schema.decode(Live, schema.encode(Live(**(live | fields))))
    schema.write(run, data)
    return data
