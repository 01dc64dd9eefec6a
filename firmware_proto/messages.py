"""Message types of the piezod board protocol: frozen dataclasses and their payload layouts.

Every message knows how to pack its payload (the bytes after the 8-byte header) and how to
unpack it again. Framing (header, CRC, COBS) lives in :mod:`firmware_proto.codec`. The byte
layouts are specified in ``PROTOCOL.md``; the ``struct`` formats below are that table.

Construction validates ranges and raises :class:`~firmware_proto.errors.ProtocolError` (a
``ValueError``) naming the field at fault. Float fields travel as IEEE-754 float32; the
constructors round them to the nearest float32 so that an object equals what the peer decodes.
Semantic checks that depend on the board (limits inside the amplifier range, rate supported...)
are in :meth:`Configure.check`.

Over 800 lines because it is the protocol's message table: one small class per message type of
PROTOCOL.md section 4, each with its payload layout, validation and pack/unpack side by side,
like the table it implements; a split by message would only scatter that table.
"""

from __future__ import annotations

import math
import operator
import struct
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from .errors import ProtocolError, VersionMismatchError

PROTOCOL_VERSION = 1
"""The protocol version this codec speaks (header byte 0, HELLO and CAPABILITIES payloads)."""

HEADER_SIZE = 8
"""Bytes of the fixed frame header (version, type, flags, reserved, sequence number)."""
CRC_SIZE = 4
"""Bytes of the CRC-32/ISO-HDLC trailer."""
MAX_FRAME_SIZE = 8192
"""Largest frame before COBS stuffing: header + payload + CRC, without the 0x00 delimiter."""
MAX_PAYLOAD_SIZE = MAX_FRAME_SIZE - HEADER_SIZE - CRC_SIZE
MAX_CHANNELS = 8
"""Most output (DAC) / sensor (ADC) channels a board may have."""
NO_INDEX = 2**64 - 1
"""Sample-index sentinel: "none" (no sample played yet) or "immediately" (STOP)."""
NO_CHANNEL = 0xFF
"""Channel sentinel in FAULT: the fault concerns no particular channel."""

_F32_MAX = 3.4028234663852886e38
_U8, _U16, _U32, _U64 = 8, 16, 32, 64

CodeArray = npt.NDArray[np.int16]
"""Sample codes, shape ``(n_samples, n_channels)``, little-endian int16."""
_WIRE_I16 = np.dtype("<i2")


class MessageType(IntEnum):
    """Header byte 1. Types 0x01-0x08 are control messages (ACK_REQ set, retransmitted)."""

    HELLO = 0x01
    CAPABILITIES = 0x02
    CONFIGURE = 0x03
    ACK = 0x04
    NAK = 0x05
    START = 0x06
    STOP = 0x07
    RAMP_TO_SAFE = 0x08
    HEARTBEAT = 0x09
    SAMPLES = 0x10
    STATUS = 0x11
    SENSOR = 0x12
    FAULT = 0x13
    SYNC = 0x14


CONTROL_TYPES = frozenset(
    {MessageType.HELLO, MessageType.CONFIGURE, MessageType.START, MessageType.STOP, MessageType.RAMP_TO_SAFE}
)
"""Requests sent with ACK_REQ: answered by ACK / NAK (HELLO: by CAPABILITIES or NAK)."""

FROZEN_TYPES = frozenset({MessageType.HELLO, MessageType.NAK})
"""Types whose payload layout is identical in every protocol version (decoded whatever the version)."""


class Flags(IntFlag):
    """Header byte 2. Bits not defined here are reserved: sent as 0, ignored on receipt."""

    NONE = 0
    ACK_REQ = 0x01


class NakReason(IntEnum):
    """Why a control request was refused (NAK ``reason``)."""

    VERSION_MISMATCH = 1
    UNKNOWN_TYPE = 2
    BAD_LENGTH = 3
    BAD_VALUE = 4
    BAD_STATE = 5
    UNSUPPORTED = 6


class FaultCode(IntEnum):
    """What a FAULT reports; bit ``code - 1`` of :class:`FaultFlags` latches it."""

    UNDERRUN = 1
    LIMIT_VIOLATION = 2
    CRC_ERRORS = 3
    WATCHDOG = 4
    CONFIG_REJECTED = 5
    OVERFLOW = 6
    INDEX_GAP = 7
    HARDWARE = 8


class FaultFlags(IntFlag):
    """Latched faults in STATUS (bit ``code - 1`` for each :class:`FaultCode`)."""

    NONE = 0
    UNDERRUN = 1 << (FaultCode.UNDERRUN - 1)
    LIMIT_VIOLATION = 1 << (FaultCode.LIMIT_VIOLATION - 1)
    CRC_ERRORS = 1 << (FaultCode.CRC_ERRORS - 1)
    WATCHDOG = 1 << (FaultCode.WATCHDOG - 1)
    CONFIG_REJECTED = 1 << (FaultCode.CONFIG_REJECTED - 1)
    OVERFLOW = 1 << (FaultCode.OVERFLOW - 1)
    INDEX_GAP = 1 << (FaultCode.INDEX_GAP - 1)
    HARDWARE = 1 << (FaultCode.HARDWARE - 1)

    @classmethod
    def of(cls, code: FaultCode) -> FaultFlags:
        """The flag bit latched by fault ``code``."""
        return cls(1 << (int(code) - 1))


class BoardState(IntEnum):
    """The board's output state machine (STATUS ``state``)."""

    UNCONFIGURED = 0
    IDLE = 1
    ARMED = 2
    RUNNING = 3
    RAMPING = 4


# ---------------------------------------------------------------------------------------------
# field validation


def _uint(owner: str, name: str, value: object, bits: int) -> int:
    try:
        v = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ProtocolError(f"{owner}.{name}: expected an integer, got {value!r}") from None
    if not 0 <= v < (1 << bits):
        raise ProtocolError(f"{owner}.{name}: {v} outside [0, 2**{bits}-1]")
    return int(v)


