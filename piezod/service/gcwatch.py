"""Time spent in the interpreter's garbage collector, for the engine's slow-block report.

A collection of the oldest generation holds the interpreter lock while it walks every tracked
object; in the daemon's process that stops the streaming thread too. The engine's "slow block"
warning says how much of the block's time went to collections (and how much was the streaming
thread's own CPU), so a stall can be told from a slow model or a starved process.
"""

from __future__ import annotations

import gc
import time
from typing import Any

# Collections never overlap (the collector runs one at a time, holding the interpreter lock), so
# the callback needs no lock of its own; one taken there could deadlock a thread whose allocation
# under that lock started the collection.
_started = 0.0
_total_s = 0.0


def _callback(phase: str, info: dict[str, Any]) -> None:
    global _started, _total_s
    if phase == "start":
        _started = time.perf_counter()
    else:
        _total_s += time.perf_counter() - _started


def install() -> None:
    """Start timing the collections of this process (idempotent)."""
    if _callback not in gc.callbacks:
        gc.callbacks.append(_callback)


def collection_seconds() -> float:
    """Seconds spent in garbage collections since :func:`install` (all threads)."""
    return _total_s


__all__ = ["collection_seconds", "install"]
