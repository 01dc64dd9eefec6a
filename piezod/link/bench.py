"""``piezod bench stream``: stream a triangular waveform to a fresh simulator and count every loss.

:func:`run_stream_bench` spawns ``python -m hil_sim`` on a real pty, opens a
:class:`~piezod.link.session.BoardSession`, streams ``axes`` channels at ``rate_hz`` for
``seconds`` through a :class:`~piezod.link.streamer.Streamer`, reads the sensor back, and returns
the counts of both sides: samples sent / played / read back, underruns, CRC errors (host and
board), losses nobody reported (``unexplained_loss``), the smallest FIFO lead seen, frame counts
and CPU use. :func:`stream_bench` does the same on an already running board (any URL).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from piezod.config import ScannerConfig, default_sim_config_path, load_config
from piezod.errors import ConfigError
from piezod.link.session import BoardSession, LinkSettings
from piezod.link.streamer import Streamer, TriangleSource
from piezod.progress import progress_bar

_AXES = ("x", "y", "z")


def bench_config(config: ScannerConfig, axes: int, rate_hz: float) -> ScannerConfig:
    """``config`` restricted to its first ``axes`` axes (x, y, z order) at ``rate_hz``."""
    names = [a for a in _AXES if a in config.axes][:axes]
    if len(names) < axes:
        raise ConfigError(f"--axes {axes}: the scanner config {config.name!r} has only {len(names)} axes")
    kept = {name: config.axes[name] for name in names}
    return config.model_copy(update={"axes": kept, "sample_rate_hz": float(rate_hz)})


def triangle_for(config: ScannerConfig, rate_hz: float, fraction: float = 0.8) -> TriangleSource:
    """A triangle per axis over ``fraction`` of its voltage range, at most 2 Hz and within its slew limit."""
    axes = list(config.axes.values())
    lo = np.array([a.voltage_min_v for a in axes])
    hi = np.array([a.voltage_max_v for a in axes])
    center = (lo + hi) / 2.0
    amp = fraction * (hi - lo) / 2.0
    slew = np.array([a.slew_rate_v_per_s for a in axes])
    freq = float(min(2.0, 0.9 * np.min(slew / (4.0 * amp))))
    phase = np.arange(len(axes)) / max(1, len(axes))
    return TriangleSource(rate_hz, amp, center, freq, phase)


class ModelSource:
    """Triangle *targets* per axis through each axis's model inverse: the model runs in the streaming path.

    The targets span ``fraction`` of what the model's static sensitivity gives for each axis's
    triangle and are shaped by the resonance part first (:data:`piezod.bench.BENCH_RESONANCE`, as
    the axis driver shapes them for a stage with a mode); the voltages are clipped to the axis
    limits (counted by the streamer as host clamping). ``ns_per_sample`` is the shaping's and the
    inverse's cost per sample and axis while streaming.
    """

    def __init__(self, config: ScannerConfig, rate_hz: float, model_name: str, fraction: float = 0.8) -> None:
        from piezod.bench import BENCH_RESONANCE, bench_models
        from piezod.model.resonance import ResonancePart

        models = bench_models()
        if model_name not in models:
            raise ConfigError(f"--model {model_name!r}: one of {', '.join(models)}")
        self.model = models[model_name]
        self.name = model_name
        self.triangle = triangle_for(config, rate_hz, fraction)
        self.dt_s = 1.0 / float(rate_hz)
        axes = list(config.axes.values())
        self.lo = np.array([a.voltage_min_v for a in axes])[:, None]
        self.hi = np.array([a.voltage_max_v for a in axes])[:, None]
        start = self.triangle.next_block(1)[:, 0]
        self.triangle.position = 0
        self.states = [self.model.rest(float(v)) for v in start]
        self.shaper = ResonancePart(*BENCH_RESONANCE)
        self.before: list[npt.NDArray[np.float64]] = [np.empty(0) for _ in start]
        rest = np.array([self.model.position(self.model.rest(float(v))) for v in (0.0, 1.0)])
        self.um_per_v = float(rest[1] - rest[0])
        self.inverse_s = 0.0
        self.samples = 0

    def next_block(self, n: int) -> npt.NDArray[np.float64]:
        """The next ``n`` samples, ``(axes, n)`` volts."""
        targets = self.um_per_v * self.triangle.next_block(n)
        out = np.empty_like(targets)
        t0 = time.perf_counter()
        for i, st in enumerate(self.states):
            shaped = self.shaper.shape(targets[i], self.before[i], np.empty(0), self.dt_s)
            self.before[i] = self.shaper.window(self.before[i], targets[i], self.dt_s)
            out[i], self.states[i] = self.model.inverse(shaped, self.dt_s, st)
        self.inverse_s += time.perf_counter() - t0
        self.samples += targets.size
        clipped: npt.NDArray[np.float64] = np.clip(out, self.lo, self.hi)
        return clipped

    @property
    def ns_per_sample(self) -> float | None:
        """Mean cost of the inverse per sample and axis (ns), including the machine's load."""
        return None if not self.samples else 1e9 * self.inverse_s / self.samples


