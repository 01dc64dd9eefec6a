"""``piezod sim``: the simulated board + piezo stage on a pty (prints the path, serves until killed)."""

from __future__ import annotations

import argparse
from typing import Any

from piezod.simulator import add_sim_arguments, run_sim


def register(sub: Any) -> None:
    """Add the ``sim`` subcommand."""
    p: argparse.ArgumentParser = sub.add_parser(
        "sim",
        help="run the simulated board and stage on a pty",
        description=(
            "Serve the simulated DAC/HV board driving the simulated piezo stage on a pseudo-terminal. "
            "Prints ONE line (the pty path, or --link) on stdout and serves until SIGTERM / SIGINT "
            "(exit 0). SIGUSR1 simulates an unplug for --unplug-s seconds."
        ),
    )
    add_sim_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``piezod sim`` (the simulator's own errors become a one-line ConfigError)."""
    return run_sim(args)