def _int(owner: str, name: str, value: object, bits: int) -> int:
    try:
        v = operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise ProtocolError(f"{owner}.{name}: expected an integer, got {value!r}") from None
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    if not lo <= v <= hi:
        raise ProtocolError(f"{owner}.{name}: {v} outside [{lo}, {hi}]")
    return int(v)


def _f32(owner: str, name: str, value: object) -> float:
    if not isinstance(value, int | float | np.floating | np.integer) or isinstance(value, bool):
        raise ProtocolError(f"{owner}.{name}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or abs(v) > _F32_MAX:
        raise ProtocolError(f"{owner}.{name}: {v} is not a finite float32")
    rounded: float = struct.unpack("<f", struct.pack("<f", v))[0]
    return rounded


def _enum(owner: str, name: str, value: object, enum: type[IntEnum]) -> Any:
    try:
        return enum(operator.index(value))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ProtocolError(f"{owner}.{name}: {value!r} is not a valid {enum.__name__}") from None


def _codes(owner: str, value: object) -> CodeArray:
    arr = np.asarray(value)
    if arr.ndim != 2:
        raise ProtocolError(f"{owner}.codes: expected a 2-D array (n_samples, n_channels), got {arr.ndim}-D")
    n, c = arr.shape
    if not 1 <= c <= MAX_CHANNELS:
        raise ProtocolError(f"{owner}.codes: {c} channels outside [1, {MAX_CHANNELS}]")
    if n < 1:
        raise ProtocolError(f"{owner}.codes: no samples")
    if arr.dtype != np.int16:
        if arr.dtype.kind not in "iu":
            raise ProtocolError(f"{owner}.codes: expected integer codes, got dtype {arr.dtype}")
        if arr.size and (arr.min() < -32768 or arr.max() > 32767):
            raise ProtocolError(f"{owner}.codes: codes outside the int16 range [-32768, 32767]")
    view: CodeArray = np.ascontiguousarray(arr, dtype=_WIRE_I16).view()
    view.flags.writeable = False
    return view


# ---------------------------------------------------------------------------------------------
# messages


class Message:
    """Base of all messages. Subclasses are frozen dataclasses with a ``TYPE``."""

    __slots__ = ()
    TYPE: ClassVar[MessageType]

    def pack_payload(self) -> bytes:
        """The payload bytes (after the header, before the CRC)."""
        raise NotImplementedError

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Message:
        """Decode a payload of this type.

        Raises
        ------
        ProtocolError
            The length or a field value is invalid.
        """
        raise NotImplementedError

    @classmethod
    def _expect_len(cls, payload: bytes, size: int) -> None:
        if len(payload) != size:
            raise _LengthError(f"{cls.TYPE.name}: payload is {len(payload)} bytes, expected {size}")


class _LengthError(ProtocolError):
    """Payload length does not match its type (reported as ErrorKind.BAD_LENGTH)."""


@dataclass(frozen=True, slots=True)
class Hello(Message):
    """HELLO (host -> board, control): opens a session.

    Attributes
    ----------
    protocol_version
        The protocol version the host speaks.
    session_id
        Arbitrary per-session number chosen by the host (e.g. its process id); a board that sees
        a new value knows the host restarted.
    """

    TYPE: ClassVar[MessageType] = MessageType.HELLO
    _S: ClassVar[struct.Struct] = struct.Struct("<HHI")

    protocol_version: int = PROTOCOL_VERSION
    session_id: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "protocol_version", _uint("Hello", "protocol_version", self.protocol_version, _U16)
        )
        object.__setattr__(self, "session_id", _uint("Hello", "session_id", self.session_id, _U32))

    def pack_payload(self) -> bytes:
        return self._S.pack(self.protocol_version, 0, self.session_id)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Hello:
        cls._expect_len(payload, cls._S.size)
        version, _, session = cls._S.unpack(payload)
        return cls(version, session)


