"""Link budget: bytes per second on the wire for a streaming configuration (worst-case COBS)."""

from __future__ import annotations

from dataclasses import dataclass

from .codec import max_encoded_size
from .messages import MessageType, Status, block_overhead

_STATUS_FRAME = 8 + Status._S.size + 4


def wire_bytes_per_block(n_channels: int, n_samples: int, msg_type: MessageType = MessageType.SAMPLES) -> int:
    """Worst-case wire bytes (COBS + delimiter) of one SAMPLES / SENSOR frame."""
    return max_encoded_size(block_overhead(msg_type) + 2 * n_channels * n_samples) + 1


@dataclass(frozen=True, slots=True)
class LinkBudget:
    """Wire load of one streaming configuration.

    Attributes
    ----------
    payload_bytes_per_s
        Raw sample bytes per second per direction (codes only).
    host_to_board_bytes_per_s
        SAMPLES frames, worst-case framing.
    board_to_host_bytes_per_s
        SENSOR + STATUS frames, worst-case framing.
    """

    n_channels: int
    rate_hz: float
    samples_per_frame: int
    sensor_decimation: int
    status_period_ms: float
    payload_bytes_per_s: float
    host_to_board_bytes_per_s: float
    board_to_host_bytes_per_s: float

    @property
    def overhead_pct(self) -> float:
        """Host -> board framing overhead relative to the raw codes (%)."""
        return 100.0 * (self.host_to_board_bytes_per_s / self.payload_bytes_per_s - 1.0)


def link_budget(
    n_channels: int,
    rate_hz: float,
    samples_per_frame: int,
    *,
    sensor_decimation: int = 1,
    status_period_ms: float = 10.0,
) -> LinkBudget:
    """Bytes per second in each direction for streaming ``n_channels`` at ``rate_hz``.

    SENSOR frames are assumed to carry ``samples_per_frame`` rows each, STATUS to be sent every
    ``status_period_ms``; COBS overhead is its worst case (no zero byte in the frame).
    """
    frames_per_s = rate_hz / samples_per_frame
    down = frames_per_s * wire_bytes_per_block(n_channels, samples_per_frame, MessageType.SAMPLES)
    sensor_rate = rate_hz / sensor_decimation
    up_sensor = (
        sensor_rate
        / samples_per_frame
        * wire_bytes_per_block(n_channels, samples_per_frame, MessageType.SENSOR)
    )
    up_status = 1000.0 / status_period_ms * (max_encoded_size(_STATUS_FRAME) + 1)
    return LinkBudget(
        n_channels=n_channels,
        rate_hz=rate_hz,
        samples_per_frame=samples_per_frame,
        sensor_decimation=sensor_decimation,
        status_period_ms=status_period_ms,
        payload_bytes_per_s=2.0 * n_channels * rate_hz,
        host_to_board_bytes_per_s=down,
        board_to_host_bytes_per_s=up_sensor + up_status,
    )


UART_12MBAUD_BYTES_PER_S = 12_000_000 / 10
"""A 12 Mbaud 8N1 UART (e.g. behind an FT232H), per direction (full duplex)."""
USB_FS_BULK_BYTES_PER_S = 19 * 64 * 1000
"""USB 1.1 full-speed bulk ceiling: 19 x 64-byte packets per 1 ms frame, shared by both directions."""


def render_budget_table() -> str:
    """The Markdown table of PROTOCOL.md's link budget section (3 channels x 100 kS/s)."""
    rows = [
        "| samples/frame | frames/s | SAMPLES frame (wire B) | host->board (B/s) | overhead | "
        "board->host, decimation 1 (B/s) | board->host, decimation 4 (B/s) |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for spf in (100, 250, 500, 1000):
        b1 = link_budget(3, 100_000, spf)
        b4 = link_budget(3, 100_000, spf, sensor_decimation=4)
        rows.append(
            f"| {spf} | {100_000 / spf:.0f} | {wire_bytes_per_block(3, spf)} | "
            f"{b1.host_to_board_bytes_per_s:,.0f} | {b1.overhead_pct:.2f} % | "
            f"{b1.board_to_host_bytes_per_s:,.0f} | {b4.board_to_host_bytes_per_s:,.0f} |"
        )
    b = link_budget(3, 100_000, 500)
    both = b.host_to_board_bytes_per_s + b.board_to_host_bytes_per_s
    b4 = link_budget(3, 100_000, 500, sensor_decimation=4)
    both4 = b4.host_to_board_bytes_per_s + b4.board_to_host_bytes_per_s
    rows += [
        "",
        f"At 500 samples/frame: host->board {b.host_to_board_bytes_per_s:,.0f} B/s = "
        f"{b.host_to_board_bytes_per_s * 10 / 1e6:.2f} Mbaud at 8N1, "
        f"{100 * b.host_to_board_bytes_per_s / UART_12MBAUD_BYTES_PER_S:.0f} % of a 12 Mbaud UART "
        f"(full duplex, each direction alone); both directions together {both:,.0f} B/s = "
        f"{100 * both / USB_FS_BULK_BYTES_PER_S:.0f} % of the USB full-speed bulk ceiling "
        f"({USB_FS_BULK_BYTES_PER_S:,} B/s, shared by both directions); with sensor decimation 4: "
        f"{both4:,.0f} B/s = {100 * both4 / USB_FS_BULK_BYTES_PER_S:.0f} %.",
    ]
    return "\n".join(rows)
