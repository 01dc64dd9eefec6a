"""The simulated board's USB side: its bulk endpoints as a byte stream over a Unix stream socket.

Kernel USB gadgets are not available on a development machine, so the simulator exposes what
the board's vendor-specific USB interface would carry: everything the host writes to bulk OUT
endpoint :data:`USB_EP_OUT` and everything the board sends on bulk IN endpoint
:data:`USB_EP_IN`, as one raw byte stream in each direction of a Unix stream socket (the same
COBS-framed stream as on the serial link; USB packet boundaries carry no meaning). A host-side
pyusb backend connects to the socket to "find" the device (:data:`USB_VENDOR_ID`:
:data:`USB_PRODUCT_ID`) and maps ``bulkWrite(USB_EP_OUT, data)`` to ``send`` and
``bulkRead(USB_EP_IN, size)`` to ``recv``.

Semantics (``PROTOCOL.md`` section "USB transport"):

- a connected socket is an attached, configured device; the simulator closing the connection
  (``python -m hil_sim`` on SIGUSR1, or exit) is an unplug: the backend should then report
  ``ENODEV`` (pyusb ``USBError`` errno 19) for every transfer;
- the socket file exists while the device is plugged in; one client at a time (a new connection
  replaces the previous one, as re-opening the device would).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import socket
import stat
import time
from pathlib import Path

from hil_sim.errors import SimLinkClosedError, SimLinkError, SimLinkTimeoutError

USB_VENDOR_ID = 0x1209
"""Vendor id of the simulated board (pid.codes, the open-source hardware VID)."""
USB_PRODUCT_ID = 0x7A01
"""Product id of the simulated board (a real board needs its own pid.codes allocation)."""
USB_MANUFACTURER = "piezod"
USB_PRODUCT = "piezod DAC board (simulated)"
USB_INTERFACE = 0
"""The vendor-specific interface (class 0xFF) holding the two bulk endpoints."""
USB_INTERFACE_CLASS = 0xFF
USB_EP_OUT = 0x01
"""Bulk OUT endpoint address: host -> board byte stream."""
USB_EP_IN = 0x81
"""Bulk IN endpoint address: board -> host byte stream."""
USB_MAX_PACKET_SIZE = 512
"""wMaxPacketSize of both bulk endpoints (USB 2.0 high speed)."""

log = logging.getLogger("hil_sim.usb")

_READ_CHUNK = 1 << 16
_MAX_BACKLOG = 8 << 20


class UsbSocketServer:
    """Server side of the USB byte-stream socket, non-blocking, driven by the simulator's select loop.

    Parameters
    ----------
    path
        Where the Unix socket is created. A stale socket file there is replaced; any other file
        is an error.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._backlog = bytearray()
        self._dropped_bytes = 0

    @property
    def is_open(self) -> bool:
        """The socket file exists and accepts connections (the device is plugged in)."""
        return self._listener is not None

    @property
    def connected(self) -> bool:
        """A host is connected."""
        return self._client is not None

    def open(self) -> None:
        """Create the listening socket (plug the device in).

        Raises
        ------
        SimLinkError
            ``path`` exists and is not a socket, or the socket cannot be created.
        """
        if self._listener is not None:
            return
        try:
            mode = os.lstat(self.path).st_mode
        except FileNotFoundError:
            pass
        else:
            if not stat.S_ISSOCK(mode):
                raise SimLinkError(f"{self.path}: exists and is not a socket; refusing to replace it")
            self.path.unlink()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.bind(str(self.path))
            sock.listen(1)
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise SimLinkError(f"{self.path}: cannot create the USB socket: {exc.strerror or exc}") from exc
        self._listener = sock
        log.info("USB socket %s (device %04x:%04x)", self.path, USB_VENDOR_ID, USB_PRODUCT_ID)

    def close(self) -> None:
        """Drop the host and remove the socket file (unplug the device)."""
        self._drop_client()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()

    def read_fds(self) -> list[int]:
        """File descriptors to watch for reading."""
        fds = [s.fileno() for s in (self._listener, self._client) if s is not None]
        return fds

    def write_fds(self) -> list[int]:
        """File descriptors to watch for writing (when output is waiting)."""
        if self._client is not None and self._backlog:
            return [self._client.fileno()]
        return []

    def poll(self, readable: set[int], max_bytes: int = 1 << 20) -> bytes:
        """Accept a new host, return what the host sent (up to ``max_bytes``)."""
        if self._listener is not None and self._listener.fileno() in readable:
            self._accept()
        client = self._client
        if client is None or client.fileno() not in readable:
            return b""
        chunks: list[bytes] = []
        got = 0
        while got < max_bytes:
            try:
                data = client.recv(_READ_CHUNK)
            except BlockingIOError:
                break
            except OSError as exc:
                log.info("USB host connection failed: %s", exc.strerror or exc)
                self._drop_client()
                break
            if not data:
                log.info("USB host disconnected")
                self._drop_client()
                break
            chunks.append(data)
            got += len(data)
        return b"".join(chunks)

    def write(self, data: bytes) -> None:
        """Queue ``data`` for the host and send what the socket takes; dropped without a host."""
        if self._client is None:
            return
        if data:
            if len(self._backlog) + len(data) > _MAX_BACKLOG:
                self._dropped_bytes += len(data)
                log.warning("USB host not reading: dropped %d bytes so far", self._dropped_bytes)
            else:
                self._backlog += data
        while self._backlog and self._client is not None:
            try:
                sent = self._client.send(self._backlog)
            except BlockingIOError:
                return
            except OSError as exc:
                log.info("USB host connection failed: %s", exc.strerror or exc)
                self._drop_client()
                return
            del self._backlog[:sent]

    def _accept(self) -> None:
        assert self._listener is not None
        try:
            conn, _ = self._listener.accept()
        except BlockingIOError:
            return
        conn.setblocking(False)
        if self._client is not None:
            log.info("USB host replaced by a new connection")
            self._drop_client()
        else:
            log.info("USB host connected")
        self._client = conn

    def _drop_client(self) -> None:
        if self._client is not None:
            with contextlib.suppress(OSError):
                self._client.shutdown(socket.SHUT_RDWR)
            self._client.close()
            self._client = None
        self._backlog.clear()


def connect(path: str | Path, timeout_s: float = 5.0) -> socket.socket:
    """Connect to a simulator's USB socket (client side, blocking), waiting for it to appear.

    Parameters
    ----------
    path
        The socket given to ``python -m hil_sim --usb-socket``.
    timeout_s
        How long to wait for the socket (s): it is absent while the device is unplugged.

    Raises
    ------
    SimLinkTimeoutError
        No socket accepted the connection in time.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.connect(str(path))
            return sock
        except OSError as exc:
            sock.close()
            if exc.errno not in (errno.ENOENT, errno.ECONNREFUSED):
                raise SimLinkClosedError(f"{path}: {exc.strerror or exc}") from exc
            if time.monotonic() >= deadline:
                raise SimLinkTimeoutError(f"{path}: no simulated USB device within {timeout_s} s") from exc
            time.sleep(0.02)


__all__ = [
    "USB_EP_IN",
    "USB_EP_OUT",
    "USB_INTERFACE",
    "USB_INTERFACE_CLASS",
    "USB_MANUFACTURER",
    "USB_MAX_PACKET_SIZE",
    "USB_PRODUCT",
    "USB_PRODUCT_ID",
    "USB_VENDOR_ID",
    "UsbSocketServer",
    "connect",
]
