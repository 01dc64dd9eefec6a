"""How long the calling thread waited for a CPU, for the engine's slow-block report.

A streaming thread that is late was either running (its own CPU time), runnable but not given a
core (the machine is busy: other processes or threads on the cores), or not runnable at all
(blocked on the interpreter lock another thread holds, or on I/O). Linux counts the second as
the thread's run-queue delay (the second field of ``/proc/thread-self/schedstat``, in ns); with
the thread's CPU time and the wall time it splits a stall into the three. Where the file does
not exist (another OS, a kernel without scheduler statistics) the delay is unknown (NaN).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading

_SCHEDSTAT = "/proc/thread-self/schedstat"
_local = threading.local()


class _ThreadFile:
    """One thread's open ``schedstat``, closed with the thread's local storage."""

    def __init__(self) -> None:
        try:
            self.fd = os.open(_SCHEDSTAT, os.O_RDONLY)
        except OSError:
            self.fd = -1

    def __del__(self) -> None:
        if self.fd >= 0:
            with contextlib.suppress(OSError):  # already closed at the interpreter's exit
                os.close(self.fd)


def _fd() -> int:
    """This thread's ``schedstat`` (-1: not available); opened once per thread, because
    ``thread-self`` names the thread that opens it."""
    f: _ThreadFile | None = getattr(_local, "file", None)
    if f is None:
        f = _local.file = _ThreadFile()
    return f.fd


def run_delay_s() -> float:
    """Seconds the calling thread has waited on a run queue since it started (NaN: unknown).

    Differences of two calls in one thread are what it waited for a core between them.
    """
    fd = _fd()
    if fd < 0:
        return math.nan
    try:
        fields = os.pread(fd, 128, 0).split()
        return int(fields[1]) * 1e-9
    except (OSError, IndexError, ValueError):
        return math.nan


__all__ = ["run_delay_s"]
