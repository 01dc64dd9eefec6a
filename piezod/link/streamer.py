"""The host side of the sample pipeline: keep the board FIFO filled ahead from a block source.

The caller supplies a :class:`BlockSource` whose ``next_block(n)`` returns the next ``n``
voltages per axis (computed ahead from the inverse model by the daemon). :class:`Streamer` runs a
thread that converts blocks to DAC codes in one vectorised step (never a code outside the
configured limits: out-of-limit or NaN volts are clamped and reported as
:class:`~piezod.link.session.HostLimitFault`), and sends SAMPLES frames of up to
``frame_samples`` rows, each with its first sample index, so that the FIFO holds at least the
lead time (default 100 ms) without ever sending beyond the credit the board granted in STATUS.
Lost frames are resent from the last acknowledged ``write_index`` (go-back-N, PROTOCOL.md 7.3).
Samples are never paced one by one from Python: the board's clock does the pacing.

Sensor readback is matched to sample indices: every :class:`~piezod.link.session.SensorBlock`
is paired with the voltages that were commanded at the same indices (:class:`MatchedBlock`).

Just over 800 lines because credits, staging, rewind after lost frames and the end of a run
(stop, underrun, link loss) are one state machine on one thread; it is the streaming half of
:class:`piezod.link.board.SerialBoard`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
import numpy.typing as npt

from firmware_proto import MAX_SYNC_EVENTS, NO_INDEX, BoardState, FaultCode, FaultFlags, Status
from firmware_proto import ProtocolError as WireProtocolError
from piezod.errors import BoardFaultError, ConfigError, LinkError, ProtocolError
from piezod.link.session import (
    BoardFault,
    BoardSession,
    ChannelPlan,
    FaultFlagsRaised,
    HostLimitFault,
    LinkDown,
    LinkEvent,
    SensorBlock,
    StatusUpdate,
)

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
RunEnd = Literal["stop", "underrun", "watchdog", "link", "limit_violation", "error", "stopped"]


class BlockSource(Protocol):
    """Produces the commanded voltages, block by block."""

    def next_block(self, n: int) -> FloatArray:
        """The next ``n`` samples: volts, shape ``(axes, n)`` in the session's axis order."""
        ...


#: Sync outputs a source needs on the board to get :meth:`SyncSource.sync_events` sent (pixel, line, frame).
SYNC_OUTPUTS_USED = 3
#: Sync events the host keeps queued on the board at most: PROTOCOL.md 4.14 guarantees 1024, a
#: margin covers the host's estimate of what was played (a SYNC that does not fit is dropped whole).
SYNC_QUEUE_EVENTS = 768
#: Pending sync events sent at once even before they are due (within the lead).
SYNC_BATCH_EVENTS = 256


class SyncSource(Protocol):
    """A block source that also drives the board's sync outputs (PROTOCOL.md 4.14)."""

    def sync_events(self, first_index: int, n: int) -> list[tuple[int, int, int]]:
        """``(offset from first_index, lines, mask)`` of the sync events at indices ``[first, first + n)``.

        Called after the samples of these indices were produced (:meth:`BlockSource.next_block`),
        in index order, and again for the same indices after a go-back-N rewind.
        """
        ...