@dataclass(frozen=True, slots=True)
class Capabilities(Message):
    """CAPABILITIES (board -> host): the reply to HELLO.

    Attributes
    ----------
    reply_to_seq
        Sequence number of the HELLO answered.
    protocol_version
        The protocol version the board speaks.
    firmware_version
        ``(major, minor, patch)``.
    dac_bits, adc_bits
        Converter resolution (1..16); codes on the wire are always 16-bit, left-justified.
    max_samples_per_frame
        Most samples per channel the board accepts in one SAMPLES frame (and sends per SENSOR).
    sample_rate_min_hz, sample_rate_max_hz
        Range of the sample clock (Hz).
    sample_clock_hz
        Base clock (Hz): exact rates are ``sample_clock_hz / k`` for integer ``k``; 0 = every integer
        rate in the range.
    fifo_depth_samples
        FIFO capacity in samples per channel.
    board_serial
        Serial number of the board.
    amplifier_ranges_v
        Per channel ``(v_min, v_max)``: the output range of the HV amplifier (V). Its length is the
        number of channels.
    sync_outputs
        Number of digital sync outputs the board drives from SYNC frames (0..8; revision 1 of the
        protocol, PROTOCOL.md 4.14). 0: none (a revision-0 board sends 0 here, a reserved byte).
    position_sensor
        False: the board's ADC channels carry no position sensor (revision 2, PROTOCOL.md 4.2:
        bit 7 of the ``sync_outputs`` byte). They may carry other signals (e.g. a z-voltage
        monitor); the host must not read them as positions. Boards of revisions 0 and 1 send the
        bit clear: a position sensor.
    """

    TYPE: ClassVar[MessageType] = MessageType.CAPABILITIES
    _S: ClassVar[struct.Struct] = struct.Struct("<IHBBHBBBBHIIIII")
    _CH: ClassVar[struct.Struct] = struct.Struct("<ff")

    reply_to_seq: int
    protocol_version: int
    firmware_version: tuple[int, int, int]
    dac_bits: int
    adc_bits: int
    max_samples_per_frame: int
    sample_rate_min_hz: int
    sample_rate_max_hz: int
    sample_clock_hz: int
    fifo_depth_samples: int
    board_serial: int
    amplifier_ranges_v: tuple[tuple[float, float], ...]
    sync_outputs: int = 0
    position_sensor: bool = True

    def __post_init__(self) -> None:
        o = "Capabilities"
        set_ = object.__setattr__
        if not isinstance(self.position_sensor, bool):
            raise ProtocolError(f"{o}.position_sensor: expected a bool, got {self.position_sensor!r}")
        set_(self, "sync_outputs", _uint(o, "sync_outputs", self.sync_outputs, _U8))
        if self.sync_outputs > MAX_SYNC_OUTPUTS:
            raise ProtocolError(f"{o}.sync_outputs: {self.sync_outputs} outside [0, {MAX_SYNC_OUTPUTS}]")
        set_(self, "reply_to_seq", _uint(o, "reply_to_seq", self.reply_to_seq, _U32))
        set_(self, "protocol_version", _uint(o, "protocol_version", self.protocol_version, _U16))
        fw = tuple(self.firmware_version)
        if len(fw) != 3:
            raise ProtocolError(f"{o}.firmware_version: expected (major, minor, patch), got {fw!r}")
        set_(
            self,
            "firmware_version",
            (
                _uint(o, "firmware_version[0]", fw[0], _U8),
                _uint(o, "firmware_version[1]", fw[1], _U8),
                _uint(o, "firmware_version[2]", fw[2], _U16),
            ),
        )
        for name in ("dac_bits", "adc_bits"):
            bits = _uint(o, name, getattr(self, name), _U8)
            if not 1 <= bits <= 16:
                raise ProtocolError(f"{o}.{name}: {bits} outside [1, 16]")
            set_(self, name, bits)
        for name in ("sample_rate_min_hz", "sample_rate_max_hz", "sample_clock_hz", "fifo_depth_samples"):
            set_(self, name, _uint(o, name, getattr(self, name), _U32))
        set_(self, "board_serial", _uint(o, "board_serial", self.board_serial, _U32))
        ranges = tuple(tuple(r) for r in self.amplifier_ranges_v)
        if not 1 <= len(ranges) <= MAX_CHANNELS:
            raise ProtocolError(f"{o}.amplifier_ranges_v: {len(ranges)} channels outside [1, {MAX_CHANNELS}]")
        checked: list[tuple[float, float]] = []
        for i, r in enumerate(ranges):
            if len(r) != 2:
                raise ProtocolError(f"{o}.amplifier_ranges_v[{i}]: expected (v_min, v_max), got {r!r}")
            lo = _f32(o, f"amplifier_ranges_v[{i}][0]", r[0])
            hi = _f32(o, f"amplifier_ranges_v[{i}][1]", r[1])
            if not lo < hi:
                raise ProtocolError(f"{o}.amplifier_ranges_v[{i}]: v_min {lo} not below v_max {hi}")
            checked.append((lo, hi))
        set_(self, "amplifier_ranges_v", tuple(checked))
        mspf = _uint(o, "max_samples_per_frame", self.max_samples_per_frame, _U16)
        limit = max_samples_per_frame(len(checked), MessageType.SAMPLES)
        if not 1 <= mspf <= limit:
            raise ProtocolError(
                f"{o}.max_samples_per_frame: {mspf} outside [1, {limit}] for {len(checked)} channels"
            )
        set_(self, "max_samples_per_frame", mspf)
        if self.sample_rate_min_hz < 1:
            raise ProtocolError(f"{o}.sample_rate_min_hz: must be >= 1")
        if self.sample_rate_min_hz > self.sample_rate_max_hz:
            raise ProtocolError(
                f"{o}.sample_rate_min_hz: {self.sample_rate_min_hz} above sample_rate_max_hz "
                f"{self.sample_rate_max_hz}"
            )

    @property
    def n_channels(self) -> int:
        """Number of output / sensor channels."""
        return len(self.amplifier_ranges_v)

    def pack_payload(self) -> bytes:
        head = self._S.pack(
            self.reply_to_seq,
            self.protocol_version,
            self.firmware_version[0],
            self.firmware_version[1],
            self.firmware_version[2],
            self.n_channels,
            self.dac_bits,
            self.adc_bits,
            self.sync_outputs | (0 if self.position_sensor else NO_POSITION_SENSOR_BIT),
            self.max_samples_per_frame,
            self.sample_rate_min_hz,
            self.sample_rate_max_hz,
            self.sample_clock_hz,
            self.fifo_depth_samples,
            self.board_serial,
        )
        return head + b"".join(self._CH.pack(lo, hi) for lo, hi in self.amplifier_ranges_v)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Capabilities:
        if len(payload) < cls._S.size:
            raise _LengthError(f"CAPABILITIES: payload is {len(payload)} bytes, expected >= {cls._S.size}")
        (
            seq,
            ver,
            fw_major,
            fw_minor,
            fw_patch,
            n_ch,
            dac_bits,
            adc_bits,
            sync_byte,
            mspf,
            rmin,
            rmax,
            clk,
            fifo,
            serial,
        ) = cls._S.unpack_from(payload)
        cls._expect_len(payload, cls._S.size + cls._CH.size * n_ch)
        ranges = tuple(cls._CH.unpack_from(payload, cls._S.size + cls._CH.size * i) for i in range(n_ch))
        return cls(
            seq,
            ver,
            (fw_major, fw_minor, fw_patch),
            dac_bits,
            adc_bits,
            mspf,
            rmin,
            rmax,
            clk,
            fifo,
            serial,
            ranges,
            sync_byte & SYNC_OUTPUTS_MASK,
            not sync_byte & NO_POSITION_SENSOR_BIT,
        )


