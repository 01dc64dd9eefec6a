"""firmware_proto codec: framing, every message's round trip, validation, decode errors, Endpoint."""

from __future__ import annotations

import dataclasses
import struct
import zlib
from collections.abc import Sequence

import numpy as np
import pytest
from cobs import cobs
from hypothesis import given
from hypothesis import strategies as st

from firmware_proto import (
    CRC_SIZE,
    HEADER_SIZE,
    MAX_FRAME_SIZE,
    MAX_WIRE_SIZE,
    NO_INDEX,
    PROTOCOL_VERSION,
    Ack,
    Acked,
    BoardState,
    Capabilities,
    ChannelConfig,
    Configure,
    DecodeError,
    Endpoint,
    ErrorKind,
    Event,
    Fault,
    FaultCode,
    FaultFlags,
    Flags,
    Frame,
    FrameDecoder,
    Heartbeat,
    Hello,
    Message,
    MessageType,
    Nacked,
    Nak,
    NakReason,
    ProtocolError,
    RampToSafe,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
    TimedOut,
    VersionMismatchError,
    check_capabilities,
    crc32_iso_hdlc,
    decode_frame,
    encode,
    max_encoded_size,
    max_samples_per_frame,
)
from firmware_proto.strategies import capabilities, configures, messages
from firmware_proto.vectors import canonical_vectors


def raw_frame(version: int, typ: int, flags: int, seq: int, payload: bytes) -> bytes:
    """A wire frame built by hand (independent of encode): COBS(header|payload|CRC) + 0x00."""
    body = struct.pack("<BBBBI", version, typ, flags, 0, seq) + payload
    stuffed: bytes = cobs.encode(body + struct.pack("<I", zlib.crc32(body)))
    return stuffed + b"\x00"


def only(events: Sequence[Event]) -> Event:
    assert len(events) == 1, events
    return events[0]


def caps_3ch(**over: object) -> Capabilities:
    base = canonical_vectors()[1].msg
    assert isinstance(base, Capabilities)
    return dataclasses.replace(base, **over)  # type: ignore[arg-type]


def config_3ch() -> Configure:
    cfg = canonical_vectors()[2].msg
    assert isinstance(cfg, Configure)
    return cfg


# ----------------------------------------------------------------------------------------------
# framing


def test_crc_is_crc32_iso_hdlc_check_value() -> None:
    assert crc32_iso_hdlc(b"123456789") == 0xCBF43926


@pytest.mark.parametrize("n", [1, 12, 253, 254, 255, 508, 509, 4000, MAX_FRAME_SIZE])
def test_max_encoded_size_is_cobs_worst_case(n: int) -> None:
    worst = bytes((i % 255) + 1 for i in range(n))  # no zero byte: maximal stuffing
    assert len(cobs.encode(worst)) == max_encoded_size(n)
    assert len(cobs.encode(bytes(n))) <= max_encoded_size(n)
    assert max_encoded_size(MAX_FRAME_SIZE) + 1 == MAX_WIRE_SIZE == 8226


def test_header_layout_and_crc_position() -> None:
    wire = encode(Heartbeat(time_us=0x0102030405060708), seq=0xA1B2C3D4)
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    frame = cobs.decode(wire[:-1])
    assert frame[0] == PROTOCOL_VERSION
    assert frame[1] == MessageType.HEARTBEAT
    assert frame[2] == 0 and frame[3] == 0
    assert frame[4:8] == bytes.fromhex("d4c3b2a1")
    assert frame[8:16] == bytes.fromhex("0807060504030201")
    assert struct.unpack("<I", frame[-4:])[0] == zlib.crc32(frame[:-4])
    assert len(frame) == HEADER_SIZE + 8 + CRC_SIZE


def test_control_requests_default_to_ack_req() -> None:
    control: list[Message] = [Hello(), config_3ch(), Start(0), Stop(), RampToSafe()]
    for msg in control:
        assert cobs.decode(encode(msg, 1)[:-1])[2] == Flags.ACK_REQ
    others: list[Message] = [Heartbeat(), Ack(1, 3), Samples(0, np.zeros((1, 1), np.int16))]
    for msg in others:
        assert cobs.decode(encode(msg, 1)[:-1])[2] == 0
    assert cobs.decode(encode(Heartbeat(), 1, flags=Flags.ACK_REQ)[:-1])[2] == 1


