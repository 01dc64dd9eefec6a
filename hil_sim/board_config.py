"""What the simulated board is (:class:`BoardConfig`: what CAPABILITIES advertises, the fault
injection) and the faults a test injects while it runs (:class:`FaultHooks`); what it does is
:mod:`hil_sim.board`, which re-exports both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from firmware_proto import PROTOCOL_VERSION, MessageType, NakReason
from hil_sim.errors import SimConfigError as ConfigError
from hil_sim.microscope import MicroscopeConfig

_U32 = 0xFFFFFFFF


@dataclass(frozen=True, slots=True)
class BoardConfig:
    """Properties of the simulated board (what CAPABILITIES advertises) and fault injection.

    Attributes
    ----------
    amplifier_ranges_v
        Per channel ``(v_min, v_max)`` of the HV amplifier (V); ``None``: +-250 V on every channel.
        :meth:`Board.from_scanner_file` uses the scanner's voltage limits.
    fifo_depth_samples
        FIFO capacity, samples per channel.
    max_samples_per_frame
        Most rows per SAMPLES / SENSOR frame; ``None``: the most that fit a frame.
    sample_rate_min_hz, sample_rate_max_hz
        Range of the sample clock (Hz).
    sample_clock_hz
        Base clock (exact rates are ``sample_clock_hz / k``); 0: every integer rate.
    dac_bits, adc_bits
        Converter resolution (1..16).
    firmware_version
        ``(major, minor, patch)`` reported in CAPABILITIES.
    board_serial
        Serial number reported in CAPABILITIES.
    amp_slew_v_per_s
        Slew-rate limit of the HV amplifier output (V/s).
    ramp_update_s
        Update interval of ramps to the safe value (s), <= 1 ms per the spec.
    idle_block_s
        Outside RUNNING the stage is stepped at least this often (s of simulated time).
    corrupt_rate
        Probability per outgoing byte of one flipped bit.
    corrupt_in_rate
        Probability per incoming byte of one flipped bit (before decoding).
    drop_rate
        Probability per outgoing frame of being dropped entirely.
    seed
        Seed of the fault-injection generator.
    microscope
        The simulated microscope (:mod:`hil_sim.microscope`), or None (a bare stage). With it the
        z channel's ADC reads the z-piezo voltage through the amplifier's monitor
        (``V_z / monitor_ratio``) while the z feedback drives the z piezo, and without its
        position sensor the x / y ADC channels read 0 and CAPABILITIES says so
        (``position_sensor`` false, protocol revision 2).
    truth_log
        With a microscope: append the hidden truth to this file, every ``truth_every``-th played sample, as
        float64 rows ``(sample_index, x_um, y_um, z_voltage_v, z_um)`` (raw, native byte order):
        the true tip position an external interferometer would measure, for checking sensorless
        calibrations (``piezod.imagecal.read_truth_log``).
    truth_every
        Log every ``truth_every``-th played sample (default 10; 1 for a z calibration that needs the
        extension at the sample rate, as a z sensor would give it).
    sync_outputs
        Digital sync outputs driven from SYNC frames (0..8; CAPABILITIES ``sync_outputs``).
    protocol_version
        The protocol version this board speaks (another one: a board the host must refuse).
    caps_protocol_version
        The version CAPABILITIES reports (None: ``protocol_version``).
    adc_loopback
        The ADC reads the DAC code it is given (ADC code = quantised DAC code, the ADC scale
        ignored): a bench with each DAC output wired to its ADC input and no stage, for link
        tests (the stage is not simulated while it is set).
    record_played
        Keep every played row of codes (:attr:`Board.played`), for tests.
    """

    amplifier_ranges_v: tuple[tuple[float, float], ...] | None = None
    fifo_depth_samples: int = 65536
    max_samples_per_frame: int | None = None
    sample_rate_min_hz: int = 1
    sample_rate_max_hz: int = 200_000
    sample_clock_hz: int = 0
    dac_bits: int = 16
    adc_bits: int = 16
    firmware_version: tuple[int, int, int] = (1, 0, 0)
    board_serial: int = 0x51A0_0001
    amp_slew_v_per_s: float = 1.0e6
    ramp_update_s: float = 1.0e-3
    idle_block_s: float = 0.1
    corrupt_rate: float = 0.0
    corrupt_in_rate: float = 0.0
    drop_rate: float = 0.0
    seed: int = 0
    microscope: MicroscopeConfig | None = None
    truth_log: str | None = None
    truth_every: int = 10
    sync_outputs: int = 3
    protocol_version: int = PROTOCOL_VERSION
    caps_protocol_version: int | None = None
    adc_loopback: bool = False
    record_played: bool = False

    def __post_init__(self) -> None:
        if not 1 <= self.truth_every <= 1 << 20:
            raise ConfigError(f"board: truth_every must lie in [1, 2**20], got {self.truth_every!r}")
        for name in ("corrupt_rate", "corrupt_in_rate", "drop_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"board: {name} must lie in [0, 1], got {value!r}")
        if not 1 <= self.fifo_depth_samples <= _U32:
            raise ConfigError(f"board: fifo_depth_samples {self.fifo_depth_samples} outside [1, 2**32-1]")
        if not (math.isfinite(self.amp_slew_v_per_s) and self.amp_slew_v_per_s > 0):
            raise ConfigError(f"board: amp_slew_v_per_s must be > 0, got {self.amp_slew_v_per_s!r}")
        if not 0.0 < self.ramp_update_s <= 1e-3:
            raise ConfigError(f"board: ramp_update_s must lie in (0, 1e-3] s, got {self.ramp_update_s!r}")
        if not self.idle_block_s > 0.0:
            raise ConfigError(f"board: idle_block_s must be > 0, got {self.idle_block_s!r}")
        if self.seed < 0:
            raise ConfigError(f"board: seed must be >= 0, got {self.seed}")


@dataclass(slots=True)
class FaultHooks:
    """Faults injected at run time (mutable: a test changes them while the board runs).

    Attributes
    ----------
    drop_replies
        Per request type, how many of the next replies are lost on the way to the host (the reply
        stays in the board's duplicate cache: a retransmission is answered from there).
    force_nak
        Per request type, ``(reason, detail)`` of the NAK every such request gets instead of
        being applied (a refused CONFIGURE also latches ``CONFIG_REJECTED``).
    drop_sensor_from
        SENSOR frames whose first row is at this sample index or later are lost on the way to the
        host (their sequence numbers are used: the host can tell frames were lost). ``None``: none.
    """

    drop_replies: dict[MessageType, int] = field(default_factory=dict)
    force_nak: dict[MessageType, tuple[NakReason, int]] = field(default_factory=dict)
    drop_sensor_from: int | None = None


__all__ = ["BoardConfig", "FaultHooks"]
