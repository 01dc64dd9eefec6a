"""Transports chosen by URL: parsing, real byte streams (loop://, TCP, Unix socket, pty), error mapping."""

from __future__ import annotations

import contextlib
import errno
import os
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial

from firmware_proto import FrameDecoder, Heartbeat, encode
from piezod.errors import ConfigError, LinkClosedError, LinkError, LinkTimeoutError
from piezod.link.transport import (
    FdTransport,
    PyserialTransport,
    map_error,
    open_transport,
    parse_url,
    socket_transport,
)

# -- URL parsing --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "kind", "target", "options"),
    [
        ("/dev/ttyACM0", "serial", "/dev/ttyACM0", {}),
        ("/dev/ttyUSB0?baudrate=12000000", "serial", "/dev/ttyUSB0", {"baudrate": "12000000"}),
        ("board.pty", "serial", "board.pty", {}),
        ("socket://localhost:7000", "pyserial", "socket://localhost:7000", {}),
        ("loop://", "pyserial", "loop://", {}),
        ("unix:///run/sim/usb.sock", "unix", "/run/sim/usb.sock", {}),
        ("usb://1209:7A01", "usb", "1209:7a01", {}),
        (
            "usb://1209:7a01?serial=AB12&interface=1&backend=simsock:/tmp/x.sock",
            "usb",
            "1209:7a01",
            {"serial": "AB12", "interface": "1", "backend": "simsock:/tmp/x.sock"},
        ),
    ],
)
def test_parse_url(url: str, kind: str, target: str, options: dict[str, str]) -> None:
    spec = parse_url(url)
    assert (spec.kind, spec.target, dict(spec.options), spec.raw) == (kind, target, options, url)


@pytest.mark.parametrize(
    ("url", "needle"),
    [
        ("", "empty"),
        ("   ", "empty"),
        ("usb://12g9:7a01", "hexadecimal"),
        ("usb://1209", "hexadecimal"),
        ("usb://1209:7a01?colour=red", "unknown option 'colour'"),
        ("usb://1209:7a01?interface=x", "interface must be a number"),
        ("/dev/ttyUSB0?baudrate=fast", "baudrate must be a positive integer"),
        ("/dev/ttyUSB0?parity=N", "unknown option 'parity'"),
        ("unix://", "no socket path"),
    ],
)
def test_parse_url_errors_name_the_problem(url: str, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        parse_url(url)


# -- error mapping ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("exc", "kind"),
    [
        (OSError(errno.EIO, "Input/output error"), LinkClosedError),
        (OSError(errno.ENOENT, "No such file"), LinkClosedError),
        (OSError(errno.ECONNRESET, "reset"), LinkClosedError),
        (OSError(errno.EACCES, "Permission denied"), LinkError),
        (TimeoutError("slow"), LinkTimeoutError),
        (serial.SerialTimeoutException("Write timeout"), LinkTimeoutError),
        (serial.SerialException("device reports readiness to read but returned no data"), LinkClosedError),
        (serial.SerialException("read failed: [Errno 5] Input/output error"), LinkClosedError),
        (serial.SerialException("something odd"), LinkError),
    ],
)
def test_map_error(exc: BaseException, kind: type[LinkError]) -> None:
    err = map_error(exc, "/dev/x", "read")
    assert type(err) is kind
    assert str(err).startswith("/dev/x: read failed")


def test_map_error_follows_the_cause_chain() -> None:
    try:
        try:
            raise OSError(errno.ENXIO, "No such device or address")
        except OSError as inner:
            raise RuntimeError("wrapped") from inner
    except RuntimeError as outer:
        assert isinstance(map_error(outer, "u", "open"), LinkClosedError)


# -- real byte streams ----------------------------------------------------------------------------


def _frames(n: int) -> bytes:
    return b"".join(encode(Heartbeat(time_us=i), seq=i) for i in range(n))


def _read_all(t: object, want: int) -> bytes:
    assert hasattr(t, "read")
    got = b""
    for _ in range(200):
        got += t.read()
        if len(got) >= want:
            break
    return got


def test_loop_url_carries_frames() -> None:
    data = _frames(50)
    with open_transport("loop://", read_timeout_s=0.01) as t:
        assert isinstance(t, PyserialTransport)
        t.write(data)
        got = _read_all(t, len(data))
    frames = FrameDecoder().feed(got)
    assert [f.msg.time_us for f in frames] == list(range(50))  # type: ignore[union-attr]


