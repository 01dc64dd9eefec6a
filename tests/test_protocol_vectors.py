"""PROTOCOL.md against the codec: test vectors byte for byte both ways, field tables, enum tables."""

from __future__ import annotations

import json
import re
import struct
import zlib
from typing import Any

import pytest
from cobs import cobs

from firmware_proto import (
    MESSAGE_CLASSES,
    BoardState,
    FaultCode,
    Frame,
    FrameDecoder,
    Message,
    MessageType,
    NakReason,
    encode,
)
from firmware_proto.budget import render_budget_table
from firmware_proto.vectors import (
    BUDGET_BEGIN,
    BUDGET_END,
    PROTOCOL_MD,
    VECTORS_BEGIN,
    VECTORS_END,
    ParsedVector,
    canonical_vectors,
    generated_section,
    message_from_json,
    message_to_json,
    parse_vectors,
    render_vectors_section,
)

SPEC = PROTOCOL_MD.read_text(encoding="utf-8")
VECTORS = parse_vectors(SPEC)


def test_spec_has_a_vector_for_every_message_type() -> None:
    assert len({v.name for v in VECTORS}) == len(VECTORS)
    assert {v.type_name for v in VECTORS} == {t.name for t in MessageType}


@pytest.mark.parametrize("vec", VECTORS, ids=[v.name for v in VECTORS])
def test_encode_matches_spec_bytes(vec: ParsedVector) -> None:
    msg = message_from_json(vec.type_name, vec.fields)
    assert encode(msg, vec.seq, flags=vec.flags, version=vec.version) == vec.wire


@pytest.mark.parametrize("vec", VECTORS, ids=[v.name for v in VECTORS])
def test_spec_bytes_decode_to_spec_fields(vec: ParsedVector) -> None:
    assert vec.wire.count(0) == 1 and vec.wire.endswith(b"\x00")
    assert cobs.decode(vec.wire[:-1]) == vec.frame
    assert struct.unpack("<I", vec.frame[-4:])[0] == zlib.crc32(vec.frame[:-4])
    assert (vec.frame[0], vec.frame[1], vec.frame[2]) == (vec.version, MessageType[vec.type_name], vec.flags)
    assert struct.unpack_from("<I", vec.frame, 4)[0] == vec.seq
    [frame] = FrameDecoder().feed(vec.wire)
    assert isinstance(frame, Frame), frame
    assert (frame.seq, int(frame.flags), frame.version) == (vec.seq, vec.flags, vec.version)
    assert frame.msg == message_from_json(vec.type_name, vec.fields)
    assert json.loads(json.dumps(message_to_json(frame.msg))) == vec.fields


def test_spec_stream_of_all_vectors_decodes_in_order() -> None:
    stream = b"".join(v.wire for v in VECTORS)
    frames = FrameDecoder().feed(stream)
    assert [f.msg.TYPE.name for f in frames if isinstance(f, Frame)] == [v.type_name for v in VECTORS]


def test_generated_sections_are_up_to_date() -> None:
    """Regenerate with ``python tools/gen_protocol_vectors.py`` if this fails after a deliberate change."""
    assert generated_section(SPEC, VECTORS_BEGIN, VECTORS_END) == render_vectors_section()
    assert generated_section(SPEC, BUDGET_BEGIN, BUDGET_END) == render_budget_table().strip()


def test_crc_check_value_is_stated() -> None:
    assert "CRC-32/ISO-HDLC" in SPEC and "0xCBF43926" in SPEC
    assert zlib.crc32(b"123456789") == 0xCBF43926


# ----------------------------------------------------------------------------------------------
# tables of the spec against the codec


def _section(title_regex: str) -> str:
    m = re.search(rf"^###+ {title_regex}.*?$(.*?)(?=^##)", SPEC, re.MULTILINE | re.DOTALL)
    assert m, f"section {title_regex!r} not found in PROTOCOL.md"
    return m.group(1)


