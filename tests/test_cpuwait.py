"""The streaming thread's wait for a core, which the engine's slow-block warning reports."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from piezod.service import cpuwait

_TWO_ON_ONE_CORE = """
import os, sys, time
from piezod.service import cpuwait
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
child = os.fork()
start = time.monotonic()
before = cpuwait.run_delay_s()
while time.monotonic() - start < 0.4:
    pass
if child == 0:
    os._exit(0)
os.waitpid(child, 0)
print(cpuwait.run_delay_s() - before)
"""


@pytest.mark.skipif(not Path("/proc/thread-self/schedstat").exists(), reason="no scheduler statistics")
def test_a_thread_that_shares_its_core_waits_for_it() -> None:
    # two busy processes pinned to one core: each waits for it about half the time, whatever else
    # the machine runs (more load only adds to the wait)
    out = subprocess.run(
        [sys.executable, "-c", _TWO_ON_ONE_CORE], capture_output=True, text=True, check=True, timeout=60
    )
    waited = float(out.stdout)
    assert 0.08 < waited < 10.0, out


def test_each_thread_reads_its_own_wait_and_unknown_is_nan(monkeypatch: pytest.MonkeyPatch) -> None:
    got: list[float] = []

    def read() -> None:
        got.append(cpuwait.run_delay_s())
        got.append(cpuwait.run_delay_s())

    t = threading.Thread(target=read)
    t.start()
    t.join()
    if Path("/proc/thread-self/schedstat").exists():
        assert 0.0 <= got[0] <= got[1] < 60.0
    monkeypatch.setattr(cpuwait, "_SCHEDSTAT", "/nonexistent/schedstat")
    got.clear()
    t = threading.Thread(target=read)  # a new thread opens the file afresh
    t.start()
    t.join()
    assert all(math.isnan(g) for g in got)