@given(messages(), st.integers(0, 2**32 - 1))
def test_every_message_round_trips(msg: Message, seq: int) -> None:
    wire = encode(msg, seq)
    assert wire.count(0) == 1 and wire[-1] == 0
    frame = only(FrameDecoder().feed(wire))
    assert isinstance(frame, Frame), frame
    assert frame.msg == msg
    assert type(frame.msg) is type(msg)
    assert frame.seq == seq
    assert frame.version == PROTOCOL_VERSION
    assert frame.wire_size == len(wire)
    assert encode(frame.msg, frame.seq, flags=frame.flags) == wire


def test_samples_layout_is_interleaved_int16_le() -> None:
    codes = np.array([[1, -2], [0x1234, -32768], [32767, 0]], dtype=np.int16)
    frame = cobs.decode(encode(Samples(5, codes), 0)[:-1])
    assert struct.unpack_from("<QBBH", frame, 8) == (5, 2, 0, 3)
    assert struct.unpack_from("<6h", frame, 20) == (1, -2, 0x1234, -32768, 32767, 0)
    assert len(frame) == 20 + 12 + 4


def test_decoded_codes_are_read_only_views() -> None:
    frame = only(FrameDecoder().feed(encode(Samples(0, np.arange(6, dtype=np.int16).reshape(3, 2)), 0)))
    assert isinstance(frame, Frame) and isinstance(frame.msg, Samples)
    assert frame.msg.codes.dtype == np.int16
    assert frame.msg.codes.shape == (3, 2)
    with pytest.raises(ValueError, match="read-only"):
        frame.msg.codes[0, 0] = 1


def test_samples_accepts_wider_integers_in_range_and_keeps_caller_array_writable() -> None:
    src = np.array([[1, 2], [-3, 4]], dtype=np.int64)
    msg = Samples(0, src)  # type: ignore[arg-type]
    assert msg.codes.dtype == np.int16
    src[0, 0] = 99  # converted copy: the message does not change
    assert msg.codes[0, 0] == 1
    arr16 = np.zeros((2, 2), np.int16)
    Samples(0, arr16)
    arr16[0, 0] = 1  # the caller's own array stays writable