@dataclass(frozen=True, slots=True)
class CodeConverter:
    """Vectorised volts -> DAC codes for one configuration (clamping to the limits).

    Built with :meth:`from_plan`. Board channels without an axis get their safe code.
    """

    axis_channels: npt.NDArray[np.intp]
    scale: FloatArray
    offset: FloatArray
    code_min: FloatArray
    code_max: FloatArray
    v_min: FloatArray
    v_max: FloatArray
    safe_codes: npt.NDArray[np.int16]
    axes: tuple[str, ...]

    @classmethod
    def from_plan(cls, plan: ChannelPlan) -> CodeConverter:
        """The converter for ``plan``'s channels."""
        chans = plan.configure.channels
        idx = np.array(plan.axis_channel_indices, dtype=np.intp)
        sel = [chans[i] for i in idx]
        return cls(
            axis_channels=idx,
            scale=np.array([c.dac_v_per_code for c in sel], dtype=np.float64),
            offset=np.array([c.dac_offset_v for c in sel], dtype=np.float64),
            code_min=np.array([c.code_min for c in sel], dtype=np.float64),
            code_max=np.array([c.code_max for c in sel], dtype=np.float64),
            v_min=np.array([plan.axis_limits_v[i][0] for i in idx], dtype=np.float64),
            v_max=np.array([plan.axis_limits_v[i][1] for i in idx], dtype=np.float64),
            safe_codes=np.array([c.safe_code for c in chans], dtype=np.int16),
            axes=plan.axes,
        )

    @property
    def n_channels(self) -> int:
        """Board channels."""
        return int(self.safe_codes.shape[0])

    def convert(self, volts: npt.ArrayLike) -> tuple[npt.NDArray[np.int16], npt.NDArray[np.bool_]]:
        """Codes ``(n, channels)`` for volts ``(axes, n)``, and the mask ``(axes, n)`` of clamped samples.

        A sample is flagged when it lies outside the configured voltage limits or is not finite;
        it is clamped to the nearest limit code (NaN: the channel's safe code).

        Raises
        ------
        ValueError
            Wrong shape.
        """
        v = np.asarray(volts, dtype=np.float64)
        n_axes = self.axis_channels.shape[0]
        if v.ndim != 2 or v.shape[0] != n_axes:
            raise ValueError(f"block source: expected volts of shape ({n_axes}, n), got {v.shape}")
        n = v.shape[1]
        out = np.empty((n, self.n_channels), dtype=np.int16)
        out[:] = self.safe_codes
        with np.errstate(invalid="ignore"):
            bad = ~((v >= self.v_min[:, None]) & (v <= self.v_max[:, None]))
            x = (v - self.offset[:, None]) / self.scale[:, None]
        if bad.any():
            nan = np.isnan(x)
            if nan.any():
                x[nan] = np.broadcast_to(self.safe_codes[self.axis_channels][:, None], x.shape)[nan]
        np.rint(x, out=x)
        np.clip(x, self.code_min[:, None], self.code_max[:, None], out=x)
        out[:, self.axis_channels] = x.T
        return out, bad

    def to_volts(self, codes: npt.NDArray[np.int16]) -> FloatArray:
        """Commanded volts ``(axes, n)`` of codes ``(n, channels)``."""
        c = codes[:, self.axis_channels].T.astype(np.float64)
        out: FloatArray = self.offset[:, None] + self.scale[:, None] * c
        return out


@dataclass(frozen=True, slots=True, eq=False)
class MatchedBlock:
    """Sensor readback paired with the commanded voltages at the same sample indices.

    Attributes
    ----------
    indices
        Sample index of every row.
    commanded_v
        Volts commanded at those indices, ``(axes, n)`` (NaN where no longer known).
    position_um
        Sensor positions, ``(axes, n)``.
    axes
        Axis names of the rows.
    """

    indices: npt.NDArray[np.int64]
    commanded_v: FloatArray
    position_um: FloatArray
    axes: tuple[str, ...]


@dataclass(slots=True)
class RunRecord:
    """One START .. stop of the board clock."""

    start_index: int
    end_index: int = 0
    last_played_index: int | None = None
    ended_by: RunEnd | None = None

    @property
    def samples_sent(self) -> int:
        """Distinct sample indices sent."""
        return self.end_index - self.start_index

    @property
    def samples_played(self) -> int:
        """Samples of the run the board applied (padding played after the last one not counted)."""
        if self.last_played_index is None or self.last_played_index < self.start_index:
            return 0
        return min(self.last_played_index + 1, self.end_index) - self.start_index

    @property
    def padding_played(self) -> int:
        """Padding rows the board played after the run's last sample, before its STOP arrived.

        A run shorter than its prefill is padded with its last row (the clock starts only on a
        full prefill); the STOP that ends it takes a round trip, and the board plays the padding
        meanwhile. The sensor reads those rows back like any other.
        """
        if self.last_played_index is None:
            return 0
        return max(0, self.last_played_index + 1 - max(self.end_index, self.start_index))


@dataclass(slots=True)
class StreamStats:
    """What the streamer did (cumulative over runs)."""

    frames_sent: int = 0
    rows_sent: int = 0
    rows_resent: int = 0
    rewinds: int = 0
    host_clamped_samples: int = 0
    host_limit_faults: int = 0
    blocks_computed: int = 0
    lead_min_samples: int | None = None
    lead_sum_samples: float = 0.0
    lead_count: int = 0
    runs: list[RunRecord] = field(default_factory=list)
    matched_rows: int = 0
    unmatched_rows: int = 0
    sync_frames_sent: int = 0
    sync_events_sent: int = 0
    sync_events_late: int = 0
    implausible_status: int = 0

    @property
    def samples_sent(self) -> int:
        """Distinct sample indices sent over all runs."""
        return sum(r.samples_sent for r in self.runs)

    @property
    def samples_played(self) -> int:
        """Samples the board applied over all runs."""
        return sum(r.samples_played for r in self.runs)

    @property
    def padding_played(self) -> int:
        """Padding rows played after the last sample of short runs (:attr:`RunRecord.padding_played`)."""
        return sum(r.padding_played for r in self.runs)

    @property
    def unexplained_output_loss(self) -> int:
        """Samples sent but never played in runs that ended without a reported fault."""
        return sum(
            max(0, r.samples_sent - r.samples_played) for r in self.runs if r.ended_by in ("stop", None)
        )