def test_message_summary_table_matches_codec_payload_sizes() -> None:
    rows = re.findall(r"^\| 0x([0-9a-f]{2}) \| (\w+) \| [^|]+ \| [^|]+ \| ([^|]+) \|$", SPEC, re.MULTILINE)
    assert {name for _, name, _ in rows} == {t.name for t in MessageType}
    by_type = {v.msg.TYPE: v.msg for v in canonical_vectors()}
    for code, name, size_expr in rows:
        assert int(code, 16) == MessageType[name]
        msg = by_type[MessageType[name]]
        c = getattr(msg, "n_channels", 0)
        n = getattr(msg, "n_samples", 0)
        e = len(getattr(msg, "events", ()))
        expr = size_expr.replace("C", str(c)).replace("N", str(n)).replace("E", str(e))
        expected = eval(expr, {})  # arithmetic only
        assert len(msg.pack_payload()) == expected, name


_TYPES = {"u8": "<B", "u16": "<H", "u32": "<I", "u64": "<Q", "i16": "<h", "f32": "<f"}
_ROW = re.compile(r"^\| (\d+) \| (\d+) \| (u8|u16|u32|u64|i16|f32) \| `(\w+)` \|", re.MULTILINE)
_ALIASES = {
    "fw_major": lambda m: m.firmware_version[0],
    "fw_minor": lambda m: m.firmware_version[1],
    "fw_patch": lambda m: m.firmware_version[2],
    "n_events": lambda m: len(m.events),
}


@pytest.mark.parametrize("msg_type", list(MessageType), ids=[t.name for t in MessageType])
def test_field_tables_match_the_encoded_bytes(msg_type: MessageType) -> None:
    """Every fixed-offset field in section 4 holds the message's value at that offset."""
    section = _section(rf"4\.\d+ {msg_type.name} \(0x{msg_type:02x}")
    msg = next(v.msg for v in canonical_vectors() if v.msg.TYPE is msg_type)
    frame = cobs.decode(encode(msg, 0)[:-1])
    main, _, channel_table = section.partition("| rel. |")
    rows = _ROW.findall(main)
    payload_rows = [r for r in rows if int(r[0]) >= 8]
    assert payload_rows or not msg.pack_payload(), f"{msg_type.name}: no field rows parsed"
    for offset, size, typ, name in payload_rows:
        fmt = _TYPES[typ]
        assert struct.calcsize(fmt) == int(size), (msg_type.name, name)
        got = struct.unpack_from(fmt, frame, int(offset))[0]
        assert got == _value(msg, name), (msg_type.name, name, offset)
    for rel, size, typ, name in _ROW.findall(channel_table):
        for i, ch in enumerate(msg.channels):  # type: ignore[attr-defined]
            got = struct.unpack_from(_TYPES[typ], frame, 24 + 32 * i + int(rel))[0]
            assert got == getattr(ch, name), (name, i)
            assert struct.calcsize(_TYPES[typ]) == int(size)


def _value(msg: Message, name: str) -> Any:
    if name in _ALIASES:
        return _ALIASES[name](msg)
    value = getattr(msg, name)
    return int(value) if not isinstance(value, float) else value


def test_header_table() -> None:
    rows = {name: (int(o), int(s)) for o, s, _, name in _ROW.findall(_section(r"2\.1 Header"))}
    assert rows == {"version": (0, 1), "type": (1, 1), "flags": (2, 1), "seq": (4, 4)}


@pytest.mark.parametrize(
    ("title", "enum"),
    [(r"4\.5 NAK", NakReason), (r"4\.13 FAULT", FaultCode), (r"6\.1 States", BoardState)],
)
def test_enum_tables_match(title: str, enum: type[Any]) -> None:
    rows = re.findall(r"^\| (\d+) \| `?([A-Z_]+)`? \|", _section(title), re.MULTILINE)
    assert {name: int(v) for v, name in rows} == {e.name: int(e) for e in enum}


def test_every_message_class_is_specified() -> None:
    for t in MESSAGE_CLASSES:
        assert re.search(rf"^### 4\.\d+ {t.name} \(0x{t:02x},", SPEC, re.MULTILINE), t.name
