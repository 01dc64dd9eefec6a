"""The real daemon process against the real simulator process over a real pty; the API over its socket."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from piezod.client import PiezodClient
from piezod.config import default_sim_config_path
from piezod.errors import ApiError


class Notify:
    """A test NOTIFY_SOCKET collecting sd_notify datagrams."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.path = path
        self.messages: list[str] = []

    def wait_for(self, key: str, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for m in self.messages:
                if key in m.split("\n"):
                    return m
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except TimeoutError:
                continue
        raise AssertionError(f"no {key} within {timeout_s} s; got {self.messages}")

    def drain(self) -> None:
        try:
            while True:
                self.messages.append(self.sock.recv(4096).decode())
        except TimeoutError:
            pass


def _start_daemon(tmp_path: Path, port: str, notify: Notify) -> subprocess.Popen[bytes]:
    env = dict(os.environ, NOTIFY_SOCKET=str(notify.path), WATCHDOG_USEC="2000000")
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "piezod",
            "serve",
            "--config",
            str(default_sim_config_path()),
            "--port",
            port,
            "--api",
            f"unix:{tmp_path / 'api.sock'}",
            "--recordings",
            str(tmp_path / "rec"),
        ],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=open(tmp_path / "daemon.log", "wb"),
    )


@pytest.fixture
def daemon(
    tmp_path: Path, spawn_board: Callable[..., Any]
) -> Iterator[tuple[PiezodClient, subprocess.Popen[bytes], Notify, object]]:
    notify = Notify(tmp_path / "notify.sock")
    link = tmp_path / "board"
    with spawn_board(default_sim_config_path(), link=str(link), extra_args=("--unplug-s", "2")) as sim:
        proc = _start_daemon(tmp_path, str(link), notify)
        try:
            notify.wait_for("READY=1", 30.0)
            with PiezodClient(f"unix:{tmp_path / 'api.sock'}", timeout=10.0) as client:
                yield client, proc, notify, sim
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            notify.sock.close()


def test_scan_change_stop_limits_and_sigterm(
    daemon: tuple[PiezodClient, subprocess.Popen[bytes], Notify, object], tmp_path: Path
) -> None:
    client, proc, notify, _ = daemon
    assert client.status().state == "idle"
    # out of the limits: refused with the reason, nothing started
    with pytest.raises(ApiError) as err:
        client.scan(range_um=500.0, line_rate_hz=1.0)
    assert err.value.status_code == 422 and "largest reachable" in str(err.value)
    # scan, polled hard by the API meanwhile
    client.scan(range_um=15.0, line_rate_hz=2.0, lines=200, frames=0, name="live")
    stop_polling = threading.Event()
    polled = [0]

    def poll() -> None:
        with PiezodClient(f"unix:{tmp_path / 'api.sock'}") as c2:
            while not stop_polling.is_set():
                c2.status()
                polled[0] += 1

    t = threading.Thread(target=poll)
    t.start()
    time.sleep(2.0)
    st = client.change(range_um=8.0, offset_x_um=3.0)
    assert st.state == "scanning"
    # The line the change lands on carries the move to the new offset (its linearity is not the
    # scan's): judge a line completed after it, however slowly a loaded machine gets there.
    settled = (st.line or 0) + 3
    deadline = time.monotonic() + 30.0
    time.sleep(2.0)
    st = client.status()
    while (st.last_line is None or st.last_line.line < settled) and time.monotonic() < deadline:
        time.sleep(0.2)
        st = client.status()
    stop_polling.set()
    t.join()
    assert st.underruns == 0, st.faults
    assert st.last_line is not None and st.last_line.line >= settled, st.last_line
    assert st.last_line.nonlinearity_pct < 2.0, st.last_line
    assert polled[0] > 20
    client.stop()
    assert client.status().state == "idle"
    assert any(r.name == "live.csv" for r in client.recordings())
    notify.wait_for("WATCHDOG=1", 5.0)
    # SIGTERM: ramp to safe, STOPPING=1, exit 0
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(30.0) == 0
    notify.wait_for("STOPPING=1", 2.0)


def test_unplug_is_reported_and_the_daemon_recovers(
    daemon: tuple[PiezodClient, subprocess.Popen[bytes], Notify, object],
) -> None:
    client, _proc, _notify, sim = daemon
    sim.unplug()  # type: ignore[attr-defined]
    deadline = time.monotonic() + 5.0
    seen_down = False
    while time.monotonic() < deadline:
        st = client.status()
        if st.state == "disconnected" or any(f.source == "link" for f in st.faults):
            seen_down = True
            break
        time.sleep(0.1)
    assert seen_down
    # the board comes back after 2 s: streaming resumes (hold), the fault stays visible until stop
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        st = client.status()
        if st.state in ("fault", "idle") and any(f.code == "RECONNECTED" for f in st.faults):
            break
        time.sleep(0.2)
    else:
        raise AssertionError(f"no recovery: {client.status()}")
    client.stop()
    st = client.status()
    assert st.state == "idle"
    client.scan(range_um=10.0, line_rate_hz=2.0, lines=2, record=False)
    time.sleep(0.5)
    assert client.status().state == "scanning"