@dataclass(frozen=True, slots=True)
class ChannelConfig:
    """Per-channel part of CONFIGURE (32 bytes on the wire).

    The output voltage of DAC code ``c`` is ``dac_offset_v + dac_v_per_code * c``; the sensor
    position of ADC code ``a`` is ``adc_offset_um + adc_um_per_code * a``. The limits and the safe
    value are DAC codes, so the board compares integers on its sample path; use
    :meth:`from_volts` to derive them from volts (rounded inwards).

    Attributes
    ----------
    dac_v_per_code
        Output volts per DAC code (V), > 0.
    dac_offset_v
        Output volts at DAC code 0 (V).
    code_min, code_max
        Lowest / highest DAC code ever applied (int16): the voltage limits.
    safe_code
        DAC code ramped to on RAMP_TO_SAFE, watchdog and CONFIGURE (int16).
    ramp_v_per_s
        Slew rate of ramps to the safe value (V/s), > 0.
    adc_um_per_code
        Sensor micrometres per ADC code (um), non-zero.
    adc_offset_um
        Sensor position at ADC code 0 (um).
    """

    _S: ClassVar[struct.Struct] = struct.Struct("<ffhhhHfffI")

    dac_v_per_code: float
    dac_offset_v: float
    code_min: int
    code_max: int
    safe_code: int
    ramp_v_per_s: float
    adc_um_per_code: float
    adc_offset_um: float

    def __post_init__(self) -> None:
        o = "ChannelConfig"
        for name in ("dac_v_per_code", "dac_offset_v", "ramp_v_per_s", "adc_um_per_code", "adc_offset_um"):
            object.__setattr__(self, name, _f32(o, name, getattr(self, name)))
        for name in ("code_min", "code_max", "safe_code"):
            object.__setattr__(self, name, _int(o, name, getattr(self, name), 16))

    @classmethod
    def from_volts(
        cls,
        *,
        v_min: float,
        v_max: float,
        safe_v: float,
        dac_v_per_code: float,
        dac_offset_v: float,
        ramp_v_per_s: float,
        adc_um_per_code: float,
        adc_offset_um: float,
    ) -> ChannelConfig:
        """Build a channel config from voltage limits (V) and scalings.

        ``code_min`` / ``code_max`` are rounded inwards (never outside ``[v_min, v_max]``), the safe
        code to the nearest code inside them.

        Raises
        ------
        ProtocolError
            A limit maps outside the int16 code range or the limits contain no code.
        """
        scale = _f32("ChannelConfig", "dac_v_per_code", dac_v_per_code)
        offset = _f32("ChannelConfig", "dac_offset_v", dac_offset_v)
        if scale <= 0:
            raise ProtocolError(f"ChannelConfig.dac_v_per_code: {scale} must be > 0")
        lo = math.ceil((v_min - offset) / scale)
        hi = math.floor((v_max - offset) / scale)
        # float rounding of the division may put a code a hair outside: step inwards
        while offset + scale * lo < v_min:
            lo += 1
        while offset + scale * hi > v_max:
            hi -= 1
        if lo > hi:
            raise ProtocolError(f"ChannelConfig: no DAC code inside [{v_min}, {v_max}] V")
        safe = min(max(round((safe_v - offset) / scale), lo), hi)
        return cls(scale, offset, lo, hi, safe, ramp_v_per_s, adc_um_per_code, adc_offset_um)

    @property
    def v_min(self) -> float:
        """Lowest output voltage (V)."""
        return self.dac_offset_v + self.dac_v_per_code * self.code_min

    @property
    def v_max(self) -> float:
        """Highest output voltage (V)."""
        return self.dac_offset_v + self.dac_v_per_code * self.code_max

    @property
    def safe_v(self) -> float:
        """The safe output voltage (V)."""
        return self.dac_offset_v + self.dac_v_per_code * self.safe_code

    def pack(self) -> bytes:
        """The 32 wire bytes of this channel."""
        return self._S.pack(
            self.dac_v_per_code,
            self.dac_offset_v,
            self.code_min,
            self.code_max,
            self.safe_code,
            0,
            self.ramp_v_per_s,
            self.adc_um_per_code,
            self.adc_offset_um,
            0,
        )

    @classmethod
    def unpack_from(cls, payload: bytes, offset: int) -> ChannelConfig:
        """Decode the channel at byte ``offset`` of ``payload``."""
        scale, off, cmin, cmax, safe, _, ramp, adc_scale, adc_off, _ = cls._S.unpack_from(payload, offset)
        return cls(scale, off, cmin, cmax, safe, ramp, adc_scale, adc_off)


CHANNEL_CONFIG_SIZE = ChannelConfig._S.size

# CONFIGURE bounds (normative, PROTOCOL.md section "CONFIGURE")
HEARTBEAT_TIMEOUT_MS_RANGE = (10, 60_000)
STATUS_PERIOD_MS_RANGE = (1, 1000)