STALL_FLOOR_S = 0.05
"""Resend after this long (s) without progress of ``write_index`` (at least 2 status periods)."""


def lead_samples_for(rate_hz: float, lead_s: float) -> int:
    """Samples per channel in ``lead_s`` at ``rate_hz`` (rounded up)."""
    return int(np.ceil(rate_hz * lead_s))


class Streamer:
    """Feeds the board from a :class:`BlockSource` (see the module docstring).

    Parameters
    ----------
    session
        A configured :class:`~piezod.link.session.BoardSession`.
    source
        The block source (volts ``(axes, n)``, axes in ``session.plan.axes`` order).
    lead_s
        Samples kept in the board FIFO ahead of the clock (s); also the START prefill.
    fill_s
        How far ahead of the clock the host fills (s), capped by the credits; default lead + 25 %.
    frame_samples
        Rows per SAMPLES frame; default 5 ms worth, at most the board's maximum.
    block_samples
        Rows asked from the source per call; default 20 ms worth.
    history_s
        How long commanded codes are kept to match the sensor readback (s).
    on_block
        Called (from the link reader thread) with every :class:`MatchedBlock`.
    auto_restart
        After an underrun, START again at a fresh index and go on (the bench); otherwise the run
        ends and the caller decides.
    """

    def __init__(
        self,
        session: BoardSession,
        source: BlockSource,
        *,
        lead_s: float = 0.1,
        fill_s: float | None = None,
        frame_samples: int | None = None,
        block_samples: int | None = None,
        history_s: float = 2.0,
        on_block: Callable[[MatchedBlock], None] | None = None,
        auto_restart: bool = False,
    ) -> None:
        plan, caps = session.plan, session.capabilities
        if plan is None or caps is None:
            raise ProtocolError("Streamer: the session is not configured")
        self.session = session
        self.source = source
        self.plan = plan
        self.rate_hz = plan.sample_rate_hz
        self.converter = CodeConverter.from_plan(plan)
        self.on_block = on_block
        self.auto_restart = auto_restart
        if lead_s <= 0:
            raise ConfigError(f"lead_s: {lead_s} must be > 0")
        self.frame_samples = int(
            frame_samples if frame_samples is not None else max(1, round(self.rate_hz * 0.005))
        )
        self.frame_samples = max(1, min(self.frame_samples, caps.max_samples_per_frame))
        self.lead_samples = lead_samples_for(self.rate_hz, lead_s)
        fifo = caps.fifo_depth_samples
        if fifo < self.lead_samples + self.frame_samples:
            raise ConfigError(
                f"the board FIFO ({fifo} samples) cannot hold the lead of {lead_s * 1000:g} ms "
                f"({self.lead_samples} samples at {self.rate_hz} Hz) plus one frame ({self.frame_samples}); "
                "lower the rate or the lead"
            )
        fill = fill_s if fill_s is not None else 1.25 * lead_s
        self.fill_samples = max(self.lead_samples + self.frame_samples, lead_samples_for(self.rate_hz, fill))
        self.block_samples = int(
            block_samples
            if block_samples is not None
            else max(self.frame_samples, round(self.rate_hz * 0.02))
        )
        self.status_period_s = plan.configure.status_period_ms / 1000.0
        sync = getattr(source, "sync_events", None)
        #: Where the sync events come from: the source's, when the board has the outputs it drives.
        self.sync: Callable[[int, int], list[tuple[int, int, int]]] | None = (
            sync if callable(sync) and caps.sync_outputs >= SYNC_OUTPUTS_USED else None
        )
        settings = getattr(session, "settings", None)  # stand-in sessions in tests may have none
        budget = settings.budget if settings is not None else None
        usable = budget.usable_bytes_per_s if budget is not None else None
        #: Seconds the link needs per row sent (a slow link: frames on the way are not lost frames).
        self._link_s_per_row = (
            budget.host_to_board_bytes_per_s / self.rate_hz / usable
            if budget is not None and usable is not None
            else 0.0
        )
        self.stats = StreamStats()
        cap = max(lead_samples_for(self.rate_hz, history_s), 4 * fifo)
        self._hist = np.zeros((cap, self.converter.n_channels), dtype=np.int16)
        # index ranges [lo, hi) written into the ring, one per run (runs never overlap in index)
        self._hist_ranges: deque[list[int]] = deque(maxlen=16)
        self._hist_top = 0
        self._hist_lock = threading.Lock()
        self._staged: deque[npt.NDArray[np.int16]] = deque()
        self._staged_rows = 0
        self._inflight: deque[tuple[int, npt.NDArray[np.int16]]] = deque()
        self._next_index = 0
        self._sent_hw = 0
        self._status_at = 0.0
        self._status_gap_s = 0.0
        self._run: RunRecord | None = None
        self._status_mark = 0
        self._credit = 0
        self._last_send = 0.0
        self._last_rewind = -1e9
        self._raw_gaps: tuple[int, int] | None = None
        self._raw_underruns: int | None = None
        self._running_seen = False
        self._finishing = False
        self._end_index: int | None = None
        self._stop_sent = False
        self._error: BaseException | None = None
        self._limit_violation = False
        self._link_down: LinkError | None = None
        self._gap_hint = False
        self._gap_pending = False
        self._w_seen = -1
        self._w_changed_at = 0.0
        self._seen_count = -1
        self._implausible_count = -1
        self._thread: threading.Thread | None = None
        self._quit = threading.Event()
        self._wake = threading.Event()
        self._done = threading.Event()
        self._sync_pending: deque[tuple[int, int, int]] = deque()
        self._sync_queued: deque[int] = deque()
        self._sync_hw = 0
        self._unsubscribe = session.subscribe(self._on_event)

    # -- public -------------------------------------------------------------------------------

    @property
    def next_index(self) -> int:
        """Index of the next sample to send."""
        return self._next_index

    @property
    def running(self) -> bool:
        """The feeding thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def start(self, start_index: int = 0, *, keep_staged: bool = False, timeout_s: float = 5.0) -> None:
        """Send START at ``start_index`` (prefill = the lead) and start feeding.

        After a run ended by a fault the source decides how to re-enter: samples computed for
        the old run but never sent are dropped unless ``keep_staged``.

        Raises
        ------
        BoardRefusedError, LinkError
            From START.
        """
        if self.running:
            raise ProtocolError("Streamer.start: already streaming")
        self._error = None
        self._limit_violation = False
        self._link_down = None
        if not keep_staged:
            self._staged.clear()
            self._staged_rows = 0
        try:
            self._begin_run(start_index, timeout_s)
        except BaseException:
            # no run began: wait() says so at once, or a supervisor waits for its end forever
            self._done.set()
            raise
        self._quit.clear()
        self._done.clear()
        self._finishing = False
        self._end_index = None
        self._stop_sent = False
        self._thread = threading.Thread(target=self._main, name="piezod-streamer", daemon=True)
        self._thread.start()

    def finish(self, *, timeout_s: float = 10.0) -> StreamStats:
        """Stop asking the source, send what is computed, STOP after the last sample, wait for IDLE.

        Returns
        -------
        StreamStats
            The statistics (also in :attr:`stats`).

        Raises
        ------
        Exception
            Whatever the block source raised, or :class:`~piezod.errors.BoardFaultError` after a
            limit violation on the board.
        """
        self._finishing = True
        self._wake.set()
        finished = self._done.wait(timeout_s)
        self._quit.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if not finished and self._run is not None and self._run.ended_by is None:
            log.error("the last run did not end within %g s of finish(): stopping it now", timeout_s)
            st = self.session.status
            try:
                self.session.stop()
            except (LinkError, WireProtocolError) as exc:
                log.warning("STOP failed: %s", exc)
            self._end_run("stopped", st.last_played_index if st is not None else None)
        self._unsubscribe()
        if not self.session.wait_readback_settled():
            log.warning("the last run's sensor readback was not accounted within the link's silence limit")
        self.check()
        return self.stats

    def abort(self) -> None:
        """Stop feeding at once and STOP the board now (outputs hold); best effort."""
        self._quit.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        try:
            self.session.stop()
        except (LinkError, WireProtocolError) as exc:
            log.warning("STOP after abort failed: %s", exc)
        self._unsubscribe()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the current run to end (e.g. after an underrun without ``auto_restart``).

        True at once after a :meth:`start` that raised (no run began).
        """
        return self._done.wait(timeout_s)

    def check(self) -> None:
        """Raise the error that ended streaming, if any."""
        if self._error is not None:
            raise self._error

    # -- events (reader thread) -----------------------------------------------------------------

    def _on_event(self, ev: LinkEvent) -> None:
        if isinstance(ev, StatusUpdate):
            self._wake.set()
        elif isinstance(ev, SensorBlock):
            self._match(ev)
        elif isinstance(ev, LinkDown):
            self._link_down = ev.error
            self._wake.set()
        elif isinstance(ev, BoardFault) and ev.code in (FaultCode.INDEX_GAP, FaultCode.OVERFLOW):
            self._gap_hint = True
            self._wake.set()
        elif (isinstance(ev, BoardFault) and ev.code is FaultCode.LIMIT_VIOLATION) or (
            isinstance(ev, FaultFlagsRaised) and ev.raised & FaultFlags.LIMIT_VIOLATION
        ):
            self._limit_violation = True
            self._wake.set()

    def _match(self, block: SensorBlock) -> None:
        idx = block.indices
        with self._hist_lock:
            known = np.zeros(idx.shape, dtype=bool)
            for lo, hi in self._hist_ranges:
                known |= (idx >= lo) & (idx < hi)
            known &= idx >= self._hist_top - self._hist.shape[0]  # not overwritten in the ring yet
            if not known.any():
                return  # another streamer's run (or too old): not ours to deliver
            codes = self._hist[idx % self._hist.shape[0]]
        volts = self.converter.to_volts(codes)
        if not known.all():
            volts[:, ~known] = np.nan
        n_known = int(known.sum())
        self.stats.matched_rows += n_known
        self.stats.unmatched_rows += idx.shape[0] - n_known
        if self.on_block is not None:
            pos = block.positions_um[self.converter.axis_channels]
            self.on_block(MatchedBlock(idx, volts, pos, self.converter.axes))

    # -- the feeding thread ---------------------------------------------------------------------

    def _begin_run(self, start_index: int, timeout_s: float) -> None:
        prefill = self.lead_samples
        self._status_mark = self.session.start(start_index, prefill, timeout_s=timeout_s)
        caps = self.session.capabilities
        assert caps is not None
        self._credit = start_index + caps.fifo_depth_samples
        self._next_index = start_index
        self._sent_hw = start_index
        self._sync_hw = start_index
        self._sync_pending.clear()
        self._sync_queued.clear()  # START empties the board's queue
        self._inflight.clear()
        self._raw_gaps = None
        self._raw_underruns = None
        self._gap_pending = False
        self._running_seen = False
        self._last_rewind = -1e9
        self._run = RunRecord(start_index, start_index)
        self.stats.runs.append(self._run)
        with self._hist_lock:
            self._hist_ranges.append([start_index, start_index])

    def _main(self) -> None:
        try:
            self._loop()
        except BaseException as exc:
            self._error = exc
            self._end_run("link" if isinstance(exc, LinkError) else "error", None)
            log.error("streaming stopped: %s", exc)
            if not isinstance(exc, LinkError):
                try:
                    self.session.stop()
                except (LinkError, WireProtocolError) as stop_exc:
                    log.warning("STOP after a streaming error failed: %s", stop_exc)
        finally:
            self._done.set()

    def _loop(self) -> None:
        wait = min(max(self.frame_samples / self.rate_hz, 0.002), 0.01)
        while not self._quit.is_set():
            # read before the snapshot: every STATUS the board sent before the link broke is in it
            link_down = self._link_down
            now = time.monotonic()
            st, st_time, st_count = self.session.status_snapshot()
            fresh = st is not None and st_count > self._status_mark
            if fresh and st is not None and not self._plausible(st, st_count):
                fresh = False  # nothing the board reported can be trusted: send nothing on it
            if fresh and st is not None:
                if self._limit_violation:
                    self.session.stop()
                    self._error = BoardFaultError(
                        "the board clamped a sample (LIMIT_VIOLATION): the host sent a code outside the "
                        "limits; streaming stopped"
                    )
                    self._end_run("limit_violation", st.last_played_index)
                    return
                ended = self._on_status(st, st_time, now, new=st_count != self._seen_count)
                self._seen_count = st_count
                if ended:
                    return
                running = st.state == BoardState.RUNNING and st.last_played_index != NO_INDEX
                played = st.last_played_index if running else self._run_start() - 1
                elapsed = max(0.0, now - st_time) if running else 0.0
                est_played = played + int(elapsed * self.rate_hz)
                acked_played = played
            else:
                est_played = acked_played = self._run_start() - 1
            if link_down is not None:
                # after what the board reported before the break: a run it reported stopped ended so
                raise link_down
            target = est_played + 1 + self.fill_samples
            limit = min(self._credit, target)
            if self._finishing:
                if self._end_index is None:
                    self._end_index = self._data_end()
                    self._pad_short_run()
                limit = min(self._credit, self._data_end())
            self._send_until(limit, urgent=self._next_index - est_played - 1 < self.lead_samples, now=now)
            if self._sync_pending:
                self._send_sync(acked_played)
            if (
                self._finishing
                and not self._stop_sent
                and self._end_index is not None
                and self._next_index >= self._data_end()
                and (self._running_seen or self._end_index <= self._run_start())
            ):
                if self._end_index > self._run_start():
                    self.session.stop(self._end_index - 1)
                else:
                    self.session.stop()
                self._stop_sent = True
            self._wake.wait(wait)
            self._wake.clear()

    def _plausible(self, st: Status, st_count: int) -> bool:
        """Whether ``st`` can describe this run: it reports no sample the host never sent.

        A STATUS claiming samples received or played beyond the highest index sent, a running
        board's write index before the run's start, or more free FIFO than the board has, comes
        from a confused (or forged) board. Acting on it,
        the host computed and queued samples up to the index it claimed played (minutes of
        samples ahead of the clock, played out after the next rewind: a scan started meanwhile
        waited for them). It is counted (:attr:`StreamStats.implausible_status`), logged once,
        and not acted on; the next plausible STATUS is. (One that a genuine STATUS replaced before
        the feeding thread looked is neither acted on nor counted.)
        """
        caps = self.session.capabilities
        depth = caps.fifo_depth_samples if caps is not None else None
        played = st.last_played_index
        reason = None
        if st.write_index > self._sent_hw:
            reason = f"write_index {st.write_index} beyond the samples sent (up to {self._sent_hw - 1})"
        elif played != NO_INDEX and played >= self._sent_hw:
            reason = f"last_played_index {played} beyond the samples sent (up to {self._sent_hw - 1})"
        elif st.state in (BoardState.ARMED, BoardState.RUNNING) and st.write_index < self._run_start():
            # a board that took this run's START holds its samples from the start index on; a
            # rewind to an index before it resent minutes of samples and underran a scan (fuzz)
            reason = f"write_index {st.write_index} before this run's start index {self._run_start()}"
        elif depth is not None and st.fifo_free_samples > depth:
            reason = f"fifo_free_samples {st.fifo_free_samples} beyond the FIFO depth {depth}"
        if reason is None:
            return True
        if st_count != self._implausible_count:
            self._implausible_count = st_count
            self.stats.implausible_status += 1
            log.warning("implausible STATUS ignored (state %s): %s", st.state.name, reason)
        return False

    def _data_end(self) -> int:
        """Index after the last row computed (staged rows follow ``next_index``, also after a rewind)."""
        return self._next_index + self._staged_rows

    def _pad_short_run(self) -> None:
        """A run shorter than its prefill would never start: hold its last row up to the prefill.

        The board discards the padding at the STOP after the real last sample.
        """
        assert self._end_index is not None
        start = self._run_start()
        pad_to = start + self.lead_samples
        if self._running_seen or not start < self._end_index < pad_to:
            return
        if self._staged_rows:
            last = self._staged[-1][-1:]
        else:
            with self._hist_lock:
                last = self._hist[(self._sent_hw - 1) % self._hist.shape[0]][None, :].copy()
        self._staged.append(np.repeat(last, pad_to - self._end_index, axis=0))
        self._staged_rows += pad_to - self._end_index

    def _run_start(self) -> int:
        return self._run.start_index if self._run is not None else 0

    def _on_status(self, st: Status, st_time: float, now: float, *, new: bool) -> bool:
        if new:
            # a long gap before the STATUS that reports an underrun: the board (or the link) was silent
            self._status_gap_s = st_time - self._status_at if self._status_at else 0.0
            self._status_at = st_time
        w = st.write_index
        credit = st.credit_limit
        if credit > self._credit:
            self._credit = credit
        while self._inflight and self._inflight[0][0] + self._inflight[0][1].shape[0] <= w:
            self._inflight.popleft()
        if w != self._w_seen:
            self._w_seen, self._w_changed_at = w, st_time
        if new and st.state == BoardState.RUNNING:
            self._running_seen = True
            if not self._finishing and st.last_played_index != NO_INDEX:
                lead = w - st.last_played_index - 1
                s = self.stats
                s.lead_min_samples = lead if s.lead_min_samples is None else min(s.lead_min_samples, lead)
                s.lead_sum_samples += lead
                s.lead_count += 1
        if self._raw_underruns is None:
            self._raw_underruns = st.underruns
        if st.state in (BoardState.IDLE, BoardState.RAMPING):
            return self._clock_stopped(st)
        gaps = (st.index_gaps, st.overflows)
        if self._raw_gaps is None:
            self._raw_gaps = gaps
        if gaps != self._raw_gaps or self._gap_hint:
            self._gap_pending = True
        self._raw_gaps = gaps
        self._gap_hint = False
        if w >= self._next_index:
            self._gap_pending = False
            return False
        # frames sent before a rewind may still report gaps for about one round trip: a gap seen
        # then is acted on when that time is over (an extra rewind costs duplicates only)
        rtt = 2 * self.status_period_s + 0.005
        # a STATUS generated this long after our last frame must show it (else it was lost), unless
        # the board is still taking in what is on the way (write_index moving): a busy board is not
        # a lost frame; the floor covers a board (or simulator) busy for a few status periods
        drain = 2 * (self._next_index - w) * self._link_s_per_row
        settle = max(2 * self.status_period_s, STALL_FLOOR_S, drain)
        if self._gap_pending and now - self._last_rewind > rtt:
            self._gap_pending = False
            self._rewind(w, now, "index gap / overflow reported")
        elif (
            st_time - self._last_send > settle
            and st_time - self._w_changed_at > settle
            and now - self._last_rewind > settle
        ):
            self._rewind(w, now, "write_index stalled")
        return False

    def _clock_stopped(self, st: Status) -> bool:
        lp = None if st.last_played_index == NO_INDEX else st.last_played_index
        underran = self._raw_underruns is not None and st.underruns != self._raw_underruns
        if st.fault_flags & FaultFlags.WATCHDOG:
            how: RunEnd = "watchdog"
        elif underran or st.fault_flags & FaultFlags.UNDERRUN:
            how = "underrun"
        elif self._stop_sent:
            how = "stop"
        elif not self._running_seen and st.state == BoardState.IDLE and self._run is not None:
            return False  # a STATUS sent before the clock started; wait for ARMED / RUNNING
        else:
            how = "stopped"
        self._end_run(how, lp)
        if how == "underrun" and self.auto_restart and not self._finishing:
            log.warning("underrun after index %s: restarting at a fresh index", lp)
            self._staged_restart()
            return False
        return True

    def _end_run(self, how: RunEnd, last_played: int | None) -> None:
        run = self._run
        if run is None or run.ended_by is not None:
            return
        run.end_index = self._sent_hw if self._end_index is None else min(self._sent_hw, self._end_index)
        run.last_played_index = last_played if last_played is not None and last_played != NO_INDEX else None
        run.ended_by = how
        if how in ("underrun", "watchdog", "link", "limit_violation", "error"):
            log.warning(
                "run from index %d ended by %s (last played %s, %d sent; STATUS frames %.0f ms apart before)",
                run.start_index,
                how,
                run.last_played_index,
                run.samples_sent,
                1e3 * self._status_gap_s,
            )

    def _staged_restart(self) -> None:
        self._begin_run(self._sent_hw, timeout_s=5.0)

    def _rewind(self, write_index: int, now: float, why: str) -> None:
        back: list[npt.NDArray[np.int16]] = []
        for first, rows in self._inflight:
            if first + rows.shape[0] <= write_index:
                continue
            back.append(rows[max(0, write_index - first) :])
        for rows in reversed(back):
            self._staged.appendleft(rows)
            self._staged_rows += rows.shape[0]
        self._inflight.clear()
        log.info("go-back-N (%s): resending from index %d (was at %d)", why, write_index, self._next_index)
        self._next_index = write_index
        if self._sync_hw > write_index:
            # the events are fetched again with their samples; the board skips those it queued
            self._sync_hw = write_index
            while self._sync_pending and self._sync_pending[-1][0] >= write_index:
                self._sync_pending.pop()
        self._last_rewind = now
        self.stats.rewinds += 1

    def _produce(self, rows_needed: int) -> bool:
        """Compute blocks until ``rows_needed`` rows are staged; ``False`` when finishing."""
        while self._staged_rows < rows_needed:
            if self._finishing:
                return False
            volts = self.source.next_block(self.block_samples)
            codes, bad = self.converter.convert(volts)
            first = self._data_end()
            if bad.any():
                self._report_clamp(np.asarray(volts, dtype=np.float64), bad, first)
            self._staged.append(codes)
            self._staged_rows += codes.shape[0]
            self.stats.blocks_computed += 1
        return True

    def _report_clamp(self, volts: FloatArray, bad: npt.NDArray[np.bool_], first: int) -> None:
        conv = self.converter
        for a in np.flatnonzero(bad.any(axis=1)):
            cols = np.flatnonzero(bad[a])
            v = volts[a, cols]
            excess = np.where(np.isnan(v), np.inf, np.maximum(conv.v_min[a] - v, v - conv.v_max[a]))
            worst = float(v[int(np.argmax(excess))])
            count = int(cols.shape[0])
            self.stats.host_clamped_samples += count
            self.stats.host_limit_faults += 1
            ev = HostLimitFault(
                time.monotonic(), int(conv.axis_channels[a]), conv.axes[a], first + int(cols[0]), count, worst
            )
            log.error(
                "host limit fault: axis %s, %d samples from index %d outside [%g, %g] V (worst %g V)",
                ev.axis,
                count,
                ev.first_index,
                conv.v_min[a],
                conv.v_max[a],
                worst,
            )
            self.session.emit(ev)

    def _send_until(self, limit: int, *, urgent: bool, now: float) -> None:
        while self._next_index < limit:
            want = min(self.frame_samples, limit - self._next_index)
            if want < self.frame_samples and not urgent and not self._finishing:
                return
            if self._staged_rows < want and not self._produce(want):
                want = min(want, self._staged_rows)
                if want <= 0:
                    return
            rows = self._take(want)
            first = self._next_index
            self.session.send_samples(first, rows)
            if self.sync is not None and first + want > self._sync_hw:
                lo = max(first, self._sync_hw)
                events = self.sync(lo, first + want - lo)
                self._sync_pending.extend((lo + o, lines, mask) for o, lines, mask in events)
                self._sync_hw = first + want
            self._inflight.append((first, rows))
            self._next_index = first + want
            self._last_send = time.monotonic()
            self.stats.frames_sent += 1
            self.stats.rows_sent += want
            if first < self._sent_hw:
                self.stats.rows_resent += min(want, self._sent_hw - first)
            if self._next_index > self._sent_hw:
                self._remember(first, rows)
                self._sent_hw = self._next_index
                if self._run is not None:
                    end = self._sent_hw if self._end_index is None else min(self._sent_hw, self._end_index)
                    self._run.end_index = end

    def _send_sync(self, played: int) -> None:
        """Send the pending sync events that fit the board's queue (events up to ``played`` are gone).

        Events of samples already played are dropped here (counted in ``sync_events_late``).
        """
        queued, pending = self._sync_queued, self._sync_pending
        while queued and queued[0] <= played:
            queued.popleft()
        while pending and pending[0][0] <= played:
            pending.popleft()
            self.stats.sync_events_late += 1
        if not pending or (pending[0][0] - played > self.lead_samples and len(pending) < SYNC_BATCH_EVENTS):
            return  # not due yet: gather more events per frame (a slow link pays ~34 bytes per frame)
        while pending and len(queued) < SYNC_QUEUE_EVENTS:
            n = min(len(pending), SYNC_QUEUE_EVENTS - len(queued), MAX_SYNC_EVENTS)
            part = [pending.popleft() for _ in range(n)]
            base = part[0][0]
            self.session.send_sync(base, tuple((i - base, lines, mask) for i, lines, mask in part))
            queued.extend(i for i, _, _ in part)
            self.stats.sync_frames_sent += 1
            self.stats.sync_events_sent += n

    def _take(self, n: int) -> npt.NDArray[np.int16]:
        parts: list[npt.NDArray[np.int16]] = []
        left = n
        while left:
            blk = self._staged[0]
            if blk.shape[0] <= left:
                parts.append(self._staged.popleft())
                left -= blk.shape[0]
            else:
                parts.append(blk[:left])
                self._staged[0] = blk[left:]
                left = 0
        self._staged_rows -= n
        out = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return np.ascontiguousarray(out)

    def _remember(self, first: int, rows: npt.NDArray[np.int16]) -> None:
        cap = self._hist.shape[0]
        new_from = max(first, self._sent_hw)
        sub = rows[new_from - first :]
        idx = (new_from + np.arange(sub.shape[0])) % cap
        with self._hist_lock:
            self._hist[idx] = sub
            self._hist_top = new_from + sub.shape[0]
            self._hist_ranges[-1][1] = self._hist_top


