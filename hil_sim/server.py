"""The simulator process: a :class:`~hil_sim.board.Board` served on a real pseudo-terminal.

``python -m hil_sim`` (or ``piezod sim``) opens a pty (raw mode, non-blocking master), prints
ONE line on stdout -- the slave path, or the ``--link`` symlink -- and serves until SIGTERM /
SIGINT (exit 0). Simulated time follows the monotonic wall clock: a ``select`` loop with a short
tick feeds the host's bytes to the board and calls :meth:`Board.advance`. When an iteration comes
later than :data:`STALL_WARN_S` (this process was not scheduled, or its own work took that long),
the simulated clock runs one tick over the stall and the stall is logged: a board's clock and its
receiver run together and are never starved, so the bytes that waited are taken in before the
board plays on, and simulated time lags the wall clock from then on (the host paces by the played
index its STATUS frames report, not by its own clock).

- ``--link PATH`` keeps a symlink ``PATH -> /dev/pts/N`` (like ``/dev/serial/by-id``).
- SIGUSR1 simulates an unplug: the master is closed (the host sees EIO / hang-up), the link
  and the USB socket disappear for ``--unplug-s`` seconds, then a new pty (and socket) appear
  and the link is re-created. The board keeps running meanwhile (its watchdog ramps the outputs
  to safe when the host goes silent) and keeps its state and latched faults.
- ``--usb-socket PATH`` also serves the board's USB bulk byte stream (:mod:`hil_sim.usb_bridge`).
- Without a host (nobody has the pty open) the board's output is discarded, as a UART's would be.

:func:`spawn_sim` starts the simulator as a subprocess for tests and for the daemon's ``--sim``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import logging
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
import tty
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType, TracebackType

import yaml

from hil_sim.board import Board, BoardConfig
from hil_sim.errors import SimConfigError, SimError, SimLinkError, SimLinkTimeoutError
from hil_sim.microscope import MicroscopeConfig
from hil_sim.stage import resolve_stage
from hil_sim.usb_bridge import UsbSocketServer

log = logging.getLogger("hil_sim.server")

DEFAULT_TICK_S = 0.002
"""Longest wait of the select loop (s): the granularity of simulated time without host traffic."""
DEFAULT_UNPLUG_S = 2.0
_READ_CHUNK = 1 << 16
#: A loop iteration this late is a stall (s): the simulated clock runs one tick over it, and it is logged.
STALL_WARN_S = 0.05
_MAX_READ_PER_STEP = 1 << 20
_MAX_BACKLOG = 8 << 20
_DEFAULT_FIFO_DEPTH: int = BoardConfig().fifo_depth_samples


class PtyPort:
    """The board's end of a pseudo-terminal; the host opens the slave path.

    Parameters
    ----------
    link
        Optional symlink kept pointing at the slave (replaced atomically).
    """

    def __init__(self, link: str | Path | None = None) -> None:
        self.link = Path(link) if link is not None else None
        self.path: str | None = None
        self._master: int | None = None
        self._present = False
        self._backlog = bytearray()
        self._dropped_bytes = 0
        if self.link is not None and self.link.exists() and not self.link.is_symlink():
            raise SimLinkError(f"--link {self.link}: exists and is not a symlink; refusing to replace it")

    @property
    def is_open(self) -> bool:
        """The pty exists (the device is plugged in)."""
        return self._master is not None

    @property
    def host_present(self) -> bool:
        """Somebody has the slave open."""
        return self._present

    @property
    def public_path(self) -> str:
        """What the host should open: the link if any, else the slave path."""
        if self.link is not None:
            return str(self.link)
        assert self.path is not None
        return self.path

    def open(self) -> str:
        """Create a new pty (raw mode) and point the link at it; returns the slave path."""
        master, slave = os.openpty()
        try:
            tty.setraw(slave)
            path = os.ttyname(slave)
        finally:
            os.close(slave)  # the host opens the path; reading the master gives EIO while nobody has
        os.set_blocking(master, False)
        self._master = master
        self.path = path
        self._present = False
        self._backlog.clear()
        if self.link is not None:
            tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            os.symlink(path, tmp)
            os.replace(tmp, self.link)
        return path

    def close(self) -> None:
        """Remove the link and close the master (the host sees a hang-up).

        In this order: once the master is closed, the system may give its pty number to another
        process, and a host reopening the link must not find it there.
        """
        if self.link is not None and self.link.is_symlink():
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
        if self._master is not None:
            os.close(self._master)
            self._master = None
        self._present = False
        self._backlog.clear()

    def read_fds(self) -> list[int]:
        """File descriptors to select for reading (none while nobody has the slave open)."""
        return [self._master] if self._master is not None and self._present else []

    def write_fds(self) -> list[int]:
        """File descriptors to select for writing (when output is waiting)."""
        return [self._master] if self._master is not None and self._present and self._backlog else []

    def poll(self, readable: set[int], max_bytes: int = _MAX_READ_PER_STEP) -> bytes:
        """Read what the host wrote; also detects a host opening / closing the slave."""
        if self._master is None:
            return b""
        if self._present and self._master not in readable:
            return b""
        chunks: list[bytes] = []
        got = 0
        while got < max_bytes:
            try:
                data = os.read(self._master, _READ_CHUNK)
            except BlockingIOError:
                self._set_present(True)
                break
            except OSError as exc:
                if exc.errno != errno.EIO:
                    raise
                self._set_present(False)
                break
            if not data:
                self._set_present(False)
                break
            self._set_present(True)
            chunks.append(data)
            got += len(data)
        return b"".join(chunks)

    def _set_present(self, present: bool) -> None:
        if present != self._present:
            log.info("host %s %s", "opened" if present else "closed", self.path)
            self._present = present
            if not present:
                self._backlog.clear()

    def write(self, data: bytes) -> None:
        """Queue ``data`` for the host and write what the pty takes; discarded without a host."""
        if self._master is None or not self._present:
            return
        if data:
            if len(self._backlog) + len(data) > _MAX_BACKLOG:
                self._dropped_bytes += len(data)
                log.warning("host not reading %s: dropped %d bytes so far", self.path, self._dropped_bytes)
            else:
                self._backlog += data
        while self._backlog:
            try:
                n = os.write(self._master, self._backlog)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno != errno.EIO:
                    raise
                self._set_present(False)
                return
            del self._backlog[:n]


class SimServer:
    """The select loop pacing a :class:`Board` by the monotonic clock, less the loop's stalls.

    Parameters
    ----------
    board
        The board (its clock origin must be ``clock()``'s).
    pty
        Serve on a pty (with this optional link).
    link
        Symlink kept pointing at the current pty slave.
    usb_socket
        Also serve the USB byte stream on this Unix socket.
    unplug_s
        How long a SIGUSR1 unplug lasts (s).
    tick_s
        Longest select wait (s).
    clock
        Monotonic clock (s).
    parent_fd
        A pipe's read end whose other end the parent process holds: its end of file (the parent
        gone, however it ended, SIGKILL included) stops the server as SIGTERM would. A simulator
        left running by a killed parent would keep its pty, and a core, for nothing.
    """

    def __init__(
        self,
        board: Board,
        *,
        pty: bool = True,
        link: str | Path | None = None,
        usb_socket: str | Path | None = None,
        unplug_s: float = DEFAULT_UNPLUG_S,
        tick_s: float = DEFAULT_TICK_S,
        clock: Callable[[], float] = time.monotonic,
        parent_fd: int | None = None,
    ) -> None:
        if not pty and usb_socket is None:
            raise SimLinkError("nothing to serve: --no-pty needs --usb-socket")
        if not unplug_s >= 0.0:
            raise SimLinkError(f"--unplug-s must be >= 0, got {unplug_s!r}")
        if not 0.0 < tick_s <= 0.1:
            raise SimLinkError(f"tick must lie in (0, 0.1] s, got {tick_s!r}")
        self.board = board
        self.pty = PtyPort(link) if pty else None
        self.usb = UsbSocketServer(usb_socket) if usb_socket is not None else None
        self.unplug_s = unplug_s
        self.tick_s = tick_s
        self.clock = clock
        self._stop_signal: int | None = None
        self._parent_fd = parent_fd
        self._parent_gone = False
        self._unplug_requested = False
        self._replug_at: float | None = None
        self._last_step: float | None = None
        self._last_work = 0.0
        self._lag = 0.0

    @property
    def lag_s(self) -> float:
        """How far the simulated clock is behind ``clock()`` (s): the stalls' total less a tick each."""
        return self._lag

    def sim_time(self) -> float:
        """The simulated board's clock (s): ``clock()`` less the time lost to stalls."""
        return self.clock() - self._lag

    @property
    def public_path(self) -> str:
        """The path printed on stdout: the pty (or its link), else the USB socket."""
        if self.pty is not None:
            return self.pty.public_path
        assert self.usb is not None
        return str(self.usb.path)

    def open(self) -> None:
        """Plug the device in: create the pty / link and the USB socket."""
        if self.pty is not None:
            path = self.pty.open()
            log.info("pty %s%s", path, f" (link {self.pty.link})" if self.pty.link else "")
        if self.usb is not None:
            self.usb.open()

    def close(self) -> None:
        """Unplug: close the pty and the USB socket, remove the link and the socket file."""
        if self.pty is not None:
            self.pty.close()
        if self.usb is not None:
            self.usb.close()

    def request_stop(self, signum: int = signal.SIGTERM) -> None:
        """Stop serving at the next loop iteration."""
        self._stop_signal = signum

    def request_unplug(self) -> None:
        """Simulate an unplug at the next loop iteration."""
        self._unplug_requested = True

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        if signum == signal.SIGUSR1:
            self.request_unplug()
        else:
            self.request_stop(signum)

    def serve_forever(self, ready: Callable[[str], None] | None = None) -> int:
        """Open the ports, call ``ready(path)``, serve until SIGTERM / SIGINT; returns exit status 0.

        The signal handlers (SIGTERM, SIGINT: stop; SIGUSR1: unplug) are installed before the
        ports open, so a signal sent as soon as the path is known is never fatal; they are restored
        and the ports closed (link and socket removed) on return. Main thread only.
        """
        handled = (signal.SIGTERM, signal.SIGINT, signal.SIGUSR1)
        previous = {s: signal.signal(s, self._on_signal) for s in handled}
        try:
            self.open()
            if ready is not None:
                ready(self.public_path)
            while self._stop_signal is None:
                self.step()
        finally:
            self.close()
            for s, h in previous.items():
                signal.signal(s, h)
        if self._parent_gone:
            log.info("stopped: the parent process is gone (end of file on its pipe)")
        else:
            log.info("stopped by %s", signal.Signals(self._stop_signal).name)
        return 0

    def step(self) -> None:
        """One loop iteration: wait for input (at most one tick), feed, advance, write."""
        ports: list[PtyPort | UsbSocketServer] = [p for p in (self.pty, self.usb) if p is not None]
        rfds = [fd for p in ports for fd in p.read_fds()]
        if self._parent_fd is not None:
            rfds.append(self._parent_fd)
        wfds = [fd for p in ports for fd in p.write_fds()]
        if rfds or wfds:
            readable, _, _ = select.select(rfds, wfds, [], self.tick_s)
        else:
            time.sleep(self.tick_s)
            readable = []
        ready = set(readable)
        if self._parent_fd is not None and self._parent_fd in ready and not os.read(self._parent_fd, 4096):
            self._parent_gone = True
            self.request_stop()
        t_step = self.clock()
        if self._last_step is not None and t_step - self._last_step > STALL_WARN_S:
            # A board's clock and its receiver run together and never starve. Were simulated time to
            # run over a stall of this process, the board would play the whole stall from what the pty
            # holds (~0.1 s at 100 kS/s on 3 axes) while the host's next samples wait for room in it:
            # underruns a board would not have had, reported as if the host had fallen behind.
            self._lag += t_step - self._last_step - self.tick_s
            log.warning(
                "simulator loop stalled %.0f ms, %.0f ms of it its own work: the simulated clock ran one "
                "tick over it (%.0f ms behind the wall clock in all)",
                1e3 * (t_step - self._last_step),
                1e3 * self._last_work,
                1e3 * self._lag,
            )
        self._last_step = t_step
        for port in ports:
            data = port.poll(ready)
            if data:
                self.board.feed(data, t_step - self._lag)
        now = self.sim_time()
        self.board.advance(now)
        out = self.board.data_to_send()
        for port in ports:
            port.write(out)
        self._last_work = self.clock() - t_step
        if self._unplug_requested:
            self._unplug_requested = False
            if self._replug_at is None:
                log.warning("unplugged (SIGUSR1) for %g s", self.unplug_s)
                self.close()
                self._replug_at = now + self.unplug_s
        if self._replug_at is not None and now >= self._replug_at:
            self._replug_at = None
            self.open()
            log.warning("plugged in again: %s", self.public_path)


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulator's command-line options (shared by ``python -m hil_sim`` and ``piezod sim``)."""
    src = parser.add_mutually_exclusive_group()
    src.add_argument(
        "--stage",
        "--config",
        dest="config",
        metavar="F",
        help=(
            "scanner YAML with a simulation: section, or a preset name NAME for configs/sim-NAME.yaml"
            " (stage, pi-stage, ...; default: configs/sim-stage.yaml)"
        ),
    )
    parser.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="switch on / set a stage effect, e.g. drift=0.4, resonance=800, resonance.q=20 (repeatable)",
    )
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of sensor noise and faults")
    parser.add_argument(
        "--corrupt-rate", type=float, default=0.0, metavar="R", help="bit-flip probability per byte sent"
    )
    parser.add_argument(
        "--corrupt-in-rate",
        type=float,
        default=0.0,
        metavar="R",
        help="bit-flip probability per byte received (before decoding)",
    )
    parser.add_argument(
        "--drop-rate", type=float, default=0.0, metavar="R", help="probability of dropping a frame sent"
    )
    parser.add_argument("--link", metavar="PATH", help="keep a symlink PATH -> the current pty")
    parser.add_argument(
        "--unplug-s",
        type=float,
        default=DEFAULT_UNPLUG_S,
        metavar="S",
        help=f"duration of a SIGUSR1 unplug (default {DEFAULT_UNPLUG_S:g} s)",
    )
    parser.add_argument("--usb-socket", metavar="PATH", help="also serve the USB bulk byte stream here")
    parser.add_argument(
        "--exit-with-stdin",
        action="store_true",
        help="stop when standard input reaches end of file: a parent holding the other end of a pipe "
        "is gone (how spawn_sim starts the simulator: it never outlives the process that started it)",
    )
    parser.add_argument("--no-pty", action="store_true", help="no pty (needs --usb-socket)")
    parser.add_argument(
        "--fifo-depth",
        type=int,
        default=_DEFAULT_FIFO_DEPTH,
        metavar="N",
        help=f"FIFO depth, samples per channel (default {_DEFAULT_FIFO_DEPTH})",
    )
    parser.add_argument(
        "--tick-ms",
        type=float,
        default=DEFAULT_TICK_S * 1e3,
        metavar="MS",
        help=f"longest wait of the serving loop (default {DEFAULT_TICK_S * 1e3:g} ms)",
    )
    parser.add_argument(
        "--sample",
        metavar="NAME",
        help="simulate a microscope imaging this sample (line-3um, grating-200nm, grating-10um, "
        "steps-100nm, flat): the z channel's ADC then reads the z-piezo voltage / 100; "
        "default: the scanner YAML's simulation.microscope section, else none",
    )
    parser.add_argument(
        "--no-position-sensor",
        action="store_true",
        help="with a microscope: the board has no x / y position sensor (those ADC channels read 0)",
    )
    parser.add_argument(
        "--feedback-bandwidth-hz", type=float, metavar="F", help="with a microscope: z loop bandwidth (Hz)"
    )
    parser.add_argument(
        "--truth-log",
        metavar="PATH",
        help="with a microscope: append the true tip position to PATH (hidden truth for checks)",
    )
    parser.add_argument(
        "--truth-every",
        type=int,
        default=10,
        metavar="N",
        help="with --truth-log: log every N-th played sample (default 10)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log every dropped frame")


