"""Test helpers: does a process started by another outlive it when that one is killed outright?"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path


def _stat_fields(pid: int | str) -> list[str] | None:
    """The fields of ``/proc/PID/stat`` after the command name (state first), None once it is gone."""
    try:
        stat = (Path("/proc") / str(pid) / "stat").read_text(encoding="ascii")
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()


def running(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, reparented to init and not yet reaped, counts as ended)."""
    fields = _stat_fields(pid)
    return fields is not None and fields[0] != "Z"


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            fields = _stat_fields(entry.name)
            if fields is not None and int(fields[1]) == pid:
                out.append(int(entry.name))
    return out


def kill_parent_of(code: str, timeout_s: float = 120.0) -> int:
    """Run ``python -c code``, which starts a process and prints its pid; SIGKILL it (no handler,
    no context manager runs) and return the pid it printed."""
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert parent.stdout is not None
        ready, _, _ = select.select([parent.stdout], [], [], timeout_s)
        line = parent.stdout.readline() if ready else b""
        assert parent.stderr is not None
        assert line.strip().isdigit(), parent.stderr.read().decode() if parent.poll() is not None else line
        return int(line)
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()


def ended_within(pids: list[int], timeout_s: float) -> bool:
    """Wait until none of ``pids`` runs; False (and every one still running SIGKILLed) after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while any(running(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    alive = [p for p in pids if running(p)]
    for p in alive:
        with contextlib.suppress(ProcessLookupError):
            os.kill(p, signal.SIGKILL)
    return not alive


@contextlib.contextmanager
def piezod_process(args: list[str]) -> Iterator[subprocess.Popen[str]]:
    """``python -m piezod ARGS`` with its output piped; SIGKILLed on leaving if still running."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "piezod", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def sigterm(proc: subprocess.Popen[str], timeout_s: float) -> str:
    """Send SIGTERM to ``proc``, wait up to ``timeout_s`` for it to end; its standard error."""
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=timeout_s)
    return err
