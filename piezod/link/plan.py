"""Link settings and the channel plan: which board channel drives which axis, with which scaling.

Pure data and arithmetic (no I/O); :class:`~piezod.link.session.BoardSession` sends the plan
as the CONFIGURE request.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from firmware_proto import (
    DEFAULT_ACK_TIMEOUT_S,
    DEFAULT_MAX_RETRIES,
    HEADER_SIZE,
    Capabilities,
    ChannelConfig,
    Configure,
)
from firmware_proto import ProtocolError as WireProtocolError
from piezod.config import ScannerConfig
from piezod.errors import (
    ConfigError,
    SafetyError,
    from_wire,
)
from piezod.link.budget import LinkBudget, plan_link_budget

DEFAULT_AXIS_CHANNELS: Mapping[str, int] = {"x": 0, "y": 1, "z": 2}
"""Board channel of each axis unless :attr:`LinkSettings.axis_channels` says otherwise."""

_U32 = 1 << 32


# ---------------------------------------------------------------------------------------------
# settings


@dataclass(frozen=True, slots=True)
class LinkSettings:
    """How the host drives the link.

    Attributes
    ----------
    heartbeat_timeout_ms
        The board's watchdog (CONFIGURE); the host sends HEARTBEAT after a quarter of it.
    status_period_ms
        The board sends STATUS at least this often.
    sensor_decimation
        One sensor sample every this many ticks.
    sensor_full_scale_um
        The sensor range: ADC code +-32768 is +-this many um (``adc_um_per_code = fs / 32768``),
        for every axis not in :attr:`sensor_full_scale_um_by_axis`.
    sensor_full_scale_um_by_axis
        Per-axis override of the sensor range (um).
    axis_channels
        Board channel of each axis; board channels without an axis are pinned to their safe code.
    ack_timeout_s, max_retries
        Retransmission of control requests (PROTOCOL.md 5.3).
    read_timeout_s, write_timeout_s
        Transport timeouts.
    reconnect
        Reopen the link after it broke.
    reconnect_initial_s, reconnect_max_s
        Backoff between reopen attempts (doubling).
    reconnect_give_up_s
        Give up (:class:`LinkLost`) after this long; ``None`` = never.
    silence_timeout_s
        A configured board that sent no valid frame for this long is considered gone;
        ``None`` = ``max(1 s, 50 status periods)``.
    frame_samples
        Rows per SAMPLES frame; ``None`` = 5 ms worth (the streamer's default).
    budget
        The link budget the status period and frame size were derived from (``None``: the defaults).
    """

    heartbeat_timeout_ms: int = 500
    status_period_ms: int = 10
    sensor_decimation: int = 1
    sensor_full_scale_um: float = 100.0
    sensor_full_scale_um_by_axis: Mapping[str, float] = field(default_factory=dict)
    axis_channels: Mapping[str, int] = field(default_factory=lambda: dict(DEFAULT_AXIS_CHANNELS))
    ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S
    max_retries: int = DEFAULT_MAX_RETRIES
    read_timeout_s: float = 0.02
    write_timeout_s: float = 2.0
    reconnect: bool = True
    reconnect_initial_s: float = 0.1
    reconnect_max_s: float = 2.0
    reconnect_give_up_s: float | None = None
    silence_timeout_s: float | None = None
    frame_samples: int | None = None
    budget: LinkBudget | None = None

    def full_scale_um(self, axis: str) -> float:
        """The sensor range of ``axis`` (um): ADC code +-32768 reads +-this."""
        return float(self.sensor_full_scale_um_by_axis.get(axis, self.sensor_full_scale_um))

    @classmethod
    def from_config(cls, config: ScannerConfig, **overrides: Any) -> LinkSettings:
        """Settings taken from the scanner config's ``service`` section, then ``overrides``."""
        svc = config.service
        base: dict[str, Any] = {"heartbeat_timeout_ms": int(svc.heartbeat_timeout_ms)}
        if svc.link_bytes_per_s is not None:
            # the board's channels: at least the axes (a SAMPLES row holds every board channel)
            budget = plan_link_budget(
                svc.link_bytes_per_s,
                float(config.sample_rate_hz),
                max(3, len(config.axes)),
                lead_s=svc.lead_ms / 1000.0,
                shared=svc.link_shared,
            )
            base.update(
                status_period_ms=budget.status_period_ms, frame_samples=budget.frame_samples, budget=budget
            )
        by_axis = {
            str(name): float(ax.sensor_full_scale_um)
            for name, ax in config.axes.items()
            if ax.sensor_full_scale_um is not None
        }
        if by_axis:
            base["sensor_full_scale_um_by_axis"] = by_axis
        if config.microscope is not None and "z" in config.axes:
            # the z channel's ADC reads the z-piezo voltage monitor (the height signal), not a sensor
            monitor = float(config.microscope.z_monitor_full_scale)
            base["sensor_full_scale_um_by_axis"] = {**by_axis, "z": monitor}
        base.update(overrides)
        return cls(**base)

    @property
    def heartbeat_interval_s(self) -> float:
        """Longest pause between two frames the host sends (s)."""
        return self.heartbeat_timeout_ms / 4000.0

    @property
    def silence_limit_s(self) -> float:
        """See :attr:`silence_timeout_s`."""
        if self.silence_timeout_s is not None:
            return self.silence_timeout_s
        return max(1.0, 0.05 * self.status_period_ms)


# ---------------------------------------------------------------------------------------------
# CONFIGURE from a scanner config


@dataclass(frozen=True, slots=True)
class ChannelPlan:
    """What each board channel does in a configuration.

    Attributes
    ----------
    configure
        The CONFIGURE message.
    channel_axes
        Axis name of each board channel, ``None`` for a channel pinned to its safe code.
    axis_limits_v
        Per board channel the configured voltage limits (V) as given (before inward rounding
        to codes); pinned channels get their single voltage.
    """

    configure: Configure
    channel_axes: tuple[str | None, ...]
    axis_limits_v: tuple[tuple[float, float], ...]

    @property
    def axes(self) -> tuple[str, ...]:
        """The streamed axes, in board-channel order."""
        return tuple(a for a in self.channel_axes if a is not None)

    @property
    def axis_channel_indices(self) -> tuple[int, ...]:
        """Board channel of each axis in :attr:`axes`."""
        return tuple(i for i, a in enumerate(self.channel_axes) if a is not None)

    @property
    def sample_rate_hz(self) -> int:
        """The configured sample clock (Hz)."""
        return self.configure.sample_rate_hz


_CONFIGURE_FIELDS = {
    0: "sample_rate_hz",
    4: "heartbeat_timeout_ms",
    8: "status_period_ms",
    10: "sensor_decimation",
    12: "n_channels",
}
_CHANNEL_FIELDS = {
    0: "dac_v_per_code",
    4: "dac_offset_v",
    8: "code_min",
    10: "code_max",
    12: "safe_code",
    16: "ramp_v_per_s",
    20: "adc_um_per_code",
    24: "adc_offset_um",
}
_CONFIGURE_HEAD = 16


def describe_configure_offset(offset: int, channel_axes: tuple[str | None, ...] = ()) -> str:
    """Name the CONFIGURE field at frame ``offset`` (NAK / FAULT detail).

    Example: ``channels[1].code_min (axis y)``.
    """
    rel = offset - HEADER_SIZE
    if rel < 0:
        return f"header byte {offset}"
    if rel < _CONFIGURE_HEAD:
        return _CONFIGURE_FIELDS.get(rel, f"byte {offset}")
    ch, within = divmod(rel - _CONFIGURE_HEAD, 32)
    name = _CHANNEL_FIELDS.get(within, f"byte {within}")
    axis = channel_axes[ch] if ch < len(channel_axes) else None
    return f"channels[{ch}].{name}" + (
        f" (axis {axis})" if axis else " (unused channel)" if channel_axes else ""
    )


def plan_channels(
    config: ScannerConfig,
    caps: Capabilities,
    settings: LinkSettings,
    *,
    sample_rate_hz: float | None = None,
) -> ChannelPlan:
    """Build the CONFIGURE message for ``config`` on a board with ``caps``.

    The DAC's full scale (int16) is assumed to span each channel's amplifier range
    (``dac_v_per_code = (v_max - v_min) / 65536``, offset at mid-range); the voltage limits and
    the safe value come from the axis config, the ramp rate from ``config.service``, the sensor
    scaling from ``settings``. Board channels without an axis are pinned to one code (their
    limits and safe value coincide, at the code nearest 0 V inside the amplifier range).

    Raises
    ------
    ConfigError
        An axis maps to a channel the board lacks, the rate is not an integer or the board
        cannot produce it, or the FIFO cannot hold the rate's lead.
    SafetyError
        An axis's voltage limits leave the amplifier range of its channel.
    ProtocolError
        The codec refused a field (e.g. no DAC code inside an axis's limits).
    """
    try:
        return _plan_channels(config, caps, settings, sample_rate_hz=sample_rate_hz)
    except WireProtocolError as exc:
        raise from_wire(exc) from exc


def _plan_channels(
    config: ScannerConfig,
    caps: Capabilities,
    settings: LinkSettings,
    *,
    sample_rate_hz: float | None,
) -> ChannelPlan:
    rate_f = float(sample_rate_hz if sample_rate_hz is not None else config.sample_rate_hz)
    if not rate_f.is_integer() or rate_f < 1:
        raise ConfigError(
            f"sample_rate_hz: {rate_f} is not a whole number of Hz (the board clock is integer)"
        )
    rate = int(rate_f)
    if not caps.sample_rate_min_hz <= rate <= caps.sample_rate_max_hz:
        raise ConfigError(
            f"sample_rate_hz: {rate} Hz outside the board's range "
            f"[{caps.sample_rate_min_hz}, {caps.sample_rate_max_hz}] Hz"
        )
    if caps.sample_clock_hz and caps.sample_clock_hz % rate:
        raise ConfigError(
            f"sample_rate_hz: {rate} Hz does not divide the board clock {caps.sample_clock_hz} Hz"
        )
    channel_axes: list[str | None] = [None] * caps.n_channels
    for axis_name in config.axes:
        axis = str(axis_name)
        ch = settings.axis_channels.get(axis)
        if ch is None or not 0 <= ch < caps.n_channels:
            raise ConfigError(
                f"axes.{axis}: no board channel for this axis (board has {caps.n_channels} channels, "
                f"axis_channels maps it to {ch})"
            )
        if channel_axes[ch] is not None:
            raise ConfigError(f"axes.{axis}: board channel {ch} already drives axis {channel_axes[ch]}")
        channel_axes[ch] = axis
    ramp = float(config.service.ramp_rate_v_per_s)
    channels: list[ChannelConfig] = []
    limits: list[tuple[float, float]] = []
    for i, ch_axis in enumerate(channel_axes):
        amp_lo, amp_hi = caps.amplifier_ranges_v[i]
        scale = float(np.float32((amp_hi - amp_lo) / 65536.0))
        offset = float(np.float32((amp_hi + amp_lo) / 2.0))
        # the int16 code range: the top code is one step below the amplifier's maximum
        code_lo_v, code_hi_v = offset - 32768 * scale, offset + 32767 * scale
        if ch_axis is None:
            full = ChannelConfig.from_volts(
                v_min=max(amp_lo, code_lo_v),
                v_max=min(amp_hi, code_hi_v),
                safe_v=min(max(0.0, amp_lo), amp_hi),
                dac_v_per_code=scale,
                dac_offset_v=offset,
                ramp_v_per_s=ramp,
                adc_um_per_code=settings.sensor_full_scale_um / 32768.0,
                adc_offset_um=0.0,
            )
            c = full.safe_code
            channels.append(
                ChannelConfig(
                    full.dac_v_per_code,
                    full.dac_offset_v,
                    c,
                    c,
                    c,
                    full.ramp_v_per_s,
                    full.adc_um_per_code,
                    full.adc_offset_um,
                )
            )
            limits.append((full.safe_v, full.safe_v))
            continue
        ax = config.axes[ch_axis]  # type: ignore[index]  # the name came from config.axes
        if ax.voltage_min_v < amp_lo or ax.voltage_max_v > amp_hi:
            raise SafetyError(
                f"axes.{ch_axis}: voltage limits [{ax.voltage_min_v}, {ax.voltage_max_v}] V leave the "
                f"amplifier range [{amp_lo}, {amp_hi}] V of board channel {i}"
            )
        fs = settings.full_scale_um(ch_axis)
        channels.append(
            ChannelConfig.from_volts(
                v_min=max(ax.voltage_min_v, code_lo_v),
                v_max=min(ax.voltage_max_v, code_hi_v),
                safe_v=ax.safe_voltage_v,
                dac_v_per_code=scale,
                dac_offset_v=offset,
                ramp_v_per_s=ramp,
                adc_um_per_code=fs / 32768.0,
                adc_offset_um=0.0,
            )
        )
        limits.append((ax.voltage_min_v, ax.voltage_max_v))
    cfg = Configure(
        sample_rate_hz=rate,
        heartbeat_timeout_ms=settings.heartbeat_timeout_ms,
        status_period_ms=settings.status_period_ms,
        sensor_decimation=settings.sensor_decimation,
        channels=tuple(channels),
    )
    problem = cfg.check(caps)
    if problem is not None:
        reason, detail = problem
        raise ConfigError(
            f"the board would refuse this configuration: {reason.name} at "
            f"{describe_configure_offset(detail, tuple(channel_axes))}"
        )
    return ChannelPlan(cfg, tuple(channel_axes), tuple(limits))
