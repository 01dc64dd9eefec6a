"""The real daemon for fault tests: ``piezod serve`` as a subprocess on the real hil_sim over a pty.

:class:`RealDaemon` starts the simulator (``python -m hil_sim`` with a stable ``--link`` path, so
it can be killed and started again on "the same cable") and ``piezod serve`` on it, waits for
``READY=1`` on a test ``NOTIFY_SOCKET``, and talks to the API over its Unix socket. Nothing is
faked: these are the processes a user runs.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType

from hil_sim.server import SimProcess, spawn_sim
from piezod.client import PiezodClient
from piezod.config import default_sim_config_path
from piezod.link.bench import _proc_cpu_s
from piezod.service.schemas import Status

#: Slow machines (2 shared cores) get more time; tests wait on conditions, never on wall clock alone.
SLOW = float(os.environ.get("PIEZOD_TEST_TIME_SCALE", "1"))


#: Scheduling priority (nice) of the simulator and the daemon when the tests may raise it (root).
#: The simulator stands in for a board with its own clock, which other work on the PC cannot
#: starve; the daemon runs as a service with priority over other work (see the systemd unit). On a
#: test machine saturated by other jobs, equal priority would measure that load, not piezod.
SIM_NICE = -10
DAEMON_NICE = -5


def _renice(pid: int, nice: int) -> None:
    """Set the nice value of every thread of ``pid`` (threads started later inherit it)."""
    with contextlib.suppress(OSError):
        for tid in os.listdir(f"/proc/{pid}/task"):
            os.setpriority(os.PRIO_PROCESS, int(tid), nice)


def _nice(nice: int) -> Callable[[], None]:
    def apply() -> None:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, 0, nice)

    return apply


class Notify:
    """A ``NOTIFY_SOCKET`` collecting the daemon's sd_notify datagrams."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.path = path
        self.messages: list[str] = []

    def wait_for(self, key: str, timeout_s: float, proc: subprocess.Popen[bytes] | None = None) -> None:
        deadline = time.monotonic() + timeout_s * SLOW
        while time.monotonic() < deadline:
            if any(key in m.split("\n") for m in self.messages):
                return
            if proc is not None and proc.poll() is not None:
                raise AssertionError(f"the daemon exited with {proc.returncode} before {key}")
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except TimeoutError:
                continue
        raise AssertionError(f"no {key} within {timeout_s} s; got {self.messages}")

    def close(self) -> None:
        self.sock.close()


