"""Request and response models of the control API, and the engine interface behind it.

The API layer (:mod:`piezod.service.api`) only talks to an object implementing
:class:`EngineControl`; the streaming engine implements it for real, tests may use
a fake. Request bodies are validated twice: by pydantic here (types, basic ranges)
and by :meth:`EngineControl.check_scan` / :meth:`EngineControl.check_move` against
the scanner's limits and model (a range the stage cannot reach is refused with the
reason).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, field_validator

EngineState = Literal["starting", "idle", "moving", "scanning", "stopping", "fault", "disconnected"]

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ScanRequest(_Body):
    """Start a raster scan (fast axis x, slow axis y, before rotation)."""

    range_um: float = Field(gt=0, le=10_000, description="fast-axis scan range (um)")
    line_rate_hz: float = Field(gt=0, le=1_000, description="lines per second (trace + retrace)")
    lines: int = Field(default=64, ge=1, le=16_384, description="lines per frame")
    pixels: int = Field(default=256, ge=2, le=16_384, description="pixels per image line (piezod image)")
    slow_range_um: float | None = Field(default=None, ge=0, le=10_000, description="slow-axis range (um)")
    offset_x_um: float = Field(default=0.0, ge=-10_000, le=10_000)
    offset_y_um: float = Field(default=0.0, ge=-10_000, le=10_000)
    rotation_deg: float = Field(default=0.0, ge=-360, le=360)
    overscan: float = Field(default=0.0, ge=0, le=0.5, description="extra travel per side, fraction of range")
    slow_mode: Literal["step", "ramp"] = "step"
    frames: int = Field(default=1, ge=0, description="frames to scan; 0 = until stopped")
    correction: bool = Field(default=True, description="false drives the plain triangle (no model)")
    record: bool = Field(default=True, description="record the sensor readback")
    name: str | None = Field(default=None, description="recording name (letters, digits, . _ -)")

    @field_validator("name")
    @classmethod
    def _safe_name(cls, value: str | None) -> str | None:
        if value is not None and not _NAME.match(value):
            raise ValueError("name may hold letters, digits, '.', '_' and '-' only (max 100)")
        return value


class ScanChange(_Body):
    """Change a running scan; takes effect at the next line."""

    range_um: float | None = Field(default=None, gt=0, le=10_000)
    line_rate_hz: float | None = Field(default=None, gt=0, le=1_000)
    offset_x_um: float | None = Field(default=None, ge=-10_000, le=10_000)
    offset_y_um: float | None = Field(default=None, ge=-10_000, le=10_000)
    rotation_deg: float | None = Field(default=None, ge=-360, le=360)


class MoveRequest(_Body):
    """Move to a position (slew-limited), then hold it."""

    x_um: float | None = None
    y_um: float | None = None
    z_um: float | None = None
    speed_um_per_s: float = Field(default=10.0, gt=0, le=10_000)


class FaultInfo(_Body):
    """One fault, from the board or the host."""

    time_s: float = Field(description="daemon uptime when it happened (s)")
    source: Literal["board", "host", "link"]
    code: str
    message: str
    index: int | None = Field(default=None, description="sample index concerned, if any")


class LineLinearity(_Body):
    """Linearity of the last complete line from the sensor readback (4.14)-(4.16).

    A line that cannot be scored from its readback has ``nonlinearity_pct`` and
    ``length_error_pct`` None and says why in ``skipped`` (readback at the sensor's full scale:
    those readings are the ADC's end code, not positions).
    """

    line: int
    direction: Literal["trace", "retrace"]
    nonlinearity_pct: float | None
    length_error_pct: float | None
    duration_s: float | None = None
    skipped: str | None = None

    def figures(self) -> str:
        """The line's figures for people: ``nonlinearity N %, length error E %``, or why it has none."""
        if self.nonlinearity_pct is None or self.length_error_pct is None:
            return f"not scored ({self.skipped or 'no figures'})"
        return f"nonlinearity {self.nonlinearity_pct:.3f} %, length error {self.length_error_pct:+.3f} %"


class Status(_Body):
    """What the daemon is doing."""

    state: EngineState
    scanner: str
    uptime_s: float
    sample_rate_hz: float
    sample_index: int
    scan: ScanRequest | None = None
    line: int | None = None
    frame: int | None = None
    fifo_level_ms: float = 0.0
    lead_target_ms: float = 0.0
    underruns: int = 0
    crc_errors: int = 0
    frames_dropped: int = 0
    faults: list[FaultInfo] = Field(default_factory=list)
    last_line: LineLinearity | None = None
    sensitivity_scale: dict[str, float] = Field(default_factory=dict)
    position_um: dict[str, float] = Field(default_factory=dict)
    voltage_v: dict[str, float] = Field(default_factory=dict)
    recording: str | None = None
    calibrated: bool = True
    uncalibrated_axes: list[str] = Field(default_factory=list)
    sensor_clipped: dict[str, int] = Field(
        default_factory=dict,
        description="readback samples at the position sensor's full scale per axis, of sensor_clipped_job",
    )
    sensor_clipped_job: str | None = Field(
        default=None, description="the scan, program or move whose readback came last (current or ended)"
    )
    sensor_clipped_total: dict[str, int] = Field(
        default_factory=dict, description="readback samples at the sensor's full scale since the start"
    )


class ScanEvent(_Body):
    """A line or a frame of a scan finished (``GET /v1/events?scans=true``).

    ``line`` events come per finished trace and retrace; a ``frame`` event when a frame's last
    retrace is recorded, and - for the frame that ends the recording - once the daemon has
    written its trace / retrace images (``.gwy`` + PNG, when the scanner has a height channel)
    beside the recording (``images``: file names in the recording directory).
    """

    kind: Literal["line", "frame"]
    recording: str | None = None
    frame: int
    lines: int
    line: int | None = None
    direction: Literal["trace", "retrace"] | None = None
    images: list[str] = Field(default_factory=list)
    image_error: str | None = None


class RecordingInfo(_Body):
    """A recording the daemon wrote."""

    name: str
    size_bytes: int
    modified_unix: float
    complete: bool


class EngineControl(Protocol):
    """What the control API needs from the engine."""

    def status(self) -> Status:
        """A snapshot of the engine's state."""
        ...

    def check_scan(self, request: ScanRequest) -> None:
        """Raise ``SafetyError`` / ``RangeUnreachableError`` if the scan is not possible."""
        ...

    def start_scan(self, request: ScanRequest) -> Status:
        """Refuse the scan as :meth:`check_scan` does, else start it (one check, not two)."""
        ...

    def change_scan(self, change: ScanChange) -> Status:
        """Change the running scan at the next line."""
        ...

    def stop(self) -> Status:
        """Stop scanning / moving and hold, or ramp to the safe value when nothing runs."""
        ...

    def check_move(self, request: MoveRequest) -> None:
        """Raise :class:`~piezod.errors.SafetyError` if the target is outside the limits."""
        ...

    def move(self, request: MoveRequest) -> Status:
        """Move to a position."""
        ...

    def recordings(self) -> list[RecordingInfo]:
        """The recordings in the recording directory."""
        ...

    def recording_path(self, name: str) -> Path:
        """Path of a recording; raises ``FileNotFoundError`` for an unknown name."""
        ...
