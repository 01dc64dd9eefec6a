"""Test vectors: the canonical examples of every message, their Markdown form, and a parser for it.

``PROTOCOL.md`` embeds the vectors rendered by :func:`render_vectors_section` (run
``python tools/gen_protocol_vectors.py`` after changing the codec); the tests parse them back with
:func:`parse_vectors` and check the codec against them byte for byte, both ways.
"""

from __future__ import annotations

import dataclasses
import json
import re
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from cobs import cobs

from .codec import encode
from .messages import (
    MESSAGE_CLASSES,
    NO_CHANNEL,
    NO_INDEX,
    PROTOCOL_VERSION,
    Ack,
    BoardState,
    Capabilities,
    ChannelConfig,
    Configure,
    Fault,
    FaultCode,
    FaultFlags,
    Flags,
    Heartbeat,
    Hello,
    Message,
    MessageType,
    Nak,
    NakReason,
    RampToSafe,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
    Sync,
)

PROTOCOL_MD = Path(__file__).with_name("PROTOCOL.md")
"""The specification shipped with the package."""

VECTORS_BEGIN = "<!-- BEGIN GENERATED VECTORS (tools/gen_protocol_vectors.py) -->"
VECTORS_END = "<!-- END GENERATED VECTORS -->"
BUDGET_BEGIN = "<!-- BEGIN GENERATED BUDGET (tools/gen_protocol_vectors.py) -->"
BUDGET_END = "<!-- END GENERATED BUDGET -->"


@dataclass(frozen=True)
class Vector:
    """One example frame.

    Attributes
    ----------
    name
        Unique name.
    msg
        The message.
    seq
        Header sequence number.
    note
        What the example shows.
    flags
        Header flags; ``None`` = the default for the type.
    version
        Header protocol version.
    """

    name: str
    msg: Message
    seq: int
    note: str
    flags: int | None = None
    version: int = PROTOCOL_VERSION

    def wire(self) -> bytes:
        """The encoded frame, delimiter included."""
        return encode(self.msg, self.seq, flags=self.flags, version=self.version)


