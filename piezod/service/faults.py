"""The engine's fault log, and what each link event means as a fault.

:class:`FaultLog` keeps the last faults for the status (repeats of one kind within
:data:`FAULT_REPEAT_S` are counted, not listed again) and tells a listener (the API's event
hub); :func:`link_event_fault` turns a :class:`~piezod.link.session.LinkEvent` into the fault it
reports, if any.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Literal

from firmware_proto import NO_INDEX
from piezod.link.session import (
    BoardFault,
    HostLimitFault,
    LinkDown,
    LinkEvent,
    LinkLost,
    Reconnected,
    SensorGap,
)
from piezod.service.schemas import FaultInfo

log = logging.getLogger("piezod.service.engine")

FaultSource = Literal["board", "host", "link"]

#: Faults of one (source, code) closer together than this (s) are counted, not listed again.
FAULT_REPEAT_S = 1.0


class FaultLog:
    """The last faults, with repeats of one kind counted (thread-safe).

    Parameters
    ----------
    t0
        :func:`time.monotonic` at the engine's start (fault times are relative to it).
    listener
        Called with every fault that is listed (not with counted repeats).
    """

    def __init__(self, t0: float, listener: Callable[[FaultInfo], None] | None = None) -> None:
        self.t0 = t0
        self.listener = listener
        self._lock = threading.Lock()
        self._faults: deque[FaultInfo] = deque(maxlen=200)
        self._last: dict[tuple[str, str], float] = {}
        self._counts: dict[tuple[str, str], int] = {}

    def add(self, source: FaultSource, code: str, message: str, index: int | None = None) -> None:
        """Record a fault (and tell the listener); repeats of one kind within a second are counted only."""
        now = time.monotonic() - self.t0
        key = (source, code)
        with self._lock:
            self._counts[key] = self._counts.get(key, 0) + 1
            last = self._last.get(key)
            if last is not None and now - last < FAULT_REPEAT_S:
                return
            self._last[key] = now
            info = FaultInfo(time_s=now, source=source, code=code, message=message, index=index)
            self._faults.append(info)
        log.warning("fault %s/%s: %s", source, code, message)
        if self.listener is not None:
            self.listener(info)

    def recent(self, n: int = 20) -> list[FaultInfo]:
        """The last ``n`` listed faults, oldest first."""
        with self._lock:
            return list(self._faults)[-n:]

    def count(self, source: FaultSource, code: str) -> int:
        """How often a fault of this kind happened (repeats included)."""
        with self._lock:
            return self._counts.get((source, code), 0)


def link_event_fault(ev: LinkEvent) -> tuple[FaultSource, str, str, int | None] | None:
    """``(source, code, message, index)`` of the fault a link event reports (None: not a fault)."""
    if isinstance(ev, BoardFault):
        index = None if ev.fault.index == NO_INDEX else int(ev.fault.index)
        return "board", ev.code.name, str(ev.fault), index
    if isinstance(ev, HostLimitFault):
        message = f"{ev.count} samples of axis {ev.axis} clamped (worst {ev.worst_v:.4g} V)"
        return "host", "LIMIT", message, ev.first_index
    if isinstance(ev, LinkDown | LinkLost):
        return "link", type(ev).__name__.upper(), str(ev.error), None
    if isinstance(ev, Reconnected):
        message = f"board back after {ev.downtime_s:.1f} s (watchdog fired: {ev.watchdog_fired})"
        return "link", "RECONNECTED", message, None
    if isinstance(ev, SensorGap) and not ev.explained:
        message = f"{ev.missing_rows} sensor rows missing at {ev.expected_index}"
        return "link", "SENSOR_GAP", message, ev.expected_index
    return None


__all__ = ["FAULT_REPEAT_S", "FaultLog", "FaultSource", "link_event_fault"]
