"""The simulated DAC / high-voltage-amplifier board: the board side of ``firmware_proto``, sans I/O.

:class:`Board` is driven by its caller's clock: :meth:`Board.feed` hands it the bytes the host
sent (at time ``now``), :meth:`Board.advance` lets simulated time pass, and
:meth:`Board.data_to_send` returns the bytes the board wrote to the link. It implements
``firmware_proto/PROTOCOL.md`` sections 2-7 (state machine, FIFO, credits, watchdog, faults).

The sample path, per block of ticks (vectorised, never per sample in Python): FIFO codes
(clamped into ``[code_min, code_max]`` when stored) -> DAC quantisation (``dac_bits``) ->
amplifier (``dac_offset_v + dac_v_per_code * code``) -> amplifier slew limit ->
:meth:`hil_sim.stage.Stage.step` -> sensor noise (:meth:`~hil_sim.stage.Stage.sense`) -> ADC
(``adc_offset_um + adc_um_per_code * code``, ``adc_bits``) -> SENSOR frames.

Timing model: ticks of the sample clock happen at ``t0 + j / sample_rate_hz``; :meth:`advance`
plays every tick due by ``now`` in one block. The stage itself is stepped lazily, in blocks of at
most ``status_period_ms`` of played samples (its fixed cost per call dominates small blocks), so
SENSOR rows leave the board at least every ``status_period_ms`` as the spec requires. Between
runs (IDLE, RAMPING, ARMED, UNCONFIGURED) the stage keeps evolving in time (creep relaxes) on a
coarse grid. Events inside one :meth:`advance` span (stop index reached, underrun, watchdog,
ramp end) are processed in time order.

Fault injection (:class:`BoardConfig`): bit flips in outgoing and incoming bytes and dropped
outgoing frames, from a generator seeded by ``BoardConfig.seed``; a board of another protocol
version; an ADC wired to the DAC (``adc_loopback``: the sensor reads back the applied code).
At run time (:attr:`Board.faults`, :class:`FaultHooks`): the next replies to a request type
lost on the way, a request type refused with a forced NAK. :mod:`hil_sim.wire` runs a board
on the wall clock over a socket pair (the link tests' board).

What the board is (:class:`BoardConfig`, :class:`FaultHooks`) lives in
:mod:`hil_sim.board_config`. This module is still over 800 lines because it is the firmware's
whole state machine (PROTOCOL.md sections 2-7) in one class, as the C firmware under
``firmware_proto/c`` is one core; splitting it would put the FIFO, the clock and the fault
handling, which change state together, in different files.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from firmware_proto import (
    HEADER_SIZE,
    NO_CHANNEL,
    NO_INDEX,
    PROTOCOL_VERSION,
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
    Heartbeat,
    Hello,
    MessageType,
    NakReason,
    RampToSafe,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
    Sync,
    max_samples_per_frame,
)
from hil_sim.board_config import BoardConfig, FaultHooks
from hil_sim.errors import SimConfigError as ConfigError
from hil_sim.microscope import Microscope, MicroscopeConfig
from hil_sim.stage import PRESET_DIR, Stage, StageConfig

F64 = NDArray[np.float64]

log = logging.getLogger("hil_sim.board")

_U32 = 0xFFFFFFFF
_TICK_EPS = 1e-6
"""Tolerance (in ticks) when deciding whether a tick is due: float rounding of ``t0 + j / rate``."""
_IDLE_MIN_SPAN_S = 1e-9
_DEFAULT_STATUS_PERIOD_S = 0.01
"""FAULT rate limit before the first CONFIGURE (no ``status_period_ms`` yet)."""
_MAX_PENDING_TICKS = 1 << 16

_NAK_FOR_DECODE_ERROR = {
    ErrorKind.UNKNOWN_TYPE: NakReason.UNKNOWN_TYPE,
    ErrorKind.BAD_VERSION: NakReason.VERSION_MISMATCH,
    ErrorKind.BAD_LENGTH: NakReason.BAD_LENGTH,
    ErrorKind.BAD_VALUE: NakReason.BAD_VALUE,
}
_HOST_TYPES = frozenset(
    {
        MessageType.HELLO,
        MessageType.CONFIGURE,
        MessageType.START,
        MessageType.STOP,
        MessageType.RAMP_TO_SAFE,
        MessageType.HEARTBEAT,
        MessageType.SAMPLES,
        MessageType.SYNC,
    }
)
SYNC_QUEUE_EVENTS = 1024
"""Capacity of the sync event queue (PROTOCOL.md 4.14: at least 1024)."""


def _f32_outward(value: float, up: bool) -> float:
    """``value`` rounded to float32, away from the inside of a range (so the range never shrinks)."""
    f = np.float32(value)
    if up and float(f) < value:
        f = np.nextafter(f, np.float32(np.inf))
    elif not up and float(f) > value:
        f = np.nextafter(f, np.float32(-np.inf))
    return float(f)


@dataclass(frozen=True, slots=True)
class BoardCounters:
    """Counters of the board since power-up (the STATUS counters, unwrapped, plus a few more)."""

    crc_errors: int
    frames_dropped: int
    underruns: int
    clamped_samples: int
    index_gaps: int
    overflows: int
    samples_played: int
    sensor_rows_sent: int
    watchdog_trips: int


def slew_limit(v: F64, prev: F64, max_step: float) -> F64:
    """Limit the per-sample change of ``v`` (channels x n) to ``max_step``, starting from ``prev``.

    Vectorised check; the sequential recursion runs only from the first violation of a channel on.
    """
    d = np.diff(v, axis=1, prepend=prev[:, None])
    bad = np.abs(d) > max_step
    if not bad.any():
        return v
    out = v.copy()
    for c in np.flatnonzero(bad.any(axis=1)):
        k = int(np.argmax(bad[c]))
        x = v[c].tolist()
        y = float(prev[c]) if k == 0 else x[k - 1]
        row = out[c]
        for j in range(k, len(x)):
            step = x[j] - y
            if step > max_step:
                y += max_step
            elif step < -max_step:
                y -= max_step
            else:
                y = x[j]
            row[j] = y
    return out


def _quantise_top_bits(codes: NDArray[np.int64], bits: int) -> NDArray[np.int64]:
    """Keep the top ``bits`` of 16-bit left-justified codes (floor), as a converter with ``bits`` does."""
    if bits >= 16:
        return codes
    step = 1 << (16 - bits)
    out: NDArray[np.int64] = (codes // step) * step
    return out


class Board:
    """The simulated board (sans I/O).

    Parameters
    ----------
    stage
        The simulated stage; one board channel per stage axis, in the stage's order.
    config
        Board properties and fault injection.
    now
        The caller's clock at power-up (s, any monotonic origin).

    Examples
    --------
    >>> from hil_sim.board import Board
    >>> board = Board.from_scanner_file(None, now=0.0)  # the built-in simulated stage
    >>> board.state.name
    'UNCONFIGURED'
    """

    def __init__(self, stage: Stage, config: BoardConfig | None = None, *, now: float = 0.0) -> None:
        self._cfg = config if config is not None else BoardConfig()
        self._stage = stage
        C = stage.channels
        self._C = C
        ranges = self._cfg.amplifier_ranges_v
        if ranges is None:
            ranges = tuple((-250.0, 250.0) for _ in range(C))
        if len(ranges) != C:
            raise ConfigError(f"board: {len(ranges)} amplifier ranges for a {C}-channel stage")
        ranges = tuple((_f32_outward(lo, False), _f32_outward(hi, True)) for lo, hi in ranges)
        limit = min(
            max_samples_per_frame(C, MessageType.SAMPLES), max_samples_per_frame(C, MessageType.SENSOR)
        )
        mspf = self._cfg.max_samples_per_frame or limit
        if not 1 <= mspf <= limit:
            raise ConfigError(f"board: max_samples_per_frame {mspf} outside [1, {limit}] for {C} channels")
        self._caps = Capabilities(
            reply_to_seq=0,
            protocol_version=(
                self._cfg.protocol_version
                if self._cfg.caps_protocol_version is None
                else self._cfg.caps_protocol_version
            ),
            firmware_version=self._cfg.firmware_version,
            dac_bits=self._cfg.dac_bits,
            adc_bits=self._cfg.adc_bits,
            max_samples_per_frame=mspf,
            sample_rate_min_hz=self._cfg.sample_rate_min_hz,
            sample_rate_max_hz=self._cfg.sample_rate_max_hz,
            sample_clock_hz=self._cfg.sample_clock_hz,
            fifo_depth_samples=self._cfg.fifo_depth_samples,
            board_serial=self._cfg.board_serial,
            amplifier_ranges_v=ranges,
            sync_outputs=self._cfg.sync_outputs,
            position_sensor=self._cfg.microscope is None or self._cfg.microscope.position_sensor,
        )
        self._ep = Endpoint()
        self._fx_rng = np.random.default_rng(self._cfg.seed)
        #: Faults injected at run time.
        self.faults = FaultHooks()
        #: Every HELLO received (the host's session ids).
        self.hellos: list[Hello] = []
        #: Control requests applied (retransmissions answered from the cache not counted), by type name.
        self.requests: dict[str, int] = {}
        #: With ``record_played``: ``(first index, codes)`` of every block played.
        self.played: list[tuple[int, NDArray[np.int16]]] = []
        #: Injected faults so far: frames dropped, bytes damaged (out / in), replies lost.
        self.injected = {"frames_dropped": 0, "bytes_out": 0, "bytes_in": 0, "replies_dropped": 0}
        #: Most samples the FIFO held, samples it accepted.
        self.max_fifo_level = 0
        self.samples_accepted = 0
        self._held_out: list[bytes] = []
        self._t = float(now)
        self._t_power_up = float(now)

        self._state = BoardState.UNCONFIGURED
        self._hello_seen = False
        self._session_id: int | None = None
        self._conf: Configure | None = None
        self._flags = FaultFlags.NONE
        self._fault_last_sent: dict[FaultCode, float] = {}
        self._status_due = False
        self._next_status_t = math.inf

        # watchdog: armed by every valid host frame, disarmed when it fires
        self._last_rx_t = float(now)
        self._wd_armed = False
        self._watchdog_index = NO_INDEX

        # counters (unwrapped)
        self._crc_errors = 0
        self._frames_dropped = 0
        self._underruns = 0
        self._clamped = 0
        self._index_gaps = 0
        self._overflows = 0
        self._samples_played = 0
        self._sensor_rows_sent = 0
        self._watchdog_trips = 0

        # FIFO and indices: the FIFO holds indices [play_index, write_index)
        depth = self._cfg.fifo_depth_samples
        self._fifo = np.zeros((depth, C), dtype=np.int16)
        self._write_index = 0
        self._play_index = 0
        self._last_played = NO_INDEX
        self._start_index = 0
        self._prefill = 1
        self._t0 = 0.0  # time of the tick that plays start_index
        self._stop_after: int | None = None

        # outputs: DAC voltage (what the codes say) and the amplifier output (after the slew limit)
        self._v_dac = np.zeros(C)
        # scalings of the configuration in force
        self._dac_scale = np.ones(C)
        self._dac_offset = np.zeros(C)
        self._code_min = np.full(C, -32768, dtype=np.int16)
        self._code_max = np.full(C, 32767, dtype=np.int16)
        self._adc_scale = np.ones(C)
        self._adc_offset = np.zeros(C)
        self._v_amp = np.zeros(C)
        # output trajectory outside RUNNING: a ramp from v0 at t0 towards the target (hold = no ramp)
        self._ramp_t0 = float(now)
        self._ramp_v0 = np.zeros(C)
        self._ramp_target = np.zeros(C)
        self._ramp_rate = np.ones(C)

        self._microscope: Microscope | None = None
        if self._cfg.microscope is not None:
            if "z" not in stage.axes:
                raise ConfigError("board: the simulated microscope needs a stage with a z axis")
            self._microscope = Microscope(self._cfg.microscope, stage.config)
        self._truth_fh = open(self._cfg.truth_log, "ab") if self._cfg.truth_log else None  # noqa: SIM115
        # sync outputs: queued events (index, lines, mask), the present levels, their changes
        self._sync_queue: deque[tuple[int, int, int]] = deque()
        self._sync_level = 0
        self._sync_last_queued = -1
        self._sync_log: deque[tuple[int, int]] = deque(maxlen=1 << 16)

        # stage: simulated up to _stage_t; played ticks waiting for the stage
        self._stage_t = float(now)
        self._pending: list[F64] = []
        self._pending_first = 0
        self._pending_n = 0

    # -- construction ----------------------------------------------------------------------

    @classmethod
    def from_scanner_file(
        cls,
        path: str | Path | None,
        *,
        effects: Sequence[str] = (),
        seed: int = 0,
        config: BoardConfig | None = None,
        now: float = 0.0,
    ) -> Board:
        """A board driving the simulated stage of a scanner YAML (its ``simulation:`` section).

        The amplifier ranges are the scanner's axis voltage limits (unless ``config`` sets them).

        Parameters
        ----------
        path
            Scanner YAML; ``None``: ``configs/sim-stage.yaml``.
        effects
            ``NAME=VALUE`` effect strings (:meth:`StageConfig.with_effects`).
        seed
            Seed of the sensor noise and of the fault injection.
        config
            Board properties (its ``seed`` is replaced by ``seed``).
        now
            The caller's clock at power-up.

        Raises
        ------
        ConfigError
            The file or an effect string is invalid (``FILE:LINE: field: reason``).
        """
        p = PRESET_DIR / "sim-stage.yaml" if path is None else Path(path)
        stage_cfg = StageConfig.from_file(p)
        limits = _voltage_limits(p)
        if effects:
            stage_cfg = stage_cfg.with_effects(*effects)
        stage = Stage(stage_cfg, seed=seed)
        cfg = config if config is not None else BoardConfig()
        if cfg.amplifier_ranges_v is None:
            ranges = tuple(limits[a] for a in stage.axes)
            cfg = dataclasses.replace(cfg, amplifier_ranges_v=ranges)
        cfg = dataclasses.replace(cfg, seed=seed)
        section = _microscope_section(p)
        if cfg.microscope is None and section is not None:
            if not isinstance(section, dict):
                raise ConfigError(f"{p}: simulation.microscope: must be a mapping")
            try:
                cfg = dataclasses.replace(cfg, microscope=MicroscopeConfig(**section))
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"{p}: simulation.microscope: {exc}") from exc
        return cls(stage, cfg, now=now)

    # -- public state ----------------------------------------------------------------------

    @property
    def capabilities(self) -> Capabilities:
        """What the board answers to HELLO (``reply_to_seq`` set per reply)."""
        return self._caps

    @property
    def configuration(self) -> Configure | None:
        """The configuration in force, or None before the first accepted CONFIGURE."""
        return self._conf

    @property
    def state(self) -> BoardState:
        """The output state machine."""
        return self._state

    @property
    def stage(self) -> Stage:
        """The simulated stage."""
        return self._stage

    @property
    def time(self) -> float:
        """The caller's clock up to which the board has been simulated."""
        return self._t

    @property
    def fault_flags(self) -> FaultFlags:
        """Latched faults (as in STATUS)."""
        return self._flags

    @property
    def session_id(self) -> int | None:
        """``session_id`` of the last HELLO, or None."""
        return self._session_id

    @property
    def output_voltages_v(self) -> F64:
        """The DAC output voltage per channel (V) at :attr:`time` (a copy)."""
        if self._state is BoardState.RUNNING:
            return self._v_dac.copy()
        return self._trajectory(np.array([self._t]))[:, 0]

    @property
    def sync_transitions(self) -> list[tuple[int, int]]:
        """``(sample index, levels)`` of the latest sync-output changes (bit 0 pixel, 1 line, 2 frame).

        The board's record of what it drove, for tests and inspection (the last 65536 changes;
        a clock stop that lowers the outputs is recorded at ``last_played_index + 1``).
        """
        return list(self._sync_log)

    @property
    def counters(self) -> BoardCounters:
        """Counters since power-up."""
        return BoardCounters(
            crc_errors=self._crc_errors,
            frames_dropped=self._frames_dropped,
            underruns=self._underruns,
            clamped_samples=self._clamped,
            index_gaps=self._index_gaps,
            overflows=self._overflows,
            samples_played=self._samples_played,
            sensor_rows_sent=self._sensor_rows_sent,
            watchdog_trips=self._watchdog_trips,
        )

    @property
    def endpoint(self) -> Endpoint:
        """The protocol endpoint (sequence numbers, reply cache, decoder statistics)."""
        return self._ep

    def status(self) -> Status:
        """The STATUS the board would send now."""
        depth = self._cfg.fifo_depth_samples
        return Status(
            state=self._state,
            fault_flags=self._flags,
            write_index=self._write_index,
            last_played_index=self._last_played,
            fifo_free_samples=depth - (self._write_index - self._play_index),
            crc_errors=self._crc_errors & _U32,
            frames_dropped=self._frames_dropped & _U32,
            underruns=self._underruns & _U32,
            clamped_samples=self._clamped & _U32,
            index_gaps=self._index_gaps & _U32,
            overflows=self._overflows & _U32,
        )

    # -- I/O boundary ----------------------------------------------------------------------

    def feed(self, data: bytes | bytearray | memoryview, now: float) -> None:
        """The host's bytes arrived at ``now``: simulate up to ``now``, then handle the frames."""
        self.advance(now)
        now = self._t
        raw = bytes(data)
        if self._cfg.corrupt_in_rate > 0.0:
            raw = self._corrupt(raw, self._cfg.corrupt_in_rate, "bytes_in")
        ok_before = self._ep.decoder_stats.frames_ok
        dup_before = self._ep.stats.duplicate_requests
        for event in self._ep.receive(raw, now):
            if isinstance(event, DecodeError):
                self._on_decode_error(event, now)
            elif isinstance(event, Frame) and event.ack_requested and self._reply_dropped(event):
                # the reply (and what it triggered) is lost on the way
                self._lost_on_the_way(functools.partial(self._on_frame, event, now))
                self.injected["replies_dropped"] += 1
            elif isinstance(event, Frame):
                self._on_frame(event, now)
            # Acked / Nacked / TimedOut cannot happen: the board sends no requests
        if self._ep.decoder_stats.frames_ok > ok_before:
            self._feed_watchdog(now)
        self._process_events(now)  # e.g. a ramp of zero length ends at once
        if self._ep.stats.duplicate_requests > dup_before:
            log.info(
                "answered %d retransmitted request(s) from the reply cache",
                self._ep.stats.duplicate_requests - dup_before,
            )
        self._periodic(now)

    def advance(self, now: float) -> None:
        """Let simulated time pass up to ``now``: play due samples, fire timers, send STATUS/SENSOR.

        A ``now`` earlier than :attr:`time` is treated as :attr:`time` (the clock never runs back).
        """
        now = max(float(now), self._t)
        self._process_events(now)
        self._run_to(now)
        self._t = now
        self._periodic(now)

    def _process_events(self, now: float) -> None:
        while True:
            t_evt, kind = self._next_event()
            if t_evt > now:
                return
            self._handle_event(kind, t_evt)

    def data_to_send(self) -> bytes:
        """The bytes the board wrote since the last call (after the fault injection)."""
        out = self._ep.data_to_send()
        if self._held_out:
            out = b"".join(self._held_out) + out
            self._held_out.clear()
        if not out:
            return b""
        if self._cfg.drop_rate > 0.0:
            frames = out.split(b"\x00")[:-1]
            keep = self._fx_rng.random(len(frames)) >= self._cfg.drop_rate
            self.injected["frames_dropped"] += int(np.count_nonzero(~keep))
            out = b"".join(f + b"\x00" for f, k in zip(frames, keep, strict=True) if k)
        if self._cfg.corrupt_rate > 0.0:
            out = self._corrupt(out, self._cfg.corrupt_rate, "bytes_out")
        return out

    def _lost_on_the_way(self, send: Callable[[], object]) -> None:
        """Run ``send`` and lose what it writes (the frames keep their sequence numbers): the
        bytes written before it go out as usual."""
        self._held_out.append(self._ep.data_to_send())
        send()
        self._ep.data_to_send()

    def _reply_dropped(self, frame: Frame) -> bool:
        left = self.faults.drop_replies.get(frame.msg.TYPE, 0)
        if left <= 0:
            return False
        self.faults.drop_replies[frame.msg.TYPE] = left - 1
        return True

    def next_deadline(self) -> float:
        """Earliest time at which :meth:`advance` has scheduled work (may be in the past)."""
        t_evt, _ = self._next_event()
        t = min(t_evt, self._next_status_t)
        if self._state is BoardState.RUNNING and self._conf is not None:
            t = min(t, self._tick_time(self._play_index))
        return t

    def _corrupt(self, data: bytes, rate: float, what: str) -> bytes:
        n = len(data)
        k = int(self._fx_rng.binomial(n, rate))
        if k == 0:
            return data
        self.injected[what] += k
        arr = np.frombuffer(data, dtype=np.uint8).copy()
        pos = self._fx_rng.integers(0, n, size=k)
        bits = self._fx_rng.integers(0, 8, size=k).astype(np.uint8)
        np.bitwise_xor.at(arr, pos, np.left_shift(np.uint8(1), bits))
        return arr.tobytes()

    # -- sending -----------------------------------------------------------------------------

    def _send_status(self, now: float) -> None:
        self._ep.send(self.status(), now)
        self._status_due = False
        if self._conf is not None:
            self._next_status_t = now + self._conf.status_period_ms * 1e-3

    def _status_period_s(self) -> float:
        return _DEFAULT_STATUS_PERIOD_S if self._conf is None else self._conf.status_period_ms * 1e-3

    def _fault(
        self,
        code: FaultCode,
        now: float,
        *,
        channel: int = NO_CHANNEL,
        index: int = NO_INDEX,
        detail: int = 0,
    ) -> None:
        """Latch ``code`` and send FAULT unless one of this code went out within a status period."""
        self._flags |= FaultFlags.of(code)
        last = self._fault_last_sent.get(code)
        if last is not None and now - last < self._status_period_s():
            return
        self._fault_last_sent[code] = now
        self._ep.send(Fault(code, channel, index, detail & _U32), now)

    def _set_state(self, state: BoardState) -> None:
        if state is not self._state:
            log.debug("state %s -> %s", self._state.name, state.name)
            self._state = state
            self._status_due = True

    def _periodic(self, now: float) -> None:
        if self._state is BoardState.RUNNING and self._pending_n:
            span = self._tick_time(self._pending_first + self._pending_n - 1) - self._tick_time(
                self._pending_first
            )
            age = now - self._tick_time(self._pending_first)
            period = self._status_period_s()
            if span >= period or age >= period or self._pending_n >= _MAX_PENDING_TICKS:
                self._flush_stage()
        if self._state is not BoardState.RUNNING and now - self._stage_t >= self._cfg.idle_block_s:
            self._sync_idle(now)
        if self._conf is not None and (self._status_due or now >= self._next_status_t):
            self._send_status(now)

    # -- the watchdog ------------------------------------------------------------------------

    def _feed_watchdog(self, now: float) -> None:
        self._last_rx_t = now
        self._wd_armed = True

    def _watchdog_deadline(self) -> float:
        if (
            not self._wd_armed
            or self._conf is None
            or self._state not in (BoardState.IDLE, BoardState.ARMED, BoardState.RUNNING)
        ):
            return math.inf
        return self._last_rx_t + self._conf.heartbeat_timeout_ms * 1e-3

    # -- events in simulated time ------------------------------------------------------------

    def _tick_time(self, index: int) -> float:
        assert self._conf is not None
        return self._t0 + (index - self._start_index) / self._conf.sample_rate_hz

    def _due_ticks(self, now: float) -> int:
        """Index one past the last tick due at ``now`` (RUNNING)."""
        assert self._conf is not None
        j = math.floor((now - self._t0) * self._conf.sample_rate_hz + _TICK_EPS)
        return self._start_index + j + 1

    def _run_end(self) -> tuple[int, str]:
        """Index of the tick at which the run ends, and why ("stop" after it / "underrun" at it)."""
        if self._stop_after is not None and self._stop_after < self._write_index:
            return self._stop_after, "stop"
        return self._write_index, "underrun"

    def _next_event(self) -> tuple[float, str]:
        best = (self._watchdog_deadline(), "watchdog")
        if self._state is BoardState.RUNNING and self._conf is not None:
            index, kind = self._run_end()
            t = self._tick_time(index) - _TICK_EPS / self._conf.sample_rate_hz
            if t <= best[0]:
                best = (t, kind)
        elif self._state is BoardState.RAMPING:
            t = self._ramp_end_time()
            if t < best[0]:
                best = (t, "ramp_end")
        return best

    def _handle_event(self, kind: str, t: float) -> None:
        if kind == "stop":
            assert self._stop_after is not None
            self._play(self._stop_after + 1 - self._play_index)
            log.info("stopped after index %d", self._last_played)
            self._stop_clock(self._tick_time(self._last_played))
            self._set_state(BoardState.IDLE)
        elif kind == "underrun":
            self._play(self._write_index - self._play_index)
            self._underruns += 1
            t_u = self._tick_time(self._write_index)
            log.warning(
                "underrun at index %d (last valid index %d)",
                self._write_index,
                self._last_played if self._last_played != NO_INDEX else -1,
            )
            self._stop_clock(t_u)
            self._set_state(BoardState.IDLE)
            self._fault(FaultCode.UNDERRUN, t_u, index=self._last_played)
        elif kind == "ramp_end":
            self._sync_idle(t)
            self._begin_hold(self._ramp_target.copy(), t)
            self._set_state(BoardState.IDLE)
        elif kind == "watchdog":
            self._run_to(t)
            self._watchdog_trips += 1
            self._wd_armed = False
            self._watchdog_index = self._last_played
            log.warning(
                "watchdog: host silent for %d ms, ramping to safe",
                self._conf.heartbeat_timeout_ms if self._conf else -1,
            )
            if self._state in (BoardState.RUNNING, BoardState.ARMED):
                self._stop_clock(t)
            self._fault(FaultCode.WATCHDOG, t, index=self._last_played)
            self._begin_ramp(t)
        else:  # pragma: no cover - the event kinds are fixed above
            raise AssertionError(kind)
        if self._status_due and self._conf is not None:
            self._send_status(t)

    def _run_to(self, now: float) -> None:
        """Play the ticks due by ``now`` (RUNNING; bounded by the FIFO and a pending stop)."""
        if self._state is not BoardState.RUNNING:
            return
        n = min(self._due_ticks(now), self._write_index) - self._play_index
        if self._stop_after is not None:
            n = min(n, self._stop_after + 1 - self._play_index)
        if n > 0:
            self._play(n)

    # -- the sample path ---------------------------------------------------------------------

    def _play(self, n: int) -> None:
        """Apply the next ``n`` FIFO rows (already clamped) and queue them for the stage."""
        if n <= 0:
            return
        assert self._conf is not None
        depth = self._cfg.fifo_depth_samples
        start = self._play_index % depth
        end = start + n
        if end <= depth:
            codes = self._fifo[start:end]
        else:
            codes = np.concatenate((self._fifo[start:], self._fifo[: end - depth]))
        c64 = _quantise_top_bits(codes.astype(np.int64), self._cfg.dac_bits)
        if self._cfg.record_played or self._cfg.adc_loopback:
            self.played.append((self._play_index, c64.astype(np.int16)))
        volts = self._dac_offset[:, None] + self._dac_scale[:, None] * c64.T
        dt = 1.0 / self._conf.sample_rate_hz
        volts = slew_limit(volts, self._v_amp, self._cfg.amp_slew_v_per_s * dt)
        if not self._pending_n:
            self._pending_first = self._play_index
        self._pending.append(volts)
        self._pending_n += n
        self._v_dac = self._dac_offset + self._dac_scale * c64[-1]
        self._v_amp = volts[:, -1].copy()
        self._apply_sync(self._play_index + n)
        self._play_index += n
        self._last_played = self._play_index - 1
        self._samples_played += n

    def _apply_sync(self, end: int) -> None:
        """Apply the queued sync events of the ticks before index ``end`` (being played now)."""
        q = self._sync_queue
        enabled = (1 << self._cfg.sync_outputs) - 1
        while q and q[0][0] < end:
            index, lines, mask = q.popleft()
            if index < self._play_index:
                continue
            mask &= enabled
            level = (self._sync_level & ~mask) | (lines & mask)
            if level != self._sync_level:
                self._sync_level = level
                self._sync_log.append((index, level))

    def _clear_sync(self) -> None:
        self._sync_queue.clear()
        self._sync_last_queued = -1
        if self._sync_level:
            self._sync_level = 0
            self._sync_log.append((self._last_played + 1 if self._last_played != NO_INDEX else 0, 0))

    def _flush_stage(self) -> None:
        """Run the stage over the played ticks and send their SENSOR rows."""
        if not self._pending_n:
            return
        assert self._conf is not None
        v = self._pending[0] if len(self._pending) == 1 else np.concatenate(self._pending, axis=1)
        first = self._pending_first
        self._pending = []
        self._pending_n = 0
        dt = 1.0 / self._conf.sample_rate_hz
        self._stage_t = self._tick_time(first + v.shape[1] - 1)
        if self._cfg.adc_loopback:
            self._send_sensor(first, self._played_codes(first, v.shape[1]).T.astype(np.float64))
            return
        x = self._stage.step(v, dt)
        z_monitor: F64 | None = None
        mic = self._microscope
        if mic is not None:
            axes = self._stage.axes
            xt = x[axes.index("x")] if "x" in axes else np.zeros(x.shape[1])
            yt = x[axes.index("y")] if "y" in axes else np.zeros(x.shape[1])
            vz, ez = mic.step(xt, yt, dt)
            z_monitor = vz / mic.config.monitor_ratio
            self._record_truth(first, np.stack((xt, yt, vz, ez)))
        dec = self._conf.sensor_decimation
        offset = (self._start_index - first) % dec
        rows = x[:, offset::dec]
        if rows.shape[1] == 0:
            return
        sensed = self._stage.sense(rows)
        if mic is not None and z_monitor is not None:
            axes = self._stage.axes
            sensed[axes.index("z")] = z_monitor[offset::dec]
            if not mic.config.position_sensor:
                for a in ("x", "y"):
                    if a in axes:
                        sensed[axes.index(a)] = 0.0
        step = float(1 << (16 - self._cfg.adc_bits))
        codes = np.rint((sensed - self._adc_offset[:, None]) / (self._adc_scale[:, None] * step)) * step
        self._send_sensor(first, codes, offset)

    def _send_sensor(self, first: int, codes: F64, offset: int | None = None) -> None:
        """SENSOR frames of ADC ``codes`` (channels x ticks, decimated from ``first + offset``)."""
        assert self._conf is not None
        dec = self._conf.sensor_decimation
        if offset is None:
            offset = (self._start_index - first) % dec
            codes = codes[:, offset::dec]
        if codes.shape[1] == 0:
            return
        step = float(1 << (16 - self._cfg.adc_bits))
        codes = np.clip(codes, -32768.0, 32768.0 - step)
        table = np.ascontiguousarray(codes.T, dtype=np.int16)
        mspf = self._caps.max_samples_per_frame
        first_row = first + offset
        now = self._t
        drop_from = self.faults.drop_sensor_from
        for lo in range(0, table.shape[0], mspf):
            msg = Sensor(first_row + lo * dec, dec, table[lo : lo + mspf])
            if drop_from is not None and msg.first_index >= drop_from:
                self._lost_on_the_way(functools.partial(self._ep.send, msg, now))
                self.injected["frames_dropped"] += 1
                continue
            self._ep.send(msg, now)
        self._sensor_rows_sent += table.shape[0]

    def _played_codes(self, first: int, n: int) -> NDArray[np.int16]:
        """The codes played at indices ``[first, first + n)`` (``adc_loopback``), rows."""
        parts = [(f, c) for f, c in self.played if f < first + n and f + c.shape[0] > first]
        rows = np.concatenate([c for _, c in parts]) if parts else np.zeros((0, self._C), np.int16)
        lo = first - (parts[0][0] if parts else first)
        out: NDArray[np.int16] = rows[lo : lo + n]
        if not self._cfg.record_played:  # keep only what a later block may still need
            self.played = [(f, c) for f, c in self.played if f + c.shape[0] > first + n]
        return out

    def _record_truth(self, first: int, rows: F64) -> None:
        if self._truth_fh is None:
            return
        j = np.arange(rows.shape[1])
        sel = (first + j) % self._cfg.truth_every == 0
        block = np.vstack(((first + j[sel]).astype(np.float64), rows[:, sel]))
        self._truth_fh.write(np.ascontiguousarray(block.T, dtype=np.float64).tobytes())
        self._truth_fh.flush()

    def _stop_clock(self, t: float) -> None:
        """Leave RUNNING / ARMED at ``t``: run the stage over what was played, empty the FIFO, hold."""
        if self._state is BoardState.RUNNING:
            self._flush_stage()
            self._set_hold(self._v_dac, self._stage_t)
        self._sync_idle(t)
        self._play_index = self._write_index
        self._stop_after = None
        self._clear_sync()

    # -- outside RUNNING: hold and ramps -----------------------------------------------------

    def _trajectory(self, times: F64) -> F64:
        """DAC voltage (channels x len(times)) of the present hold / ramp at ``times``."""
        dv = self._ramp_target - self._ramp_v0
        elapsed = np.maximum(times - self._ramp_t0, 0.0)
        moved = np.minimum(self._ramp_rate[:, None] * elapsed[None, :], np.abs(dv)[:, None])
        out: F64 = self._ramp_v0[:, None] + np.sign(dv)[:, None] * moved
        return out

    def _ramp_end_time(self) -> float:
        dv = np.abs(self._ramp_target - self._ramp_v0)
        return self._ramp_t0 + float(np.max(dv / self._ramp_rate))

    def _sync_idle(self, t: float) -> None:
        """Step the stage through the hold / ramp up to ``t`` (outside RUNNING)."""
        span = t - self._stage_t
        if span <= _IDLE_MIN_SPAN_S:
            return
        moving = self._state is BoardState.RAMPING and self._ramp_end_time() > self._stage_t
        n = max(1, math.ceil(span / self._cfg.ramp_update_s - 1e-9)) if moving else 1
        dt = span / n
        times: F64 = np.asarray(self._stage_t + dt * np.arange(1, n + 1), dtype=np.float64)
        v = self._trajectory(times)
        self._stage.step(v, dt)
        self._stage_t = t
        self._v_amp = v[:, -1].copy()

    def _begin_hold(self, v: F64, t: float) -> None:
        self._sync_idle(t)
        self._set_hold(v, t)

    def _set_hold(self, v: F64, t: float) -> None:
        self._ramp_t0 = t
        self._ramp_v0 = v.copy()
        self._ramp_target = v.copy()
        self._v_dac = v.copy()

    def _begin_ramp(self, t: float) -> None:
        """Start ramping from the present output to the safe values at ``t`` (RAMPING)."""
        assert self._conf is not None
        present = (
            self._trajectory(np.array([t]))[:, 0] if self._state is not BoardState.RUNNING else self._v_dac
        )
        self._sync_idle(t)
        self._ramp_t0 = max(t, self._stage_t)
        self._ramp_v0 = present.copy()
        self._ramp_target = np.array([ch.safe_v for ch in self._conf.channels])
        self._ramp_rate = np.array([ch.ramp_v_per_s for ch in self._conf.channels])
        self._set_state(BoardState.RAMPING)

    # -- receiving ---------------------------------------------------------------------------

    def _on_decode_error(self, err: DecodeError, now: float) -> None:
        self._frames_dropped += 1
        if err.kind is ErrorKind.BAD_CRC:
            self._crc_errors += 1
            self._fault(FaultCode.CRC_ERRORS, now, detail=self._crc_errors)
        log.debug("dropped frame: %s: %s", err.kind.value, err.detail)
        reason = _NAK_FOR_DECODE_ERROR.get(err.kind)
        if reason is not None and err.ack_requested:
            detail = PROTOCOL_VERSION if reason is NakReason.VERSION_MISMATCH else 0
            self._ep.nak(err, reason, detail)

    def _on_frame(self, frame: Frame, now: float) -> None:
        msg = frame.msg
        if msg.TYPE not in _HOST_TYPES:
            self._frames_dropped += 1
            log.debug("dropped a %s frame from the host", msg.TYPE.name)
            return
        if isinstance(msg, Samples):
            self._on_samples(msg, now)
            return
        if isinstance(msg, Sync):
            self._on_sync(msg, now)
            return
        if isinstance(msg, Heartbeat):
            return
        if isinstance(msg, Hello):
            self._on_hello(frame, msg, now)
            return
        reply = frame.ack_requested
        self.requests[msg.TYPE.name] = self.requests.get(msg.TYPE.name, 0) + 1
        forced = self.faults.force_nak.get(msg.TYPE)
        if forced is not None and self._hello_seen:
            if reply:
                self._ep.nak(frame, forced[0], forced[1])
            if isinstance(msg, Configure):
                self._fault(FaultCode.CONFIG_REJECTED, now, detail=forced[1])
            return
        if not self._hello_seen or (
            self._state is BoardState.UNCONFIGURED and not isinstance(msg, Configure)
        ):
            if reply:
                self._ep.nak(frame, NakReason.BAD_STATE, int(self._state))
            return
        if isinstance(msg, Configure):
            self._on_configure(frame, msg, now)
        elif isinstance(msg, Start):
            self._on_start(frame, msg, now)
        elif isinstance(msg, Stop):
            self._on_stop(frame, msg, now)
        elif isinstance(msg, RampToSafe):
            if reply:
                self._ep.ack(frame)
            log.info("RAMP_TO_SAFE from %s", self._state.name)
            self._leave_for_ramp(now)

    def _on_hello(self, frame: Frame, msg: Hello, now: float) -> None:
        self.hellos.append(msg)
        if msg.protocol_version != self._cfg.protocol_version:
            log.warning(
                "HELLO in protocol version %d refused (this board speaks %d)",
                msg.protocol_version,
                self._cfg.protocol_version,
            )
            self._ep.nak(frame, NakReason.VERSION_MISMATCH, self._cfg.protocol_version)
            return
        self._hello_seen = True
        self._session_id = msg.session_id
        log.info(
            "HELLO session %d (state %s, latched faults %s)",
            msg.session_id,
            self._state.name,
            self._flags.name if self._flags else "none",
        )
        self._ep.reply(frame, dataclasses.replace(self._caps, reply_to_seq=frame.seq))
        if self._conf is not None:
            self._status_due = True
            if self._flags & FaultFlags.WATCHDOG:
                self._fault(FaultCode.WATCHDOG, now, index=self._watchdog_index)

    def _on_configure(self, frame: Frame, msg: Configure, now: float) -> None:
        if self._state not in (BoardState.UNCONFIGURED, BoardState.IDLE):
            if frame.ack_requested:
                self._ep.nak(frame, NakReason.BAD_STATE, int(self._state))
            return
        refusal = msg.check(self._caps)
        if refusal is not None:
            reason, offset = refusal
            log.warning("CONFIGURE refused: %s at frame offset %d", reason.name, offset)
            if frame.ack_requested:
                self._ep.nak(frame, reason, offset)
            self._fault(FaultCode.CONFIG_REJECTED, now, detail=offset)
            return
        if frame.ack_requested:
            self._ep.ack(frame)
        self._conf = msg
        self._dac_scale = np.array([ch.dac_v_per_code for ch in msg.channels])
        self._dac_offset = np.array([ch.dac_offset_v for ch in msg.channels])
        self._code_min = np.array([ch.code_min for ch in msg.channels], dtype=np.int16)
        self._code_max = np.array([ch.code_max for ch in msg.channels], dtype=np.int16)
        self._adc_scale = np.array([ch.adc_um_per_code for ch in msg.channels])
        self._adc_offset = np.array([ch.adc_offset_um for ch in msg.channels])
        self._flags = FaultFlags.NONE
        self._fault_last_sent.clear()
        log.info(
            "CONFIGURE accepted: %d Hz, watchdog %d ms, status every %d ms, decimation %d",
            msg.sample_rate_hz,
            msg.heartbeat_timeout_ms,
            msg.status_period_ms,
            msg.sensor_decimation,
        )
        self._begin_ramp(now)
        self._status_due = True

    def _on_start(self, frame: Frame, msg: Start, now: float) -> None:
        reply = frame.ack_requested
        if self._state is not BoardState.IDLE:
            if reply:
                self._ep.nak(frame, NakReason.BAD_STATE, int(self._state))
            return
        if msg.start_index == NO_INDEX:
            if reply:
                self._ep.nak(frame, NakReason.BAD_VALUE, HEADER_SIZE + 0)
            return
        if msg.prefill_samples > self._cfg.fifo_depth_samples:
            if reply:
                self._ep.nak(frame, NakReason.BAD_VALUE, HEADER_SIZE + 8)
            return
        if reply:
            self._ep.ack(frame)
        self._write_index = msg.start_index
        self._play_index = msg.start_index
        self._start_index = msg.start_index
        self._prefill = max(msg.prefill_samples, 1)
        self._stop_after = None
        self._flags = FaultFlags.NONE
        self._fault_last_sent.clear()
        self._clear_sync()
        log.info("START at index %d, prefill %d", msg.start_index, self._prefill)
        self._set_state(BoardState.ARMED)

    def _on_stop(self, frame: Frame, msg: Stop, now: float) -> None:
        if frame.ack_requested:
            self._ep.ack(frame)
        state = self._state
        if (
            state is BoardState.RUNNING
            and msg.stop_after_index != NO_INDEX
            and (msg.stop_after_index >= self._play_index)
        ):
            self._stop_after = msg.stop_after_index
            log.info("STOP after index %d", msg.stop_after_index)
            return
        if state in (BoardState.RUNNING, BoardState.ARMED):
            log.info("STOP at index %d", self._last_played if self._last_played != NO_INDEX else -1)
            self._stop_clock(now)
        elif state is BoardState.RAMPING:
            log.info("STOP: ramp cancelled")
            self._begin_hold(self._trajectory(np.array([now]))[:, 0], now)
        self._set_state(BoardState.IDLE)

    def _leave_for_ramp(self, now: float) -> None:
        if self._state in (BoardState.RUNNING, BoardState.ARMED):
            self._stop_clock(now)
        self._begin_ramp(now)

    def _on_sync(self, msg: Sync, now: float) -> None:
        if self._state not in (BoardState.ARMED, BoardState.RUNNING) or not self._cfg.sync_outputs:
            self._frames_dropped += 1
            return
        floor = max(self._sync_last_queued + 1, self._play_index)
        new = [(msg.first_index + off, lines, mask) for off, lines, mask in msg.events]
        new = [ev for ev in new if ev[0] >= floor]
        if len(self._sync_queue) + len(new) > SYNC_QUEUE_EVENTS:
            self._frames_dropped += 1
            self._overflows += 1
            self._fault(FaultCode.OVERFLOW, now, index=msg.first_index)
            return
        self._sync_queue.extend(new)
        if new:
            self._sync_last_queued = new[-1][0]

    def _on_samples(self, msg: Samples, now: float) -> None:
        if self._state not in (BoardState.ARMED, BoardState.RUNNING) or msg.n_channels != self._C:
            self._frames_dropped += 1
            return
        F, N = msg.first_index, msg.n_samples
        W = self._write_index
        depth = self._cfg.fifo_depth_samples
        L = W + depth - (W - self._play_index)
        if F + N <= W:
            self._frames_dropped += 1
            return
        if F > W:
            self._frames_dropped += 1
            self._index_gaps += 1
            self._fault(FaultCode.INDEX_GAP, now, index=W)
            return
        if F + N > L:
            self._frames_dropped += 1
            self._overflows += 1
            self._fault(FaultCode.OVERFLOW, now, index=F)
            return
        rows = msg.codes[W - F :]
        bad = (rows < self._code_min) | (rows > self._code_max)
        if bad.any():
            n_bad = int(np.count_nonzero(bad))
            r, c = divmod(int(np.argmax(bad)), self._C)
            raw = int(rows[r, c])
            self._clamped += n_bad
            log.warning(
                "clamped %d code(s) to the limits; first: index %d channel %d code %d", n_bad, W + r, c, raw
            )
            self._fault(FaultCode.LIMIT_VIOLATION, now, channel=c, index=W + r, detail=raw & 0xFFFF)
            rows = np.clip(rows, self._code_min, self._code_max)
        n = rows.shape[0]
        start = W % depth
        first_part = min(n, depth - start)
        self._fifo[start : start + first_part] = rows[:first_part]
        if first_part < n:
            self._fifo[: n - first_part] = rows[first_part:]
        self.samples_accepted += F + N - max(W, F)
        self._write_index = F + N
        self.max_fifo_level = max(self.max_fifo_level, self._write_index - self._play_index)
        if self._state is BoardState.ARMED and self._write_index - self._play_index >= self._prefill:
            assert self._conf is not None
            self._sync_idle(now)
            self._t0 = now + 1.0 / self._conf.sample_rate_hz
            self._set_state(BoardState.RUNNING)
            log.info("clock running from index %d", self._start_index)