@dataclass(frozen=True, slots=True)
class Configure(Message):
    """CONFIGURE (host -> board, control): sample clock, limits, scalings, watchdog.

    Attributes
    ----------
    sample_rate_hz
        Sample clock (Hz, integer).
    heartbeat_timeout_ms
        Watchdog: with no valid frame from the host for this long (ms) the board ramps every
        output to its safe value.
    status_period_ms
        The board sends STATUS at least this often (ms).
    sensor_decimation
        The board reports one sensor sample every ``sensor_decimation`` ticks (>= 1).
    channels
        One :class:`ChannelConfig` per channel (as many as CAPABILITIES reports).
    """

    TYPE: ClassVar[MessageType] = MessageType.CONFIGURE
    _S: ClassVar[struct.Struct] = struct.Struct("<IIHHBBH")

    sample_rate_hz: int
    heartbeat_timeout_ms: int
    status_period_ms: int
    sensor_decimation: int
    channels: tuple[ChannelConfig, ...]

    def __post_init__(self) -> None:
        o = "Configure"
        set_ = object.__setattr__
        set_(self, "sample_rate_hz", _uint(o, "sample_rate_hz", self.sample_rate_hz, _U32))
        set_(self, "heartbeat_timeout_ms", _uint(o, "heartbeat_timeout_ms", self.heartbeat_timeout_ms, _U32))
        set_(self, "status_period_ms", _uint(o, "status_period_ms", self.status_period_ms, _U16))
        set_(self, "sensor_decimation", _uint(o, "sensor_decimation", self.sensor_decimation, _U16))
        chans = tuple(self.channels)
        if not 1 <= len(chans) <= MAX_CHANNELS:
            raise ProtocolError(f"{o}.channels: {len(chans)} channels outside [1, {MAX_CHANNELS}]")
        for i, ch in enumerate(chans):
            if not isinstance(ch, ChannelConfig):
                raise ProtocolError(f"{o}.channels[{i}]: expected a ChannelConfig, got {type(ch).__name__}")
        set_(self, "channels", chans)

    @property
    def n_channels(self) -> int:
        """Number of configured channels."""
        return len(self.channels)

    def pack_payload(self) -> bytes:
        head = self._S.pack(
            self.sample_rate_hz,
            self.heartbeat_timeout_ms,
            self.status_period_ms,
            self.sensor_decimation,
            self.n_channels,
            0,
            0,
        )
        return head + b"".join(ch.pack() for ch in self.channels)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Configure:
        if len(payload) < cls._S.size:
            raise _LengthError(f"CONFIGURE: payload is {len(payload)} bytes, expected >= {cls._S.size}")
        rate, hb, period, decim, n_ch, _, _ = cls._S.unpack_from(payload)
        cls._expect_len(payload, cls._S.size + CHANNEL_CONFIG_SIZE * n_ch)
        chans = tuple(
            ChannelConfig.unpack_from(payload, cls._S.size + CHANNEL_CONFIG_SIZE * i) for i in range(n_ch)
        )
        return cls(rate, hb, period, decim, chans)

    def check(self, caps: Capabilities) -> tuple[NakReason, int] | None:
        """Check this configuration against a board's capabilities (the board's acceptance rules).

        Returns
        -------
        tuple[NakReason, int] | None
            ``None`` if acceptable, else the NAK reason and detail: the byte offset (within the
            frame, header included) of the first offending field.
        """
        base = HEADER_SIZE
        if self.n_channels != caps.n_channels:
            return NakReason.BAD_VALUE, base + 12
        if not max(caps.sample_rate_min_hz, 1) <= self.sample_rate_hz <= caps.sample_rate_max_hz:
            return NakReason.UNSUPPORTED, base + 0
        if caps.sample_clock_hz and caps.sample_clock_hz % self.sample_rate_hz:
            return NakReason.UNSUPPORTED, base + 0
        lo, hi = HEARTBEAT_TIMEOUT_MS_RANGE
        if not lo <= self.heartbeat_timeout_ms <= hi:
            return NakReason.BAD_VALUE, base + 4
        lo, hi = STATUS_PERIOD_MS_RANGE
        if not lo <= self.status_period_ms <= hi:
            return NakReason.BAD_VALUE, base + 8
        if self.sensor_decimation < 1:
            return NakReason.BAD_VALUE, base + 10
        for i, ch in enumerate(self.channels):
            at = base + self._S.size + CHANNEL_CONFIG_SIZE * i
            amp_lo, amp_hi = caps.amplifier_ranges_v[i]
            if ch.dac_v_per_code <= 0:
                return NakReason.BAD_VALUE, at + 0
            if not ch.code_min <= ch.code_max:
                return NakReason.BAD_VALUE, at + 8
            if not ch.code_min <= ch.safe_code <= ch.code_max:
                return NakReason.BAD_VALUE, at + 12
            if ch.v_min < amp_lo or ch.v_max > amp_hi:
                return NakReason.BAD_VALUE, at + (8 if ch.v_min < amp_lo else 10)
            if ch.ramp_v_per_s <= 0:
                return NakReason.BAD_VALUE, at + 16
            if ch.adc_um_per_code == 0:
                return NakReason.BAD_VALUE, at + 20
        return None


@dataclass(frozen=True, slots=True)
class Ack(Message):
    """ACK: a control request was accepted.

    Attributes
    ----------
    acked_seq
        Sequence number of the request.
    acked_type
        Message type of the request (raw byte).
    """

    TYPE: ClassVar[MessageType] = MessageType.ACK
    _S: ClassVar[struct.Struct] = struct.Struct("<IBBH")

    acked_seq: int
    acked_type: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "acked_seq", _uint("Ack", "acked_seq", self.acked_seq, _U32))
        object.__setattr__(self, "acked_type", _uint("Ack", "acked_type", self.acked_type, _U8))

    def pack_payload(self) -> bytes:
        return self._S.pack(self.acked_seq, self.acked_type, 0, 0)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Ack:
        cls._expect_len(payload, cls._S.size)
        seq, typ, _, _ = cls._S.unpack(payload)
        return cls(seq, typ)


@dataclass(frozen=True, slots=True)
class Nak(Message):
    """NAK: a control request was refused (layout frozen across protocol versions).

    Attributes
    ----------
    nacked_seq
        Sequence number of the request.
    nacked_type
        Message type byte of the request (may be a type the board does not know).
    reason
        Why.
    detail
        VERSION_MISMATCH: the protocol version the sender speaks; BAD_VALUE / UNSUPPORTED: byte
        offset within the request frame of the offending field; otherwise 0.
    """

    TYPE: ClassVar[MessageType] = MessageType.NAK
    _S: ClassVar[struct.Struct] = struct.Struct("<IBBHI")

    nacked_seq: int
    nacked_type: int
    reason: NakReason
    detail: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "nacked_seq", _uint("Nak", "nacked_seq", self.nacked_seq, _U32))
        object.__setattr__(self, "nacked_type", _uint("Nak", "nacked_type", self.nacked_type, _U8))
        object.__setattr__(self, "reason", _enum("Nak", "reason", self.reason, NakReason))
        object.__setattr__(self, "detail", _uint("Nak", "detail", self.detail, _U32))

    def pack_payload(self) -> bytes:
        return self._S.pack(self.nacked_seq, self.nacked_type, self.reason, 0, self.detail)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Nak:
        cls._expect_len(payload, cls._S.size)
        seq, typ, reason, _, detail = cls._S.unpack(payload)
        return cls(seq, typ, reason, detail)

    def to_error(self) -> ProtocolError:
        """The exception a requester raises for this NAK (:class:`VersionMismatchError` for versions)."""
        try:
            what = MessageType(self.nacked_type).name
        except ValueError:
            what = f"type 0x{self.nacked_type:02x}"
        if self.reason == NakReason.VERSION_MISMATCH:
            return VersionMismatchError(
                f"board refused {what} (seq {self.nacked_seq}): it speaks protocol version {self.detail}, "
                f"this host speaks {PROTOCOL_VERSION}"
            )
        where = f" (field at frame offset {self.detail})" if self.reason in _OFFSET_REASONS else ""
        return ProtocolError(f"board refused {what} (seq {self.nacked_seq}): {self.reason.name}{where}")


