"""Sans-I/O framing: :func:`encode` a message to wire bytes, :class:`FrameDecoder` turns bytes back.

Wire format (``PROTOCOL.md``): ``COBS(header | payload | CRC-32/ISO-HDLC) 0x00``. The decoder never
raises on bad input: it yields :class:`DecodeError` events, counts them by :class:`ErrorKind`, and
resynchronises at the next 0x00. No I/O, no clocks.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from enum import Enum

from cobs import cobs

from .errors import ProtocolError
from .messages import (
    CONTROL_TYPES,
    CRC_SIZE,
    FROZEN_TYPES,
    HEADER_SIZE,
    MAX_FRAME_SIZE,
    MESSAGE_CLASSES,
    PROTOCOL_VERSION,
    Flags,
    Message,
    MessageType,
    _LengthError,
)

DELIMITER = b"\x00"
"""Ends every frame on the wire."""
_HEADER = struct.Struct("<BBBBI")
_CRC = struct.Struct("<I")


def max_encoded_size(frame_size: int) -> int:
    """Worst-case COBS-stuffed size of a ``frame_size``-byte frame, without the delimiter."""
    return frame_size + max(1, -(-frame_size // 254))


MAX_WIRE_SIZE = max_encoded_size(MAX_FRAME_SIZE) + 1
"""Largest frame on the wire, delimiter included."""


def crc32_iso_hdlc(data: bytes) -> int:
    """CRC-32/ISO-HDLC (poly 0x04C11DB7 reflected, init/xorout 0xFFFFFFFF; check 0xCBF43926)."""
    return zlib.crc32(data)


def encode(
    msg: Message,
    seq: int,
    *,
    flags: Flags | int | None = None,
    version: int = PROTOCOL_VERSION,
) -> bytes:
    """Encode ``msg`` as one complete wire frame, 0x00 delimiter included.

    Parameters
    ----------
    msg
        The message.
    seq
        Sequence number (uint32) of this frame.
    flags
        Header flags; default: ``ACK_REQ`` for control types (:data:`CONTROL_TYPES`), else none.
    version
        Protocol version written into the header (tests and version negotiation only).

    Returns
    -------
    bytes
        ``COBS(frame) + b"\\x00"``.

    Raises
    ------
    ProtocolError
        ``seq`` / ``flags`` / ``version`` out of range, or the frame exceeds :data:`MAX_FRAME_SIZE`.
    """
    if flags is None:
        flags = Flags.ACK_REQ if msg.TYPE in CONTROL_TYPES else Flags.NONE
    if not 0 <= seq <= 0xFFFFFFFF:
        raise ProtocolError(f"seq: {seq} outside [0, 2**32-1]")
    if not 0 <= int(flags) <= 0xFF or not 0 <= version <= 0xFF:
        raise ProtocolError(f"flags {int(flags)} / version {version}: outside [0, 255]")
    payload = msg.pack_payload()
    size = HEADER_SIZE + len(payload) + CRC_SIZE
    if size > MAX_FRAME_SIZE:
        raise ProtocolError(f"{msg.TYPE.name}: frame of {size} bytes exceeds MAX_FRAME_SIZE {MAX_FRAME_SIZE}")
    head = _HEADER.pack(version, msg.TYPE, int(flags), 0, seq)
    crc = zlib.crc32(payload, zlib.crc32(head))
    out: bytes = cobs.encode(b"".join((head, payload, _CRC.pack(crc)))) + DELIMITER
    return out


class ErrorKind(Enum):
    """Why the decoder dropped a frame."""

    BAD_COBS = "bad_cobs"
    """COBS stuffing inconsistent (a length code runs past the frame)."""
    TOO_SHORT = "too_short"
    """Fewer bytes than header + CRC."""
    BAD_CRC = "bad_crc"
    """CRC-32 mismatch."""
    UNKNOWN_TYPE = "unknown_type"
    """CRC fine, message type not defined."""
    BAD_VERSION = "bad_version"
    """CRC fine, header version foreign and the type's layout not frozen."""
    BAD_LENGTH = "bad_length"
    """CRC fine, payload length wrong for its type."""
    BAD_VALUE = "bad_value"
    """CRC fine, a field value invalid (e.g. unknown enum value, zero samples)."""
    OVERSIZE = "oversize"
    """More bytes than :data:`MAX_WIRE_SIZE` before a delimiter."""


