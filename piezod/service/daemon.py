"""``piezod serve``: the daemon. Engine + control API + systemd notifications + signals.

Start-up: load the scanner config, connect to the board (or start the simulator for
``--sim``), start streaming (hold), serve the API, then tell systemd ``READY=1``. While
streaming is healthy the systemd watchdog is pinged; a stalled stream stops the pings and
systemd restarts the service (``Restart=on-failure``). SIGTERM / SIGINT: ``STOPPING=1``, stop
the API, ramp the outputs to the safe values, flush and close the recordings, close the link,
exit 0.
"""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

from piezod.config import ScannerConfig
from piezod.service.api import EventHub, create_app
from piezod.service.engine import Engine
from piezod.service.sdnotify import SystemdNotifier
from piezod.service.server import ApiServer, private_dir

log = logging.getLogger("piezod.daemon")


def default_api_spec(
    scanner: str,
    *,
    run_dir: Path = Path("/run/piezod"),
    runtime_dir: str | None = os.environ.get("XDG_RUNTIME_DIR"),
    tmp_root: Path = Path("/tmp"),
) -> str:
    """``unix:/run/piezod/<scanner>.sock`` when that directory is writable, else a per-user socket.

    The per-user fallback ``/tmp/piezod-<uid>`` must be a directory this user owns with mode
    0700 (see :func:`~piezod.service.server.private_dir`); one created by someone else is refused.
    """
    if run_dir.is_dir() and os.access(run_dir, os.W_OK):
        return f"unix:{run_dir / (scanner + '.sock')}"
    if runtime_dir and os.access(runtime_dir, os.W_OK):
        return f"unix:{Path(runtime_dir) / f'piezod-{scanner}.sock'}"
    d = private_dir(tmp_root / f"piezod-{os.geteuid()}")
    return f"unix:{d / (scanner + '.sock')}"


@dataclass
class Daemon:
    """A running daemon (engine + API)."""

    engine: Engine
    server: ApiServer
    hub: EventHub
    notifier: SystemdNotifier
    api_spec: str

    def run_until_stopped(self, stop: threading.Event) -> None:
        """Serve until ``stop`` is set; ping the watchdog while streaming is healthy."""
        interval = self.notifier.watchdog_interval_s or 1.0
        last_state = ""
        while not stop.wait(min(interval, 1.0)):
            st = self.engine.status()
            if st.state != last_state:
                self.notifier.status(f"{st.state}; API {self.api_spec}")
                last_state = st.state
            if self.engine.healthy():
                self.notifier.watchdog()

    def shutdown(self) -> None:
        """Stop the API, ramp to safe, close recordings and the link."""
        self.notifier.stopping("ramping to the safe values")
        try:
            self.server.stop()
        finally:
            self.hub.close()
            self.engine.close(ramp=True)
            self.notifier.close()


@contextlib.contextmanager
def running_daemon(
    config: ScannerConfig,
    url: str,
    *,
    api_spec: str | None = None,
    recording_dir: Path | None = None,
    notifier: SystemdNotifier | None = None,
    before_ready: Callable[[Engine], None] | None = None,
) -> Iterator[Daemon]:
    """Start engine and API; yield the daemon; shut it down (ramping to safe) on exit."""
    notifier = notifier or SystemdNotifier.from_env()
    hub = EventHub()
    # line / frame events on the API; a scanner with a height channel gets its images per frame
    engine = Engine(
        config,
        url,
        recording_dir=recording_dir,
        on_fault=hub.publish_fault,
        on_scan_event=hub.publish_scan,
        write_images=config.microscope is not None,
    )
    # the API settings are checked before the board is touched: a bad --api changes nothing
    spec = api_spec or default_api_spec(config.name)
    server = ApiServer(create_app(engine, events=hub), spec, config.api)
    notifier.status(f"connecting to the board at {url}")
    engine.open()
    try:
        server.start()
    except BaseException:
        engine.close(ramp=True)
        raise
    daemon = Daemon(engine, server, hub, notifier, spec)
    try:
        if before_ready is not None:
            before_ready(engine)
        notifier.ready(f"streaming {len(engine.drivers)} axes at {engine.rate_hz:g} S/s; API {spec}")
        yield daemon
    finally:
        daemon.shutdown()


def stop_on_signals() -> threading.Event:
    """An event set by SIGTERM or SIGINT (installed in the main thread).

    SIGUSR1 writes every thread's stack to stderr (the journal) and changes nothing: what a
    daemon that answers but no longer streams is waiting for (``systemctl kill -s USR1 piezod@x``).

    The stacks are written from a Python-level handler, which runs in the main thread with the
    interpreter lock held, so no other thread's frames change while they are read.
    ``faulthandler.register`` reads them from the C signal handler while the streaming threads
    run; that crashed the streaming daemon with SIGSEGV (after 4, 18, 49 and 339 signals in four trials;
    CPython gh-116008). The cost: a daemon whose main thread can no longer run Python code gives
    no stacks; the systemd watchdog restarts that one.

    A fatal signal (SIGSEGV, SIGABRT, SIGBUS, SIGFPE, SIGILL) also writes the threads' stacks, by
    ``faulthandler.enable``: the process is ending then, and the journal tells where.
    """
    stop = threading.Event()
    faulthandler.enable(file=sys.stderr, all_threads=True)

    def dump_stacks(_signum: int, _frame: FrameType | None) -> None:
        sys.stderr.flush()
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)

    def handler(signum: int, _frame: FrameType | None) -> None:
        log.info("signal %s: shutting down", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGUSR1, dump_stacks)
    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    return stop


def wait_started(check: Callable[[], bool], timeout_s: float) -> bool:
    """Poll ``check`` until true or the timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.05)
    return False