_OFFSET_REASONS = frozenset({NakReason.BAD_VALUE, NakReason.UNSUPPORTED})


@dataclass(frozen=True, slots=True)
class Start(Message):
    """START (host -> board, control): arm the output at sample ``start_index``.

    Attributes
    ----------
    start_index
        Index of the first sample to play; the FIFO is emptied and expects this index next.
    prefill_samples
        The clock starts once the FIFO holds this many samples per channel (0 = at the first
        sample).
    """

    TYPE: ClassVar[MessageType] = MessageType.START
    _S: ClassVar[struct.Struct] = struct.Struct("<QII")

    start_index: int
    prefill_samples: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "start_index", _uint("Start", "start_index", self.start_index, _U64))
        object.__setattr__(
            self, "prefill_samples", _uint("Start", "prefill_samples", self.prefill_samples, _U32)
        )

    def pack_payload(self) -> bytes:
        return self._S.pack(self.start_index, self.prefill_samples, 0)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Start:
        cls._expect_len(payload, cls._S.size)
        index, prefill, _ = cls._S.unpack(payload)
        return cls(index, prefill)


@dataclass(frozen=True, slots=True)
class Stop(Message):
    """STOP (host -> board, control): stop the clock and hold the outputs.

    Attributes
    ----------
    stop_after_index
        Play up to and including this sample index, then stop; :data:`NO_INDEX` = now.
    """

    TYPE: ClassVar[MessageType] = MessageType.STOP
    _S: ClassVar[struct.Struct] = struct.Struct("<Q")

    stop_after_index: int = NO_INDEX

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "stop_after_index", _uint("Stop", "stop_after_index", self.stop_after_index, _U64)
        )

    def pack_payload(self) -> bytes:
        return self._S.pack(self.stop_after_index)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Stop:
        cls._expect_len(payload, cls._S.size)
        return cls(cls._S.unpack(payload)[0])


@dataclass(frozen=True, slots=True)
class RampToSafe(Message):
    """RAMP_TO_SAFE (host -> board, control): stop the clock and ramp every output to its safe value."""

    TYPE: ClassVar[MessageType] = MessageType.RAMP_TO_SAFE

    def pack_payload(self) -> bytes:
        return b""

    @classmethod
    def unpack_payload(cls, payload: bytes) -> RampToSafe:
        cls._expect_len(payload, 0)
        return cls()


@dataclass(frozen=True, slots=True)
class Heartbeat(Message):
    """HEARTBEAT (host -> board): keeps the watchdog quiet when no other frame is due.

    Attributes
    ----------
    time_us
        The sender's monotonic clock (us), informational.
    """

    TYPE: ClassVar[MessageType] = MessageType.HEARTBEAT
    _S: ClassVar[struct.Struct] = struct.Struct("<Q")

    time_us: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "time_us", _uint("Heartbeat", "time_us", self.time_us, _U64))

    def pack_payload(self) -> bytes:
        return self._S.pack(self.time_us)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Heartbeat:
        cls._expect_len(payload, cls._S.size)
        return cls(cls._S.unpack(payload)[0])


class _Block(Message):
    """Shared code of SAMPLES and SENSOR (first index + interleaved int16 codes)."""

    __slots__ = ()
    first_index: int
    codes: CodeArray

    @property
    def n_samples(self) -> int:
        """Samples per channel in this frame."""
        return int(self.codes.shape[0])

    @property
    def n_channels(self) -> int:
        """Channels per sample."""
        return int(self.codes.shape[1])

    def _eq_fields(self) -> tuple[Any, ...]:
        raise NotImplementedError

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, _Block)
        return self._eq_fields() == other._eq_fields() and np.array_equal(self.codes, other.codes)

    def __hash__(self) -> int:
        return hash((type(self), *self._eq_fields(), self.codes.shape, self.codes.tobytes()))

    @classmethod
    def _unpack_block(cls, payload: bytes, head: struct.Struct) -> tuple[tuple[Any, ...], CodeArray]:
        if len(payload) < head.size:
            raise _LengthError(f"{cls.TYPE.name}: payload is {len(payload)} bytes, expected >= {head.size}")
        fields = head.unpack_from(payload)
        n_ch, n = fields[1], fields[3]
        if not 1 <= n_ch <= MAX_CHANNELS:
            raise ProtocolError(f"{cls.TYPE.name}.n_channels: {n_ch} outside [1, {MAX_CHANNELS}]")
        cls._expect_len(payload, head.size + 2 * n_ch * n)
        codes: CodeArray = np.frombuffer(payload, dtype=_WIRE_I16, count=n * n_ch, offset=head.size).reshape(
            n, n_ch
        )
        return fields, codes


