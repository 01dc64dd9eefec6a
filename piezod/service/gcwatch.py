"""Time spent in the interpreter's garbage collector, for the engine's slow-block report.

A collection of the oldest generation holds the interpreter lock while it walks every tracked
object; in the daemon's process that stops the streaming thread too. The engine's "slow block"
warning says how much of the block's time went to collections (and how much was the streaming
thread's own CPU), so a stall can be told from a slow model or a starved process.
"""

from __future__ import annotations

import gc
import threading
import time
from typing import Any

_lock = threading.Lock()
_started: dict[int, float] = {}
_total_s = 0.0
_installed = False


def _callback(phase: str, info: dict[str, Any]) -> None:
    global _total_s
    ident = threading.get_ident()
    if phase == "start":
        _started[ident] = time.perf_counter()
        return
    t0 = _started.pop(ident, None)
    if t0 is not None:
        with _lock:
            _total_s += time.perf_counter() - t0


def install() -> None:
    """Start timing the collections of this process (idempotent)."""
    global _installed
    with _lock:
        if not _installed:
            gc.callbacks.append(_callback)
            _installed = True


def collection_seconds() -> float:
    """Seconds spent in garbage collections since :func:`install` (all threads)."""
    with _lock:
        return _total_s


__all__ = ["collection_seconds", "install"]