@dataclass(frozen=True, slots=True)
class Frame:
    """A valid frame delivered by :class:`FrameDecoder`.

    Attributes
    ----------
    msg
        The decoded message.
    seq
        Header sequence number.
    flags
        Header flags.
    version
        Header protocol version (differs from :data:`PROTOCOL_VERSION` only for HELLO / NAK).
    wire_size
        Bytes this frame took on the wire, delimiter included.
    """

    msg: Message
    seq: int
    flags: Flags
    version: int = PROTOCOL_VERSION
    wire_size: int = 0

    @property
    def msg_type(self) -> int:
        """The message type byte."""
        return int(self.msg.TYPE)

    @property
    def ack_requested(self) -> bool:
        """The sender expects an ACK / NAK (a control request)."""
        return bool(self.flags & Flags.ACK_REQ)


@dataclass(frozen=True, slots=True)
class DecodeError:
    """An event (not an exception): the decoder dropped a frame.

    Attributes
    ----------
    kind
        Why.
    detail
        One line for logs.
    wire_size
        Bytes dropped, delimiter included (for OVERSIZE: the bytes seen so far).
    seq, msg_type, flags, version
        Header fields when the CRC was valid (so a receiver can NAK a bad control request),
        else ``None``.
    """

    kind: ErrorKind
    detail: str
    wire_size: int
    seq: int | None = None
    msg_type: int | None = None
    flags: Flags | None = None
    version: int | None = None

    @property
    def ack_requested(self) -> bool:
        """The dropped frame was a valid-CRC control request expecting an ACK / NAK."""
        return self.flags is not None and bool(self.flags & Flags.ACK_REQ)


@dataclass(slots=True)
class DecoderStats:
    """Counters of a :class:`FrameDecoder` (monotonic)."""

    bytes_in: int = 0
    frames_ok: int = 0
    bad_cobs: int = 0
    too_short: int = 0
    bad_crc: int = 0
    unknown_type: int = 0
    bad_version: int = 0
    bad_length: int = 0
    bad_value: int = 0
    oversize: int = 0
    by_type: dict[int, int] = field(default_factory=dict)

    @property
    def errors(self) -> int:
        """Frames dropped for any reason."""
        return (
            self.bad_cobs
            + self.too_short
            + self.bad_crc
            + self.unknown_type
            + self.bad_version
            + self.bad_length
            + self.bad_value
            + self.oversize
        )

    def count(self, kind: ErrorKind) -> int:
        """The counter of ``kind``."""
        value: int = getattr(self, kind.value)
        return value


