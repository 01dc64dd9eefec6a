"""``piezod scan``: run one scan end to end on the stage and write the recording."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from piezod.cli._common import (
    add_microscope_options,
    add_port_options,
    board_url,
    finite_float,
    human_stream,
    nonneg_float,
    positive_float,
    positive_int,
    recording_label,
    scanner_config_path,
    with_microscope,
)
from piezod.config import load_config, uncalibrated_warning
from piezod.errors import BoardFaultError, ConfigError, RecordingError
from piezod.progress import progress_bar
from piezod.service.engine import Engine
from piezod.service.schemas import ScanRequest


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``piezod scan``."""
    p = sub.add_parser("scan", help="run one scan on the stage and record it", description=__doc__)
    p.add_argument(
        "--config", metavar="F", help="scanner YAML (default with --sim: configs/sim-stage-calibrated.yaml)"
    )
    add_port_options(p, required=True)
    p.add_argument("--effect", action="append", metavar="NAME=VALUE", help="simulator effect (with --sim)")
    p.add_argument("--range-um", type=positive_float, required=True, help="fast-axis scan range (um)")
    p.add_argument(
        "--line-rate-hz", type=positive_float, required=True, help="lines per second (trace + retrace)"
    )
    p.add_argument("--lines", type=positive_int, default=8, help="lines per frame (default 8)")
    p.add_argument("--pixels", type=positive_int, default=None, help="pixels per image line (default 256)")
    p.add_argument(
        "--offset-um", type=finite_float, default=0.0, help="fast-axis offset of the image centre (um)"
    )
    p.add_argument(
        "--slow-range-um", type=nonneg_float, default=None, help="slow-axis range (default: range)"
    )
    p.add_argument("--no-correction", action="store_true", help="drive the plain triangle (no model)")
    p.add_argument(
        "--model",
        choices=("thesis", "dynamic", "family"),
        help="override the scanner config's model on every axis",
    )
    add_microscope_options(p)
    p.add_argument("--out", required=True, metavar="REC.csv", help="the recording to write")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the scan."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    config_path = scanner_config_path(args)
    config = with_microscope(args, load_config(config_path))
    slow = args.range_um if args.slow_range_um is None else args.slow_range_um
    warning = uncalibrated_warning(config, config_path, ("x", "y") if slow > 0 and args.lines > 1 else ("x",))
    if warning and not args.no_correction:
        print(f"warning: {warning}", file=sys.stderr)
    if args.model:
        if args.model != "thesis" and getattr(config.axes["x"], args.model) is None:
            raise ConfigError(
                f"{config_path}: --model {args.model} needs a '{args.model}:' section on axis x"
                " (calibrate first)"
            )
        # axes without what the model needs keep their own model
        axes = {
            name: ax.model_copy(update={"model": args.model})
            if args.model == "thesis" or getattr(ax, args.model) is not None
            else ax
            for name, ax in config.axes.items()
        }
        config = config.model_copy(update={"axes": axes})
    out = Path(args.out)
    if out.exists() or out.is_symlink():
        raise RecordingError("exists; recordings are never overwritten: choose another --out", str(out))
    request = ScanRequest(
        range_um=args.range_um,
        line_rate_hz=args.line_rate_hz,
        lines=args.lines,
        pixels=args.pixels or (config.microscope.pixels if config.microscope is not None else 256),
        slow_range_um=args.slow_range_um,
        offset_x_um=args.offset_um,
        correction=not args.no_correction,
        name=recording_label(out),
    )
    say = human_stream(args)
    with board_url(args, config_path) as url:
        engine = Engine(config, url, recording_dir=out.parent if str(out.parent) else Path("."))
        engine.check_scan(request)
        engine.open()
        try:
            engine.start_scan(request, path=out)
            total = (request.lines + 2) / request.line_rate_hz
            t0 = time.monotonic()
            with progress_bar(desc="scanning", total=round(total, 1), unit="s") as bar:
                shown = 0.0
                while engine.status().state == "scanning":
                    time.sleep(0.1)
                    now = round(min(time.monotonic() - t0, total), 1)
                    bar.update(now - shown)
                    shown = now
            state = engine.wait_idle(timeout_s=10.0)
            engine.wait_recorded()
            status = engine.status()
        finally:
            engine.close()
    if state != "idle":
        faults = "; ".join(f"{f.code}: {f.message}" for f in status.faults[-3:])
        raise BoardFaultError(f"the scan ended in state {state}: {faults}")
    model = config.axes["x"].model + (" model, UNCALIBRATED" if warning else " model")
    mode = f"corrected ({model})" if request.correction else "uncorrected (plain triangle)"
    print(
        f"scanned {request.lines} lines of {request.range_um:g} um at {request.line_rate_hz:g} Hz, {mode}",
        file=say,
    )
    print(f"recording: {out}  (underruns {status.underruns}, faults {len(status.faults)})", file=say)
    sensorless = config.microscope is not None and not config.microscope.position_sensor
    if status.last_line is not None and not sensorless:
        ll = status.last_line
        print(f"last line ({ll.direction}): {ll.figures()}", file=say)
    return 0
