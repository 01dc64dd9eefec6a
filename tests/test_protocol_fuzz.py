"""Fuzzing the decoder: garbage, bit flips, truncation, chunking; plus the codec benchmarks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_proto import (
    MAX_WIRE_SIZE,
    DecodeError,
    Endpoint,
    ErrorKind,
    Frame,
    FrameDecoder,
    Heartbeat,
    Message,
    Samples,
    Sensor,
    decode_frame,
    encode,
)
from firmware_proto.strategies import messages

frame_lists = st.lists(st.tuples(messages(max_samples=16), st.integers(0, 2**32 - 1)), min_size=1, max_size=6)


def wires(items: list[tuple[Message, int]]) -> list[bytes]:
    return [encode(msg, seq) for msg, seq in items]


def delivered(events: list[Frame | DecodeError]) -> list[bytes]:
    """Re-encode every delivered frame: proves what came out is a frame with a valid CRC."""
    return [encode(e.msg, e.seq, flags=e.flags, version=e.version) for e in events if isinstance(e, Frame)]


@given(st.binary(max_size=2000))
def test_random_bytes_never_raise_and_every_chunk_is_accounted(data: bytes) -> None:
    dec = FrameDecoder()
    events = dec.feed(data)
    chunks = [c for c in data.split(b"\x00")[:-1] if c]
    assert len(events) == len(chunks)  # one event per completed non-empty frame
    assert dec.stats.frames_ok + dec.stats.errors == len(events)
    for e in events:
        if isinstance(e, Frame):
            assert isinstance(
                decode_frame(encode(e.msg, e.seq, flags=e.flags, version=e.version)[:-1]), Frame
            )
    assert dec.buffered <= len(data)


@given(st.binary(max_size=300))
def test_endpoint_receive_never_raises(data: bytes) -> None:
    Endpoint().receive(data, 0.0)


@given(frame_lists, st.data())
def test_bit_flips_drop_exactly_the_hit_frames(items: list[tuple[Message, int]], data: st.DataObject) -> None:
    ws = wires(items)
    stream = bytearray(b"".join(ws))
    ends = np.cumsum([len(w) for w in ws])  # exclusive end of every frame (its delimiter at end-1)
    flips = data.draw(st.lists(st.integers(0, len(stream) * 8 - 1), max_size=4, unique=True))
    for bit in flips:
        stream[bit // 8] ^= 1 << (bit % 8)
    hit = {int(np.searchsorted(ends, bit // 8, side="right")) for bit in flips}
    # a flipped delimiter merges its frame with the next: both are lost
    merged = {i + 1 for i in hit if any(bit // 8 == ends[i] - 1 for bit in flips)}
    expected = [w for i, w in enumerate(ws) if i not in hit and i not in merged]
    events = FrameDecoder().feed(bytes(stream))
    assert delivered(events) == expected


@given(frame_lists, st.data())
def test_truncated_frames_are_dropped_and_the_rest_delivered(
    items: list[tuple[Message, int]], data: st.DataObject
) -> None:
    ws = wires(items)
    cut = data.draw(st.sets(st.integers(0, len(ws) - 1)))
    stream = b""
    for i, w in enumerate(ws):
        if i in cut:
            keep = data.draw(st.integers(0, len(w) - 2))
            stream += w[:keep] + b"\x00"
        else:
            stream += w
    dec = FrameDecoder()
    assert delivered(dec.feed(stream)) == [w for i, w in enumerate(ws) if i not in cut]


@given(frame_lists, st.lists(st.binary(max_size=64), min_size=1, max_size=6))
def test_resync_after_garbage_and_delimiter(items: list[tuple[Message, int]], garbage: list[bytes]) -> None:
    ws = wires(items)
    stream = b""
    for i, w in enumerate(ws):
        stream += garbage[i % len(garbage)] + b"\x00" + w
    dec = FrameDecoder()
    assert delivered(dec.feed(stream)) == ws
    assert dec.stats.frames_ok == len(ws)


@given(frame_lists, st.binary(max_size=100), st.lists(st.integers(0, 5000), max_size=12))
def test_any_chunking_gives_the_same_events(
    items: list[tuple[Message, int]], garbage: bytes, cuts: list[int]
) -> None:
    stream = garbage + b"\x00".join(wires(items)) + garbage + b"\x00" + wires(items)[0]
    whole_dec = FrameDecoder()
    whole = whole_dec.feed(stream)
    points = sorted({min(c, len(stream)) for c in cuts})
    pieces = [stream[a:b] for a, b in zip([0, *points], [*points, len(stream)], strict=True)]
    split_dec = FrameDecoder()
    split = [e for piece in pieces for e in split_dec.feed(piece)]
    assert delivered(split) == delivered(whole)
    assert [e.kind for e in split if isinstance(e, DecodeError)] == [
        e.kind for e in whole if isinstance(e, DecodeError)
    ]
    assert split_dec.stats == whole_dec.stats


@given(st.integers(1, 3 * MAX_WIRE_SIZE), st.lists(st.integers(1, 4000), min_size=1, max_size=8))
def test_oversize_is_bounded_and_followed_by_resync(length: int, chunk_sizes: list[int]) -> None:
    good = encode(Heartbeat(time_us=3), 9)
    stream = b"\x01" * length + b"\x00" + good
    dec = FrameDecoder()
    events: list[Frame | DecodeError] = []
    pos, i = 0, 0
    while pos < len(stream):
        step = chunk_sizes[i % len(chunk_sizes)]
        events += dec.feed(stream[pos : pos + step])
        assert dec.buffered < MAX_WIRE_SIZE
        pos, i = pos + step, i + 1
    assert delivered(events) == [good]
    errors = [e for e in events if isinstance(e, DecodeError)]
    assert len(errors) == 1
    if length + 1 > MAX_WIRE_SIZE:
        expected = ErrorKind.OVERSIZE
    else:  # 0x01 * L is valid COBS for L-1 zero bytes
        expected = ErrorKind.TOO_SHORT if length - 1 < 12 else ErrorKind.BAD_CRC
    assert errors[0].kind is expected


# ----------------------------------------------------------------------------------------------
# benchmarks (run with: python -m pytest tests/test_protocol_fuzz.py --benchmark-enable -k bench -s)

REALTIME_SAMPLES_PER_S = 3 * 100_000  # 3 channels x 100 kS/s


def _block() -> Samples:
    rng = np.random.default_rng(1)
    return Samples(123_456, rng.integers(-32768, 32768, size=(1000, 3), dtype=np.int16))


def _report(benchmark: pytest.FixtureRequest, what: str, samples: int) -> None:
    stats = getattr(benchmark, "stats", None)
    if stats is None:  # benchmarks disabled: the function ran once as a test
        return
    rate = samples / stats.stats.mean
    print(f"\n{what}: {rate / 1e6:.1f} MS/s = {rate / REALTIME_SAMPLES_PER_S:.0f}x real time (3 x 100 kS/s)")


def test_bench_encode_samples_3x1000(benchmark: pytest.FixtureRequest) -> None:
    msg = _block()
    wire = benchmark(encode, msg, 1)  # type: ignore[operator]
    assert wire.endswith(b"\x00")
    _report(benchmark, "encode SAMPLES 3x1000", 3000)


def test_bench_decode_samples_3x1000(benchmark: pytest.FixtureRequest) -> None:
    wire = encode(_block(), 1)

    def decode() -> list[Frame | DecodeError]:
        return FrameDecoder().feed(wire)

    [frame] = benchmark(decode)  # type: ignore[operator]
    assert isinstance(frame, Frame) and frame.msg == _block()
    _report(benchmark, "decode SAMPLES 3x1000", 3000)


def test_bench_decode_sensor_stream_chunked(benchmark: pytest.FixtureRequest) -> None:
    """10 SENSOR frames of 3x500 read in 4 KiB chunks, as from a serial port."""
    rng = np.random.default_rng(2)
    stream = b"".join(
        encode(Sensor(500 * k, 1, rng.integers(-32768, 32768, size=(500, 3), dtype=np.int16)), k)
        for k in range(10)
    )
    chunks = [stream[i : i + 4096] for i in range(0, len(stream), 4096)]

    def decode() -> int:
        dec = FrameDecoder()
        return sum(len(dec.feed(c)) for c in chunks)

    assert benchmark(decode) == 10  # type: ignore[operator]
    _report(benchmark, "decode SENSOR 10x(3x500) chunked", 15_000)