def _proc_cpu_s(pid: int) -> float | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def stream_bench(
    url: str,
    config: ScannerConfig,
    *,
    rate_hz: float,
    seconds: float,
    lead_s: float | None = None,
    settings: LinkSettings | None = None,
    board_pid: int | None = None,
    auto_restart: bool = True,
    model: str | None = None,
) -> dict[str, Any]:
    """Stream a triangle over ``url`` for ``seconds`` and return the counts (see the module docstring)."""
    lead = lead_s if lead_s is not None else config.service.lead_ms / 1000.0
    session = BoardSession.open(url, config=config, settings=settings, sample_rate_hz=rate_hz)
    try:
        plan = session.plan
        caps = session.capabilities
        assert plan is not None and caps is not None
        source: TriangleSource | ModelSource = (
            triangle_for(config, rate_hz) if model is None else ModelSource(config, rate_hz, model)
        )
        if lead_s is None:
            lead = min(lead, 0.6 * caps.fifo_depth_samples / float(rate_hz))  # the config's lead may not fit
        streamer = Streamer(session, source, lead_s=lead, auto_restart=auto_restart)
        cpu0, wall0 = time.process_time(), time.monotonic()
        board_cpu0 = _proc_cpu_s(board_pid) if board_pid is not None else None
        streamer.start(0)
        with progress_bar(desc="streaming", total=round(seconds, 1), unit="s") as bar:
            shown = 0.0
            while (elapsed := time.monotonic() - wall0) < seconds:
                if not streamer.running:
                    break  # the run ended (link lost, error): report what happened
                time.sleep(min(0.2, seconds - elapsed))
                now_s = round(min(time.monotonic() - wall0, seconds), 1)
                bar.update(now_s - shown)
                shown = now_s
        streamed_s = time.monotonic() - wall0
        stats = streamer.finish()
        wall = time.monotonic() - wall0
        cpu = time.process_time() - cpu0
        board_cpu1 = _proc_cpu_s(board_pid) if board_pid is not None else None
        c = session.counters()
    finally:
        session.close()
    rate = float(rate_hz)
    lead_min_ms = None if stats.lead_min_samples is None else 1000.0 * stats.lead_min_samples / rate
    lead_mean_ms = None if not stats.lead_count else 1000.0 * stats.lead_sum_samples / stats.lead_count / rate
    # decimation 1: one sensor row per row played, padding of a short run included
    sensor_expected = stats.samples_played + stats.padding_played
    sensor_missing = max(0, sensor_expected - c.sensor_rows)
    unexplained = stats.unexplained_output_loss + c.sensor_rows_lost_unexplained
    # rows that neither arrived nor were reported lost would also be unexplained
    unexplained += max(0, sensor_missing - c.sensor_rows_lost)
    result: dict[str, Any] = {
        "axes": len(plan.axes),
        "rate_hz": rate,
        "seconds": float(seconds),
        "streamed_s": streamed_s,
        "samples_sent": stats.samples_sent,
        "samples_played": stats.samples_played,
        "samples_read": c.sensor_rows,
        "underruns": c.underruns,
        "crc_errors": c.crc_errors,
        "crc_errors_host": c.crc_errors_host,
        "crc_errors_board": c.crc_errors_board,
        "decode_errors_host": c.decode_errors,
        "frames_dropped_board": c.frames_dropped_board,
        "sensor_rows_lost": c.sensor_rows_lost,
        "unexplained_loss": unexplained,
        "runs": len(stats.runs),
        "run_ends": [r.ended_by for r in stats.runs],
        "rewinds": stats.rewinds,
        "rows_resent": stats.rows_resent,
        "index_gaps": c.index_gaps,
        "overflows": c.overflows,
        "watchdogs": c.watchdogs,
        "board_clamped_samples": c.clamped_samples,
        "host_clamped_samples": stats.host_clamped_samples,
        "min_lead_ms": lead_min_ms,
        "mean_lead_ms": lead_mean_ms,
        "lead_target_ms": 1000.0 * lead,
        "model": None if not isinstance(source, ModelSource) else source.name,
        "model_ns_per_sample": None if not isinstance(source, ModelSource) else source.ns_per_sample,
        "samples_per_frame": streamer.frame_samples,
        "samples_frames_sent": c.samples_frames_sent,
        "sensor_frames": c.sensor_frames,
        "status_frames": c.status_frames,
        "frames_sent": c.frames_sent,
        "frames_received": c.frames_received,
        "bytes_sent": c.bytes_sent,
        "bytes_received": c.bytes_received,
        "retransmits": c.retransmits,
        "fifo_depth_samples": caps.fifo_depth_samples,
        "host_cpu_pct": 100.0 * cpu / wall if wall > 0 else None,
        "board_cpu_pct": (
            100.0 * (board_cpu1 - board_cpu0) / wall
            if board_cpu0 is not None and board_cpu1 is not None and wall > 0
            else None
        ),
        "wall_s": wall,
        "url": url,
    }
    return result