def _microscope_from_args(args: argparse.Namespace, stage_path: Path | None) -> MicroscopeConfig:
    """The scanner YAML's ``simulation.microscope`` section, overridden by ``--sample`` /
    ``--no-position-sensor`` / ``--feedback-bandwidth-hz``."""
    section: dict[str, object] = {}
    if stage_path is not None:
        try:
            doc = yaml.safe_load(Path(stage_path).read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError):
            doc = None  # Board.from_scanner_file reports the file's problem
        sim = doc.get("simulation") if isinstance(doc, dict) else None
        found = sim.get("microscope") if isinstance(sim, dict) else None
        if isinstance(found, dict):
            section = dict(found)
    if args.sample is not None:
        section["sample"] = args.sample
    if args.no_position_sensor:
        section["position_sensor"] = False
    if args.feedback_bandwidth_hz is not None:
        section["feedback_bandwidth_hz"] = args.feedback_bandwidth_hz
    section.setdefault("seed", args.seed)
    try:
        return MicroscopeConfig(**section)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise SimConfigError(f"--sample / simulation.microscope: {exc}") from exc


def _setup_logging(verbose: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s hil_sim[%(process)d] %(levelname)s: %(message)s"))
    root = logging.getLogger("hil_sim")
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    root.propagate = False


def run_from_args(args: argparse.Namespace) -> int:
    """Build the board from parsed :func:`add_sim_arguments` options and serve it.

    Raises
    ------
    SimError
        Invalid configuration or options (the caller prints one line and exits 2).
    """
    _setup_logging(args.verbose)
    clock = time.monotonic
    config = BoardConfig(
        fifo_depth_samples=args.fifo_depth,
        corrupt_rate=args.corrupt_rate,
        corrupt_in_rate=args.corrupt_in_rate,
        drop_rate=args.drop_rate,
    )
    if args.sample is not None or args.no_position_sensor or args.feedback_bandwidth_hz is not None:
        config = dataclasses.replace(
            config, microscope=_microscope_from_args(args, resolve_stage(args.config))
        )
    if args.truth_log:
        config = dataclasses.replace(config, truth_log=str(args.truth_log), truth_every=args.truth_every)
    board = Board.from_scanner_file(
        resolve_stage(args.config), effects=tuple(args.effect), seed=args.seed, config=config, now=clock()
    )
    server = SimServer(
        board,
        pty=not args.no_pty,
        link=args.link,
        usb_socket=args.usb_socket,
        unplug_s=args.unplug_s,
        tick_s=args.tick_ms * 1e-3,
        clock=clock,
        parent_fd=sys.stdin.fileno() if args.exit_with_stdin else None,
    )
    log.info(
        "board %d channels (%s), serial 0x%08x, FIFO %d, faults: corrupt out %g in %g, drop %g",
        board.stage.channels,
        "".join(board.stage.axes),
        board.capabilities.board_serial,
        board.capabilities.fifo_depth_samples,
        args.corrupt_rate,
        args.corrupt_in_rate,
        args.drop_rate,
    )
    return server.serve_forever(_print_path)


def _print_path(path: str) -> None:
    sys.stdout.write(path + "\n")
    sys.stdout.flush()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m hil_sim``: returns the exit status (2 with one line on stderr for bad input)."""
    parser = argparse.ArgumentParser(
        prog="python -m hil_sim",
        description="Simulated DAC/HV board + piezo stage on a pty: prints the path, serves until killed.",
    )
    add_sim_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_from_args(args)
    except (SimError, ValueError, OSError) as exc:
        print(f"hil_sim: error: {exc}", file=sys.stderr)
        return 2


# ---------------------------------------------------------------------------------------------
# the simulator as a subprocess


class SimProcess:
    """A running ``python -m hil_sim`` subprocess (see :func:`spawn_sim`); a context manager.

    Attributes
    ----------
    path
        What the host opens: the pty slave path, or the ``link`` symlink when one was given.
    process
        The :class:`subprocess.Popen` object.
    stderr_path
        File receiving the simulator's log (kept until :meth:`close`).
    link
        The symlink the simulator keeps (``--link``), if any: :meth:`kill` removes it, as the device
        node of a board that lost power goes away.
    """

    def __init__(
        self, process: subprocess.Popen[bytes], path: str, stderr_path: Path, link: Path | None = None
    ) -> None:
        self.process = process
        self.path = path
        self.stderr_path = stderr_path
        self.link = link

    @property
    def pid(self) -> int:
        """Process id of the simulator."""
        return self.process.pid

    def poll(self) -> int | None:
        """Exit status, or None while running."""
        return self.process.poll()

    def unplug(self) -> None:
        """Simulate an unplug (SIGUSR1): the pty goes away for ``--unplug-s`` seconds and comes back."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGUSR1)

    def terminate(self, timeout_s: float = 10.0) -> int:
        """SIGTERM and wait; SIGKILL after ``timeout_s``. Returns the exit status."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._close_pipes()
        return self.process.returncode

    def _close_pipes(self) -> None:
        for pipe in (self.process.stdin, self.process.stdout):
            if pipe is not None:
                pipe.close()

    def kill(self) -> int:
        """Remove the link (if any), SIGKILL and wait. Returns the exit status.

        The link goes first: a killed simulator cannot remove it, and a link left dangling at a pty
        number the system hands out again would lead the host to another process's port.
        """
        if self.link is not None and self.link.is_symlink():
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        self._close_pipes()
        return self.process.returncode

    def stderr_text(self) -> str:
        """The simulator's log so far."""
        try:
            return self.stderr_path.read_text(encoding="utf-8", errors="replace")
        except FileNotFoundError:
            return ""

    def close(self) -> None:
        """Terminate (if running) and remove the log file."""
        self.terminate()
        with contextlib.suppress(FileNotFoundError):
            self.stderr_path.unlink()

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def spawn_sim(
    config_path: str | Path | None = None,
    effects: Sequence[str] = (),
    seed: int = 0,
    extra_args: Sequence[str] = (),
    link: str | Path | None = None,
    *,
    timeout_s: float = 30.0,
) -> SimProcess:
    """Start ``python -m hil_sim`` and wait for the path it prints.

    Parameters
    ----------
    config_path
        Scanner YAML with a ``simulation:`` section (default: ``configs/sim-stage.yaml``).
    effects
        ``NAME=VALUE`` stage effects.
    seed
        Seed of the sensor noise and the fault injection.
    extra_args
        More command-line options (e.g. ``("--corrupt-rate", "1e-3", "--unplug-s", "0.5")``).
    link
        Keep a stable symlink at this path (:attr:`SimProcess.path` is then the link).
    timeout_s
        How long to wait for the path line (s).

    Returns
    -------
    SimProcess
        The running simulator; use it as a context manager.

    Raises
    ------
    SimLinkError
        The simulator exited before printing its path (the message carries its last log line).
    SimLinkTimeoutError
        No path line within ``timeout_s``.
    """
    cmd = [sys.executable, "-m", "hil_sim", "--seed", str(seed), "--exit-with-stdin"]
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    for effect in effects:
        cmd += ["--effect", effect]
    if link is not None:
        cmd += ["--link", str(link)]
    cmd += [str(a) for a in extra_args]
    fd, name = tempfile.mkstemp(prefix="hil_sim-", suffix=".log")
    stderr_path = Path(name)
    with os.fdopen(fd, "wb") as err:
        # stdin a pipe nobody writes to: its end of file tells the simulator this process is gone
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err)
    sim = SimProcess(proc, "", stderr_path, Path(link) if link is not None else None)
    try:
        sim.path = _read_path_line(proc, timeout_s, stderr_path)
    except BaseException:
        sim.close()
        raise
    return sim


def _read_path_line(proc: subprocess.Popen[bytes], timeout_s: float, stderr_path: Path) -> str:
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    deadline = time.monotonic() + timeout_s
    buf = b""
    while b"\n" not in buf:
        left = deadline - time.monotonic()
        if left <= 0:
            raise SimLinkTimeoutError(f"hil_sim printed no path within {timeout_s} s (log: {stderr_path})")
        ready, _, _ = select.select([fd], [], [], left)
        if not ready:
            continue
        chunk = os.read(fd, 4096)
        if not chunk:
            status = proc.wait()
            lines = stderr_path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
            last = lines[-1] if lines else "(no log)"
            raise SimLinkError(f"hil_sim exited with status {status} before printing its path: {last}")
        buf += chunk
    return buf.split(b"\n", 1)[0].decode()


__all__ = [
    "DEFAULT_TICK_S",
    "DEFAULT_UNPLUG_S",
    "PtyPort",
    "SimProcess",
    "SimServer",
    "add_sim_arguments",
    "main",
    "run_from_args",
    "spawn_sim",
]