def canonical_vectors() -> list[Vector]:
    """The vectors of PROTOCOL.md (every message type at least once)."""
    caps = Capabilities(
        reply_to_seq=0,
        protocol_version=PROTOCOL_VERSION,
        firmware_version=(1, 2, 3),
        dac_bits=16,
        adc_bits=16,
        max_samples_per_frame=1024,
        sample_rate_min_hz=1000,
        sample_rate_max_hz=200_000,
        sample_clock_hz=0,
        fifo_depth_samples=16384,
        board_serial=0x00C0FFEE,
        amplifier_ranges_v=((-150.0, 150.0), (-150.0, 150.0), (-10.0, 150.0)),
    )
    xy = ChannelConfig(
        dac_v_per_code=300.0 / 65536,
        dac_offset_v=0.0,
        code_min=-30583,
        code_max=30583,
        safe_code=0,
        ramp_v_per_s=100.0,
        adc_um_per_code=200.0 / 65536,
        adc_offset_um=0.0,
    )
    z = ChannelConfig(
        dac_v_per_code=160.0 / 65536,
        dac_offset_v=70.0,
        code_min=-28672,
        code_max=28672,
        safe_code=-28672,
        ramp_v_per_s=50.0,
        adc_um_per_code=100.0 / 65536,
        adc_offset_um=50.0,
    )
    cfg = Configure(
        sample_rate_hz=100_000,
        heartbeat_timeout_ms=500,
        status_period_ms=10,
        sensor_decimation=1,
        channels=(xy, xy, z),
    )
    samples = np.array(
        [[0, -1, 32767], [-32768, 256, 1], [100, -100, 0], [0x1234, -0x1234, 7]], dtype=np.int16
    )
    sensor = np.array([[10, 20, -30], [11, 21, -31], [-2, 0, 32767]], dtype=np.int16)
    return [
        Vector("HELLO", Hello(PROTOCOL_VERSION, session_id=0x12345678), 0, "host opens a session"),
        Vector("CAPABILITIES", caps, 0, "board answers HELLO seq 0: 3 channels, 16-bit, FIFO 16384"),
        Vector("CONFIGURE", cfg, 1, "100 kS/s, x/y +-140 V, z 0..140 V, watchdog 500 ms"),
        Vector("ACK", Ack(1, MessageType.CONFIGURE), 1, "board accepts CONFIGURE seq 1"),
        Vector(
            "NAK_BAD_VALUE",
            Nak(1, MessageType.CONFIGURE, NakReason.BAD_VALUE, 64),
            2,
            "board refuses CONFIGURE seq 1: field at frame offset 64 (channel 1 code_min)",
        ),
        Vector(
            "NAK_VERSION_MISMATCH",
            Nak(0, MessageType.HELLO, NakReason.VERSION_MISMATCH, PROTOCOL_VERSION),
            3,
            "board refuses a HELLO of another version; it speaks version 1",
        ),
        Vector(
            "HELLO_V2",
            Hello(2, session_id=7),
            0,
            "a future version-2 host says HELLO: still decodable (frozen layout), answered by "
            "NAK_VERSION_MISMATCH",
            version=2,
        ),
        Vector(
            "START",
            Start(start_index=0, prefill_samples=10_000),
            2,
            "arm at index 0, run once 100 ms is queued",
        ),
        Vector("STOP_NOW", Stop(), 3, "stop immediately, hold the outputs"),
        Vector("STOP_AFTER", Stop(stop_after_index=1_999_999), 4, "stop after playing index 1999999"),
        Vector("RAMP_TO_SAFE", RampToSafe(), 5, "ramp every output to its safe value"),
        Vector("HEARTBEAT", Heartbeat(time_us=1_000_000), 6, "host alive at t = 1 s"),
        Vector(
            "SAMPLES",
            Samples(first_index=10_000, codes=samples),
            7,
            "4 samples x 3 channels from index 10000",
        ),
        Vector(
            "STATUS",
            Status(
                state=BoardState.RUNNING,
                fault_flags=FaultFlags.CRC_ERRORS,
                write_index=20_000,
                last_played_index=12_345,
                fifo_free_samples=8_729,
                crc_errors=2,
                frames_dropped=3,
                underruns=0,
                clamped_samples=1,
                index_gaps=1,
                overflows=0,
            ),
            4,
            "running; credit limit 28729",
        ),
        Vector(
            "SENSOR",
            Sensor(first_index=12_000, stride=2, codes=sensor),
            5,
            "3 sensor samples x 3 channels at indices 12000, 12002, 12004",
        ),
        Vector(
            "FAULT_UNDERRUN",
            Fault(FaultCode.UNDERRUN, NO_CHANNEL, index=19_999),
            6,
            "FIFO ran dry after index 19999",
        ),
        Vector(
            "FAULT_LIMIT",
            Fault(FaultCode.LIMIT_VIOLATION, channel=1, index=10_001, detail=0x8000),
            7,
            "sample 10001 of channel 1 (code -32768) clamped",
        ),
        Vector(
            "FAULT_WATCHDOG",
            Fault(FaultCode.WATCHDOG, NO_CHANNEL, index=NO_INDEX),
            8,
            "host silent: ramping to safe before any sample was played",
        ),
        Vector(
            "CAPABILITIES_SYNC",
            dataclasses.replace(caps, sync_outputs=3),
            0,
            "revision 1: the board of the CAPABILITIES vector with 3 sync outputs (pixel, line, frame)",
        ),
        Vector(
            "CAPABILITIES_NO_SENSOR",
            dataclasses.replace(caps, position_sensor=False),
            0,
            "revision 2: the board of the CAPABILITIES vector without a position sensor "
            "(its ADC channels carry other signals, e.g. a z-voltage monitor)",
        ),
        Vector(
            "SYNC",
            Sync(
                first_index=20_000,
                events=((0, 0b111, 0b111), (5, 0b000, 0b111), (10, 0b001, 0b001), (15, 0b000, 0b001)),
            ),
            9,
            "revision 1: frame, line and pixel clocks high at index 20000, all low at 20005, "
            "the next pixel at 20010..20014",
        ),
    ]