def run_stream_bench(args: argparse.Namespace) -> dict[str, Any]:
    """The ``piezod bench stream`` benchmark: a fresh simulator over a pty (``hil_sim.server.spawn_sim``).

    Parameters
    ----------
    args
        ``axes``, ``rate_hz``, ``seconds``; optional ``config`` (scanner YAML with a simulation
        section), ``seed``, ``lead_ms``, ``sim_args`` (extra simulator options), ``port`` (stream
        to that board instead of spawning hil_sim).

    Returns
    -------
    dict
        At least ``axes, rate_hz, seconds, samples_sent, samples_read, underruns, crc_errors``,
        plus ``unexplained_loss``, ``min_lead_ms``, frame counts and CPU use.
    """
    from piezod.simulator import spawn_sim

    axes = int(args.axes)
    rate_hz = float(args.rate_hz)
    seconds = float(args.seconds)
    if not 1 <= axes <= 3:
        raise ConfigError(f"--axes: {axes} outside [1, 3]")
    if seconds <= 0:
        raise ConfigError(f"--seconds: {seconds} must be > 0")
    config_path = getattr(args, "config", None) or default_sim_config_path()
    config = bench_config(load_config(config_path), axes, rate_hz)
    lead_ms = getattr(args, "lead_ms", None)
    extra = tuple(getattr(args, "sim_args", None) or ())
    port = getattr(args, "port", None)
    model = getattr(args, "model", None)
    if port:
        lead_s = None if lead_ms is None else float(lead_ms) / 1000.0
        result = stream_bench(str(port), config, rate_hz=rate_hz, seconds=seconds, lead_s=lead_s, model=model)
        result["simulator"] = f"the board at {port}"
        return result
    with spawn_sim(config_path, seed=int(getattr(args, "seed", 0) or 0), extra_args=extra) as sim:
        result = stream_bench(
            sim.path,
            config,
            rate_hz=rate_hz,
            seconds=seconds,
            lead_s=None if lead_ms is None else float(lead_ms) / 1000.0,
            board_pid=sim.pid,
            model=model,
        )
    result["simulator"] = "hil_sim over a pty"
    return result


__all__ = ["ModelSource", "bench_config", "run_stream_bench", "stream_bench", "triangle_for"]
