"""USB transport: a board with vendor-class bulk endpoints, through pyusb.

The board enumerates as (what :func:`open_usb` looks for, and the descriptors the simulator's
pyusb backend :class:`hil_sim.usb_backend.SimSocketBackend` reports):

- ``idVendor`` 0x1209 (pid.codes), ``idProduct`` 0x7A01, ``iSerialNumber`` = the board serial;
- configuration 1 with one interface (number 0, class 0xFF vendor specific, no alternate
  settings) holding one bulk OUT endpoint (0x01) and one bulk IN endpoint (0x81), 512-byte
  packets at high speed (64 at full speed);
- the bulk endpoints carry the same byte stream as the serial link (COBS frames delimited by 0x00,
  ``firmware_proto/PROTOCOL.md``); transfer boundaries mean nothing.

URL: ``usb://VID:PID[?serial=S][&interface=N][&backend=simsock:/path/to.sock]``. Without
``backend`` the environment variable ``PIEZOD_USB_BACKEND`` is used (same syntax), else pyusb's
default (libusb1). ``simsock:PATH`` selects the simulator's pyusb backend (reached through
:mod:`piezod.simulator`) that enumerates one simulated device and forwards its bulk
transfers to the simulator's ``--usb-socket`` (a Unix stream socket with the raw bulk byte
stream). That is how the USB code path is tested; a real USB device and libusb were not exercised.
"""

from __future__ import annotations

import array
import contextlib
import errno
import os
from typing import Any

import usb.backend
import usb.core
import usb.util

from piezod.errors import ConfigError, LinkClosedError, LinkError, LinkTimeoutError
from piezod.link.transport import (
    DEFAULT_READ_TIMEOUT_S,
    DEFAULT_WRITE_TIMEOUT_S,
    READ_CHUNK,
    InFlight,
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
        self._buf = array.array("B", bytes(READ_CHUNK))
        self._inflight = InFlight(url)  # the handle is released only when no transfer is in progress

    @property
    def closed(self) -> bool:
        return self._inflight.closed

    def _error(self, exc: BaseException, what: str) -> LinkError:
        if isinstance(exc, usb.core.USBTimeoutError):
            return LinkTimeoutError(f"{self.url}: {what} timed out: {exc}")
        code = getattr(exc, "errno", None)
        if self._inflight.closed or code in _USB_CLOSED_ERRNOS or "no such device" in str(exc).lower():
            return LinkClosedError(f"{self.url}: {what} failed: {exc}")
        return map_error(exc, self.url, what)

    def read(self, max_bytes: int = READ_CHUNK) -> bytes:
        self._inflight.enter()
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
            self._inflight.leave()

    def write(self, data: bytes) -> None:
        if not data:
            return
        self._inflight.enter()
        try:
            n = self.device.write(self.ep_out, data, max(1, round(self.write_timeout_s * 1000)))
        except Exception as exc:
            raise self._error(exc, "bulk write") from exc
        finally:
            self._inflight.leave()
        if n != len(data):
            raise LinkTimeoutError(f"{self.url}: bulk write accepted {n} of {len(data)} bytes")

    def close(self) -> None:
        """Release the interface once the transfers in progress ended (they time out by themselves)."""
        if not self._inflight.close(self.write_timeout_s + 1.0):
            return
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
        from piezod.simulator import usb_sim_backend

        return usb_sim_backend(arg)
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
__all__ = [
    "BACKEND_ENV",
    "BOARD_PID",
    "BOARD_VID",
    "EP_IN",
    "EP_OUT",
    "UsbTransport",
    "backend_from_spec",
    "open_usb",
]