@pytest.mark.parametrize(
    ("codes", "match"),
    [
        (np.array([[40000]]), "int16 range"),
        (np.array([[0.5]]), "integer codes"),
        (np.zeros((0, 3), np.int16), "no samples"),
        (np.zeros((2, 9), np.int16), "9 channels"),
        (np.zeros(4, np.int16), "2-D"),
    ],
)
def test_samples_rejects_bad_codes(codes: np.ndarray, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        Samples(0, codes)


def test_sensor_indices_and_validation() -> None:
    s = Sensor(100, 3, np.zeros((4, 2), np.int16))
    assert s.indices.tolist() == [100, 103, 106, 109]
    with pytest.raises(ProtocolError, match="stride"):
        Sensor(0, 0, np.zeros((1, 1), np.int16))
    with pytest.raises(ProtocolError, match="last sample index"):
        Samples(NO_INDEX - 1, np.zeros((2, 1), np.int16))


@pytest.mark.parametrize(
    ("factory", "match"),
    [
        (lambda: Hello(protocol_version=70000), r"Hello.protocol_version"),
        (lambda: Ack(-1, 3), r"Ack.acked_seq"),
        (lambda: Start(2**64), r"Start.start_index"),
        (lambda: Nak(1, 3, 99), r"Nak.reason"),  # type: ignore[arg-type]
        (lambda: Fault(42), r"Fault.code"),  # type: ignore[arg-type]
        (lambda: Heartbeat(time_us=1.5), r"expected an integer"),  # type: ignore[arg-type]
        (lambda: ChannelConfig(float("nan"), 0, 0, 0, 0, 1, 1, 0), r"dac_v_per_code.*finite"),
        (lambda: ChannelConfig(1e39, 0, 0, 0, 0, 1, 1, 0), r"finite float32"),
        (lambda: ChannelConfig(1.0, 0, 40000, 0, 0, 1, 1, 0), r"code_min"),
        (lambda: Status(9, 0, 0, 0, 0), r"Status.state"),  # type: ignore[arg-type]
        (lambda: caps_3ch(dac_bits=17), r"dac_bits"),
        (lambda: caps_3ch(amplifier_ranges_v=((1.0, 1.0),)), r"v_min"),
        (lambda: caps_3ch(max_samples_per_frame=5000), r"max_samples_per_frame"),
        (lambda: caps_3ch(sample_rate_min_hz=10**6), r"sample_rate_min_hz"),
        (lambda: Configure(1, 1, 1, 1, ()), r"0 channels"),
    ],
)
def test_constructors_name_the_bad_field(factory: object, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        factory()  # type: ignore[operator]


def test_floats_are_rounded_to_float32_at_construction() -> None:
    ch = ChannelConfig(0.1, 0.0, -1, 1, 0, 1.0, 0.1, 0.0)
    assert ch.dac_v_per_code == struct.unpack("<f", struct.pack("<f", 0.1))[0]
    assert ch.dac_v_per_code != 0.1


def test_encode_rejects_oversize_frames_and_max_samples_fit() -> None:
    for n_ch in (1, 3, 8):
        n = max_samples_per_frame(n_ch)
        wire = encode(Samples(0, np.zeros((n, n_ch), np.int16)), 0)
        assert len(cobs.decode(wire[:-1])) <= MAX_FRAME_SIZE
        with pytest.raises(ProtocolError, match="exceeds MAX_FRAME_SIZE"):
            encode(Samples(0, np.zeros((n + 1, n_ch), np.int16)), 0)
        n_s = max_samples_per_frame(n_ch, MessageType.SENSOR)
        encode(Sensor(0, 1, np.zeros((n_s, n_ch), np.int16)), 0)
        with pytest.raises(ProtocolError):
            encode(Sensor(0, 1, np.zeros((n_s + 1, n_ch), np.int16)), 0)
    with pytest.raises(ProtocolError, match="seq"):
        encode(Heartbeat(), 2**32)


# ----------------------------------------------------------------------------------------------
# decode errors


def kind_of(wire: bytes) -> ErrorKind:
    ev = only(FrameDecoder().feed(wire))
    assert isinstance(ev, DecodeError), ev
    return ev.kind


def test_error_kinds() -> None:
    good = cobs.decode(encode(Ack(7, 3), 9)[:-1])
    assert kind_of(b"\x05ab\x00") is ErrorKind.BAD_COBS
    assert kind_of(cobs.encode(good[:11]) + b"\x00") is ErrorKind.TOO_SHORT
    flipped = bytearray(good)
    flipped[9] ^= 0x10
    assert kind_of(cobs.encode(bytes(flipped)) + b"\x00") is ErrorKind.BAD_CRC
    assert kind_of(raw_frame(1, 0x7F, 1, 5, b"")) is ErrorKind.UNKNOWN_TYPE
    assert kind_of(raw_frame(2, MessageType.STATUS, 0, 5, bytes(56))) is ErrorKind.BAD_VERSION
    assert kind_of(raw_frame(1, MessageType.ACK, 0, 5, bytes(9))) is ErrorKind.BAD_LENGTH
    assert kind_of(raw_frame(1, MessageType.NAK, 0, 5, struct.pack("<IBBHI", 1, 3, 99, 0, 0))) is (
        ErrorKind.BAD_VALUE
    )
    assert kind_of(raw_frame(1, MessageType.SAMPLES, 0, 5, struct.pack("<QBBH", 0, 2, 0, 0))) is (
        ErrorKind.BAD_VALUE
    )
    assert kind_of(raw_frame(1, MessageType.SAMPLES, 0, 5, struct.pack("<QBBH", 0, 2, 0, 2) + bytes(6))) is (
        ErrorKind.BAD_LENGTH
    )
    assert kind_of(b"\x01" * (MAX_WIRE_SIZE + 5) + b"\x00") is ErrorKind.OVERSIZE


def test_valid_crc_errors_carry_the_header_for_a_nak() -> None:
    ev = only(FrameDecoder().feed(raw_frame(1, 0x7F, Flags.ACK_REQ, 1234, b"xyz")))
    assert isinstance(ev, DecodeError)
    assert (ev.seq, ev.msg_type, ev.version, ev.ack_requested) == (1234, 0x7F, 1, True)
    bad = bytearray(cobs.decode(encode(Start(0), 3)[:-1]))
    bad[-1] ^= 1
    ev = only(FrameDecoder().feed(cobs.encode(bytes(bad)) + b"\x00"))
    assert isinstance(ev, DecodeError) and ev.seq is None and not ev.ack_requested


def test_foreign_version_hello_and_nak_still_decode() -> None:
    frame = only(FrameDecoder().feed(encode(Hello(2, 7), 0, version=2)))
    assert isinstance(frame, Frame) and frame.version == 2 and frame.msg == Hello(2, 7)
    frame = only(FrameDecoder().feed(encode(Nak(0, 1, NakReason.VERSION_MISMATCH, 3), 0, version=3)))
    assert isinstance(frame, Frame) and frame.version == 3


def test_stats_count_by_kind_and_empty_frames_are_ignored() -> None:
    dec = FrameDecoder()
    stream = b"\x00\x00" + encode(Heartbeat(), 1) + b"\x05ab\x00" + b"\x00" + raw_frame(1, 0x7F, 0, 1, b"")
    events = dec.feed(stream)
    assert [type(e).__name__ for e in events] == ["Frame", "DecodeError", "DecodeError"]
    assert dec.stats.frames_ok == 1 and dec.stats.bad_cobs == 1 and dec.stats.unknown_type == 1
    assert dec.stats.errors == 2 and dec.stats.bytes_in == len(stream)
    assert dec.stats.by_type == {int(MessageType.HEARTBEAT): 1}


def test_decode_frame_single() -> None:
    wire = encode(Stop(5), 1)
    frame = decode_frame(wire[:-1])
    assert isinstance(frame, Frame) and frame.msg == Stop(5) and frame.ack_requested


# ----------------------------------------------------------------------------------------------
# semantic checks shared by host and board


def test_configure_check_accepts_the_canonical_config() -> None:
    assert config_3ch().check(caps_3ch()) is None


def _replace_channel(cfg: Configure, i: int, **over: object) -> Configure:
    chans = list(cfg.channels)
    chans[i] = dataclasses.replace(chans[i], **over)  # type: ignore[arg-type]
    return dataclasses.replace(cfg, channels=tuple(chans))


@pytest.mark.parametrize(
    ("mutate", "reason", "field_fmt", "value"),
    [
        (lambda c: Configure(300_000, 500, 10, 1, c.channels), NakReason.UNSUPPORTED, "<I", 300_000),
        (lambda c: Configure(100_000, 5, 10, 1, c.channels), NakReason.BAD_VALUE, "<I", 5),
        (lambda c: Configure(100_000, 500, 0, 1, c.channels), NakReason.BAD_VALUE, "<H", 0),
        (lambda c: Configure(100_000, 500, 10, 0, c.channels), NakReason.BAD_VALUE, "<H", 0),
        (lambda c: Configure(100_000, 500, 10, 1, c.channels[:2]), NakReason.BAD_VALUE, "<B", 2),
        (lambda c: _replace_channel(c, 1, code_min=30584), NakReason.BAD_VALUE, "<h", 30584),
        (lambda c: _replace_channel(c, 2, dac_offset_v=100.0), NakReason.BAD_VALUE, "<h", 28672),
        (lambda c: _replace_channel(c, 2, safe_code=30000), NakReason.BAD_VALUE, "<h", 30000),
        (lambda c: _replace_channel(c, 0, ramp_v_per_s=0.0), NakReason.BAD_VALUE, "<f", 0.0),
        (lambda c: _replace_channel(c, 2, dac_v_per_code=-1.0), NakReason.BAD_VALUE, "<f", -1.0),
        (lambda c: _replace_channel(c, 0, adc_um_per_code=0.0), NakReason.BAD_VALUE, "<f", 0.0),
    ],
)
def test_configure_check_points_at_the_offending_field(
    mutate: object, reason: NakReason, field_fmt: str, value: float
) -> None:
    cfg = mutate(config_3ch())  # type: ignore[operator]
    result = cfg.check(caps_3ch())
    assert result is not None and result[0] == reason
    frame = cobs.decode(encode(cfg, 0)[:-1])
    assert struct.unpack_from(field_fmt, frame, result[1])[0] == value


@given(configures(), capabilities())
def test_configure_check_never_raises_and_points_into_the_frame(cfg: Configure, caps: Capabilities) -> None:
    result = cfg.check(caps)
    if result is not None:
        reason, offset = result
        assert reason in (NakReason.BAD_VALUE, NakReason.UNSUPPORTED)
        assert HEADER_SIZE <= offset < len(cobs.decode(encode(cfg, 0)[:-1])) - CRC_SIZE


def test_configure_check_clock_divider() -> None:
    caps = caps_3ch(sample_clock_hz=1_000_000)
    assert config_3ch().check(caps) is None
    odd = Configure(30_000, 500, 10, 1, config_3ch().channels)
    assert odd.check(caps) == (NakReason.UNSUPPORTED, 8)


@given(
    st.floats(-200, 0),
    st.floats(0.5, 200),
    st.floats(1e-3, 1e-2),
    st.floats(-5, 5),
)
def test_channel_from_volts_rounds_limits_inwards(
    lo: float, span: float, scale: float, offset: float
) -> None:
    hi = lo + span
    try:
        ch = ChannelConfig.from_volts(
            v_min=lo,
            v_max=hi,
            safe_v=0.0,
            dac_v_per_code=scale,
            dac_offset_v=offset,
            ramp_v_per_s=10,
            adc_um_per_code=1e-3,
            adc_offset_um=0,
        )
    except ProtocolError as exc:
        assert "int16" in str(exc) or "code" in str(exc)
        return
    assert lo <= ch.v_min <= ch.v_max <= hi
    assert ch.dac_offset_v + ch.dac_v_per_code * (ch.code_min - 1) < lo or ch.code_min == -32768
    assert ch.dac_offset_v + ch.dac_v_per_code * (ch.code_max + 1) > hi or ch.code_max == 32767
    assert ch.code_min <= ch.safe_code <= ch.code_max


def test_status_credit_limit_and_fault_flags() -> None:
    st_ = Status(BoardState.RUNNING, FaultFlags.of(FaultCode.WATCHDOG), 100, 50, 30)
    assert st_.credit_limit == 130
    assert st_.fault_flags == FaultFlags.WATCHDOG == 1 << 3


def test_nak_errors() -> None:
    err = Nak(1, MessageType.HELLO, NakReason.VERSION_MISMATCH, 2).to_error()
    assert isinstance(err, VersionMismatchError) and "version 2" in str(err)
    err = Nak(4, MessageType.CONFIGURE, NakReason.BAD_VALUE, 64).to_error()
    assert type(err) is ProtocolError and "CONFIGURE" in str(err) and "offset 64" in str(err)
    check_capabilities(caps_3ch())
    with pytest.raises(VersionMismatchError):
        check_capabilities(caps_3ch(protocol_version=2))


# ----------------------------------------------------------------------------------------------
# Endpoint


def test_endpoint_retransmits_then_times_out() -> None:
    host = Endpoint(ack_timeout_s=0.1, max_retries=2)
    seq = host.send(Start(0), now=0.0)
    first = host.data_to_send()
    assert host.next_deadline() == pytest.approx(0.1)
    assert host.poll(0.05) == [] and host.data_to_send() == b""
    assert host.poll(0.1) == [] and host.data_to_send() == first  # byte-identical retransmission
    assert host.poll(0.2) == [] and host.data_to_send() == first
    events = host.poll(0.31)
    assert events == [TimedOut(seq, Start(0), 3)]
    assert host.pending == {} and host.next_deadline() is None
    assert host.stats.retransmits == 2 and host.stats.timeouts == 1


def test_endpoint_matches_replies_and_ignores_strays() -> None:
    host, board = Endpoint(), Endpoint(initial_seq=1000)
    seq = host.send(Hello(session_id=5), 0.0)
    [req] = board.receive(host.data_to_send(), 0.0)
    assert isinstance(req, Frame) and req.ack_requested and board.last_rx_time == 0.0
    board.reply(req, caps_3ch(reply_to_seq=req.seq))
    board.ack(req)  # a stray extra reply: HELLO is answered by CAPABILITIES
    events = host.receive(board.data_to_send(), 0.01)
    assert isinstance(events[0], Acked) and events[0].seq == seq
    assert isinstance(events[0].reply, Capabilities)
    assert isinstance(events[1], Frame) and isinstance(events[1].msg, Ack)
    assert host.stats.stray_replies == 1 and host.pending == {}


def test_endpoint_answers_retransmitted_request_from_cache() -> None:
    host, board = Endpoint(), Endpoint()
    host.send(Hello(), 0.0)
    [hello] = board.receive(host.data_to_send(), 0.0)
    assert isinstance(hello, Frame)
    board.reply(hello, caps_3ch(reply_to_seq=hello.seq))
    host.receive(board.data_to_send(), 0.0)
    seq = host.send(config_3ch(), 0.0)
    request = host.data_to_send()
    [cfg] = board.receive(request, 0.0)
    assert isinstance(cfg, Frame)
    board.ack(cfg)
    lost_ack = board.data_to_send()  # lost on the way
    host.poll(0.2)
    assert board.receive(host.data_to_send(), 0.2) == []  # not delivered twice
    assert board.stats.duplicate_requests == 1
    assert board.data_to_send() == lost_ack
    [ev] = host.receive(lost_ack, 0.21)
    assert isinstance(ev, Acked) and ev.seq == seq


def test_endpoint_hello_clears_reply_cache() -> None:
    board = Endpoint()
    req = only(board.receive(encode(Start(0), 1), 0.0))
    assert isinstance(req, Frame)
    board.nak(req, NakReason.BAD_STATE, 0)
    board.data_to_send()
    assert board.receive(encode(Start(0), 1), 0.1) == []  # answered from cache
    board.receive(encode(Hello(), 0), 0.2)
    assert len(board.receive(encode(Start(0), 1), 0.3)) == 1  # new session: processed again


def test_endpoint_version_mismatch_nak() -> None:
    host, board = Endpoint(), Endpoint()
    host.send(Hello(), 0.0)
    wire = host.data_to_send()
    req = only(board.receive(wire, 0.0))
    assert isinstance(req, Frame)
    board.nak(req, NakReason.VERSION_MISMATCH, 2)
    [ev] = host.receive(board.data_to_send(), 0.0)
    assert isinstance(ev, Nacked)
    assert isinstance(ev.error(), VersionMismatchError)


def test_endpoint_can_nak_a_decode_error() -> None:
    board = Endpoint()
    [ev] = board.receive(raw_frame(1, 0x7E, Flags.ACK_REQ, 77, b""), 0.0)
    assert isinstance(ev, DecodeError)
    board.nak(ev, NakReason.UNKNOWN_TYPE)
    [frame] = FrameDecoder().feed(board.data_to_send())
    assert isinstance(frame, Frame) and frame.msg == Nak(77, 0x7E, NakReason.UNKNOWN_TYPE, 0)
    [bad] = board.receive(b"\x05ab\x00", 0.0)
    assert isinstance(bad, DecodeError)
    with pytest.raises(ProtocolError, match="header is unknown"):
        board.nak(bad, NakReason.BAD_LENGTH)


# ----------------------------------------------------------------------------------------------
# two endpoints wired together in memory: a minimal board and a minimal host


class MiniBoard:
    """The board rules of PROTOCOL.md sections 5-7, just enough for an in-memory session."""

    def __init__(self, caps: Capabilities) -> None:
        self.ep = Endpoint(initial_seq=500)
        self.caps = caps
        self.state = BoardState.UNCONFIGURED
        self.cfg: Configure | None = None
        self.fifo = np.zeros((0, caps.n_channels), np.int16)
        self.write_index = 0
        self.last_played = NO_INDEX
        self.stop_after = NO_INDEX
        self.played: list[np.ndarray] = []
        self.counters = dict(crc_errors=0, frames_dropped=0, index_gaps=0, overflows=0, underruns=0)
        self.hello_seen = False

    def handle(self, data: bytes, now: float) -> None:
        for ev in self.ep.receive(data, now):
            if isinstance(ev, DecodeError):
                self.counters["frames_dropped"] += 1
                self.counters["crc_errors"] += ev.kind is ErrorKind.BAD_CRC
            elif isinstance(ev, Frame):
                self._frame(ev)
            else:
                raise AssertionError(f"board got a reply event {ev}")

    def _frame(self, fr: Frame) -> None:
        msg = fr.msg
        if isinstance(msg, Hello):
            self.hello_seen = True
            if msg.protocol_version != PROTOCOL_VERSION:
                self.ep.nak(fr, NakReason.VERSION_MISMATCH, PROTOCOL_VERSION)
            else:
                self.ep.reply(fr, dataclasses.replace(self.caps, reply_to_seq=fr.seq))
        elif isinstance(msg, Configure):
            bad = msg.check(self.caps)
            if bad is not None:
                self.ep.nak(fr, *bad)
            elif self.state not in (BoardState.UNCONFIGURED, BoardState.IDLE):
                self.ep.nak(fr, NakReason.BAD_STATE, self.state)
            else:
                self.cfg, self.state = msg, BoardState.IDLE
                self.ep.ack(fr)
        elif isinstance(msg, Start):
            if self.state is not BoardState.IDLE:
                self.ep.nak(fr, NakReason.BAD_STATE, self.state)
                return
            self.fifo = self.fifo[:0]
            self.write_index, self.start, self.prefill = msg.start_index, msg.start_index, msg.prefill_samples
            self.state = BoardState.ARMED
            self.ep.ack(fr)
        elif isinstance(msg, Stop):
            self.stop_after = msg.stop_after_index
            self.ep.ack(fr)
        elif isinstance(msg, Samples):
            self._samples(msg)

    def _samples(self, msg: Samples) -> None:
        w = self.write_index
        limit = w + self.caps.fifo_depth_samples - len(self.fifo)
        f, n = msg.first_index, msg.n_samples
        if self.state not in (BoardState.ARMED, BoardState.RUNNING) or f + n <= w:
            self.counters["frames_dropped"] += 1
        elif f > w:
            self.counters["index_gaps"] += 1
            self.counters["frames_dropped"] += 1
        elif f + n > limit:
            self.counters["overflows"] += 1
            self.counters["frames_dropped"] += 1
        else:
            self.fifo = np.concatenate([self.fifo, msg.codes[w - f :]])
            self.write_index = f + n
            if self.state is BoardState.ARMED and len(self.fifo) >= max(self.prefill, 1):
                self.state = BoardState.RUNNING

    def tick(self, n: int) -> None:
        if self.state is not BoardState.RUNNING:
            return
        first = self.start if self.last_played == NO_INDEX else self.last_played + 1
        if self.stop_after != NO_INDEX:
            n = min(n, self.stop_after - first + 1)
        take = min(n, len(self.fifo))
        if take:
            rows, self.fifo = self.fifo[:take], self.fifo[take:]
            self.played.append(rows)
            self.last_played = first + take - 1
            self.ep.send(Sensor(first, 1, rows // 2), 0.0)
        if self.last_played == self.stop_after:
            self.state, self.fifo = BoardState.IDLE, self.fifo[:0]
        elif take < n:
            self.counters["underruns"] += 1
            self.state = BoardState.IDLE
            self.ep.send(Fault(FaultCode.UNDERRUN, index=self.last_played), 0.0)

    def status(self) -> Status:
        free = self.caps.fifo_depth_samples - len(self.fifo)
        return Status(self.state, FaultFlags.NONE, self.write_index, self.last_played, free, **self.counters)


def test_two_endpoints_session_with_a_lost_samples_frame_and_a_lost_ack() -> None:
    caps = caps_3ch(fifo_depth_samples=1000, max_samples_per_frame=100)
    board = MiniBoard(caps)
    host = Endpoint()
    now = 0.0

    def exchange(drop_host_bytes: bool = False, drop_board_bytes: bool = False) -> list[object]:
        data = host.data_to_send()
        if not drop_host_bytes:
            board.handle(data, now)
        back = board.ep.data_to_send()
        return [] if drop_board_bytes else list(host.receive(back, now))

    # handshake
    host.send(Hello(session_id=42), now)
    [ev] = exchange()
    assert isinstance(ev, Acked) and isinstance(ev.reply, Capabilities)
    check_capabilities(ev.reply)
    # configure; its ACK is lost once: the retransmission is answered from the cache
    host.send(config_3ch(), now)
    assert exchange(drop_board_bytes=True) == []
    now += 0.15
    assert host.poll(now) == []
    [ev] = exchange()
    assert (
        isinstance(ev, Acked) and isinstance(ev.reply, Ack) and ev.reply.acked_type == MessageType.CONFIGURE
    )
    assert board.ep.stats.duplicate_requests == 1 and board.state is BoardState.IDLE
    # stream 2000 samples, 100 per frame, the board playing 100 per round; the 5th frame is lost
    total, per_frame = 2000, 100
    ramp = (np.arange(total) * 37 % 20000 - 10000).astype(np.int16)
    codes = np.stack([ramp, -ramp, ramp // 3], axis=1)
    host.send(Start(0, prefill_samples=300), now)
    [ev] = exchange()
    assert isinstance(ev, Acked)
    host.send(Stop(total - 1), now)
    [ev] = exchange()
    assert isinstance(ev, Acked)
    next_index, credit, gaps_seen, sent_frames = 0, caps.fifo_depth_samples, 0, 0
    sensor: dict[int, np.ndarray] = {}
    for _round in range(200):
        now += 0.001
        for _ in range(3):
            if next_index >= min(credit, total):
                break
            n = min(per_frame, total - next_index)
            host.send(Samples(next_index, codes[next_index : next_index + n]), now)
            next_index += n
            sent_frames += 1
            data = host.data_to_send()
            if sent_frames != 5:
                board.handle(data, now)
        board.tick(100)
        board.ep.send(board.status(), now)
        for ev in host.receive(board.ep.data_to_send(), now):
            assert isinstance(ev, Frame), ev
            if isinstance(ev.msg, Status):
                credit = ev.msg.credit_limit
                if ev.msg.index_gaps > gaps_seen:  # go-back-N from the board's write_index
                    gaps_seen, next_index = ev.msg.index_gaps, ev.msg.write_index
            elif isinstance(ev.msg, Sensor):
                for i, row in zip(ev.msg.indices.tolist(), ev.msg.codes, strict=True):
                    sensor[i] = row
            else:
                raise AssertionError(f"unexpected {ev.msg}")
        if board.state is BoardState.IDLE and board.last_played == total - 1:
            break
    else:
        raise AssertionError(f"did not finish: board {board.state.name}, last played {board.last_played}")
    played = np.concatenate(board.played)
    np.testing.assert_array_equal(played, codes)  # every sample once, in order, despite the loss
    assert sorted(sensor) == list(range(total))
    np.testing.assert_array_equal(np.array([sensor[i] for i in range(total)]), codes // 2)
    assert board.counters["index_gaps"] >= 1 and board.counters["underruns"] == 0
    assert host.decoder.stats.errors == 0 and board.ep.decoder.stats.errors == 0
    assert host.pending == {}