@dataclass(frozen=True, slots=True, eq=False)
class Samples(_Block):
    """SAMPLES (host -> board): DAC codes to play, interleaved by sample.

    Attributes
    ----------
    first_index
        Sample index of ``codes[0]``; consecutive rows are consecutive indices.
    codes
        int16 DAC codes, shape ``(n_samples, n_channels)`` (read-only view).
    """

    TYPE: ClassVar[MessageType] = MessageType.SAMPLES
    _S: ClassVar[struct.Struct] = struct.Struct("<QBBH")

    first_index: int
    codes: CodeArray = field(repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "first_index", _uint("Samples", "first_index", self.first_index, _U64))
        object.__setattr__(self, "codes", _codes("Samples", self.codes))
        if self.first_index + self.n_samples - 1 >= NO_INDEX:
            raise ProtocolError("Samples.first_index: the block runs past the last sample index")

    def _eq_fields(self) -> tuple[Any, ...]:
        return (self.first_index,)

    def pack_payload(self) -> bytes:
        n, c = self.codes.shape
        return self._S.pack(self.first_index, c, 0, n) + self.codes.tobytes()

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Samples:
        fields, codes = cls._unpack_block(payload, cls._S)
        return cls(fields[0], codes)


@dataclass(frozen=True, slots=True, eq=False)
class Sensor(_Block):
    """SENSOR (board -> host): ADC codes of the position sensor, interleaved by sample.

    Attributes
    ----------
    first_index
        Sample-clock index at which ``codes[0]`` was converted.
    stride
        Index step between rows (the configured ``sensor_decimation``).
    codes
        int16 ADC codes, shape ``(n_samples, n_channels)`` (read-only view).
    """

    TYPE: ClassVar[MessageType] = MessageType.SENSOR
    _S: ClassVar[struct.Struct] = struct.Struct("<QBBHHH")

    first_index: int
    stride: int
    codes: CodeArray = field(repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "first_index", _uint("Sensor", "first_index", self.first_index, _U64))
        object.__setattr__(self, "stride", _uint("Sensor", "stride", self.stride, _U16))
        if self.stride < 1:
            raise ProtocolError("Sensor.stride: must be >= 1")
        object.__setattr__(self, "codes", _codes("Sensor", self.codes))
        if self.first_index + (self.n_samples - 1) * self.stride >= NO_INDEX:
            raise ProtocolError("Sensor.first_index: the block runs past the last sample index")

    def _eq_fields(self) -> tuple[Any, ...]:
        return (self.first_index, self.stride)

    @property
    def indices(self) -> npt.NDArray[np.uint64]:
        """Sample index of every row."""
        return np.uint64(self.first_index) + np.arange(self.n_samples, dtype=np.uint64) * np.uint64(
            self.stride
        )

    def pack_payload(self) -> bytes:
        n, c = self.codes.shape
        return self._S.pack(self.first_index, c, 0, n, self.stride, 0) + self.codes.tobytes()

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Sensor:
        fields, codes = cls._unpack_block(payload, cls._S)
        return cls(fields[0], fields[4], codes)


@dataclass(frozen=True, slots=True)
class Status(Message):
    """STATUS (board -> host, every ``status_period_ms``): credits, progress, faults, counters.

    Attributes
    ----------
    state
        The output state machine.
    fault_flags
        Latched faults (cleared by an accepted START or CONFIGURE).
    write_index
        The sample index the FIFO expects next: every sample below it has been received.
    last_played_index
        Index of the last sample applied to the outputs; :data:`NO_INDEX` before the first.
    fifo_free_samples
        Free FIFO slots (samples per channel). The host may send samples with index below
        :attr:`credit_limit`.
    crc_errors
        Frames dropped for a bad CRC since power-up.
    frames_dropped
        Frames discarded for any reason (decode errors, SAMPLES not accepted) since power-up.
    underruns
        Ticks that found the FIFO empty while running.
    clamped_samples
        Samples outside ``[code_min, code_max]`` that were clamped.
    index_gaps
        SAMPLES frames dropped because ``first_index`` was beyond ``write_index``.
    overflows
        SAMPLES frames dropped because they reached beyond the credit limit.
    """

    TYPE: ClassVar[MessageType] = MessageType.STATUS
    _S: ClassVar[struct.Struct] = struct.Struct("<BBHIQQIIIIIIII")

    state: BoardState
    fault_flags: FaultFlags
    write_index: int
    last_played_index: int
    fifo_free_samples: int
    crc_errors: int = 0
    frames_dropped: int = 0
    underruns: int = 0
    clamped_samples: int = 0
    index_gaps: int = 0
    overflows: int = 0

    def __post_init__(self) -> None:
        o = "Status"
        object.__setattr__(self, "state", _enum(o, "state", self.state, BoardState))
        object.__setattr__(self, "fault_flags", FaultFlags(_uint(o, "fault_flags", self.fault_flags, _U32)))
        for name in ("write_index", "last_played_index"):
            object.__setattr__(self, name, _uint(o, name, getattr(self, name), _U64))
        for name in (
            "fifo_free_samples",
            "crc_errors",
            "frames_dropped",
            "underruns",
            "clamped_samples",
            "index_gaps",
            "overflows",
        ):
            object.__setattr__(self, name, _uint(o, name, getattr(self, name), _U32))

    @property
    def credit_limit(self) -> int:
        """Exclusive upper bound of the sample indices the host may send now."""
        return self.write_index + self.fifo_free_samples

    def pack_payload(self) -> bytes:
        return self._S.pack(
            self.state,
            0,
            0,
            self.fault_flags,
            self.write_index,
            self.last_played_index,
            self.fifo_free_samples,
            self.crc_errors,
            self.frames_dropped,
            self.underruns,
            self.clamped_samples,
            self.index_gaps,
            self.overflows,
            0,
        )

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Status:
        cls._expect_len(payload, cls._S.size)
        (state, _, _, flags, wi, lp, free, crc, dropped, under, clamped, gaps, over, _) = cls._S.unpack(
            payload
        )
        return cls(state, flags, wi, lp, free, crc, dropped, under, clamped, gaps, over)


MAX_SYNC_OUTPUTS = 8
#: CAPABILITIES byte 21: bits 0-3 ``sync_outputs`` (revision 1), bits 4-6 reserved,
#: bit 7 set = the board has no position sensor (revision 2).
SYNC_OUTPUTS_MASK = 0x0F
NO_POSITION_SENSOR_BIT = 0x80
"""Most digital sync outputs a board may advertise (one bit each in a SYNC event)."""
SYNC_EVENT_SIZE = 8
MAX_SYNC_EVENTS = (MAX_FRAME_SIZE - HEADER_SIZE - 12 - CRC_SIZE) // SYNC_EVENT_SIZE
"""Most events in one SYNC frame (1021)."""


