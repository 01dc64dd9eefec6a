"""The USB transport through a custom pyusb backend (SimSocketBackend) forwarding to a Unix socket.

Real USB hardware and libusb are NOT exercised here: the backend enumerates one simulated device
with the board's descriptors and carries its bulk transfers over the simulator's ``--usb-socket``
(or the socket of hil_sim's board in the test process, tests/wire_board.py).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import usb.core
import usb.util
from wire_board import TestBoard

from firmware_proto import FrameDecoder, Hello, encode
from hil_sim.usb_backend import SimSocketBackend
from piezod.config import default_sim_config_path, load_config
from piezod.errors import ConfigError, LinkClosedError
from piezod.link.session import BoardSession, LinkSettings
from piezod.link.streamer import Streamer, TriangleSource
from piezod.link.transport import open_transport
from piezod.link.usb import BACKEND_ENV, BOARD_PID, BOARD_VID, EP_IN, EP_OUT, UsbTransport


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[TestBoard, str]]:
    board = TestBoard()
    path = str(tmp_path / "usb.sock")
    board.serve_unix(path)
    yield board, path
    board.close()


def test_backend_enumerates_the_documented_device(served: tuple[TestBoard, str]) -> None:
    _, path = served
    dev = usb.core.find(idVendor=BOARD_VID, idProduct=BOARD_PID, backend=SimSocketBackend(path))
    assert dev is not None
    assert (dev.idVendor, dev.idProduct) == (0x1209, 0x7A01)
    assert dev.serial_number == "SIM0001" and dev.manufacturer == "piezod"
    cfg = dev[0]
    intf = cfg[(0, 0)]
    assert intf.bInterfaceClass == 0xFF
    eps = {ep.bEndpointAddress: ep for ep in intf}
    assert set(eps) == {EP_OUT, EP_IN}
    assert all(usb.util.endpoint_type(ep.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK for ep in eps.values())
    usb.util.dispose_resources(dev)


def test_no_device_without_the_socket(tmp_path: Path) -> None:
    with pytest.raises(LinkClosedError, match="no USB device 1209:7a01 present"):
        open_transport(f"usb://1209:7a01?backend=simsock:{tmp_path / 'absent.sock'}")


def test_serial_filter(served: tuple[TestBoard, str]) -> None:
    _, path = served
    open_transport(f"usb://1209:7a01?serial=SIM0001&backend=simsock:{path}").close()
    with pytest.raises(LinkClosedError, match="serial 'OTHER'"):
        open_transport(f"usb://1209:7a01?serial=OTHER&backend=simsock:{path}")
    with pytest.raises(LinkClosedError):
        open_transport(f"usb://1209:7a02?backend=simsock:{path}")


def test_unknown_backend_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="unknown"):
        open_transport("usb://1209:7a01?backend=warp:/x")


def test_bulk_transfers_carry_the_byte_stream(served: tuple[TestBoard, str]) -> None:
    board, path = served
    t = open_transport(f"usb://1209:7a01?backend=simsock:{path}", read_timeout_s=0.02)
    assert isinstance(t, UsbTransport) and (t.ep_out, t.ep_in) == (EP_OUT, EP_IN)
    try:
        t.write(encode(Hello(1, 77), seq=5))
        got = b""
        for _ in range(100):
            got += t.read()
            if got.endswith(b"\x00"):
                break
        frames = FrameDecoder().feed(got)
        assert frames and frames[0].msg.reply_to_seq == 5  # type: ignore[union-attr]
        assert board.hellos[-1].session_id == 77
        assert t.read() == b""  # a read timeout is not an error
        board.unplug(1.0)
        with pytest.raises(LinkClosedError, match="no such device"):
            for _ in range(100):
                t.read()
    finally:
        t.close()


def test_session_streams_over_usb_selected_by_env(
    served: tuple[TestBoard, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    board, path = served
    monkeypatch.setenv(BACKEND_ENV, f"simsock:{path}")
    config = load_config(default_sim_config_path())
    with BoardSession.open("usb://1209:7a01", config=config, sample_rate_hz=10_000) as s:
        streamer = Streamer(s, TriangleSource(10_000, [100.0] * 3, [0.0] * 3, 5.0))
        streamer.start(0)
        time.sleep(0.4)
        stats = streamer.finish()
        c = s.counters()
    assert stats.runs[0].ended_by == "stop" and stats.samples_played == stats.samples_sent > 2000
    assert c.sensor_rows == stats.samples_played and c.underruns == 0
    assert board.stats.samples_accepted == stats.samples_sent


def test_real_simulator_usb_socket(tmp_path: Path) -> None:
    spawn_sim = pytest.importorskip("hil_sim.server", reason="hil_sim.server (simulator) missing").spawn_sim
    sock = tmp_path / "sim-usb.sock"
    config = load_config(default_sim_config_path())
    with spawn_sim(seed=0, extra_args=("--usb-socket", str(sock), "--no-pty")) as sim:
        assert Path(sim.path) == sock
        url = f"usb://1209:7a01?backend=simsock:{sock}"
        settings = LinkSettings(reconnect=False)
        with BoardSession.open(url, config=config, settings=settings, sample_rate_hz=20_000) as s:
            assert s.capabilities is not None and s.capabilities.n_channels == 3
            streamer = Streamer(s, TriangleSource(20_000, [100.0] * 3, [0.0] * 3, 2.0))
            streamer.start(0)
            time.sleep(0.3)
            stats = streamer.finish()
            c = s.counters()
    assert stats.runs[0].ended_by == "stop" and stats.samples_played == stats.samples_sent > 3000
    assert c.underruns == 0 and c.sensor_rows == stats.samples_played and c.decode_errors == 0