def test_read_returns_empty_after_the_timeout() -> None:
    with open_transport("loop://", read_timeout_s=0.01) as t:
        assert t.read() == b""


def test_socket_url_and_peer_close() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    accepted: list[socket.socket] = []
    th = threading.Thread(target=lambda: accepted.append(server.accept()[0]))
    th.start()
    t = open_transport(f"socket://127.0.0.1:{port}", read_timeout_s=0.02)
    th.join(5)
    peer = accepted[0]
    try:
        t.write(b"hello")
        assert peer.recv(100) == b"hello"
        peer.sendall(b"\x01\x02\x00")
        assert _read_all(t, 3) == b"\x01\x02\x00"
        peer.close()
        with pytest.raises(LinkClosedError):
            for _ in range(100):
                t.read()
    finally:
        t.close()
        server.close()


def test_socket_url_refused_is_closed() -> None:
    probe = socket.create_server(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    with pytest.raises(LinkClosedError, match="refused"):
        open_transport(f"socket://127.0.0.1:{port}")


def test_unix_socket_transport(tmp_path: Path) -> None:
    path = tmp_path / "board.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(path))
    server.listen(1)
    t = open_transport(f"unix://{path}", read_timeout_s=0.02)
    peer, _ = server.accept()
    try:
        data = _frames(20)
        peer.sendall(data)
        assert _read_all(t, len(data)) == data
        t.write(b"abc")
        assert peer.recv(10) == b"abc"
        peer.shutdown(socket.SHUT_RDWR)
        peer.close()
        with pytest.raises(LinkClosedError, match="end of stream"):
            for _ in range(100):
                t.read()
    finally:
        t.close()
        server.close()


def test_missing_unix_socket_is_closed(tmp_path: Path) -> None:
    with pytest.raises(LinkClosedError):
        open_transport(f"unix://{tmp_path / 'absent.sock'}")


def test_missing_device_is_closed(tmp_path: Path) -> None:
    with pytest.raises(LinkClosedError, match="No such file"):
        open_transport(str(tmp_path / "ttyNONE"))


def test_directory_is_a_plain_link_error(tmp_path: Path) -> None:
    with pytest.raises(LinkError) as info:
        open_transport(str(tmp_path))
    assert not isinstance(info.value, LinkClosedError | LinkTimeoutError)


# -- a real pty -----------------------------------------------------------------------------------


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    yield master, path
    with contextlib.suppress(OSError):
        os.close(master)


def test_pty_is_opened_exclusively(pty_pair: tuple[int, str]) -> None:
    master, path = pty_pair
    with open_transport(path, read_timeout_s=0.02) as t:
        assert isinstance(t, FdTransport)
        with pytest.raises(LinkError, match="held by another process"):
            open_transport(path)
        os.write(master, b"\x05\x06\x00")
        assert _read_all(t, 3) == b"\x05\x06\x00"
        t.write(b"xyz")
        assert os.read(master, 10) == b"xyz"
    # released on close: a second open works
    open_transport(path).close()


def test_pty_hangup_is_link_closed(pty_pair: tuple[int, str]) -> None:
    master, path = pty_pair
    t = open_transport(path, read_timeout_s=0.02)
    try:
        os.close(master)  # the board side goes away (unplug)
        with pytest.raises(LinkClosedError):
            for _ in range(100):
                t.read()
    finally:
        t.close()


def test_pty_write_times_out_when_nobody_reads(pty_pair: tuple[int, str]) -> None:
    _, path = pty_pair
    with (
        open_transport(path, read_timeout_s=0.02, write_timeout_s=0.2) as t,
        pytest.raises(LinkTimeoutError, match="does not read"),
    ):
        t.write(b"\x01" * (4 << 20))


def test_close_wakes_a_blocked_read() -> None:
    a, b = socket.socketpair()
    t = socket_transport(a, "pair://", read_timeout_s=30.0)
    errors: list[BaseException] = []

    def _reader() -> None:
        try:
            t.read()
        except BaseException as exc:
            errors.append(exc)

    th = threading.Thread(target=_reader)
    th.start()
    t.close()
    th.join(5.0)
    b.close()
    assert not th.is_alive()
    assert len(errors) == 1 and isinstance(errors[0], LinkClosedError)
    with pytest.raises(LinkClosedError):
        t.write(b"x")
