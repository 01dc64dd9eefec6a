"""USB transport: a board with vendor-class bulk endpoints, through pyusb.

The board enumerates as (the descriptors :class:`SimSocketBackend` reports, and what
:func:`open_usb` looks for):

- ``idVendor`` 0x1209 (pid.codes), ``idProduct`` 0x7A01, ``iSerialNumber`` = the board serial;
- configuration 1 with one interface (number 0, class 0xFF vendor specific, no alternate
  settings) holding one bulk OUT endpoint (0x01) and one bulk IN endpoint (0x81), 512-byte
  packets at high speed (64 at full speed);
- the bulk endpoints carry the same byte stream as the serial link (COBS frames delimited by 0x00,
  ``firmware_proto/PROTOCOL.md``); transfer boundaries mean nothing.

URL: ``usb://VID:PID[?serial=S][&interface=N][&backend=simsock:/path/to.sock]``. Without
``backend`` the environment variable ``PIEZOD_USB_BACKEND`` is used (same syntax), else pyusb's
default (libusb1). ``simsock:PATH`` selects :class:`SimSocketBackend`: a pyusb backend that
enumerates one simulated device and forwards its bulk transfers to the simulator's
``--usb-socket`` (a Unix stream socket with the raw bulk byte stream). That is how the USB code
path is tested; a real USB device and libusb were not exercised.
"""

from __future__ import annotations

import array
import contextlib
import errno
import os
import select
import socket
import threading
import time
from types import SimpleNamespace
from typing import Any

import usb.backend
import usb.core
import usb.util

from piezod.errors import ConfigError, LinkClosedError, LinkError, LinkTimeoutError
from piezod.link.transport import (
    DEFAULT_READ_TIMEOUT_S,
    DEFAULT_WRITE_TIMEOUT_S,
    READ_CHUNK,
    LinkUrl,
    Transport,
    map_error,
    parse_url,
)

BOARD_VID = 0x1209
"""USB vendor id of the board (pid.codes)."""
BOARD_PID = 0x7A01
"""USB product id of the board."""
EP_OUT = 0x01
"""Bulk OUT endpoint address (host -> board)."""
EP_IN = 0x81
"""Bulk IN endpoint address (board -> host)."""
BACKEND_ENV = "PIEZOD_USB_BACKEND"
"""Environment variable selecting a pyusb backend (``simsock:/path``) when the URL names none."""

_USB_CLOSED_ERRNOS = frozenset({errno.ENODEV, errno.EPIPE, errno.EIO, errno.ENOENT, errno.ESHUTDOWN})


class UsbTransport(Transport):
    """Bulk OUT / bulk IN endpoints of a claimed interface.

    Parameters
    ----------
    device
        A configured :class:`usb.core.Device`.
    interface
        ``bInterfaceNumber`` claimed.
    ep_out, ep_in
        Endpoint addresses.
    url
        For messages.
    read_timeout_s, write_timeout_s
        See :class:`~piezod.link.transport.Transport`.
    """

    def __init__(
        self,
        device: Any,
        interface: int,
        ep_out: int,
        ep_in: int,
        url: str,
        *,
        read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
        write_timeout_s: float = DEFAULT_WRITE_TIMEOUT_S,
    ) -> None:
        self.url = url
        self.read_timeout_s = read_timeout_s
        self.write_timeout_s = write_timeout_s
        self.device = device
        self.interface = interface
        self.ep_out = ep_out
        self.ep_in = ep_in
        self._closed = False
        self._buf = array.array("B", bytes(READ_CHUNK))
        self._busy = 0  # transfers in progress: the handle is released only when none is
        self._idle = threading.Condition()

    @property
    def closed(self) -> bool:
        return self._closed

    def _error(self, exc: BaseException, what: str) -> LinkError:
        if isinstance(exc, usb.core.USBTimeoutError):
            return LinkTimeoutError(f"{self.url}: {what} timed out: {exc}")
        code = getattr(exc, "errno", None)
        if self._closed or code in _USB_CLOSED_ERRNOS or "no such device" in str(exc).lower():
            return LinkClosedError(f"{self.url}: {what} failed: {exc}")
        return map_error(exc, self.url, what)

    def _enter(self) -> None:
        with self._idle:
            if self._closed:
                raise LinkClosedError(f"{self.url}: transport closed")
            self._busy += 1

    def _leave(self) -> None:
        with self._idle:
            self._busy -= 1
            self._idle.notify_all()

    def read(self, max_bytes: int = READ_CHUNK) -> bytes:
        self._enter()
        try:
            buf = self._buf if max_bytes >= len(self._buf) else array.array("B", bytes(max_bytes))
            try:
                n = self.device.read(self.ep_in, buf, max(1, round(self.read_timeout_s * 1000)))
            except usb.core.USBTimeoutError:
                return b""
            except Exception as exc:
                raise self._error(exc, "bulk read") from exc
            return buf[:n].tobytes()
        finally:
            self._leave()

    def write(self, data: bytes) -> None:
        if not data:
            return
        self._enter()
        try:
            n = self.device.write(self.ep_out, data, max(1, round(self.write_timeout_s * 1000)))
        except Exception as exc:
            raise self._error(exc, "bulk write") from exc
        finally:
            self._leave()
        if n != len(data):
            raise LinkTimeoutError(f"{self.url}: bulk write accepted {n} of {len(data)} bytes")

    def close(self) -> None:
        """Release the interface once the transfers in progress ended (they time out by themselves)."""
        with self._idle:
            if self._closed:
                return
            self._closed = True
            self._idle.wait_for(lambda: self._busy == 0, timeout=self.write_timeout_s + 1.0)
        with contextlib.suppress(Exception):
            usb.util.release_interface(self.device, self.interface)
        with contextlib.suppress(Exception):
            usb.util.dispose_resources(self.device)


