"""``piezod bench stream --api-load``: the whole daemon streaming while its API is hammered.

A fresh simulator on a pty, the daemon's engine scanning continuously (endless raster, fast axis
corrected), its control API on a Unix socket, ``clients`` threads requesting ``/v1/status`` as
fast as they can over the socket, and optionally (``with_fit``) a calibration fit running over and
over in the daemon's analysis worker. Reports the streaming counts of docs/formats.md plus the
API's request rate, so the cost of the API and the fits on the stream is measured in one run.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from piezod.client import PiezodClient
from piezod.config import default_sim_config_path, load_config
from piezod.errors import ConfigError
from piezod.link.bench import bench_config
from piezod.link.board import SerialBoard
from piezod.progress import progress_bar
from piezod.service.api import EventHub, create_app
from piezod.service.engine import Engine
from piezod.service.schemas import ScanRequest
from piezod.service.server import ApiServer


def _fit_loop(stop: threading.Event, counter: list[int]) -> None:
    """Fit a synthetic 12-experiment session again and again in a spawned worker."""
    from piezod.stagecal import AnalysisWorker

    with tempfile.TemporaryDirectory() as tmp, AnalysisWorker() as worker:
        path = Path(tmp) / "frame.csv"
        worker.synth_frame(path)
        base = load_config(default_sim_config_path())
        while not stop.is_set():
            worker.fit_thesis(path, base, "x")
            counter[0] += 1


def run_api_load_bench(args: argparse.Namespace) -> dict[str, Any]:
    """Stream with the daemon while the API is polled (and a fit runs); see the module docstring."""
    from piezod.simulator import spawn_sim

    axes, rate_hz, seconds = int(args.axes), float(args.rate_hz), float(args.seconds)
    clients = int(getattr(args, "api_clients", 2) or 2)
    if not 1 <= axes <= 3:
        raise ConfigError(f"--axes: {axes} outside [1, 3]")
    config_path = getattr(args, "config", None) or default_sim_config_path()
    config = bench_config(load_config(config_path), axes, rate_hz)
    with tempfile.TemporaryDirectory() as tmp, spawn_sim(config_path) as sim:
        hub = EventHub()
        engine = Engine(config, sim.path, recording_dir=Path(tmp), on_fault=hub.publish_fault)
        engine.open()
        spec = f"unix:{Path(tmp) / 'api.sock'}"
        server = ApiServer(create_app(engine, events=hub), spec)
        server.start()
        stop = threading.Event()
        requests = [0] * clients
        fits = [0]

        def poll(i: int) -> None:
            with PiezodClient(spec) as c:
                while not stop.is_set():
                    c.status()
                    requests[i] += 1

        threads = [threading.Thread(target=poll, args=(i,), daemon=True) for i in range(clients)]
        if getattr(args, "with_fit", False):
            threads.append(threading.Thread(target=_fit_loop, args=(stop, fits), daemon=True))
        try:
            line_rate = 5.0
            engine.start_scan(
                ScanRequest(range_um=20.0, line_rate_hz=line_rate, lines=256, frames=0, record=False)
            )
            for t in threads:
                t.start()
            t0 = time.monotonic()
            with progress_bar(desc="streaming under API load", total=round(seconds, 1), unit="s") as bar:
                shown = 0.0
                while (elapsed := time.monotonic() - t0) < seconds:
                    time.sleep(min(0.2, seconds - elapsed))
                    now = round(min(time.monotonic() - t0, seconds), 1)
                    bar.update(now - shown)
                    shown = now
            wall = time.monotonic() - t0
            stop.set()
            for t in threads:
                t.join(timeout=60.0)
            status = engine.status()
            board = engine.board
            assert isinstance(board, SerialBoard) and board.session is not None
            c = board.session.counters()
            stats = board.streamer.stats if board.streamer is not None else None
        finally:
            stop.set()
            server.stop()
            hub.close()
            engine.close()
    return {
        "axes": axes,
        "rate_hz": rate_hz,
        "seconds": seconds,
        "samples_sent": stats.samples_sent if stats is not None else 0,
        "samples_read": c.sensor_rows,
        "underruns": c.underruns,
        "crc_errors": c.crc_errors,
        "engine_state": status.state,
        "faults": [f"{f.source}/{f.code}: {f.message}" for f in status.faults],
        "api_clients": clients,
        "api_requests": sum(requests),
        "api_requests_per_s": sum(requests) / wall,
        "fits_completed": fits[0],
        "min_lead_ms": None
        if stats is None or stats.lead_min_samples is None
        else 1000.0 * stats.lead_min_samples / rate_hz,
        "simulator": "hil_sim over a pty; daemon engine + API in this process",
    }