class TriangleSource:
    """A symmetric triangular waveform per axis (bench and tests).

    Parameters
    ----------
    rate_hz
        Sample rate.
    amplitude_v, center_v
        Per axis (sequences of the same length).
    frequency_hz
        Triangle frequency.
    phase
        Per-axis phase offset (fraction of a period).
    """

    def __init__(
        self,
        rate_hz: float,
        amplitude_v: npt.ArrayLike,
        center_v: npt.ArrayLike,
        frequency_hz: float,
        phase: npt.ArrayLike | None = None,
    ) -> None:
        self.rate_hz = float(rate_hz)
        self.amplitude = np.asarray(amplitude_v, dtype=np.float64)
        self.center = np.asarray(center_v, dtype=np.float64)
        self.frequency_hz = float(frequency_hz)
        self.phase = np.zeros_like(self.amplitude) if phase is None else np.asarray(phase, dtype=np.float64)
        self.position = 0

    def next_block(self, n: int) -> FloatArray:
        """The next ``n`` samples, ``(axes, n)`` volts."""
        t = (self.position + np.arange(n)) * (self.frequency_hz / self.rate_hz)
        self.position += n
        frac = (t[None, :] + self.phase[:, None]) % 1.0
        tri = 1.0 - 4.0 * np.abs(frac - 0.5)  # -1 .. 1, starts at -1
        out: FloatArray = self.center[:, None] + self.amplitude[:, None] * tri
        return out


__all__ = [
    "BlockSource",
    "CodeConverter",
    "MatchedBlock",
    "RunRecord",
    "StreamStats",
    "Streamer",
    "TriangleSource",
    "lead_samples_for",
]
