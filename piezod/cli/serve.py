"""``piezod serve``: run the daemon (the systemd service's command)."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import TextIO

from piezod.cli._common import add_port_options, board_url, fresh_dir, scanner_config_path
from piezod.config import load_config, uncalibrated_warning
from piezod.service.daemon import running_daemon, stop_on_signals
from piezod.service.engine import Engine
from piezod.service.logs import setup_logging
from piezod.service.schemas import ScanRequest
from piezod.stagecal import AnalysisWorker, Frame, default_frame, frame_summary, run_frame

log = logging.getLogger("piezod.serve")


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``piezod serve``."""
    p = sub.add_parser(
        "serve", help="run the daemon: stream, record, serve the control API", description=__doc__
    )
    p.add_argument(
        "--config", metavar="F", help="scanner YAML (default with --sim: configs/sim-stage-calibrated.yaml)"
    )
    add_port_options(p, required=True)
    p.add_argument(
        "--api", metavar="SPEC", help="unix:PATH (default /run/piezod/<scanner>.sock) or tcp:HOST:PORT"
    )
    p.add_argument("--recordings", metavar="DIR", help="recording directory (default: the config's)")
    p.add_argument("--effect", action="append", metavar="NAME=VALUE", help="simulator effect (with --sim)")
    p.add_argument(
        "--demo",
        action="store_true",
        help="calibrate on the stage (quick frame), scan uncorrected and corrected, print the linearity",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run until SIGTERM / SIGINT; exit 0 after ramping the outputs to the safe values."""
    setup_logging(logging.DEBUG if args.verbose else logging.INFO)
    stop = stop_on_signals()
    # the demo calibrates on the stage: it starts from the first guess
    config_path = scanner_config_path(args, first_guess=args.demo)
    config = load_config(config_path)
    warning = uncalibrated_warning(config, config_path, ("x", "y"))
    if warning:
        log.warning("%s", warning)
    recdir = Path(args.recordings or config.service.recording_dir)
    with board_url(args, config_path) as url:
        demo = _demo if args.demo else None
        with running_daemon(
            config, url, api_spec=args.api, recording_dir=recdir, before_ready=demo
        ) as daemon:
            say = sys.stdout
            print(f"piezod serving {config.name} on {url}; API {daemon.api_spec}", file=say)
            print(f"  try: piezod ctl --api {daemon.api_spec} status", file=say)
            print(
                "  stop with Ctrl-C (or SIGTERM): the outputs ramp to the safe values", file=say, flush=True
            )
            daemon.run_until_stopped(stop)
    return 0


def _demo(engine: Engine) -> None:
    """Calibrate on the stage, then scan uncorrected and corrected and show the linearity."""
    say = sys.stdout
    frame = default_frame(engine.config, "x", reduced=True)
    demo_dir = fresh_dir(engine.recording_dir / time.strftime("demo-%Y%m%d-%H%M%S"))
    print(f"demo 1/3: calibration frame on the stage: {frame_summary(frame)}", file=say, flush=True)
    with AnalysisWorker() as worker:
        _demo_steps(engine, worker, frame, say, demo_dir)


def _demo_steps(engine: Engine, worker: AnalysisWorker, frame: Frame, say: TextIO, demo_dir: Path) -> None:
    frame_path = run_frame(engine, frame, demo_dir / "demo-frame.csv")
    fitted = worker.fit_thesis(frame_path, engine.config, "x")
    axis_cfg = fitted.config.axes["x"]
    engine.set_axis_model("x", axis_cfg)
    if "y" in engine.drivers:
        engine.set_axis_model("y", engine.config.axes["y"].model_copy(update={"thesis": axis_cfg.thesis}))
    p = axis_cfg.thesis
    print(
        f"  fitted (3.8): alpha {p.alpha_per_v:.4g} 1/V, b {p.b_um_per_v:.4g} um/V, "
        f"u {p.u_um_per_v:.4g} um/V, "
        f"tau {p.tau_s:.3g} s, A1 {p.a1:.3g}, A2 {p.a2_per_v:.3g} 1/V, A3 {p.a3:.3g}; "
        f"worst fit error {fitted.fit_error_pct:.3f} %",
        file=say,
        flush=True,
    )
    rows = []
    for i, correction in enumerate((False, True)):
        what = "corrected" if correction else "uncorrected"
        print(f"demo {2 + i}/3: {what} scan, 20 um at 1 Hz, 8 lines", file=say, flush=True)
        path = demo_dir / f"demo-{what}.csv"
        req = ScanRequest(
            range_um=20.0, line_rate_hz=1.0, lines=8, correction=correction, name=f"demo-{what}"
        )
        engine.start_scan(req, path=path)
        engine.wait_idle(60.0)
        engine.wait_recorded()
        figures = worker.linearity(path, "x")
        rows.append((what, figures.nonlinearity_pct, figures.length_error_pct, path))
    _table(rows, say)


def _table(rows: list[tuple[str, float, float, Path]], out: TextIO) -> None:
    print(f"  {'scan':<12} {'nonlinearity %':>15} {'length error %':>15}  recording", file=out)
    for what, nl, le, path in rows:
        print(f"  {what:<12} {nl:15.3f} {le:+15.3f}  {path}", file=out)
    print("  (one pixel of a 512-pixel line is 0.2 %)", file=out, flush=True)
