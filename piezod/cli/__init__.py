"""The ``piezod`` command line (contract: docs/formats.md).

Each subcommand lives in its own module of this package exposing
``register(subparsers)``; ``register`` adds the parser and sets ``func`` to a
callable ``(args) -> int``. Errors derived from :class:`~piezod.errors.PiezodError`
end the program with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from types import FrameType
from typing import NoReturn

# One BLAS thread: the fits are small, and on the controller PC the streaming thread needs the
# other core; multithreaded BLAS was 2-5x slower on a loaded 2-core machine.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from pydantic import ValidationError  # noqa: E402

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


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors: ``piezod scan: error: argument --lines: ...`` (exit 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def _one_line_validation(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or exc.title
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)


def build_parser() -> argparse.ArgumentParser:
    """Build the top-level parser with every available subcommand."""
    parser = OneLineParser(
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


class _TerminatedError(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: the command unwinds as on Ctrl-C."""


def _terminate_unwinds() -> Callable[[], None]:
    """Make SIGTERM unwind the command as Ctrl-C does; returns what restores the previous handler.

    Without it SIGTERM (``kill``, a job scheduler, a session's end) ends the process on the spot:
    the recording being written loses its buffered rows, a simulator it started is left running
    and the board's watchdog is what brings the outputs down. ``piezod serve`` and ``piezod sim``
    install handlers of their own over this one. Only the main thread can, and only a handler
    nobody else installed is replaced.
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous = signal.getsignal(signal.SIGTERM)
    if previous is not signal.SIG_DFL:
        return lambda: None

    def handler(signum: int, frame: FrameType | None) -> None:
        raise _TerminatedError

    signal.signal(signal.SIGTERM, handler)

    def restore() -> None:
        signal.signal(signal.SIGTERM, previous)

    return restore


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit status.

    SIGTERM unwinds the command as Ctrl-C does (exit status 143, Ctrl-C's 130).
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a one-line argument error already printed
        return exc.code if isinstance(exc.code, int) else 2
    restore = _terminate_unwinds()
    try:
        return _run(args)
    finally:
        restore()


def _run(args: argparse.Namespace) -> int:
    try:
        status: int = args.func(args)
    except PiezodError as exc:
        print(f"piezod {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:
        print(f"piezod {args.command}: error: {_one_line_validation(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:
        # a file the user named (--out, --json, -o, a token file) cannot be read or written
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"piezod {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except _TerminatedError:
        print(f"piezod {args.command}: terminated (SIGTERM)", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print(f"piezod {args.command}: interrupted", file=sys.stderr)
        return 130
    return status


if __name__ == "__main__":  # pragma: no cover - exercised through the console script
    sys.exit(main())
