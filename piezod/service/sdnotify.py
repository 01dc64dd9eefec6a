"""systemd service notifications (sd_notify(3)), written from the protocol.

The protocol is one datagram per notification, ``KEY=VALUE`` lines, sent to the
``AF_UNIX`` socket named by ``$NOTIFY_SOCKET`` (a leading ``@`` means the Linux
abstract namespace). The watchdog interval comes from ``$WATCHDOG_USEC`` (only
when ``$WATCHDOG_PID`` is unset or names this process); the service must send
``WATCHDOG=1`` more often than that, and piezod pings only while streaming is
healthy so that systemd restarts a daemon whose streaming has stalled.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class SystemdNotifier:
    """Send sd_notify messages; a no-op when not started by systemd with ``Type=notify``.

    Parameters
    ----------
    socket_path
        The notification socket (``$NOTIFY_SOCKET``); None disables notifications.
    watchdog_usec
        The watchdog interval in microseconds, or None when no watchdog is configured.
    """

    def __init__(self, socket_path: str | None, watchdog_usec: int | None = None) -> None:
        self._address: str | bytes | None = None
        if socket_path:
            self._address = b"\0" + socket_path[1:].encode() if socket_path.startswith("@") else socket_path
        self.watchdog_usec = watchdog_usec
        self._sock: socket.socket | None = None
        #: notifications dropped because the receiver's queue was full
        self.dropped = 0

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> SystemdNotifier:
        """Build from ``$NOTIFY_SOCKET``, ``$WATCHDOG_USEC`` and ``$WATCHDOG_PID``."""
        env = os.environ if environ is None else environ
        usec: int | None = None
        raw = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        if raw and (not pid or pid == str(os.getpid())):
            usec = int(raw)
            if usec <= 0:
                usec = None
        return cls(env.get("NOTIFY_SOCKET") or None, usec)

    @property
    def enabled(self) -> bool:
        """True when a notification socket is configured."""
        return self._address is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to ping: half the watchdog timeout (s), or None without a watchdog."""
        return None if self.watchdog_usec is None else self.watchdog_usec / 2e6

    def notify(self, **fields: str | int) -> None:
        """Send one notification, e.g. ``notify(READY=1, STATUS="streaming")``.

        Never blocks: the daemon's main loop sends these, and it must stay free to act on SIGTERM
        (ramp to safe) even when the receiver stops reading. A notification the receiver's full
        queue cannot take is dropped, counted in :attr:`dropped` and logged (the first one, then
        every 100th).

        Raises
        ------
        OSError
            When the datagram cannot be sent for another reason (systemd gone).
        """
        if self._address is None:
            return
        if self._sock is None:
            self._sock = socket.socket(
                socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK
            )
        payload = "\n".join(f"{key}={value}" for key, value in fields.items())
        try:
            self._sock.sendto(payload.encode(), self._address)
        except BlockingIOError:
            self.dropped += 1
            if self.dropped % 100 == 1:
                log.warning(
                    "systemd notification dropped (%d so far): the receiver's queue is full: %s",
                    self.dropped,
                    ", ".join(fields),
                )

    def ready(self, status: str) -> None:
        """``READY=1`` with a status line."""
        self.notify(READY=1, STATUS=status)

    def status(self, status: str) -> None:
        """Update the status line shown by ``systemctl status``."""
        self.notify(STATUS=status)

    def watchdog(self) -> None:
        """``WATCHDOG=1``: the service is healthy."""
        self.notify(WATCHDOG=1)

    def stopping(self, status: str = "stopping") -> None:
        """``STOPPING=1``: shutdown has begun."""
        self.notify(STOPPING=1, STATUS=status)

    def close(self) -> None:
        """Close the notification socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
