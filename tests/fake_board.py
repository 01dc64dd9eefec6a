"""An in-memory board built from the codec, for the link tests (not a test module).

It implements the board side of ``firmware_proto/PROTOCOL.md`` closely enough to exercise the
host: handshake, CONFIGURE checks, START / STOP / RAMP_TO_SAFE, the FIFO with credits and the
SAMPLES acceptance rules (7.2), a real-time sample clock with underruns, the watchdog, ramps,
STATUS, SENSOR (the sensor reads back the applied DAC code: ADC code = DAC code) and FAULT. Hooks
inject faults: byte corruption per direction, dropped replies, forced NAKs, unplugging.
It runs in its own thread and talks over a socket pair (or a Unix socket server).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from firmware_proto import (
    NO_CHANNEL,
    NO_INDEX,
    BoardState,
    Capabilities,
    Configure,
    DecodeError,
    Endpoint,
    ErrorKind,
    Fault,
    FaultCode,
    FaultFlags,
    Frame,
    Hello,
    MessageType,
    NakReason,
    RampToSafe,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
)
from piezod.errors import LinkClosedError
from piezod.link.transport import Transport, socket_transport


@dataclass
class BoardStats:
    crc_errors: int = 0
    frames_dropped: int = 0
    underruns: int = 0
    clamped_samples: int = 0
    index_gaps: int = 0
    overflows: int = 0
    max_fifo_level: int = 0
    samples_accepted: int = 0
    bytes_corrupted_rx: int = 0
    bytes_corrupted_tx: int = 0
    frames_tx: int = 0
    frames_dropped_tx: int = 0
    watchdogs: int = 0
    requests: dict[str, int] = field(default_factory=dict)


class FakeBoard:
    """See the module docstring.

    Parameters
    ----------
    n_channels, fifo_depth, max_samples_per_frame, rate_range_hz, amp_v, protocol_version, serial
        What CAPABILITIES reports.
    corrupt_rx, corrupt_tx
        Probability per byte of damaging a byte received from / sent to the host.
    drop_tx
        Probability per frame of not sending it at all (it keeps its sequence number).
    seed
        Random generator seed (corruption).
    """

    def __init__(
        self,
        *,
        n_channels: int = 3,
        fifo_depth: int = 16384,
        max_samples_per_frame: int = 1024,
        rate_range_hz: tuple[int, int] = (100, 200_000),
        amp_v: tuple[float, float] = (-250.0, 250.0),
        protocol_version: int = 1,
        serial: int = 0xB0A4D,
        corrupt_rx: float = 0.0,
        corrupt_tx: float = 0.0,
        drop_tx: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.version = protocol_version
        self.caps_version = protocol_version
        self.n_channels = n_channels
        self.fifo_depth = fifo_depth
        self.mspf = max_samples_per_frame
        self.rate_range = rate_range_hz
        self.amp = amp_v
        self.serial = serial
        self.corrupt_rx = corrupt_rx
        self.corrupt_tx = corrupt_tx
        self.drop_tx = drop_tx
        self.rng = np.random.default_rng(seed)
        self.stats = BoardStats()
        self.drop_replies: dict[MessageType, int] = {}
        self.force_nak: dict[MessageType, tuple[NakReason, int]] = {}
        self.silent = False
        self.played: list[tuple[int, np.ndarray]] = []
        self.record_played = True
        self.hellos: list[Hello] = []
        self._lock = threading.RLock()
        self._sock: socket.socket | None = None
        self._unplugged_until = 0.0
        self._running = True
        self._listener: socket.socket | None = None
        self._reset_protocol()
        self.state = BoardState.UNCONFIGURED
        self.config: Configure | None = None
        self.flags = FaultFlags.NONE
        self.outputs = np.zeros(n_channels, dtype=np.float64)
        self.write_index = 0
        self.last_played = NO_INDEX
        self.fifo: deque[np.ndarray] = deque()
        self.fifo_len = 0
        self.play_next = 0
        self.prefill = 0
        self.run_start = 0
        self.pending_stop: int | None = None
        self.sensor_rows: list[np.ndarray] = []
        self.sensor_first: int | None = None
        self.sensor_next_flush = 0.0
        self.next_status = 0.0
        self.clock_t0 = 0.0
        self.ticks_done = 0
        self.last_host_rx = time.monotonic()
        self.watchdog_armed = True
        self.last_fault_sent: dict[FaultCode, float] = {}
        self.last_t = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="fake-board", daemon=True)
        self._thread.start()

    # -- wiring -----------------------------------------------------------------------------

    def _reset_protocol(self) -> None:
        self.endpoint = Endpoint()
        self.hello_seen = False

    def capabilities(self, reply_to: int) -> Capabilities:
        return Capabilities(
            reply_to_seq=reply_to,
            protocol_version=self.caps_version,
            firmware_version=(0, 9, 1),
            dac_bits=16,
            adc_bits=16,
            max_samples_per_frame=self.mspf,
            sample_rate_min_hz=self.rate_range[0],
            sample_rate_max_hz=self.rate_range[1],
            sample_clock_hz=0,
            fifo_depth_samples=self.fifo_depth,
            board_serial=self.serial,
            amplifier_ranges_v=tuple(self.amp for _ in range(self.n_channels)),
        )

    def connect(self) -> Transport:
        """A transport factory: a fresh socket pair attached to the board."""
        with self._lock:
            if time.monotonic() < self._unplugged_until:
                raise LinkClosedError("fake://board: unplugged")
            host, board = socket.socketpair()
            self._attach(board)
        return socket_transport(host, "fake://board", read_timeout_s=0.01)

    def serve_unix(self, path: str) -> None:
        """Accept connections on a Unix stream socket (one at a time)."""
        lst = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        lst.bind(path)
        lst.listen(1)
        self._listener = lst

        def _accept() -> None:
            while self._running:
                try:
                    conn, _ = lst.accept()
                except OSError:
                    return
                with self._lock:
                    self._attach(conn)

        threading.Thread(target=_accept, name="fake-board-accept", daemon=True).start()

    def _attach(self, sock: socket.socket) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
        sock.setblocking(False)
        self._sock = sock
        self._reset_protocol()

    def unplug(self, seconds: float) -> None:
        """Drop the connection; :meth:`connect` fails for ``seconds``. The board keeps running."""
        with self._lock:
            self._unplugged_until = time.monotonic() + seconds
            if self._sock is not None:
                with contextlib.suppress(OSError):
                    self._sock.shutdown(socket.SHUT_RDWR)
                self._sock.close()
                self._sock = None

    def close(self) -> None:
        self._running = False
        self._thread.join(timeout=2.0)
        with self._lock:
            if self._sock is not None:
                self._sock.close()
            if self._listener is not None:
                self._listener.close()

    def __enter__(self) -> FakeBoard:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- main loop --------------------------------------------------------------------------

    def _run(self) -> None:
        while self._running:
            with self._lock:
                sock = self._sock
            data = b""
            if sock is not None:
                try:
                    ready, _, _ = select.select([sock], [], [], 0.001)
                    if ready:
                        data = sock.recv(65536)
                        if not data:
                            with self._lock:
                                if self._sock is sock:
                                    sock.close()
                                    self._sock = None
                except OSError:
                    with self._lock:
                        if self._sock is sock:
                            self._sock = None
            else:
                time.sleep(0.001)
            with self._lock:
                now = time.monotonic()
                if data and not self.silent:
                    self._receive(self._corrupt(data, self.corrupt_rx, rx=True), now)
                self._tick(now)
                out = self.endpoint.data_to_send()
                sock = self._sock
            if out and sock is not None and not self.silent:
                out = self._drop(out)
                out = self._corrupt(out, self.corrupt_tx, rx=False)
                try:
                    sock.setblocking(True)
                    sock.settimeout(1.0)
                    sock.sendall(out)
                    sock.setblocking(False)
                except OSError:
                    with self._lock:
                        if self._sock is sock:
                            self._sock = None

    def _drop(self, data: bytes) -> bytes:
        if self.drop_tx <= 0:
            return data
        frames = data.split(b"\x00")[:-1]
        keep = self.rng.random(len(frames)) >= self.drop_tx
        self.stats.frames_dropped_tx += int((~keep).sum())
        return b"".join(f + b"\x00" for f, k in zip(frames, keep, strict=True) if k)

    def _corrupt(self, data: bytes, rate: float, *, rx: bool) -> bytes:
        if rate <= 0 or not data:
            return data
        arr = np.frombuffer(data, dtype=np.uint8).copy()
        hit = np.flatnonzero(self.rng.random(arr.size) < rate)
        if hit.size:
            arr[hit] ^= self.rng.integers(1, 256, hit.size, dtype=np.uint8)
            if rx:
                self.stats.bytes_corrupted_rx += hit.size
            else:
                self.stats.bytes_corrupted_tx += hit.size
        return arr.tobytes()

    # -- receiving ----------------------------------------------------------------------------

    def _configured(self) -> bool:
        return self.config is not None

    def _receive(self, data: bytes, now: float) -> None:
        for ev in self.endpoint.receive(data, now):
            if isinstance(ev, DecodeError):
                self.stats.frames_dropped += 1
                if ev.kind is ErrorKind.BAD_CRC:
                    self.stats.crc_errors += 1
                    self._fault(FaultCode.CRC_ERRORS, now, detail=self.stats.crc_errors)
                if ev.ack_requested and ev.kind in (ErrorKind.UNKNOWN_TYPE, ErrorKind.BAD_LENGTH):
                    reason = (
                        NakReason.UNKNOWN_TYPE if ev.kind is ErrorKind.UNKNOWN_TYPE else NakReason.BAD_LENGTH
                    )
                    self.endpoint.nak(ev, reason)
                continue
            if not isinstance(ev, Frame):
                continue
            self._feed_watchdog(now)
            if ev.ack_requested:
                self._request(ev, now)
            elif isinstance(ev.msg, Samples):
                self._samples(ev.msg, now)

    def _feed_watchdog(self, now: float) -> None:
        self.last_host_rx = now
        self.watchdog_armed = True

    def _reply_dropped(self, typ: MessageType) -> bool:
        left = self.drop_replies.get(typ, 0)
        if left > 0:
            self.drop_replies[typ] = left - 1
            return True
        return False

    def _request(self, frame: Frame, now: float) -> None:
        msg = frame.msg
        typ = msg.TYPE
        self.stats.requests[typ.name] = self.stats.requests.get(typ.name, 0) + 1
        pending = self.endpoint.data_to_send()
        drop = self._reply_dropped(typ)
        self._answer(frame, now)
        reply = self.endpoint.data_to_send()
        self.endpoint._outbox.append(pending)
        if not drop:
            self.endpoint._outbox.append(reply)

    def _answer(self, frame: Frame, now: float) -> None:
        msg = frame.msg
        ep = self.endpoint
        if isinstance(msg, Hello):
            self.hellos.append(msg)
            if msg.protocol_version != self.version:
                ep.nak(frame, NakReason.VERSION_MISMATCH, self.version)
                return
            self.hello_seen = True
            ep.reply(frame, self.capabilities(frame.seq))
            return
        if not self.hello_seen:
            ep.nak(frame, NakReason.BAD_STATE, int(self.state))
            return
        forced = self.force_nak.get(msg.TYPE)
        if forced is not None:
            ep.nak(frame, forced[0], forced[1])
            if isinstance(msg, Configure):
                self._fault(FaultCode.CONFIG_REJECTED, now, detail=forced[1], latch=True)
            return
        if isinstance(msg, Configure):
            if self.state not in (BoardState.UNCONFIGURED, BoardState.IDLE):
                ep.nak(frame, NakReason.BAD_STATE, int(self.state))
                return
            problem = msg.check(self.capabilities(0))
            if problem is not None:
                ep.nak(frame, problem[0], problem[1])
                self._fault(FaultCode.CONFIG_REJECTED, now, detail=problem[1], latch=True)
                return
            self.config = msg
            self.flags = FaultFlags.NONE
            ep.ack(frame)
            self._set_state(BoardState.RAMPING, now)
            return
        if not self._configured():
            ep.nak(frame, NakReason.BAD_STATE, int(self.state))
            return
        if isinstance(msg, Start):
            if self.state != BoardState.IDLE:
                ep.nak(frame, NakReason.BAD_STATE, int(self.state))
                return
            if msg.prefill_samples > self.fifo_depth:  # type: ignore[call-overload]
                ep.nak(frame, NakReason.BAD_VALUE, 16)
                return
            self._clear_fifo()
            self.write_index = msg.start_index
            self.play_next = msg.start_index
            self.run_start = msg.start_index
            self.prefill = msg.prefill_samples
            self.pending_stop = None
            self.flags = FaultFlags.NONE
            self.sensor_rows = []
            self.sensor_first = None
            ep.ack(frame)
            self._set_state(BoardState.ARMED, now)
        elif isinstance(msg, Stop):
            ep.ack(frame)
            lp = self.last_played
            if (
                self.state == BoardState.RUNNING
                and msg.stop_after_index != NO_INDEX
                and (lp == NO_INDEX or msg.stop_after_index > lp)
            ):
                self.pending_stop = msg.stop_after_index
            else:
                self._stop_clock(now)
                self._set_state(BoardState.IDLE, now)
        elif isinstance(msg, RampToSafe):
            ep.ack(frame)
            self._stop_clock(now)
            self._set_state(BoardState.RAMPING, now)
        else:
            ep.nak(frame, NakReason.UNKNOWN_TYPE)

    def _samples(self, msg: Samples, now: float) -> None:
        cfg = self.config
        if (
            self.state not in (BoardState.ARMED, BoardState.RUNNING)
            or cfg is None
            or msg.n_channels != cfg.n_channels
        ):
            self.stats.frames_dropped += 1
            return
        w = self.write_index
        limit = w + self.fifo_depth - self.fifo_len  # type: ignore[call-overload]
        f, n = msg.first_index, msg.n_samples
        if f + n <= w:
            self.stats.frames_dropped += 1
            return
        if f > w:
            self.stats.frames_dropped += 1
            self.stats.index_gaps += 1
            self._fault(FaultCode.INDEX_GAP, now, index=w, latch=True)
            return
        if f + n > limit:
            self.stats.frames_dropped += 1
            self.stats.overflows += 1
            self._fault(FaultCode.OVERFLOW, now, index=f, latch=True)
            return
        rows = np.array(msg.codes[w - f :], dtype=np.int16)
        lo = np.array([c.code_min for c in cfg.channels], dtype=np.int16)
        hi = np.array([c.code_max for c in cfg.channels], dtype=np.int16)
        bad = (rows < lo) | (rows > hi)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            self.stats.clamped_samples += int(bad.sum())
            self._fault(
                FaultCode.LIMIT_VIOLATION,
                now,
                channel=int(c),
                index=w + int(r),
                detail=int(rows[r, c]) & 0xFFFF,
                latch=True,
            )
            rows = np.clip(rows, lo, hi)
        self.fifo.append(rows)
        self.fifo_len += rows.shape[0]
        self.write_index = f + n
        self.stats.samples_accepted += rows.shape[0]
        self.stats.max_fifo_level = max(self.stats.max_fifo_level, self.fifo_len)

    # -- board behaviour ----------------------------------------------------------------------

    def _fault(
        self,
        code: FaultCode,
        now: float,
        *,
        channel: int = NO_CHANNEL,
        index: int = NO_INDEX,
        detail: int = 0,
        latch: bool = False,
    ) -> None:
        if latch or code in (FaultCode.UNDERRUN, FaultCode.WATCHDOG, FaultCode.CRC_ERRORS):
            self.flags |= FaultFlags.of(code)
        period = (self.config.status_period_ms if self.config else 10) / 1000.0
        if now - self.last_fault_sent.get(code, -1e9) < period:
            return
        self.last_fault_sent[code] = now
        self.endpoint.send(Fault(code, channel, index, detail), now)

    def _set_state(self, state: BoardState, now: float) -> None:
        if state != self.state:
            self.state = state
            self._status(now)

    def _clear_fifo(self) -> None:
        self.fifo.clear()
        self.fifo_len = 0

    def _stop_clock(self, now: float) -> None:
        self._flush_sensor(now)
        self._clear_fifo()
        self.pending_stop = None

    def _status(self, now: float) -> None:
        if self.config is None:
            return
        s = self.stats
        self.endpoint.send(
            Status(
                self.state,
                self.flags,
                self.write_index,
                self.last_played,
                self.fifo_depth - self.fifo_len,  # type: ignore[call-overload]
                s.crc_errors,
                s.frames_dropped,
                s.underruns,
                s.clamped_samples,
                s.index_gaps,
                s.overflows,
            ),
            now,
        )
        self.next_status = now + self.config.status_period_ms / 1000.0

    def _flush_sensor(self, now: float) -> None:
        cfg = self.config
        if cfg is None or not self.sensor_rows or self.sensor_first is None:
            self.sensor_next_flush = now + (cfg.status_period_ms / 1000.0 if cfg else 0.01)
            return
        rows = np.concatenate(self.sensor_rows)
        mspf = self.mspf
        d = cfg.sensor_decimation
        for i in range(0, rows.shape[0], mspf):
            self.endpoint.send(Sensor(self.sensor_first + i * d, d, rows[i : i + mspf]), now)
        self.sensor_first += rows.shape[0] * d
        self.sensor_rows = []
        self.sensor_next_flush = now + cfg.status_period_ms / 1000.0

    def _tick(self, now: float) -> None:
        dt = now - self.last_t
        self.last_t = now
        cfg = self.config
        if cfg is None:
            return
        st = self.state
        hb = cfg.heartbeat_timeout_ms / 1000.0
        if (
            st in (BoardState.IDLE, BoardState.ARMED, BoardState.RUNNING)
            and self.watchdog_armed
            and now - self.last_host_rx > hb
        ):
            self.watchdog_armed = False
            self.stats.watchdogs += 1
            self._stop_clock(now)
            self._fault(FaultCode.WATCHDOG, now, index=self.last_played, latch=True)
            self._set_state(BoardState.RAMPING, now)
        if self.state == BoardState.ARMED and self.fifo_len >= max(self.prefill, 1):
            self.clock_t0 = now
            self.ticks_done = 0
            self.sensor_first = None
            self.sensor_rows = []
            self._set_state(BoardState.RUNNING, now)
        if self.state == BoardState.RUNNING:
            self._play(now)
        if self.state == BoardState.RAMPING:
            safe = np.array([c.safe_code for c in cfg.channels], dtype=np.float64)
            step = np.array([c.ramp_v_per_s / c.dac_v_per_code for c in cfg.channels]) * dt
            delta = np.clip(safe - self.outputs, -step, step)
            self.outputs = self.outputs + delta
            if np.array_equal(np.round(self.outputs), safe) or np.allclose(self.outputs, safe, atol=0.5):
                self.outputs = safe
                self._set_state(BoardState.IDLE, now)
        if self.sensor_rows and now >= self.sensor_next_flush:
            self._flush_sensor(now)
        sensor_pending = sum(r.shape[0] for r in self.sensor_rows)
        if sensor_pending >= self.mspf:  # type: ignore[call-overload]
            self._flush_sensor(now)
        if now >= self.next_status:
            self._status(now)

    def _play(self, now: float) -> None:
        cfg = self.config
        assert cfg is not None
        due = int((now - self.clock_t0) * cfg.sample_rate_hz) - self.ticks_done
        if due <= 0:
            return
        start = self.play_next
        limit = due
        if self.pending_stop is not None:
            limit = min(limit, self.pending_stop - start + 1)
        k = min(limit, self.fifo_len)
        if k > 0:
            rows = self._pop(k)
            self.ticks_done += k
            self.play_next = start + k
            self.last_played = start + k - 1
            self.outputs = rows[-1].astype(np.float64)
            if self.record_played:
                self.played.append((start, rows))
            d = cfg.sensor_decimation
            idx = start + np.arange(k)
            take = (idx - self.run_start) % d == 0
            if take.any():
                if self.sensor_first is None:
                    self.sensor_first = int(idx[take][0])
                self.sensor_rows.append(rows[take])
        if self.pending_stop is not None and self.play_next > self.pending_stop:
            self._stop_clock(now)
            self._set_state(BoardState.IDLE, now)
            return
        if due > k:
            self.stats.underruns += 1
            self._stop_clock(now)
            self._fault(FaultCode.UNDERRUN, now, index=self.last_played, latch=True)
            self._set_state(BoardState.IDLE, now)

    def _pop(self, k: int) -> np.ndarray:
        parts = []
        left = k
        while left:
            blk = self.fifo[0]
            if blk.shape[0] <= left:
                parts.append(self.fifo.popleft())
                left -= blk.shape[0]
            else:
                parts.append(blk[:left])
                self.fifo[0] = blk[left:]
                left = 0
        self.fifo_len -= k
        return np.concatenate(parts) if len(parts) > 1 else parts[0]

    # -- checks used by the tests -------------------------------------------------------------

    def played_codes(self) -> tuple[int, np.ndarray]:
        """First index and all codes played (rows), assuming one contiguous run."""
        with self._lock:
            if not self.played:
                return 0, np.zeros((0, self.n_channels), dtype=np.int16)
            return self.played[0][0], np.concatenate([r for _, r in self.played])


def unix_socket_path(tmpdir: str, name: str = "board.sock") -> str:
    path = os.path.join(tmpdir, name)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    return path