class RealDaemon:
    """``piezod serve`` on a running ``hil_sim``; a context manager.

    Parameters
    ----------
    tmp
        A directory for the link, socket, recordings and logs.
    config
        Scanner YAML (default: the simulated stage).
    sim_args
        Extra simulator options (fault injection: ``--corrupt-rate``, ``--drop-rate``...).
    serve_args
        Extra ``piezod serve`` options.
    recordings
        Recording directory (default ``tmp/rec``).
    api, token
        ``--api`` (default ``unix:tmp/api.sock``) and the bearer token the client sends.
    port_via
        Given the simulator's path, the path the daemon connects to instead (a proxy between them).
    """

    def __init__(
        self,
        tmp: Path,
        *,
        config: Path | None = None,
        sim_args: Sequence[str] = (),
        serve_args: Sequence[str] = (),
        recordings: Path | None = None,
        api: str | None = None,
        token: str | None = None,
        port_via: Callable[[str], str] | None = None,
    ) -> None:
        self.tmp = tmp
        self.config = config or default_sim_config_path()
        self.sim_args = tuple(sim_args)
        self.serve_args = tuple(serve_args)
        self.link = tmp / "board"
        self.socket = tmp / "api.sock"
        self.api = api or f"unix:{self.socket}"
        self.token = token
        self.port_via = port_via
        self.recordings = recordings or tmp / "rec"
        self.log_path = tmp / "daemon.log"
        self.sim: SimProcess | None = None
        self.proc: subprocess.Popen[bytes] | None = None
        self.notify = Notify(tmp / "notify.sock")

    def start_sim(self) -> SimProcess:
        self.sim = spawn_sim(self.config, link=str(self.link), extra_args=self.sim_args, timeout_s=60 * SLOW)
        _renice(self.sim.pid, SIM_NICE)
        return self.sim

    def __enter__(self) -> RealDaemon:
        sim = self.start_sim()
        port = self.port_via(sim.path) if self.port_via is not None else str(self.link)
        env = dict(os.environ, NOTIFY_SOCKET=str(self.notify.path), WATCHDOG_USEC="5000000")
        cmd = [
            sys.executable,
            "-m",
            "piezod",
            "serve",
            "--config",
            str(self.config),
            "--port",
            port,
            "--api",
            self.api,
            "--recordings",
            str(self.recordings),
            *self.serve_args,
        ]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                cmd, env=env, stdout=subprocess.DEVNULL, stderr=log, preexec_fn=_nice(DAEMON_NICE)
            )
        try:
            self.notify.wait_for("READY=1", 60.0, self.proc)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def client(self, timeout: float = 30.0) -> PiezodClient:
        return PiezodClient(self.api, token=self.token, timeout=timeout * SLOW)

    def status(self) -> Status:
        with self.client() as c:
            return c.status()

    def wait_state(self, states: set[str], timeout_s: float) -> Status:
        deadline = time.monotonic() + timeout_s * SLOW
        st = self.status()
        while st.state not in states:
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"state {st.state}, not {states} within {timeout_s} s: {st.faults[-3:]}\n{self.stacks()}"
                )
            time.sleep(0.1)
            st = self.status()
        return st

    def stacks(self) -> str:
        """The daemon's threads' stacks (SIGUSR1 writes them to its log): what a wedged daemon waits for."""
        if self.proc is None or self.proc.poll() is not None:
            return "(the daemon is not running)"
        before = len(self.log_text())
        self.proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        return self.log_text()[before:]

    def log_text(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def kill_sim(self) -> None:
        if self.sim is not None:
            self.sim.kill()  # the link goes with the power, before the pty number is free again
            self.sim.close()
            self.sim = None

    def sigkill(self, sig: signal.Signals = signal.SIGKILL) -> None:
        """End the daemon with ``sig`` (a crash: SIGKILL, or SIGSEGV as a faulting extension would)."""
        assert self.proc is not None
        self.proc.send_signal(sig)
        self.proc.wait()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        hung = False
        try:
            if self.proc is not None and self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.proc.wait(30 * SLOW)
                except subprocess.TimeoutExpired:
                    hung = True
                    self.proc.kill()
                    self.proc.wait()
        finally:
            if self.sim is not None:
                # kept beside the daemon's log: a failure's evidence is on both sides of the link
                (self.tmp / "sim.log").write_text(self.sim.stderr_text(), encoding="utf-8")
                self.sim.close()
            self.notify.close()
        # SIGTERM must stop the daemon (ramp to safe, flush, exit): a hang is a failure, not a kill
        if hung and exc_type is None:
            raise AssertionError(f"the daemon outlived SIGTERM by {30 * SLOW:g} s: {self.log_path}")


def _busy_s() -> float:
    """CPU seconds the whole machine has spent busy since boot (``/proc/stat``)."""
    with open("/proc/stat") as f:
        fields = [int(v) for v in f.readline().split()[1:]]
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system, all threads) process ``pid`` has used; 0 once it is gone."""
    return _proc_cpu_s(pid) or 0.0


class OtherWork:
    """How much of the machine work other than the test's own processes took, over a window.

    The load average lags by a minute and counts the test's own processes; this measures the
    window itself: the machine's busy CPU time (``/proc/stat``) less what this process and ``pids``
    (the daemon, the simulator) used.

    Parameters
    ----------
    pids
        The test's child processes.
    """

    def __init__(self, pids: Sequence[int]) -> None:
        self.pids = tuple(pids)
        self._t0 = time.monotonic()
        self._busy0 = _busy_s()
        self._own0 = self._own()
        self._end: tuple[float, float, float] | None = None

    def stop(self) -> None:
        """End the window (before the test's processes exit: their CPU time goes with them)."""
        self._end = (time.monotonic(), _busy_s(), self._own())

    def _own(self) -> float:
        return _cpu_s(os.getpid()) + sum(_cpu_s(p) for p in self.pids)

    def cores(self) -> tuple[float, float]:
        """(cores the machine kept busy, cores other work kept busy) on average since the start."""
        t, busy_s, own_s = self._end or (time.monotonic(), _busy_s(), self._own())
        span = max(t - self._t0, 1e-3)
        busy = (busy_s - self._busy0) / span
        return busy, max(busy - (own_s - self._own0) / span, 0.0)

    def saturated(self) -> bool:
        """The machine was busy on (nearly) every core, at least a quarter of one of them by others."""
        busy, others = self.cores()
        return busy >= 0.9 * (os.cpu_count() or 1) and others >= 0.25
