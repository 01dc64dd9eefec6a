"""Soaks against the real daemon on the real simulator: a corrupted, lossy link; hostile API clients
while scanning 3 axes at 20 kS/s; a board side that sends fuzzed but well-framed messages.

Each runs briefly by default (CI) and long with ``-m soak``. What every one checks: the daemon stays
up and answers, nothing it logs is a traceback, the board never had to clamp a sample (no voltage
outside the limits reached it), refused requests changed nothing, and (clients) no underrun.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import select
import termios
import threading
import time
import tty
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import pytest
from real_daemon import SLOW, OtherWork, RealDaemon

from firmware_proto import BoardState, FaultFlags, Message, Sensor, encode
from firmware_proto import Status as BoardStatus
from piezod.client import PiezodClient
from piezod.config import load_config
from piezod.errors import ApiError, RecordingError
from piezod.recording import read_recording
from piezod.service.schemas import Status


def _no_crash(d: RealDaemon) -> None:
    text = d.log_text()
    assert "Traceback" not in text and "Exception in thread" not in text, text[-3000:]
    assert d.proc is not None and d.proc.poll() is None, "the daemon died"
    assert d.sim is not None
    clamped = [ln for ln in d.sim.stderr_text().splitlines() if "clamped" in ln]
    assert not clamped, clamped[:3]


def _in_limits(d: RealDaemon, st: Status) -> None:
    cfg = load_config(d.config)
    for axis, v in st.voltage_v.items():
        ax = cfg.axes[axis]  # type: ignore[index]
        assert ax.voltage_min_v <= v <= ax.voltage_max_v, (axis, v)


def _complete(d: RealDaemon, name: str, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s * SLOW
    with d.client() as c:
        while not any(r.name == name and r.complete for r in c.recordings()):
            assert time.monotonic() < deadline, f"{name} not complete"
            time.sleep(0.2)
    time.sleep(1.0)


# --------------------------------------------------------------------------------------------- lossy link


def _lossy_link(tmp: Path, seconds: float) -> None:
    args = ("--corrupt-rate", "2e-5", "--corrupt-in-rate", "2e-5", "--drop-rate", "2e-3")
    with RealDaemon(tmp, sim_args=args) as d, d.client() as c:
        c.scan(range_um=10.0, line_rate_hz=4.0, lines=64, frames=0, name="lossy")
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            st = c.status()
            _in_limits(d, st)
            time.sleep(0.5)
        st = c.status()
        assert st.crc_errors + st.frames_dropped > 0, "the link was not lossy: the soak tested nothing"
        c.stop()
        d.wait_state({"idle"}, 30.0)
        _complete(d, "lossy.csv")
        _no_crash(d)
        rec = read_recording(d.recordings / "lossy.csv")  # every line parses
        assert rec.t_s.size > 1000
        assert (d.recordings / "lossy.csv").read_bytes().endswith(b"\n")


def test_lossy_link_short(tmp_path: Path) -> None:
    """Tried: 8 s scanning over a link with 2e-5 bit flips per byte both ways and 2e-3 dropped frames (300
    s with -m soak). Held: daemon up, no traceback, the board never clamped a sample, the recording
    parses.
    """
    _lossy_link(tmp_path, 8.0)


@pytest.mark.soak
def test_lossy_link_soak(tmp_path: Path) -> None:
    _lossy_link(tmp_path, float(os.environ.get("PIEZOD_SOAK_S", "300")))


# --------------------------------------------------------------------------------------------- clients


@dataclass
class _Tally:
    ok: int = 0
    refused: dict[int, int] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    other: OtherWork | None = None

    def add(self, code: int) -> None:
        if code < 400:
            self.ok += 1
        else:
            self.refused[code] = self.refused.get(code, 0) + 1


def _raw(d: RealDaemon) -> httpx.Client:
    return httpx.Client(
        transport=httpx.HTTPTransport(uds=str(d.socket)), base_url="http://piezod", timeout=30.0
    )


_JSON = {"content-type": "application/json"}
_HOSTILE: list[tuple[str, str, bytes, dict[str, str]]] = [
    ("PATCH", "/v1/scan", b'{"range_um": NaN}', _JSON),
    ("PATCH", "/v1/scan", b'{"range_um": 500}', _JSON),
    ("POST", "/v1/scan", b'{"range_um": 5, "line_rate_hz": 2}', _JSON),  # busy: 409
    ("POST", "/v1/move", json.dumps({f"k{i}": i for i in range(2000)}).encode(), _JSON),  # 413
    ("POST", "/v1/move", b'{"x_um": 1, "speed_um_per_s": 1e-6}', _JSON),  # busy / too slow
    ("POST", "/v1/stop", b"{}", {"content-type": "text/plain", "origin": "http://evil.example"}),
    ("POST", "/v1/stop", b"", {"host": "evil.example"}),
    ("GET", "/v1/recordings/..%2f..%2fetc%2fpasswd", b"", {}),
    ("PATCH", "/v1/scan", b"[" * 3000, _JSON),
]


def _hostile_clients(tmp: Path, seconds: float) -> tuple[int, _Tally]:
    with RealDaemon(tmp) as d:
        cfg = load_config(d.config)
        assert len(cfg.axes) == 3 and cfg.sample_rate_hz >= 20_000
        with d.client() as c:
            c.scan(range_um=10.0, line_rate_hz=4.0, lines=64, frames=0, name="under-fire")
        d.wait_state({"scanning"}, 20.0)
        first = d.status()
        assert d.proc is not None and d.sim is not None
        other = OtherWork([d.proc.pid, d.sim.pid])
        stop = threading.Event()
        tally = _Tally(other=other)
        lock = threading.Lock()

        def run(fn: Callable[[], None]) -> None:
            while not stop.is_set():
                try:
                    fn()
                except Exception as exc:  # collected, asserted empty below
                    with lock:
                        tally.errors.append(repr(exc))
                    return

        def hostile() -> None:
            rnd = random.Random(threading.get_ident())
            with _raw(d) as h:
                while not stop.is_set():
                    method, path, body, headers = rnd.choice(_HOSTILE)
                    r = h.request(method, path, content=body or None, headers=headers)
                    with lock:
                        tally.add(r.status_code)

        def poller() -> None:
            with PiezodClient(d.api, timeout=30.0) as pc:
                while not stop.is_set():
                    pc.status()
                    pc.recordings()
                    with lock:
                        tally.add(200)

        def watcher() -> None:
            with PiezodClient(d.api, timeout=30.0) as pc:
                for _ in pc.events(rate_hz=50.0):
                    if stop.is_set():
                        return

        def downloader() -> None:
            with PiezodClient(d.api, timeout=30.0) as pc:
                while not stop.is_set():
                    for _ in pc.iter_recording("under-fire.csv"):
                        if stop.is_set():
                            return

        threads = [threading.Thread(target=run, args=(fn,)) for fn in (hostile,) * 6]
        threads += [threading.Thread(target=run, args=(fn,)) for fn in (poller,) * 2]
        threads += [
            threading.Thread(target=run, args=(watcher,)),
            threading.Thread(target=run, args=(downloader,)),
        ]
        for t in threads:
            t.start()
        time.sleep(seconds)
        stop.set()
        for t in threads:
            t.join(60.0)
        other.stop()
        st = d.status()
        assert not tally.errors, tally.errors[:5]
        new_faults = [f for f in st.faults if f.time_s > first.uptime_s]
        # the only faults a starved host may show are the stream's (an underrun and its restart);
        # nothing a request could have caused
        assert {f.code for f in new_faults} <= {"UNDERRUN", "STREAM", "STREAM_END"}, new_faults[-3:]
        if not new_faults:
            assert st.state == "scanning" and st.scan == first.scan, st.faults[-3:]
        _in_limits(d, st)
        _no_crash(d)
        assert set(tally.refused) <= {403, 404, 409, 413, 415, 422, 429, 503}, tally.refused
        return st.underruns - first.underruns, tally


def test_hostile_clients_short(tmp_path: Path) -> None:
    """Tried: 8 s of 6 hostile clients (NaN, huge, cross-site, rebinding, refused and busy requests) +
    pollers, a 50 Hz event stream and a downloader while scanning 3 axes at 20 kS/s. Held: 0 underruns,
    no fault, the scan unchanged, every refusal a 4xx.
    """
    underruns, tally = _hostile_clients(tmp_path, 8.0)
    assert tally.other is not None
    busy, others = tally.other.cores()
    print(
        f"hostile clients 8 s: {tally.ok} answered, refused {tally.refused}, "
        f"underruns {underruns}, {busy:.1f} cores busy, {others:.1f} of them by other work"
    )
    assert sum(tally.refused.values()) > 50
    if underruns and tally.other.saturated():
        # the stream's margin (the FIFO lead) cannot cover a machine saturated by other work; the
        # soak variant (-m soak) asserts 0 unconditionally and is run on a quiet machine
        warnings.warn(
            f"{underruns} underruns, {busy:.1f} of {os.cpu_count()} cores busy, {others:.1f} by other work",
            stacklevel=1,
        )
    else:
        assert underruns == 0


@pytest.mark.soak
def test_hostile_clients_60s_no_underrun(tmp_path: Path) -> None:
    """Tried: the same client mix for 60 s (-m soak). Held: 0 underruns."""
    underruns, tally = _hostile_clients(tmp_path, 60.0)
    print(f"hostile clients 60 s: {tally.ok} answered, refused {tally.refused}, underruns {underruns}")
    assert underruns == 0


# --------------------------------------------------------------------------------------------- board side


class FuzzProxy:
    """A pty between the daemon and the simulator that adds fuzzed, correctly framed messages.

    Bytes pass both ways unchanged; towards the host, every ``1/rate_hz`` s on average, a message
    of any type with arbitrary field values (firmware_proto's hypothesis strategies) and an
    arbitrary sequence number is inserted between two frames, as a confused or hostile board would.
    """

    def __init__(self, rate_hz: float, seed: int) -> None:
        from firmware_proto.strategies import messages

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.pool: list[Message] = [messages(max_samples=8).example() for _ in range(300)]
        self.rate_hz = rate_hz
        self.rnd = random.Random(seed)
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        self._slave = slave
        self.board = -1
        self.sent = 0
        self._forged: list[Message] = []
        self._forged_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def connect(self, board_path: str) -> str:
        self.board = os.open(board_path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.board)
        termios.tcflush(self.board, termios.TCIOFLUSH)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self.path

    def forge(self, msg: Message) -> None:
        """Insert ``msg`` towards the host between the next two frames of the board."""
        with self._forged_lock:
            self._forged.append(msg)

    def _run(self) -> None:
        next_fuzz = time.monotonic()
        pending = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master, self.board], [], [], 0.01)
            with contextlib.suppress(OSError):
                if self.master in ready:
                    os.write(self.board, os.read(self.master, 65536))
                if self.board in ready:
                    pending += os.read(self.board, 65536)
                    cut = pending.rfind(b"\0") + 1  # forward whole frames, insert between them
                    if cut:
                        os.write(self.master, pending[:cut])
                        pending = pending[cut:]
                with self._forged_lock:
                    forged, self._forged = self._forged, []
                for msg in forged:
                    os.write(self.master, encode(msg, self.rnd.getrandbits(32)))
                now = time.monotonic()
                if now >= next_fuzz:
                    msg = self.rnd.choice(self.pool)
                    os.write(self.master, encode(msg, self.rnd.getrandbits(32)))
                    self.sent += 1
                    next_fuzz = now + self.rnd.expovariate(self.rate_hz)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for fd in (self.master, self._slave, self.board):
            with contextlib.suppress(OSError):
                os.close(fd)


def _board_fuzz(tmp: Path, seconds: float, rate_hz: float) -> None:
    proxy = FuzzProxy(rate_hz, seed=13)
    try:
        with RealDaemon(tmp, port_via=proxy.connect) as d, d.client() as c:
            with contextlib.suppress(ApiError):  # a fuzzed FAULT may already have latched one
                c.scan(range_um=10.0, line_rate_hz=4.0, lines=64, frames=0, name="fuzzed")
            end = time.monotonic() + seconds
            states: set[str] = set()
            while time.monotonic() < end:
                st = c.status()  # the API always answers
                states.add(st.state)
                _in_limits(d, st)
                time.sleep(0.2)
            assert proxy.sent > seconds * rate_hz / 3
            proxy.rate_hz = 1e-9  # the board behaves again: the daemon must be usable, not wedged
            time.sleep(1.0)
            deadline = time.monotonic() + 60.0 * SLOW
            while True:
                st = c.stop()
                if st.state == "idle":
                    break
                assert time.monotonic() < deadline, f"wedged in {st.state}: {st.faults[-3:]}\n{d.stacks()}"
                time.sleep(0.5)
            c.scan(range_um=5.0, line_rate_hz=8.0, lines=1, name="after-fuzz")
            d.wait_state({"idle"}, 60.0)
            _no_crash(d)
            print(f"board fuzz: {proxy.sent} fuzzed messages, states {sorted(states)}")
    finally:
        proxy.close()


def test_board_side_fuzz_short(tmp_path: Path) -> None:
    """Tried: 8 s of fuzzed, correctly framed board messages of every type (hypothesis strategies) inserted
    by a pty proxy at 20/s (300 s at 50/s with -m soak). Held: the API always answers, no traceback, the
    board never clamped a sample; afterwards stop reaches idle and a scan runs.
    """
    _board_fuzz(tmp_path, 8.0, rate_hz=20.0)


def test_forged_frames_around_a_stop_leave_the_next_scan_alone(tmp_path: Path) -> None:
    """Tried: what made the fuzz test above fail once (session 6), on purpose: while a recorded scan
    runs, a SENSOR frame restarting the readback at index 1, one of rows never sent, and a STATUS
    claiming 500,000 samples more played than sent with a credit of 2**40; then stop and a new
    recorded scan. Held: the new scan ends in its own time (before: the daemon computed the 25 s of
    samples the STATUS claimed played, and the new scan waited for them to be played first; the fuzz
    test's STATUS frames claim up to 10**7), its recording is complete with every row, no sensor gap
    is reported, the frame of rows never sent is logged as ignored.
    """
    proxy = FuzzProxy(1e-9, seed=13)
    try:
        with RealDaemon(tmp_path, port_via=proxy.connect) as d, d.client() as c:
            channels = len(load_config(d.config).axes)
            c.scan(range_um=10.0, line_rate_hz=4.0, lines=64, frames=0, name="forged")
            time.sleep(1.0)
            claimed = c.status().sample_index + 500_000
            proxy.forge(Sensor(1, 1, np.zeros((1, channels), np.int16)))
            proxy.forge(Sensor(2**40, 1, np.zeros((2, channels), np.int16)))
            proxy.forge(BoardStatus(BoardState.RUNNING, FaultFlags.NONE, 2**40, claimed, 2**32 - 1))
            time.sleep(3.0)  # before: long enough to compute those samples (about 1 s)
            assert c.stop().state == "idle"
            c.scan(range_um=5.0, line_rate_hz=8.0, lines=1, name="after")
            # one line at 8 Hz: 2500 samples per scanned axis, read back within about 2 s
            rate = load_config(d.config).sample_rate_hz
            path, per_axis = d.recordings / "after.csv", round(rate / 8.0)
            deadline = time.monotonic() + 10.0 * SLOW
            while True:
                try:
                    rec = read_recording(path)
                    counts = [int(np.count_nonzero(rec.axis == a)) for a in ("x", "y")]
                except RecordingError as exc:
                    if "no data rows" not in str(exc):
                        raise
                    counts = [0, 0]
                if counts == [per_axis] * 2:
                    break
                assert time.monotonic() < deadline, f"after.csv holds {counts} rows of x, y, not {per_axis}"
                time.sleep(0.2)
            assert c.status().state == "idle"
            _complete(d, "after.csv")
            _no_crash(d)
            st = c.status()
            assert not [f for f in st.faults if f.code == "SENSOR_GAP"], st.faults
            # (the STATUS is logged only if the streamer looked before the next genuine one came)
            assert "SENSOR frame ignored: rows 1099511627776.." in d.log_text()
        for axis in ("x", "y"):
            t = rec.t_s[rec.axis == axis]
            assert np.allclose(np.diff(t), 1.0 / rate), axis  # every row, once
    finally:
        proxy.close()


@pytest.mark.soak
def test_board_side_fuzz_soak(tmp_path: Path) -> None:
    _board_fuzz(tmp_path, float(os.environ.get("PIEZOD_SOAK_S", "300")), rate_hz=50.0)
