"""The link budget: how many bytes per second the host and the board ask of the link.

A fast link (USB, a pty to hil_sim) carries far more than the stream needs and the defaults
apply: STATUS every 10 ms, SAMPLES frames of 5 ms. A slow one does not: a UART at 115200 baud
carries 11.5 kB/s each way, QEMU's emulated CMSDK UART on a pty a few kB/s for both directions
together, and a 10 ms STATUS alone is 7 kB/s. With the link's capacity given (scanner YAML
``service.link_bytes_per_s``, and ``service.link_shared`` when both directions share it),
:func:`plan_link_budget` derives the status period and the frame size from the capacity and the
sample rate so that neither direction asks for more than :data:`USABLE_FRACTION` of it, and
refuses (:class:`~piezod.errors.ConfigError`, with the figures) a stream the link cannot carry.

Per direction (wire bytes, COBS and delimiter included, from the codec's own sizes):

- host -> board: SAMPLES ``rate / n * wire(12 + 2 C n)`` for frames of ``n`` rows, plus SYNC
  (``wire(12 + 8 E)`` per frame) when the board has sync outputs; HEARTBEAT is only sent when
  nothing else went out for a quarter of the watchdog timeout, so never while streaming;
- board -> host: STATUS ``wire(56)`` per status period, SENSOR rows ``rate / decimation * 2 C``
  bytes plus one frame header per status period (the board flushes its readback at least then).

The frame size grows until the host's share fits (at most a quarter of the lead, so the FIFO
still holds four frames); the status period grows until the board's share fits (at most a third
of the lead: the host must see several STATUS frames within the lead to keep the FIFO filled).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_proto import HEADER_SIZE, max_encoded_size
from piezod.errors import ConfigError

#: Fraction of the link's capacity the stream may use (the rest: control frames, retransmissions).
USABLE_FRACTION = 0.7
#: The defaults on a fast link.
DEFAULT_STATUS_PERIOD_MS = 10
DEFAULT_FRAME_S = 0.005
_CRC = 4
_STATUS_PAYLOAD = 56
_SAMPLES_HEAD = 12
_SENSOR_HEAD = 16
_SYNC_HEAD, _SYNC_EVENT = 12, 8


def wire_bytes(payload: int) -> int:
    """Bytes on the wire of a frame with ``payload`` payload bytes (worst-case COBS + delimiter)."""
    return max_encoded_size(HEADER_SIZE + payload + _CRC) + 1


@dataclass(frozen=True, slots=True)
class LinkBudget:
    """What the stream asks of the link (bytes/s per direction) with the derived cadences."""

    capacity_bytes_per_s: float | None
    shared: bool
    sample_rate_hz: float
    channels: int
    frame_samples: int
    status_period_ms: int
    host_to_board_bytes_per_s: float
    board_to_host_bytes_per_s: float

    @property
    def usable_bytes_per_s(self) -> float | None:
        """Bytes/s each direction may use (``None``: a fast link, not limited)."""
        if self.capacity_bytes_per_s is None:
            return None
        return USABLE_FRACTION * self.capacity_bytes_per_s / (2.0 if self.shared else 1.0)

    def describe(self) -> str:
        """One line for the log and the docs."""
        cap = (
            "a fast link (no capacity given)"
            if self.capacity_bytes_per_s is None
            else f"{self.capacity_bytes_per_s:,.0f} B/s {'both ways' if self.shared else 'each way'}"
            f" ({self.usable_bytes_per_s:,.0f} B/s usable per direction)"
        )
        return (
            f"link budget at {self.sample_rate_hz:g} S/s x {self.channels} channels on {cap}: "
            f"host->board {self.host_to_board_bytes_per_s:,.0f} B/s (SAMPLES of {self.frame_samples} rows), "
            f"board->host {self.board_to_host_bytes_per_s:,.0f} B/s (STATUS every {self.status_period_ms} ms)"
        )


def host_bytes_per_s(
    rate_hz: float, channels: int, frame_samples: int, sync_events_per_s: float = 0.0
) -> float:
    """Host -> board bytes/s of SAMPLES frames of ``frame_samples`` rows (+ SYNC events)."""
    frames = rate_hz / frame_samples
    sync = 0.0
    if sync_events_per_s > 0:
        sync = frames * wire_bytes(_SYNC_HEAD) + sync_events_per_s * _SYNC_EVENT
    return frames * wire_bytes(_SAMPLES_HEAD + 2 * channels * frame_samples) + sync


def board_bytes_per_s(
    rate_hz: float, channels: int, status_period_ms: int, sensor_decimation: int = 1
) -> float:
    """Board -> host bytes/s: STATUS every ``status_period_ms`` and the sensor readback."""
    per_s = 1000.0 / status_period_ms
    return (
        per_s * (wire_bytes(_STATUS_PAYLOAD) + wire_bytes(_SENSOR_HEAD))
        + rate_hz / sensor_decimation * 2 * channels
    )


def plan_link_budget(
    capacity_bytes_per_s: float | None,
    rate_hz: float,
    channels: int,
    *,
    lead_s: float,
    shared: bool = False,
    sensor_decimation: int = 1,
    sync_events_per_s: float = 0.0,
    max_samples_per_frame: int | None = None,
) -> LinkBudget:
    """The status period and frame size that keep the stream within the link (module docstring).

    Raises
    ------
    ConfigError
        The link cannot carry the stream at this rate, with the figures.
    """
    n = max(1, round(rate_hz * DEFAULT_FRAME_S))
    period = DEFAULT_STATUS_PERIOD_MS
    if max_samples_per_frame is not None:
        n = min(n, max_samples_per_frame)
    if capacity_bytes_per_s is not None:
        if not capacity_bytes_per_s > 0:
            raise ConfigError(f"service.link_bytes_per_s: {capacity_bytes_per_s} must be > 0")
        usable = USABLE_FRACTION * capacity_bytes_per_s / (2.0 if shared else 1.0)
        n_max = max(1, math.floor(rate_hz * lead_s / 4))
        if max_samples_per_frame is not None:
            n_max = min(n_max, max_samples_per_frame)
        while n < n_max and host_bytes_per_s(rate_hz, channels, n, sync_events_per_s) > usable:
            n += max(1, n // 8)
        n = min(n, n_max)
        p_max = max(DEFAULT_STATUS_PERIOD_MS, min(1000, math.floor(1000 * lead_s / 3)))
        while period < p_max and board_bytes_per_s(rate_hz, channels, period, sensor_decimation) > usable:
            period += max(1, period // 8)
        period = min(period, p_max)
        host = host_bytes_per_s(rate_hz, channels, n, sync_events_per_s)
        board = board_bytes_per_s(rate_hz, channels, period, sensor_decimation)
        if host > usable or board > usable:
            raise ConfigError(
                f"the link carries {capacity_bytes_per_s:,.0f} B/s{' for both directions' if shared else ''} "
                f"({usable:,.0f} B/s usable per direction); {rate_hz:g} S/s on {channels} channels needs "
                f"host->board {host:,.0f} B/s (frames of {n} rows) and board->host {board:,.0f} B/s "
                f"(STATUS every {period} ms): lower sample_rate_hz or raise the lead (service.lead_ms)"
            )
    return LinkBudget(
        capacity_bytes_per_s,
        shared,
        rate_hz,
        channels,
        n,
        period,
        host_bytes_per_s(rate_hz, channels, n, sync_events_per_s),
        board_bytes_per_s(rate_hz, channels, period, sensor_decimation),
    )


__all__ = ["LinkBudget", "board_bytes_per_s", "host_bytes_per_s", "plan_link_budget", "wire_bytes"]