# ---------------------------------------------------------------------------------------------
# JSON form of message fields


def message_to_json(msg: Message) -> dict[str, Any]:
    """The fields of ``msg`` as JSON-compatible values (enums by name, arrays as nested lists)."""
    out: dict[str, Any] = {}
    for f in fields(msg):  # type: ignore[arg-type]
        value = getattr(msg, f.name)
        out[f.name] = _to_json(f.name, value)
    return out


def _to_json(name: str, value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, FaultFlags):
        return [flag.name for flag in FaultFlags if flag and flag in value]
    if isinstance(value, BoardState | NakReason | FaultCode):
        return value.name
    if name in ("acked_type", "nacked_type"):
        try:
            return MessageType(value).name
        except ValueError:
            return int(value)
    if isinstance(value, ChannelConfig):
        return {f.name: getattr(value, f.name) for f in fields(value)}
    if isinstance(value, tuple):
        return [_to_json(name, v) for v in value]
    return value


def message_from_json(type_name: str, data: dict[str, Any]) -> Message:
    """Inverse of :func:`message_to_json` for message type ``type_name`` (e.g. ``"SAMPLES"``)."""
    cls = MESSAGE_CLASSES[MessageType[type_name]]
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key == "codes":
            kwargs[key] = np.array(value, dtype=np.int64)
        elif key == "channels":
            kwargs[key] = tuple(ChannelConfig(**c) for c in value)
        elif key == "amplifier_ranges_v":
            kwargs[key] = tuple(tuple(r) for r in value)
        elif key == "firmware_version":
            kwargs[key] = tuple(value)
        elif key in ("acked_type", "nacked_type"):
            kwargs[key] = MessageType[value] if isinstance(value, str) else value
        elif key == "reason":
            kwargs[key] = NakReason[value]
        elif key == "code":
            kwargs[key] = FaultCode[value]
        elif key == "state":
            kwargs[key] = BoardState[value]
        elif key == "fault_flags":
            flags = FaultFlags.NONE
            for flag_name in value:
                flags |= FaultFlags[flag_name]
            kwargs[key] = flags
        else:
            kwargs[key] = value
    msg: Message = cls(**kwargs)
    return msg


# ---------------------------------------------------------------------------------------------
# Markdown


def _hex_lines(data: bytes, per_line: int = 16) -> list[str]:
    return ["    " + data[i : i + per_line].hex(" ") for i in range(0, len(data), per_line)]


def _fields_lines(data: dict[str, Any]) -> list[str]:
    one = json.dumps(data)
    if len(one) <= 96:
        return [one]
    items = list(data.items())
    lines = ["    {"]
    for i, (key, value) in enumerate(items):
        comma = "," if i < len(items) - 1 else ""
        if isinstance(value, list) and value and isinstance(value[0], dict | list):
            lines.append(f"      {json.dumps(key)}: [")
            for j, elem in enumerate(value):
                sep = "," if j < len(value) - 1 else ""
                lines += _wrapped_json(elem, sep)
            lines.append(f"      ]{comma}")
        else:
            lines.append(f"      {json.dumps(key)}: {json.dumps(value)}{comma}")
    lines.append("    }")
    return ["", *lines]


def _wrapped_json(elem: Any, sep: str, width: int = 96) -> list[str]:
    one = json.dumps(elem)
    if len(one) <= width or not isinstance(elem, dict):
        return [f"        {one}{sep}"]
    parts = [f"{json.dumps(k)}: {json.dumps(v)}" for k, v in elem.items()]
    lines: list[str] = []
    current = ""
    for i, part in enumerate(parts):
        piece = part + ("," if i < len(parts) - 1 else "}" + sep)
        candidate = f"{current} {piece}" if current else piece
        if current and len(candidate) > width:
            lines.append(current)
            current = piece
        else:
            current = candidate
    lines.append(current)
    return ["        {" + lines[0]] + ["         " + line for line in lines[1:]]


