"""sd_notify messages over a real datagram socket."""

from __future__ import annotations

import logging
import os
import socket
from pathlib import Path

from piezod.service.logs import JournalPrefixFormatter
from piezod.service.sdnotify import SystemdNotifier


def _receiver(path: Path) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    return sock


def test_messages_reach_the_socket(tmp_path: Path) -> None:
    path = tmp_path / "notify.sock"
    rx = _receiver(path)
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "4000000"})
    assert n.enabled and n.watchdog_interval_s == 2.0
    n.ready("streaming 3 axes")
    n.watchdog()
    n.stopping()
    got = [rx.recv(4096).decode() for _ in range(3)]
    assert got == ["READY=1\nSTATUS=streaming 3 axes", "WATCHDOG=1", "STOPPING=1\nSTATUS=stopping"]
    n.close()
    rx.close()


def test_abstract_namespace_socket() -> None:
    name = f"piezod-test-{os.getpid()}"
    rx = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    rx.bind(b"\0" + name.encode())
    rx.settimeout(2.0)
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": "@" + name})
    n.status("ok")
    assert rx.recv(100) == b"STATUS=ok"
    rx.close()


def test_disabled_without_socket_and_watchdog_for_other_pid() -> None:
    n = SystemdNotifier.from_env({"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"})
    assert not n.enabled and n.watchdog_interval_s is None
    n.ready("nobody listens")  # no socket configured: nothing is sent


def test_journal_priority_prefix() -> None:
    fmt = JournalPrefixFormatter("%(message)s")
    rec = logging.LogRecord("piezod", logging.ERROR, __file__, 1, "link lost\nsecond line", None, None)
    assert fmt.format(rec) == "<3>link lost\n<3>second line"
    rec = logging.LogRecord("piezod", logging.INFO, __file__, 1, "streaming", None, None)
    assert fmt.format(rec) == "<6>streaming"


def test_a_receiver_that_stops_reading_never_blocks_the_daemon(tmp_path: Path) -> None:
    """The daemon's main loop pings the watchdog and must stay free to act on SIGTERM: when the
    receiver's queue is full, notifications are dropped and counted, not waited for (a blocked
    sendto held the real daemon past its stop timeout in the fault tests)."""
    import threading

    path = tmp_path / "notify.sock"
    rx = _receiver(path)
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "4000000"})

    def ping() -> None:
        for _ in range(5000):  # far more than a datagram queue holds
            n.watchdog()

    t = threading.Thread(target=ping, daemon=True)
    t.start()
    t.join(30.0)
    assert not t.is_alive(), "notify blocked on a receiver that does not read"
    assert n.dropped > 0
    assert rx.recv(4096) == b"WATCHDOG=1"  # what fitted was delivered
    n.close()
    rx.close()
