"""The C reference firmware (firmware_proto/c): its codec against PROTOCOL.md's vectors, and a
byte-level fuzz of its input (AddressSanitizer + UBSan) that must find no crash, no hang and no
sample applied outside the configured limits."""

from __future__ import annotations

import struct
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_proto import encode
from firmware_proto.strategies import messages
from firmware_proto.vectors import PROTOCOL_MD, parse_vectors
from hil_sim.firmware import build_firmware, missing_tools

VECTOR_CHECKS = ("cobs-encode", "cobs-decode", "frame-checks", "crc")
REPLY_CHECKS = {
    "CAPABILITIES": "reply-to-HELLO",
    "ACK": "reply-to-CONFIGURE",
    "NAK_VERSION_MISMATCH": "reply-to-HELLO_V2",
    "NAK_BAD_VALUE": "reply-to-CONFIGURE",
    "CAPABILITIES_SYNC": "reply-to-HELLO",
    "SYNC": "outputs-follow-events",
}


@pytest.fixture(scope="module")
def tools(tmp_path_factory: pytest.TempPathFactory) -> Path:
    missing = missing_tools("make", "cc")
    if missing:
        pytest.skip(f"the C firmware tools need {', '.join(missing)} (apt-get install build-essential)")
    out = build_firmware(tmp_path_factory.mktemp("fw-tools"), "tools")
    return out / "host"


@pytest.fixture(scope="module")
def fuzzer(tools: Path) -> Path:
    """The fuzz harness with sanitizers when the compiler has them, else the plain build."""
    try:
        build_firmware(tools.parent, "fuzz")
    except OSError:
        return tools / "fw-fuzz"
    return tools / "fw-fuzz-asan"


def _run(
    binary: Path, args: list[str], stdin: bytes = b"", timeout: float = 120.0
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(binary), *args],
        input=stdin.decode("latin-1"),
        capture_output=True,
        text=True,
        encoding="latin-1",
        timeout=timeout,
        check=False,
    )


def test_c_codec_and_core_reproduce_the_protocol_vectors(tools: Path) -> None:
    vectors = parse_vectors(PROTOCOL_MD.read_text(encoding="utf-8"))
    lines = "".join(f"{v.name} {v.frame.hex()} {v.wire.hex()}\n" for v in vectors).encode()
    done = _run(tools / "fw-vectors", [], lines)
    assert done.returncode == 0, done.stdout + done.stderr
    ok = {tuple(line.split()[1:3]) for line in done.stdout.splitlines() if line.startswith("ok ")}
    assert ("CRC", "check-value") in ok
    for v in vectors:
        for check in VECTOR_CHECKS:
            assert (v.name, check) in ok, (v.name, check)
    for name, check in REPLY_CHECKS.items():
        assert (name, check) in ok, (name, check)


def test_fuzz_random_frames_under_sanitizers(fuzzer: Path) -> None:
    done = _run(fuzzer, ["--random", "3000", "--seed", "1"])
    assert done.returncode == 0, done.stderr[-2000:]
    assert "violations 0" in done.stdout


def test_the_fuzz_catches_a_firmware_without_its_clamp(tools: Path) -> None:
    build_firmware(tools.parent, str(tools / "fw-fuzz-mutant"))
    done = _run(tools / "fw-fuzz-mutant", ["--random", "3000", "--seed", "1"])
    assert done.returncode != 0 and "sample outside the limits" in done.stderr


def _case(chunks: list[tuple[int, bytes]]) -> bytes:
    out = bytearray()
    for op, data in chunks:
        if op == 0:
            for i in range(0, len(data), 255):
                part = data[i : i + 255]
                out += bytes((0, len(part))) + part
        else:
            out += bytes((op, data[0] if data else 0))
    return struct.pack("<I", len(out)) + bytes(out)


def _wire_messages() -> st.SearchStrategy[bytes]:
    return st.builds(lambda m, seq: encode(m, seq), messages(max_samples=16), st.integers(0, 2**32 - 1))


@st.composite
def adversarial_streams(draw: st.DrawFn) -> list[tuple[int, bytes]]:
    """Valid frames, cut, bit-flipped, concatenated without delimiters, mixed with time and ticks."""
    chunks: list[tuple[int, bytes]] = []
    for _ in range(draw(st.integers(1, 12))):
        kind = draw(st.sampled_from(("frame", "flip", "cut", "raw", "nodelim", "tick", "time")))
        if kind in ("tick", "time"):
            chunks.append((2 if kind == "tick" else 1, bytes([draw(st.integers(0, 255))])))
            continue
        wire = bytearray(draw(_wire_messages()))
        if kind == "flip":
            pos = draw(st.integers(0, len(wire) - 1))
            wire[pos] ^= 1 << draw(st.integers(0, 7))
        elif kind == "cut":
            wire = wire[: draw(st.integers(0, len(wire)))]
        elif kind == "raw":
            wire = bytearray(draw(st.binary(min_size=1, max_size=600)))
        elif kind == "nodelim":
            wire = wire[:-1]
        chunks.append((0, bytes(wire)))
    return chunks


@settings(max_examples=30)
@given(st.lists(adversarial_streams(), min_size=1, max_size=8))
def test_fuzz_adversarial_frames_through_the_input(
    fuzzer: Path, cases: list[list[tuple[int, bytes]]]
) -> None:
    done = _run(fuzzer, [], b"".join(_case(c) for c in cases), timeout=60.0)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"cases {len(cases)} " in done.stdout and "violations 0" in done.stdout


@pytest.mark.slow
def test_fuzz_random_frames_long(fuzzer: Path) -> None:
    done = _run(fuzzer, ["--random", "300000", "--seed", "7"], timeout=1800.0)
    assert done.returncode == 0, done.stderr[-2000:]
