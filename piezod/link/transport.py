"""Byte transports to the board, chosen by URL.

A :class:`Transport` moves raw bytes; framing is :mod:`firmware_proto`'s job. Every failure is
mapped onto the link part of the error tree (:mod:`piezod.errors`):

- :class:`~piezod.errors.LinkClosedError`: the board went away (unplugged, EIO, hangup, peer
  closed the socket, device path missing);
- :class:`~piezod.errors.LinkTimeoutError`: a write could not complete in time;
- :class:`~piezod.errors.LinkError`: anything else (permissions, port held by another process).

URLs accepted by :func:`open_transport`:

``/dev/ttyACM0``, ``./board.pty``, ``/dev/ttyUSB0?baudrate=12000000``
    A serial device path (a pty of the simulator, a USB CDC device, a UART bridge), opened
    exclusively with ``serial.serial_for_url(path, exclusive=True)``.
``socket://host:port``, ``loop://``, ``rfc2217://...``
    Any other pyserial URL (exclusive access is not supported there).
``unix:///path/to/socket``
    A Unix stream socket carrying the raw byte stream (e.g. ``python -m hil_sim --usb-socket``).
``usb://VID:PID[?serial=S][&interface=N][&backend=simsock:/path]``
    A board with vendor bulk endpoints through pyusb (:mod:`piezod.link.usb`).
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import os
import re
import select
import socket
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Literal
from urllib.parse import parse_qsl

from piezod.errors import ConfigError, LinkClosedError, LinkError, LinkTimeoutError

DEFAULT_READ_TIMEOUT_S = 0.05
"""How long :meth:`Transport.read` waits for the first byte before returning ``b""``."""
DEFAULT_WRITE_TIMEOUT_S = 2.0
"""How long :meth:`Transport.write` may block before :class:`LinkTimeoutError`."""
READ_CHUNK = 65536
"""Bytes asked for per read."""

TransportKind = Literal["serial", "pyserial", "unix", "usb"]

_CLOSED_ERRNOS = frozenset(
    {
        errno.ENOENT,
        errno.ENXIO,
        errno.ENODEV,
        errno.EIO,
        errno.EBADF,
        errno.EPIPE,
        errno.ECONNRESET,
        errno.ECONNREFUSED,
        errno.ECONNABORTED,
        errno.ENOTCONN,
        errno.ESHUTDOWN,
        errno.EHOSTDOWN,
    }
)
_CLOSED_WORDS = ("disconnected", "returned no data", "device reports error", "port not open", "hangup")
_ERRNO_IN_TEXT = re.compile(r"\[Errno (\d+)\]")


@dataclass(frozen=True, slots=True)
class LinkUrl:
    """A parsed transport URL.

    Attributes
    ----------
    kind
        ``serial`` (device path, opened exclusively), ``pyserial`` (other pyserial URL),
        ``unix`` (Unix stream socket) or ``usb`` (pyusb bulk endpoints).
    target
        The device path, the pyserial URL, the socket path or ``VID:PID``.
    options
        Query options (``baudrate`` for serial; ``serial``, ``interface``, ``backend`` for usb).
    raw
        The URL as given.
    """

    kind: TransportKind
    target: str
    options: Mapping[str, str] = field(default_factory=dict)
    raw: str = ""


_USB_OPTIONS = frozenset({"serial", "interface", "backend"})


def parse_url(url: str) -> LinkUrl:
    """Classify a transport URL (see the module docstring).

    Raises
    ------
    ConfigError
        The URL is empty or malformed, or carries an unknown option.
    """
    if not isinstance(url, str) or not url.strip():
        raise ConfigError("link URL: empty")
    url = url.strip()
    if url.startswith("usb://"):
        rest, _, query = url[len("usb://") :].partition("?")
        if not re.fullmatch(r"[0-9A-Fa-f]{1,4}:[0-9A-Fa-f]{1,4}", rest):
            raise ConfigError(f"link URL {url!r}: expected usb://VID:PID with hexadecimal ids, got {rest!r}")
        opts = _query(url, query, _USB_OPTIONS)
        if "interface" in opts and not opts["interface"].isdigit():
            raise ConfigError(f"link URL {url!r}: interface must be a number, got {opts['interface']!r}")
        return LinkUrl("usb", rest.lower(), opts, url)
    if url.startswith("unix://"):
        path = url[len("unix://") :]
        if not path:
            raise ConfigError(f"link URL {url!r}: no socket path")
        return LinkUrl("unix", path, {}, url)
    if "://" in url:
        return LinkUrl("pyserial", url, {}, url)
    path, _, query = url.partition("?")
    opts = _query(url, query, frozenset({"baudrate"}))
    if "baudrate" in opts and not (opts["baudrate"].isdigit() and int(opts["baudrate"]) > 0):
        raise ConfigError(f"link URL {url!r}: baudrate must be a positive integer, got {opts['baudrate']!r}")
    return LinkUrl("serial", path, opts, url)


def _query(url: str, query: str, allowed: frozenset[str]) -> dict[str, str]:
    if not query:
        return {}
    try:
        pairs = parse_qsl(query, keep_blank_values=True, strict_parsing=True)
    except ValueError:
        raise ConfigError(f"link URL {url!r}: malformed query {query!r}") from None
    opts = dict(pairs)
    unknown = sorted(set(opts) - allowed)
    if unknown:
        raise ConfigError(
            f"link URL {url!r}: unknown option {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})"
        )
    return opts


def _errno_of(exc: BaseException) -> int | None:
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        code = getattr(cur, "errno", None)
        if isinstance(code, int):
            return code
        m = _ERRNO_IN_TEXT.search(str(cur))
        if m:
            return int(m.group(1))
        cur = cur.__cause__ or cur.__context__
    return None


def map_error(exc: BaseException, url: str, what: str) -> LinkError:
    """Translate an OS / pyserial / pyusb exception into the link error tree.

    Parameters
    ----------
    exc
        The exception raised by the transport library.
    url
        The transport URL (named in the message).
    what
        The operation (``open``, ``read``, ``write``).
    """
    if isinstance(exc, LinkError):
        return exc
    code = _errno_of(exc)
    text = str(exc) or type(exc).__name__
    msg = f"{url}: {what} failed: {text}"
    name = type(exc).__name__
    if isinstance(exc, TimeoutError) or "Timeout" in name or code == errno.ETIMEDOUT:
        return LinkTimeoutError(msg)
    if code in _CLOSED_ERRNOS or any(w in text.lower() for w in _CLOSED_WORDS):
        return LinkClosedError(msg)
    return LinkError(msg)


class Transport(ABC):
    """A bidirectional byte stream to the board.

    :meth:`read` and :meth:`write` may be called from two different threads at the same time;
    :meth:`close` wakes a blocked :meth:`read`.

    Attributes
    ----------
    url
        The URL it was opened from.
    read_timeout_s
        :meth:`read` returns ``b""`` after this long without data.
    write_timeout_s
        :meth:`write` raises :class:`LinkTimeoutError` when it cannot finish in this time.
    """

    url: str
    read_timeout_s: float
    write_timeout_s: float

    @abstractmethod
    def read(self, max_bytes: int = READ_CHUNK) -> bytes:
        """Return the bytes available (at most ``max_bytes``), waiting at most :attr:`read_timeout_s`.

        Returns ``b""`` when nothing arrived in time.

        Raises
        ------
        LinkClosedError
            The board went away or the transport was closed.
        LinkError
            Any other transport failure.
        """

    @abstractmethod
    def write(self, data: bytes) -> None:
        """Write all of ``data``.

        Raises
        ------
        LinkTimeoutError
            Not everything could be written within :attr:`write_timeout_s`.
        LinkClosedError
            The board went away or the transport was closed.
        """

    @abstractmethod
    def close(self) -> None:
        """Release the port (idempotent)."""

    @property
    @abstractmethod
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""

    def __enter__(self) -> Transport:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url}{' closed' if self.closed else ''}>"


class InFlight:
    """The read / write calls in progress on a transport, so that :meth:`close` releases the
    handle only when none is (thread-safe; shared by the transports that own a handle).

    Parameters
    ----------
    url
        For messages.
    """

    def __init__(self, url: str) -> None:
        self.url = url
        self.closed = False
        self._count = 0
        self._idle = threading.Condition()

    def enter(self) -> None:
        """A call begins.

        Raises
        ------
        LinkClosedError
            The transport is closed.
        """
        with self._idle:
            if self.closed:
                raise LinkClosedError(f"{self.url}: transport closed")
            self._count += 1

    def leave(self) -> None:
        """A call ended."""
        with self._idle:
            self._count -= 1
            self._idle.notify_all()

    def close(self, timeout_s: float, wake: Callable[[], None] | None = None) -> bool:
        """Mark the transport closed, ``wake`` blocked calls, wait (at most ``timeout_s``) until none
        is in progress; False when it was closed already."""
        with self._idle:
            if self.closed:
                return False
            self.closed = True
            if wake is not None:
                wake()
            self._idle.wait_for(lambda: self._count == 0, timeout=timeout_s)
        return True


class FdTransport(Transport):
    """A transport over a non-blocking POSIX file descriptor (tty, pty or socket), ``select`` based.

    Parameters
    ----------
    fd
        The descriptor; switched to non-blocking mode.
    url
        For messages.
    on_close
        Releases the underlying object (pyserial port, socket); called once by :meth:`close`.
    read_timeout_s, write_timeout_s
        See :class:`Transport`.
    """

    def __init__(
        self,
        fd: int,
        url: str,
        on_close: Any = None,
        *,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        write_timeout_s: float = DEFAULT_WRITE_TIMEOUT_S,
    ) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        self.write_timeout_s = write_timeout_s
        self._fd = fd
        self._on_close = on_close
        os.set_blocking(fd, False)
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        self._inflight = InFlight(url)  # the fd is closed only when no read / write is in progress

    @property
    def closed(self) -> bool:
        return self._inflight.closed

    def fileno(self) -> int:
        """The file descriptor."""
        return self._fd

    def read(self, max_bytes: int = READ_CHUNK) -> bytes:
        self._inflight.enter()
        try:
            try:
                ready, _, _ = select.select([self._fd, self._wake_r], [], [], self.read_timeout_s)
            except (OSError, ValueError) as exc:
                raise map_error(exc, self.url, "read") from exc
            if self._inflight.closed:
                raise LinkClosedError(f"{self.url}: transport closed")
            if self._fd not in ready:
                return b""
            try:
                data = os.read(self._fd, max_bytes)
            except BlockingIOError:
                return b""
            except OSError as exc:
                raise map_error(exc, self.url, "read") from exc
            if not data:
                raise LinkClosedError(f"{self.url}: read failed: end of stream (peer closed / hangup)")
            return data
        finally:
            self._inflight.leave()

    def write(self, data: bytes) -> None:
        if not data:
            return
        self._inflight.enter()
        try:
            view = memoryview(data)
            deadline = time.monotonic() + self.write_timeout_s
            while view:
                if self._inflight.closed:
                    raise LinkClosedError(f"{self.url}: transport closed")
                try:
                    n = os.write(self._fd, view)
                    view = view[n:]
                    continue
                except BlockingIOError:
                    pass
                except OSError as exc:
                    raise map_error(exc, self.url, "write") from exc
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkTimeoutError(
                        f"{self.url}: write timed out after {self.write_timeout_s:g} s "
                        f"({len(view)} of {len(data)} bytes not accepted: the board does not read)"
                    )
                try:
                    select.select([self._wake_r], [self._fd], [], left)
                except (OSError, ValueError) as exc:
                    raise map_error(exc, self.url, "write") from exc
        finally:
            self._inflight.leave()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def close(self) -> None:
        if not self._inflight.close(self.write_timeout_s + 1.0, self._wake):
            return
        try:
            if self._on_close is not None:
                self._on_close()
            else:
                os.close(self._fd)
        except OSError:
            pass  # the board is gone already; nothing left to release
        finally:
            os.close(self._wake_r)
            os.close(self._wake_w)


class PyserialTransport(Transport):
    """A transport over any pyserial object (``socket://``, ``loop://``, ``rfc2217://`` ...).

    Reads ask for what :attr:`serial.Serial.in_waiting` reports so that a read never waits for a
    full buffer.
    """

    def __init__(
        self,
        port: Any,
        url: str,
        *,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        write_timeout_s: float = DEFAULT_WRITE_TIMEOUT_S,
    ) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        self.write_timeout_s = write_timeout_s
        self._port = port
        self._closed = False
        port.timeout = read_timeout_s
        port.write_timeout = write_timeout_s

    @property
    def closed(self) -> bool:
        return self._closed

    def read(self, max_bytes: int = READ_CHUNK) -> bytes:
        if self._closed:
            raise LinkClosedError(f"{self.url}: transport closed")
        try:
            waiting = self._port.in_waiting
            if waiting:
                data: bytes = self._port.read(min(waiting, max_bytes))
                return data
            first: bytes = self._port.read(1)
            if not first:
                return b""
            more = self._port.in_waiting
            return first + self._port.read(min(more, max_bytes - 1)) if more and max_bytes > 1 else first
        except Exception as exc:
            if self._closed:
                raise LinkClosedError(f"{self.url}: transport closed") from exc
            raise map_error(exc, self.url, "read") from exc

    def write(self, data: bytes) -> None:
        if self._closed:
            raise LinkClosedError(f"{self.url}: transport closed")
        try:
            n = self._port.write(data)
        except Exception as exc:
            raise map_error(exc, self.url, "write") from exc
        if n is not None and n != len(data):
            raise LinkTimeoutError(f"{self.url}: write timed out ({len(data) - n} of {len(data)} bytes left)")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self._port.cancel_read()
        with contextlib.suppress(Exception):
            self._port.close()


def _open_serial(spec: LinkUrl, read_timeout_s: float, write_timeout_s: float) -> Transport:
    import serial

    kwargs: dict[str, Any] = {"timeout": read_timeout_s, "write_timeout": write_timeout_s}
    if spec.kind == "serial":
        kwargs["exclusive"] = True
        kwargs["baudrate"] = int(spec.options.get("baudrate", "115200"))
    try:
        port = serial.serial_for_url(spec.target, **kwargs)
    except Exception as exc:
        code = _errno_of(exc)
        if code in (errno.EAGAIN, errno.EWOULDBLOCK) or "exclusive" in str(exc).lower():
            raise LinkError(f"{spec.raw}: open failed: the port is held by another process ({exc})") from exc
        raise map_error(exc, spec.raw, "open") from exc
    if spec.kind == "serial" and isinstance(port, serial.Serial) and sys.platform != "win32":
        return FdTransport(
            port.fileno(),
            spec.raw,
            port.close,
            read_timeout_s=read_timeout_s,
            write_timeout_s=write_timeout_s,
        )
    return PyserialTransport(port, spec.raw, read_timeout_s=read_timeout_s, write_timeout_s=write_timeout_s)


def socket_transport(
    sock: socket.socket,
    url: str,
    *,
    read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
    write_timeout_s: float = DEFAULT_WRITE_TIMEOUT_S,
) -> FdTransport:
    """Wrap a connected stream socket (Unix or TCP); the transport owns and closes it."""

    def _close() -> None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        sock.close()

    return FdTransport(
        sock.fileno(), url, _close, read_timeout_s=read_timeout_s, write_timeout_s=write_timeout_s
    )


def _open_unix(spec: LinkUrl, read_timeout_s: float, write_timeout_s: float) -> Transport:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.settimeout(max(write_timeout_s, 1.0))
        sock.connect(spec.target)
    except OSError as exc:
        sock.close()
        raise map_error(exc, spec.raw, "open") from exc
    return socket_transport(sock, spec.raw, read_timeout_s=read_timeout_s, write_timeout_s=write_timeout_s)


#: Transports in their own modules, looked up by URL kind and imported on first use
#: (``"module:function"``, called with the parsed :class:`LinkUrl` and the timeouts). The USB
#: transport needs pyusb, and depends on this module, not this module on it.
BACKENDS: dict[str, str] = {"usb": "piezod.link.usb:open_usb"}


def open_transport(
    url: str,
    *,
    read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
    write_timeout_s: float = DEFAULT_WRITE_TIMEOUT_S,
) -> Transport:
    """Open the transport named by ``url`` (see the module docstring).

    Parameters
    ----------
    url
        Device path, pyserial URL, ``unix://PATH`` or ``usb://VID:PID[?...]``.
    read_timeout_s
        :meth:`Transport.read` returns ``b""`` after this long without data.
    write_timeout_s
        :meth:`Transport.write` gives up (:class:`LinkTimeoutError`) after this long.

    Raises
    ------
    ConfigError
        Malformed URL.
    LinkClosedError
        The device / socket does not exist (unplugged) or refused the connection.
    LinkError
        Any other failure (permissions, port held by another process, no USB backend).
    """
    if read_timeout_s <= 0 or write_timeout_s <= 0:
        raise ValueError("read_timeout_s and write_timeout_s must be > 0")
    spec = parse_url(url)
    if spec.kind in BACKENDS:
        module, _, name = BACKENDS[spec.kind].partition(":")
        opener: Callable[..., Transport] = getattr(importlib.import_module(module), name)
        return opener(spec, read_timeout_s=read_timeout_s, write_timeout_s=write_timeout_s)
    if spec.kind == "unix":
        return _open_unix(spec, read_timeout_s, write_timeout_s)
    return _open_serial(spec, read_timeout_s, write_timeout_s)


__all__ = [
    "BACKENDS",
    "DEFAULT_READ_TIMEOUT_S",
    "DEFAULT_WRITE_TIMEOUT_S",
    "READ_CHUNK",
    "FdTransport",
    "InFlight",
    "LinkUrl",
    "PyserialTransport",
    "Transport",
    "map_error",
    "open_transport",
    "parse_url",
    "socket_transport",
]