def decode_frame(stuffed: bytes, wire_size: int | None = None) -> Frame | DecodeError:
    """Decode one COBS-stuffed frame (delimiter already removed).

    Never raises on bad input; returns a :class:`DecodeError` instead.
    """
    size = len(stuffed) + 1 if wire_size is None else wire_size
    try:
        raw: bytes = cobs.decode(stuffed)
    except cobs.DecodeError as exc:
        return DecodeError(ErrorKind.BAD_COBS, f"bad COBS: {exc}", size)
    if len(raw) < HEADER_SIZE + CRC_SIZE:
        return DecodeError(ErrorKind.TOO_SHORT, f"{len(raw)} bytes, need >= {HEADER_SIZE + CRC_SIZE}", size)
    body = raw[:-CRC_SIZE]
    (got,) = _CRC.unpack_from(raw, len(body))
    want = zlib.crc32(body)
    if got != want:
        return DecodeError(ErrorKind.BAD_CRC, f"CRC 0x{got:08x} != computed 0x{want:08x}", size)
    version, typ, flags_b, _, seq = _HEADER.unpack_from(raw)
    flags = Flags(flags_b)
    try:
        msg_type = MessageType(typ)
    except ValueError:
        return DecodeError(ErrorKind.UNKNOWN_TYPE, f"type 0x{typ:02x}", size, seq, typ, flags, version)
    if version != PROTOCOL_VERSION and msg_type not in FROZEN_TYPES:
        return DecodeError(
            ErrorKind.BAD_VERSION,
            f"{msg_type.name} of protocol version {version}, this codec speaks {PROTOCOL_VERSION}",
            size,
            seq,
            typ,
            flags,
            version,
        )
    try:
        msg = MESSAGE_CLASSES[msg_type].unpack_payload(body[HEADER_SIZE:])
    except _LengthError as exc:
        return DecodeError(ErrorKind.BAD_LENGTH, str(exc), size, seq, typ, flags, version)
    except ProtocolError as exc:
        return DecodeError(ErrorKind.BAD_VALUE, str(exc), size, seq, typ, flags, version)
    return Frame(msg, seq, flags, version, size)


class FrameDecoder:
    """Incremental decoder: feed it any chunks of the byte stream, get frames and error events.

    Parameters
    ----------
    max_wire_size
        Frames longer than this (delimiter included) are dropped as OVERSIZE without buffering
        more than this many bytes.

    Examples
    --------
    >>> from firmware_proto import FrameDecoder, Heartbeat, encode
    >>> dec = FrameDecoder()
    >>> wire = encode(Heartbeat(time_us=5), seq=1)
    >>> dec.feed(wire[:3]) + dec.feed(wire[3:])  # doctest: +ELLIPSIS
    [Frame(msg=Heartbeat(time_us=5), seq=1, ...)]
    """

    def __init__(self, max_wire_size: int = MAX_WIRE_SIZE) -> None:
        self.max_wire_size = max_wire_size
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._skipping = False  # inside an oversize frame: discard until the next delimiter

    @property
    def buffered(self) -> int:
        """Bytes of an unfinished frame held back."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame | DecodeError]:
        """Consume ``data``; return the frames (and errors) it completed, in stream order.

        Empty frames (consecutive delimiters) are ignored silently. Never raises on bad input.
        """
        data = bytes(data)
        self.stats.bytes_in += len(data)
        out: list[Frame | DecodeError] = []
        start = 0
        limit = self.max_wire_size - 1  # stuffed bytes allowed before the delimiter
        while True:
            end = data.find(0, start)
            if end < 0:
                self._append_partial(data, start, limit, out)
                return out
            if self._skipping:
                self._skipping = False
            elif self._buf:
                self._buf += data[start:end]
                chunk = bytes(self._buf)
                self._buf.clear()
                self._handle(chunk, limit, out)
            elif end > start:
                self._handle(data[start:end], limit, out)
            start = end + 1

    def _append_partial(self, data: bytes, start: int, limit: int, out: list[Frame | DecodeError]) -> None:
        if self._skipping or start >= len(data):
            return
        self._buf += data[start:]
        if len(self._buf) > limit:
            self._oversize(len(self._buf), out)
            self._buf.clear()
            self._skipping = True

    def _oversize(self, seen: int, out: list[Frame | DecodeError]) -> None:
        self.stats.oversize += 1
        out.append(DecodeError(ErrorKind.OVERSIZE, f"frame exceeds {self.max_wire_size} wire bytes", seen))

    def _handle(self, chunk: bytes, limit: int, out: list[Frame | DecodeError]) -> None:
        if len(chunk) > limit:
            self._oversize(len(chunk) + 1, out)
            return
        result = decode_frame(chunk)
        if isinstance(result, Frame):
            self.stats.frames_ok += 1
            t = result.msg_type
            self.stats.by_type[t] = self.stats.by_type.get(t, 0) + 1
        else:
            setattr(self.stats, result.kind.value, self.stats.count(result.kind) + 1)
        out.append(result)