def render_vector(v: Vector) -> str:
    """One vector as a fenced ```` ```vector ```` block with a heading."""
    wire = v.wire()
    frame = cobs.decode(wire[:-1])
    flags = int(v.flags) if v.flags is not None else int(frame[2])
    flag_names = "ACK_REQ" if flags & Flags.ACK_REQ else "none"
    fields_lines = _fields_lines(message_to_json(v.msg))
    lines = [
        f"#### {v.name}",
        "",
        f"{v.note}. Frame {len(frame)} bytes, wire {len(wire)} bytes.",
        "",
        "```vector",
        f"name: {v.name}",
        f"type: {v.msg.TYPE.name}",
        f"version: {v.version}",
        f"seq: {v.seq}",
        f"flags: 0x{flags:02x} ({flag_names})",
        f"fields: {fields_lines[0]}".rstrip(),
        *fields_lines[1:],
        "frame:",
        *_hex_lines(frame),
        "wire:",
        *_hex_lines(wire),
        "```",
    ]
    return "\n".join(lines)


def render_vectors_section() -> str:
    """All canonical vectors, as embedded in PROTOCOL.md between the markers."""
    return "\n\n".join(render_vector(v) for v in canonical_vectors())


@dataclass(frozen=True)
class ParsedVector:
    """A vector read back from Markdown."""

    name: str
    type_name: str
    version: int
    seq: int
    flags: int
    fields: dict[str, Any]
    frame: bytes
    wire: bytes


_BLOCK = re.compile(r"^```vector\n(.*?)^```", re.DOTALL | re.MULTILINE)
_KEY = re.compile(r"^([a-z_]+):\s?(.*)$")


def parse_vectors(markdown: str) -> list[ParsedVector]:
    """Every ```` ```vector ```` block of ``markdown``.

    Raises
    ------
    ValueError
        A block misses a key or holds malformed hex / JSON (the message names the block).
    """
    out: list[ParsedVector] = []
    for n, m in enumerate(_BLOCK.finditer(markdown), 1):
        entries: dict[str, list[str]] = {}
        current: str | None = None
        for line in m.group(1).splitlines():
            km = _KEY.match(line)
            if km:
                current = km.group(1)
                entries[current] = [km.group(2)] if km.group(2) else []
            elif line.startswith(" ") and current is not None:
                entries[current].append(line.strip())
            elif line.strip():
                raise ValueError(f"vector block {n}: unexpected line {line!r}")
        where = f"vector block {n} ({''.join(entries.get('name', ['?']))})"
        try:
            out.append(
                ParsedVector(
                    name=entries["name"][0],
                    type_name=entries["type"][0],
                    version=int(entries["version"][0]),
                    seq=int(entries["seq"][0]),
                    flags=int(entries["flags"][0].split()[0], 16),
                    fields=json.loads("\n".join(entries["fields"])),
                    frame=bytes.fromhex(" ".join(entries["frame"])),
                    wire=bytes.fromhex(" ".join(entries["wire"])),
                )
            )
        except (KeyError, IndexError, ValueError) as exc:
            raise ValueError(f"{where}: {type(exc).__name__}: {exc}") from exc
    return out


def generated_section(markdown: str, begin: str, end: str) -> str:
    """The text between the ``begin`` and ``end`` markers (stripped)."""
    try:
        start = markdown.index(begin) + len(begin)
        stop = markdown.index(end, start)
    except ValueError:
        raise ValueError(f"markers {begin!r} / {end!r} not found") from None
    return markdown[start:stop].strip()


def replace_section(markdown: str, begin: str, end: str, body: str) -> str:
    """``markdown`` with the text between the markers replaced by ``body``."""
    start = markdown.index(begin) + len(begin)
    stop = markdown.index(end, start)
    return markdown[:start] + "\n\n" + body.strip() + "\n\n" + markdown[stop:]
