"""Helpers shared by the subcommands: JSON output, config and port options."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(target: str | None, payload: dict[str, Any]) -> None:
    """Write ``payload`` as JSON to ``target`` (``-`` is stdout, None does nothing).

    NaN / inf become ``null`` so that the output is strict JSON.
    """
    if target is None:
        return
    text = json.dumps(_jsonable(payload), indent=2, allow_nan=False)
    if target == "-":
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
    else:
        Path(target).write_text(text + "\n", encoding="utf-8")


def add_json_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--json F`` (``-`` for stdout)."""
    parser.add_argument("--json", metavar="F", help="write machine-readable results to F ('-' = stdout)")


def add_reading_options(parser: argparse.ArgumentParser) -> None:
    """``--encoding`` and ``--allow-truncated-tail``: how the recordings are read
    (:func:`piezod.recording.read_experiments`)."""
    parser.add_argument(
        "--encoding",
        metavar="NAME",
        help="text encoding of the recordings (default: detected; UTF-8, else Windows-1252/Latin-1)",
    )
    parser.add_argument(
        "--allow-truncated-tail",
        action="store_true",
        help="drop an unterminated last line (crash while writing)",
    )


def add_family_laws_option(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, default: Sequence[str], what: str
) -> None:
    """``--family-laws LAW...``: which laws of the model family are fitted (``what`` starts the help)."""
    from piezod.calibrate_family import LAWS  # the fitting stack only for the commands that fit

    parser.add_argument(
        "--family-laws",
        nargs="+",
        choices=LAWS,
        default=list(default),
        metavar="LAW",
        help=f"{what} ({', '.join(LAWS)}; each with both creep drivers; default {', '.join(default)})",
    )


def add_port_options(parser: argparse.ArgumentParser, *, required: bool = False) -> None:
    """Add the mutually exclusive ``--sim`` / ``--port URL`` pair."""
    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument("--sim", action="store_true", help="start the built-in simulated stage on a pty")
    group.add_argument("--port", metavar="URL", help="pyserial URL or device of the board (or usb://VID:PID)")


def human_stream(args: argparse.Namespace) -> Any:
    """Where human-readable output goes: stderr when ``--json -`` owns stdout."""
    return sys.stderr if getattr(args, "json", None) == "-" else sys.stdout


def scanner_config_path(args: argparse.Namespace, *, first_guess: bool = False) -> Path:
    """``--config`` or, with ``--sim``, the built-in simulated stage's config.

    With ``--sim`` that is the stage with its shipped calibration
    (``configs/sim-stage-calibrated.yaml``), or with ``first_guess`` (``calibrate --sim``) the
    uncalibrated ``configs/sim-stage.yaml``.
    """
    from piezod.config import default_sim_config_path, default_sim_scan_config_path
    from piezod.errors import ConfigError

    if getattr(args, "config", None):
        return Path(args.config)
    if getattr(args, "sim", False):
        return default_sim_config_path() if first_guess else default_sim_scan_config_path()
    raise ConfigError("--config F is required with --port (the scanner's YAML)")


def add_microscope_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--sample NAME`` / ``--no-position-sensor`` (the simulated microscope, with ``--sim``)."""
    parser.add_argument(
        "--sample",
        metavar="NAME",
        help="with --sim: image this sample in the simulated microscope (line-3um, grating-200nm, "
        "grating-10um, steps-100nm, flat); records the height channel (z_voltage)",
    )
    parser.add_argument(
        "--no-position-sensor",
        action="store_true",
        help="with --sim --sample: the simulated board has no x / y position sensor",
    )


def sim_microscope_args(args: argparse.Namespace) -> tuple[str, ...]:
    """The simulator's options for ``--sample`` / ``--no-position-sensor``."""
    out: tuple[str, ...] = ()
    if getattr(args, "sample", None):
        out += ("--sample", str(args.sample))
    if getattr(args, "no_position_sensor", False):
        out += ("--no-position-sensor",)
    if getattr(args, "truth_log", None):
        out += ("--truth-log", str(args.truth_log))
    return out


def with_microscope(args: argparse.Namespace, config: Any) -> Any:
    """``config`` with a ``microscope`` section when ``--sim --sample`` asks for one."""
    from piezod.config import MicroscopeSection

    if not getattr(args, "sample", None):
        return config
    section = config.microscope or MicroscopeSection()
    if getattr(args, "no_position_sensor", False):
        section = section.model_copy(update={"position_sensor": False})
    return config.model_copy(update={"microscope": section})


@contextlib.contextmanager
def board_url(args: argparse.Namespace, config_path: Path) -> Iterator[str]:
    """The board's URL: ``--port``, or a simulator started for ``--sim`` (stopped afterwards)."""
    from piezod.errors import ConfigError

    if getattr(args, "sim", False):
        from piezod.simulator import spawn_sim

        effects = tuple(getattr(args, "effect", None) or ())
        extra = sim_microscope_args(args)
        with spawn_sim(config_path, effects=effects, extra_args=extra) as sim:
            yield sim.path
    elif getattr(args, "port", None):
        yield str(args.port)
    else:
        raise ConfigError("give --sim or --port URL")


def _number(text: str, kind: type[float] | type[int]) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not {'an integer' if kind is int else 'a number'}"
        ) from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def finite_float(text: str) -> float:
    """argparse type: a finite number (no nan / inf)."""
    return float(_number(text, float))


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be above 0")
    return value


def nonneg_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must not be negative")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = int(_number(text, int))
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be at least 1")
    return value


def nonneg_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    value = int(_number(text, int))
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must not be negative")
    return value


def recording_label(path: Path) -> str:
    """A recording name for ``path``: its stem with anything but letters, digits, ``. _ -`` as ``_``."""
    import re

    label = re.sub(r"[^A-Za-z0-9._-]", "_", path.stem).lstrip("._-")[:100]
    return label or "scan"


def input_file(text: str) -> str:
    """argparse type: a path to an existing regular file (not a device such as /dev/zero, not a FIFO)."""
    import os
    import stat

    try:
        st = os.stat(text)
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"{text}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise argparse.ArgumentTypeError(f"{text}: not a regular file")
    return text


def fresh_dir(path: Path) -> Path:
    """Create a new directory ``path`` (or ``path-2``, ``path-3``, ... if it exists) and return it.

    Recordings are never overwritten: a run that writes fixed file names gets a directory of its own.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    for n in range(1, 10_000):
        candidate = path if n == 1 else path.with_name(f"{path.name}-{n}")
        try:
            candidate.mkdir()
        except FileExistsError:
            continue
        return candidate
    raise FileExistsError(f"{path}: no free directory name")
