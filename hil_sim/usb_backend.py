"""A pyusb backend with one simulated board: bulk transfers forwarded to the simulator's USB socket.

:class:`SimSocketBackend` implements :class:`usb.backend.IBackend`: it enumerates one device with
the board's descriptors (vendor 0x1209, product 0x7A01, one vendor-class interface with bulk
endpoints 0x01 OUT / 0x81 IN) and forwards bulk transfers to a Unix stream socket served by
``python -m hil_sim --usb-socket PATH`` (:mod:`hil_sim.usb_bridge`). The host selects it with
``usb://1209:7a01?backend=simsock:PATH``; this is how the host's USB code path is tested without
libusb or a device. It lives in hil_sim because it is the simulator's side of the USB link.
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

from hil_sim.usb_bridge import USB_PRODUCT_ID, USB_VENDOR_ID

BOARD_VID = USB_VENDOR_ID
BOARD_PID = USB_PRODUCT_ID
EP_OUT = 0x01
"""Bulk OUT endpoint address (host -> board)."""
EP_IN = 0x81
"""Bulk IN endpoint address (board -> host)."""


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


__all__ = ["EP_IN", "EP_OUT", "SimSocketBackend"]
