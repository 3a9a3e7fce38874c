"""Options that several commands of ``surprise-master`` take alike."""

from __future__ import annotations

import argparse

__all__ = ["add_timeout"]


def add_timeout(parser: argparse.ArgumentParser, default: float, waiting_for: str) -> None:
    """``--timeout S``: seconds the command waits for ``waiting_for`` (``"the master's
    answer"``), ``default`` unless given; the help says both."""
    parser.add_argument(
        "--timeout",
        type=float,
        default=default,
        metavar="S",
        help=f"seconds to wait for {waiting_for} (default: {default:g})",
    )