@dataclass(frozen=True, slots=True)
class Sync(Message):
    """SYNC (host -> board, data; protocol revision 1): levels of the digital sync outputs.

    Each event sets the outputs selected by ``mask`` to the bits of ``lines`` at the tick that
    plays sample ``first_index + offset`` (after that tick's DAC update); the other outputs keep
    their level. Bit 0 is the pixel clock, bit 1 the line clock, bit 2 the frame clock.

    Attributes
    ----------
    first_index
        Sample index the event offsets count from.
    events
        ``(offset, lines, mask)`` per event, offsets non-decreasing (u32, u8, u8).
    """

    TYPE: ClassVar[MessageType] = MessageType.SYNC
    _S: ClassVar[struct.Struct] = struct.Struct("<QHH")
    _EV: ClassVar[struct.Struct] = struct.Struct("<IBBH")

    first_index: int
    events: tuple[tuple[int, int, int], ...]

    def __post_init__(self) -> None:
        o = "Sync"
        object.__setattr__(self, "first_index", _uint(o, "first_index", self.first_index, _U64))
        evs: list[tuple[int, int, int]] = []
        for i, ev in enumerate(self.events):
            try:
                offset, lines, mask = ev
            except (TypeError, ValueError):
                raise ProtocolError(f"{o}.events[{i}]: expected (offset, lines, mask), got {ev!r}") from None
            offset = _uint(o, f"events[{i}].offset", offset, _U32)
            if evs and offset < evs[-1][0]:
                raise ProtocolError(f"{o}.events[{i}].offset: {offset} below the previous event's")
            lines = _uint(o, f"events[{i}].lines", lines, _U8)
            evs.append((offset, lines, _uint(o, f"events[{i}].mask", mask, _U8)))
        if not 1 <= len(evs) <= MAX_SYNC_EVENTS:
            raise ProtocolError(f"{o}.events: {len(evs)} events outside [1, {MAX_SYNC_EVENTS}]")
        if self.first_index + evs[-1][0] >= NO_INDEX:
            raise ProtocolError(f"{o}.first_index: the events run past the last sample index")
        object.__setattr__(self, "events", tuple(evs))

    def pack_payload(self) -> bytes:
        head = self._S.pack(self.first_index, len(self.events), 0)
        return head + b"".join(self._EV.pack(off, lines, mask, 0) for off, lines, mask in self.events)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Sync:
        if len(payload) < cls._S.size:
            raise _LengthError(f"SYNC: payload is {len(payload)} bytes, expected >= {cls._S.size}")
        first, n, _ = cls._S.unpack_from(payload)
        cls._expect_len(payload, cls._S.size + cls._EV.size * n)
        events = tuple(cls._EV.unpack_from(payload, cls._S.size + cls._EV.size * i)[:3] for i in range(n))
        return cls(first, events)


@dataclass(frozen=True, slots=True)
class Fault(Message):
    """FAULT (board -> host, best effort): a fault happened; its flag is latched in STATUS.

    Attributes
    ----------
    code
        What happened.
    channel
        Channel concerned, :data:`NO_CHANNEL` if none.
    index
        UNDERRUN / WATCHDOG: last played index; LIMIT_VIOLATION: index of the first clamped
        sample; INDEX_GAP: the expected ``write_index``; OVERFLOW: ``first_index`` of the dropped
        frame; :data:`NO_INDEX` if none.
    detail
        LIMIT_VIOLATION: the offending code as uint16 bit pattern; CRC_ERRORS: total CRC errors;
        CONFIG_REJECTED: frame offset of the offending field; HARDWARE: board specific; else 0.
    """

    TYPE: ClassVar[MessageType] = MessageType.FAULT
    _S: ClassVar[struct.Struct] = struct.Struct("<BBHIQ")

    code: FaultCode
    channel: int = NO_CHANNEL
    index: int = NO_INDEX
    detail: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "code", _enum("Fault", "code", self.code, FaultCode))
        object.__setattr__(self, "channel", _uint("Fault", "channel", self.channel, _U8))
        object.__setattr__(self, "index", _uint("Fault", "index", self.index, _U64))
        object.__setattr__(self, "detail", _uint("Fault", "detail", self.detail, _U32))

    def pack_payload(self) -> bytes:
        return self._S.pack(self.code, self.channel, 0, self.detail, self.index)

    @classmethod
    def unpack_payload(cls, payload: bytes) -> Fault:
        cls._expect_len(payload, cls._S.size)
        code, channel, _, detail, index = cls._S.unpack(payload)
        return cls(code, channel, index, detail)


MESSAGE_CLASSES: dict[MessageType, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        Sync,
        Hello,
        Capabilities,
        Configure,
        Ack,
        Nak,
        Start,
        Stop,
        RampToSafe,
        Heartbeat,
        Samples,
        Status,
        Sensor,
        Fault,
    )
}
"""Message class of every type."""


def block_overhead(msg_type: MessageType) -> int:
    """Frame bytes of a SAMPLES / SENSOR frame besides the codes (header + block header + CRC)."""
    head = {MessageType.SAMPLES: Samples._S.size, MessageType.SENSOR: Sensor._S.size}[msg_type]
    return HEADER_SIZE + head + CRC_SIZE


def max_samples_per_frame(n_channels: int, msg_type: MessageType = MessageType.SAMPLES) -> int:
    """Most samples per channel one SAMPLES / SENSOR frame can carry within :data:`MAX_FRAME_SIZE`."""
    if not 1 <= n_channels <= MAX_CHANNELS:
        raise ProtocolError(f"n_channels: {n_channels} outside [1, {MAX_CHANNELS}]")
    return min((MAX_FRAME_SIZE - block_overhead(msg_type)) // (2 * n_channels), 0xFFFF)