def _microscope_section(path: Path) -> object:
    """``simulation.microscope`` of a scanner YAML, or None (read problems are reported elsewhere)."""
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return None
    sim = data.get("simulation") if isinstance(data, dict) else None
    return sim.get("microscope") if isinstance(sim, dict) else None


def _voltage_limits(path: Path) -> dict[str, tuple[float, float]]:
    """``axes.<a>.voltage_min_v / voltage_max_v`` of a scanner YAML (the amplifier ranges).

    Raises
    ------
    SimConfigError
        ``FILE: axes.<a>: ...`` when the limits are missing or not numbers.
    """
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: cannot read the scanner YAML: {exc}") from exc
    axes = data.get("axes") if isinstance(data, dict) else None
    if not isinstance(axes, dict):
        raise ConfigError(f"{path}: axes: missing or not a mapping")
    out: dict[str, tuple[float, float]] = {}
    for name, ax in axes.items():
        try:
            lo, hi = float(ax["voltage_min_v"]), float(ax["voltage_max_v"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(
                f"{path}: axes.{name}: voltage_min_v / voltage_max_v missing or not numbers"
            ) from exc
        out[str(name)] = (lo, hi)
    return out


__all__ = ["Board", "BoardConfig", "BoardCounters", "FaultHooks", "slew_limit"]