def backend_from_spec(spec: str) -> Any:
    """The pyusb backend named by ``spec`` (``simsock:/path``).

    Raises
    ------
    ConfigError
        Unknown backend name.
    """
    name, _, arg = spec.partition(":")
    if name == "simsock" and arg:
        return SimSocketBackend(arg)
    raise ConfigError(f"USB backend {spec!r}: unknown (supported: simsock:/path/to/usb.sock)")


def open_usb(
    spec: LinkUrl | str,
    *,
    read_timeout_s: float = DEFAULT_READ_TIMEOUT_S,
    write_timeout_s: float = DEFAULT_WRITE_TIMEOUT_S,
    backend: Any = None,
) -> UsbTransport:
    """Find the board on USB, claim its interface and return a :class:`UsbTransport`.

    Parameters
    ----------
    spec
        ``usb://VID:PID[?serial=S][&interface=N][&backend=simsock:PATH]`` or its parsed form.
    read_timeout_s, write_timeout_s
        Transfer timeouts.
    backend
        A pyusb backend object; overrides the URL and :data:`BACKEND_ENV`.

    Raises
    ------
    LinkClosedError
        No matching device is present.
    LinkError
        No pyusb backend, the interface is claimed by someone else, endpoints missing.
    """
    if isinstance(spec, str):
        spec = parse_url(spec)
    vid_s, pid_s = spec.target.split(":")
    vid, pid = int(vid_s, 16), int(pid_s, 16)
    if backend is None:
        name = spec.options.get("backend") or os.environ.get(BACKEND_ENV)
        if name:
            backend = backend_from_spec(name)
    want_serial = spec.options.get("serial")
    intf_no = int(spec.options.get("interface", "0"))

    def _match(dev: Any) -> bool:
        if want_serial is None:
            return True
        try:
            return bool(dev.serial_number == want_serial)
        except (ValueError, usb.core.USBError):
            return False

    try:
        device = usb.core.find(idVendor=vid, idProduct=pid, backend=backend, custom_match=_match)
    except usb.core.NoBackendError as exc:
        raise LinkError(f"{spec.raw}: no pyusb backend available (install libusb-1.0): {exc}") from exc
    except Exception as exc:
        raise map_error(exc, spec.raw, "USB enumeration") from exc
    if device is None:
        who = f"{vid:04x}:{pid:04x}" + (f" serial {want_serial!r}" if want_serial else "")
        raise LinkClosedError(f"{spec.raw}: no USB device {who} present")
    try:
        with contextlib.suppress(NotImplementedError, usb.core.USBError):
            if device.is_kernel_driver_active(intf_no):
                device.detach_kernel_driver(intf_no)
        try:
            cfg = device.get_active_configuration()
        except usb.core.USBError:
            device.set_configuration()
            cfg = device.get_active_configuration()
        intf = usb.util.find_descriptor(cfg, bInterfaceNumber=intf_no)
        if intf is None:
            raise LinkError(f"{spec.raw}: the device has no interface {intf_no}")
        try:
            usb.util.claim_interface(device, intf_no)
        except usb.core.USBError as exc:
            if getattr(exc, "errno", None) == errno.EBUSY:
                raise LinkError(f"{spec.raw}: interface {intf_no} is claimed by another process") from exc
            raise

        def _bulk(direction: int) -> int | None:
            for ep in intf:
                if (
                    usb.util.endpoint_type(ep.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK
                    and usb.util.endpoint_direction(ep.bEndpointAddress) == direction
                ):
                    return int(ep.bEndpointAddress)
            return None

        ep_out, ep_in = _bulk(usb.util.ENDPOINT_OUT), _bulk(usb.util.ENDPOINT_IN)
        if ep_out is None or ep_in is None:
            raise LinkError(f"{spec.raw}: interface {intf_no} lacks a bulk OUT and a bulk IN endpoint")
    except LinkError:
        with contextlib.suppress(Exception):
            usb.util.dispose_resources(device)
        raise
    except Exception as exc:
        with contextlib.suppress(Exception):
            usb.util.dispose_resources(device)
        raise map_error(exc, spec.raw, "USB open") from exc
    return UsbTransport(
        device,
        intf_no,
        ep_out,
        ep_in,
        spec.raw,
        read_timeout_s=read_timeout_s,
        write_timeout_s=write_timeout_s,
    )


# ---------------------------------------------------------------------------------------------
# simulated device: a pyusb backend forwarding bulk transfers to a Unix socket


class _SimHandle:
    """An open simulated device: the socket to the simulator."""

    def __init__(self, path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(2.0)
        self.sock.connect(path)
        self.sock.setblocking(False)
        self.configuration = 0
        self.claimed: set[int] = set()
        self.lock = threading.Lock()
        self.eof = False


def _usb_error(text: str, code: int) -> Exception:
    err: Exception = usb.core.USBError(text, None, code)
    return err


class SimSocketBackend(usb.backend.IBackend):  # type: ignore[misc]
    """A pyusb backend (:class:`usb.backend.IBackend`) with one simulated board.

    It enumerates one device with the board's descriptors (module docstring) while ``socket_path``
    exists; opening the device connects to that Unix stream socket, ``bulkWrite`` to EP 0x01 sends
    the bytes, ``bulkRead`` from EP 0x81 receives them. A closed socket reads as a disconnected
    device (``USBError`` ENODEV), a read with no data as ``USBTimeoutError``.

    Parameters
    ----------
    socket_path
        The simulator's ``--usb-socket``.
    serial
        The ``iSerialNumber`` string reported.
    high_speed
        512-byte bulk packets (else 64, full speed).
    """

    def __init__(self, socket_path: str, *, serial: str = "SIM0001", high_speed: bool = True) -> None:
        self.socket_path = socket_path
        self.serial = serial
        self.packet = 512 if high_speed else 64
        self.strings = {1: "piezod", 2: "piezod DAC board (simulated)", 3: serial}

    # -- enumeration and descriptors --------------------------------------------------------

    def enumerate_devices(self) -> Any:
        if os.path.exists(self.socket_path):
            yield "simsock0"

    def get_parent(self, dev: Any) -> None:
        return None

    def get_device_descriptor(self, dev: Any) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=0,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=BOARD_VID,
            idProduct=BOARD_PID,
            bcdDevice=0x0100,
            iManufacturer=1,
            iProduct=2,
            iSerialNumber=3,
            bNumConfigurations=1,
            address=1,
            bus=1,
            port_number=1,
            port_numbers=(1,),
            speed=3 if self.packet == 512 else 2,
        )

    def get_configuration_descriptor(self, dev: Any, config: int) -> SimpleNamespace:
        if config != 0:
            raise IndexError(f"configuration index {config}")
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=9 + 9 + 7 + 7,
            bNumInterfaces=1,
            bConfigurationValue=1,
            iConfiguration=0,
            bmAttributes=0x80,
            bMaxPower=50,
            extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev: Any, intf: int, alt: int, config: int) -> SimpleNamespace:
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError(f"interface {intf} alt {alt} config {config}")
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=0,
            bAlternateSetting=0,
            bNumEndpoints=2,
            bInterfaceClass=0xFF,
            bInterfaceSubClass=0,
            bInterfaceProtocol=0,
            iInterface=0,
            extra_descriptors=[],
        )

    def get_endpoint_descriptor(self, dev: Any, ep: int, intf: int, alt: int, config: int) -> SimpleNamespace:
        if ep not in (0, 1) or (intf, alt, config) != (0, 0, 0):
            raise IndexError(f"endpoint {ep}")
        return SimpleNamespace(
            bLength=7,
            bDescriptorType=5,
            bEndpointAddress=EP_OUT if ep == 0 else EP_IN,
            bmAttributes=0x02,
            wMaxPacketSize=self.packet,
            bInterval=0,
            bRefresh=0,
            bSynchAddress=0,
            extra_descriptors=[],
        )

    # -- device handle -----------------------------------------------------------------------

    def open_device(self, dev: Any) -> _SimHandle:
        try:
            return _SimHandle(self.socket_path)
        except OSError as exc:
            raise _usb_error(f"cannot open the simulated device: {exc}", errno.ENODEV) from exc

    def close_device(self, dev_handle: _SimHandle) -> None:
        with contextlib.suppress(OSError):
            dev_handle.sock.close()

    def set_configuration(self, dev_handle: _SimHandle, config_value: int) -> None:
        if config_value not in (0, 1):
            raise _usb_error(f"invalid configuration {config_value}", errno.EINVAL)
        dev_handle.configuration = config_value

    def get_configuration(self, dev_handle: _SimHandle) -> int:
        return dev_handle.configuration

    def set_interface_altsetting(self, dev_handle: _SimHandle, intf: int, altsetting: int) -> None:
        if (intf, altsetting) != (0, 0):
            raise _usb_error(f"invalid alternate setting {intf}/{altsetting}", errno.EINVAL)

    def claim_interface(self, dev_handle: _SimHandle, intf: int) -> None:
        if intf != 0:
            raise _usb_error(f"no interface {intf}", errno.ENOENT)
        dev_handle.claimed.add(intf)

    def release_interface(self, dev_handle: _SimHandle, intf: int) -> None:
        dev_handle.claimed.discard(intf)

    def is_kernel_driver_active(self, dev_handle: _SimHandle, intf: int) -> bool:
        return False

    def detach_kernel_driver(self, dev_handle: _SimHandle, intf: int) -> None:
        return None

    def clear_halt(self, dev_handle: _SimHandle, ep: int) -> None:
        return None

    # -- transfers ---------------------------------------------------------------------------

    def _check(self, dev_handle: _SimHandle, ep: int, want: int, intf: int) -> None:
        if dev_handle.configuration != 1:
            raise _usb_error("device not configured", errno.EPIPE)
        if intf not in dev_handle.claimed:
            raise _usb_error(f"interface {intf} not claimed", errno.EACCES)
        if ep != want:
            raise _usb_error(f"no bulk endpoint 0x{ep:02x} in this direction", errno.EPIPE)

    def bulk_write(
        self, dev_handle: _SimHandle, ep: int, intf: int, data: array.array[int], timeout: int
    ) -> int:
        self._check(dev_handle, ep, EP_OUT, intf)
        view = memoryview(data).cast("B")
        deadline = time.monotonic() + timeout / 1000.0
        sent = 0
        while sent < len(view):
            try:
                sent += dev_handle.sock.send(view[sent:])
                continue
            except BlockingIOError:
                pass
            except OSError as exc:
                raise _usb_error(f"no such device (simulator socket: {exc})", errno.ENODEV) from exc
            left = deadline - time.monotonic()
            if left <= 0:
                raise usb.core.USBTimeoutError("bulk write timed out", None, errno.ETIMEDOUT)
            select.select([], [dev_handle.sock], [], left)
        return sent

    def bulk_read(
        self, dev_handle: _SimHandle, ep: int, intf: int, buff: array.array[int], timeout: int
    ) -> int:
        self._check(dev_handle, ep, EP_IN, intf)
        if dev_handle.eof:
            raise _usb_error("no such device (simulator closed the socket)", errno.ENODEV)
        ready, _, _ = select.select([dev_handle.sock], [], [], timeout / 1000.0)
        if not ready:
            raise usb.core.USBTimeoutError("bulk read timed out", None, errno.ETIMEDOUT)
        try:
            n = dev_handle.sock.recv_into(memoryview(buff).cast("B"))
        except BlockingIOError:
            raise usb.core.USBTimeoutError("bulk read timed out", None, errno.ETIMEDOUT) from None
        except OSError as exc:
            raise _usb_error(f"no such device (simulator socket: {exc})", errno.ENODEV) from exc
        if n == 0:
            dev_handle.eof = True
            raise _usb_error("no such device (simulator closed the socket)", errno.ENODEV)
        return n

    def ctrl_transfer(
        self,
        dev_handle: _SimHandle,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: array.array[int],
        timeout: int,
    ) -> int:
        if bmRequestType & 0x80 and bRequest == 0x06 and (wValue >> 8) == 3:
            index = wValue & 0xFF
            if index == 0:
                desc = bytes([4, 3, 0x09, 0x04])
            elif index in self.strings:
                text = self.strings[index].encode("utf-16-le")
                desc = bytes([2 + len(text), 3]) + text
            else:
                raise _usb_error(f"no string descriptor {index}", errno.EPIPE)
            n = min(len(desc), len(data))
            data[:n] = array.array("B", desc[:n])
            return n
        raise _usb_error(f"control request 0x{bmRequestType:02x}/0x{bRequest:02x} not supported", errno.EPIPE)


__all__ = [
    "BACKEND_ENV",
    "BOARD_PID",
    "BOARD_VID",
    "EP_IN",
    "EP_OUT",
    "SimSocketBackend",
    "UsbTransport",
    "backend_from_spec",
    "open_usb",
]
