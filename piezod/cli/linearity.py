"""``piezod linearity``: non-linearity and length error (4.14)-(4.16) of recorded scans."""

from __future__ import annotations

import argparse
import re
from typing import Any

from piezod.cli._common import (
    add_json_option,
    add_reading_options,
    human_stream,
    input_file,
    nonneg_float,
    positive_float,
    write_json,
)
from piezod.linearity import LinearityReport, linearity
from piezod.recording import AXES, read_experiments


def register(sub: Any) -> None:
    """Add the ``linearity`` subcommand."""
    p: argparse.ArgumentParser = sub.add_parser(
        "linearity",
        help="non-linearity and length error of recorded scans (thesis 4.14-4.16)",
        description=(
            "Per experiment and branch, regress the measured position on the commanded target (or, "
            "without a target column, on the pixel coordinate of the nominal range) and report the "
            "residual non-linearity sigma / measured range and the length error, in %."
        ),
    )
    p.add_argument(
        "recordings", nargs="+", type=input_file, metavar="REC.csv", help="recording files (docs/formats.md)"
    )
    add_json_option(p)
    p.add_argument("--range-um", type=positive_float, metavar="R", help="nominal scan range (um)")
    p.add_argument(
        "--overscan", type=nonneg_float, metavar="O", help="overscan fraction (default: from the file)"
    )
    p.add_argument("--axis", choices=AXES, help="only this axis")
    add_reading_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``piezod linearity``."""
    exps = read_experiments(
        args.recordings,
        axis=args.axis,
        allow_truncated_tail=args.allow_truncated_tail,
        encoding=args.encoding,
    )
    several_axes = len({e.axis for e in exps}) > 1
    report = linearity(
        exps,
        range_um=args.range_um,
        overscan=args.overscan,
        skip_non_scans=args.axis is None and several_axes,
    )
    _print_table(report, human_stream(args))
    write_json(args.json, report.to_json())
    return 0


def _print_table(report: LinearityReport, out: Any) -> None:
    w = max([10, *(len(e.label) for e in report.experiments)])  # whole names, never cut
    print(
        f"{'experiment':<{w}} {'axis':>4} {'f Hz':>7} {'offs V':>7} {'range um':>9} {'meas um':>9} "
        f"{'nonlin %':>9} {'length %':>9}",
        file=out,
    )
    for e in report.experiments:
        print(
            f"{e.label:<{w}} {e.axis or '-':>4} {e.frequency_hz:7.3g} {e.offset_v:7.1f} "
            f"{e.range_um:9.4g} {e.measured_range_um:9.4g} "
            f"{e.nonlinearity_pct:9.4f} {e.length_error_pct:+9.4f}",
            file=out,
        )
    _print_skipped(report.skipped, out)
    print(
        f"max non-linearity {report.max_nonlinearity_pct:.4f} %, "
        f"max |length error| {report.max_abs_length_error_pct:.4f} %",
        file=out,
    )


def _print_skipped(skipped: tuple[tuple[str, str, str], ...], out: Any) -> None:
    """One line per axis and reason (a raster's slow axis is skipped in every experiment)."""
    groups: dict[tuple[str, str], list[str]] = {}
    for label, axis, reason in skipped:
        why = re.sub(r"^experiment '.*?'( \(axis \w\))?: ", "", reason)
        groups.setdefault((axis, why), []).append(label)
    for (axis, why), labels in groups.items():
        which = f"experiment {labels[0]}" if len(labels) == 1 else f"{len(labels)} experiments"
        print(f"skipped axis {axis} of {which}: {why}", file=out)
