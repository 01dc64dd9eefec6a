"""The ``piezod`` command line (DESIGN section 4).

Each subcommand lives in its own module of this package exposing
``register(subparsers)``; ``register`` adds the parser and sets ``func`` to a
callable ``(args) -> int``. Errors derived from :class:`~piezod.errors.PiezodError`
end the program with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

# One BLAS thread: the fits are small, and on the controller PC the streaming thread needs the
# other core; multithreaded BLAS was 2-5x slower on a loaded 2-core machine.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from piezod import __version__  # noqa: E402
from piezod.errors import PiezodError  # noqa: E402

#: Subcommand modules, in the order ``piezod --help`` lists them.
SUBCOMMANDS: tuple[str, ...] = (
    "serve",
    "scan",
    "calibrate",
    "linearity",
    "image",
    "audit",
    "bench",
    "sim",
    "probe",
    "ctl",
)


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="piezod",
        description="Online hysteresis + creep linearisation for SPM piezo scanners.",
    )
    parser.add_argument("--version", action="version", version=f"piezod {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"piezod.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"piezod.cli.{name}":
                raise
            continue  # subcommand not built yet
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        status: int = args.func(args)
    except PiezodError as exc:
        print(f"piezod {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"piezod {args.command}: interrupted", file=sys.stderr)
        return 130
    return status


if __name__ == "__main__":  # pragma: no cover - exercised through the console script
    sys.exit(main())
