"""A protocol session with the board: handshake, configuration, I/O threads, faults, reconnection.

:class:`BoardSession` owns the transport and two threads per connection: a *reader* that decodes
everything the board sends (the :class:`~firmware_proto.FrameDecoder` resynchronises after
corruption and every dropped frame is counted), and a *writer* that sends queued frames,
retransmits unanswered control requests (:class:`~firmware_proto.Endpoint`) and sends HEARTBEAT
whenever nothing else went out for ``heartbeat_timeout_ms / 4``. Callers talk to it from any
thread: control requests block until ACK / NAK (:meth:`BoardSession.configure`,
:meth:`BoardSession.start`, :meth:`BoardSession.stop`...), SAMPLES are queued without blocking
(:meth:`BoardSession.send_samples`), and everything the board reports arrives as typed events
(:class:`LinkEvent` subclasses) at the callbacks registered with :meth:`BoardSession.subscribe`,
plus cumulative :class:`LinkCounters`.

When the link breaks (unplugged, EIO, hangup, a control request unanswered after all
retransmissions, the board silent) the session reports :class:`LinkDown`, reopens the same URL
with exponential backoff, redoes the handshake, reads the board's STATUS to learn what happened
meanwhile (watchdog ramp, last played index, counters) and reports :class:`Reconnected`. It does
not reconfigure or restart the output by itself: the caller decides how to re-enter (see
:meth:`BoardSession.prepare_restart`).

Settings and the channel plan live in :mod:`piezod.link.plan`, the events, counters and the
polling :class:`EventQueue` in :mod:`piezod.link.events` (re-exported here), the detection of
frames lost whole by sequence number in :mod:`piezod.link.seqwatch`. Why this module is still
over 800 lines: the reader and writer threads, the reconnection supervisor and the request /
acknowledge state of one connection share one lock and one set of invariants (sequence
numbers, retransmission, the connection generation); split across modules they would have to
reach into each other's private state. The board-level interface the engine uses is
:class:`piezod.link.board.Board`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

import numpy as np

from firmware_proto import (
    NO_INDEX,
    PROTOCOL_VERSION,
    Acked,
    BoardState,
    Capabilities,
    CodeArray,
    Configure,
    DecodeError,
    Fault,
    FaultCode,
    FaultFlags,
    Frame,
    Heartbeat,
    Hello,
    Message,
    MessageType,
    Nacked,
    NakReason,
    RampToSafe,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
    Sync,
    TimedOut,
    check_capabilities,
)
from firmware_proto import ProtocolError as WireProtocolError
from piezod.config import ScannerConfig
from piezod.errors import (
    ConfigError,
    LinkClosedError,
    LinkError,
    LinkTimeoutError,
    ProtocolError,
    from_wire,
)
from piezod.link.events import (
    BoardCounter,
    BoardFault,
    BoardRefusedError,
    DecodeFailure,
    EventQueue,
    FaultFlagsRaised,
    HostLimitFault,
    LinkCounters,
    LinkDown,
    LinkEvent,
    LinkLost,
    LinkTally,
    LinkUp,
    Reconnected,
    SensorBlock,
    SensorGap,
    StatusUpdate,
)
from piezod.link.plan import (
    _U32,
    DEFAULT_AXIS_CHANNELS,
    ChannelPlan,
    LinkSettings,
    describe_configure_offset,
    plan_channels,
)
from piezod.link.seqwatch import SeqWatch, gap_before, missing_frames, new_endpoint
from piezod.link.transport import Transport, open_transport

log = logging.getLogger(__name__)

_BOARD_COUNTERS = (
    ("crc_errors", "crc_errors_board"),
    ("frames_dropped", "frames_dropped_board"),
    ("underruns", "underruns"),
    ("clamped_samples", "clamped_samples"),
    ("index_gaps", "index_gaps"),
    ("overflows", "overflows"),
)


# ---------------------------------------------------------------------------------------------
# the session


class _Request:
    __slots__ = ("done", "error", "msg", "reply", "status_mark")

    def __init__(self, msg: Message) -> None:
        self.msg = msg
        self.done = threading.Event()
        self.reply: Message | None = None
        self.error: BaseException | None = None
        self.status_mark = 0  # STATUS frames received before the reply


class _Connection:
    def __init__(self, transport: Transport, settings: LinkSettings, generation: int) -> None:
        self.transport = transport
        self.generation = generation
        self.endpoint = new_endpoint(settings)
        self.alive = True
        self.wake = threading.Event()
        self.requests: dict[int, _Request] = {}
        self.last_tx = time.monotonic()
        self.last_rx = time.monotonic()
        self.got_status = False
        self.hello_done = False
        self.established = False  # handshake done: a later failure is a LinkDown
        self.retired = False
        self.reader: threading.Thread | None = None
        self.writer: threading.Thread | None = None


def _alive(conn: _Connection) -> bool:
    """Re-read the flag another thread may have cleared (defeats mypy's narrowing)."""
    return conn.alive


Subscriber = Callable[[LinkEvent], None]


class BoardSession:
    """One host session with the board (see the module docstring).

    Use :meth:`open`; the constructor does no I/O.

    Parameters
    ----------
    transport_factory
        Opens a fresh transport (called again to reconnect).
    url
        For messages and events.
    settings
        Link settings.
    session_id
        HELLO ``session_id``; default: the process id.
    """

    def __init__(
        self,
        transport_factory: Callable[[], Transport],
        *,
        url: str,
        settings: LinkSettings | None = None,
        session_id: int | None = None,
    ) -> None:
        self.url = url
        self.settings = settings or LinkSettings()
        self.session_id = (os.getpid() if session_id is None else session_id) & 0xFFFFFFFF
        self._factory = transport_factory
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._conn: _Connection | None = None
        self._generation = 0
        self._subscribers: list[Subscriber] = []
        self._tally = LinkTally()
        self._closing = False
        self._closed_event = threading.Event()
        self._dead: LinkError | None = None
        self._supervisor: threading.Thread | None = None
        # set under the lock by whoever starts the reconnecting thread, cleared by that thread under the
        # lock once nothing is pending: a break while it finishes is handed over, never dropped
        self._reconnecting = False
        self._pending_break: tuple[_Connection, LinkError] | None = None
        self._down_since: float | None = None
        self.capabilities: Capabilities | None = None
        self._config: ScannerConfig | None = None
        self._sample_rate_override: float | None = None
        self.plan: ChannelPlan | None = None
        self._adc_scale = np.ones(1)
        self._adc_offset = np.zeros(1)
        # STATUS tracking
        self._status: Status | None = None
        self._status_time = 0.0
        self._status_count = 0
        self._board_raw: dict[str, int] | None = None
        self._flags_seen = FaultFlags.NONE
        # sensor accounting
        self._run_start: int | None = None
        self._sensor_next: int | None = None
        self._sensor_stride = 1
        self._sensor_err_mark = 0
        self._loss_pos = 0  # frames known lost up to the event being handled (stream order)
        self._tail: tuple[int, float] | None = None
        self._link_broke_in_run = False
        self._last_played_seen: int | None = None
        self._sent_hw = 0  # one past the highest sample index sent in this session
        self._pending_axes: tuple[str | None, ...] | None = None

    # -- opening ----------------------------------------------------------------------------

    @classmethod
    def open(
        cls,
        url: str | None = None,
        *,
        config: ScannerConfig | None = None,
        settings: LinkSettings | None = None,
        sample_rate_hz: float | None = None,
        transport_factory: Callable[[], Transport] | None = None,
        on_event: Subscriber | None = None,
        session_id: int | None = None,
        timeout_s: float = 5.0,
    ) -> BoardSession:
        """Connect, say HELLO, and (with ``config``) CONFIGURE and wait for the board to be IDLE.

        Parameters
        ----------
        url
            Transport URL (:func:`~piezod.link.transport.open_transport`).
        config
            Scanner config to configure the board with; ``None`` = handshake only.
        settings
            Link settings; default :meth:`LinkSettings.from_config` (or the defaults).
        sample_rate_hz
            Overrides ``config.sample_rate_hz``.
        transport_factory
            Instead of ``url``: a callable opening the transport (tests: hil_sim.wire on a socket pair).
        on_event
            Subscribed before the handshake (sees :class:`LinkUp`).
        session_id
            HELLO ``session_id``.
        timeout_s
            For the handshake and the initial ramp to the safe values.

        Raises
        ------
        LinkError
            The port cannot be opened or the board does not answer.
        VersionMismatchError
            The board speaks another protocol version (the message names both).
        BoardRefusedError
            The board refused the configuration (the message names the field).
        """
        if settings is None:
            settings = LinkSettings.from_config(config) if config is not None else LinkSettings()
        if transport_factory is None:
            if url is None:
                raise ConfigError("BoardSession.open: give a URL or a transport_factory")
            target = url
            rt, wt = settings.read_timeout_s, settings.write_timeout_s

            def transport_factory() -> Transport:
                return open_transport(target, read_timeout_s=rt, write_timeout_s=wt)

        session = cls(transport_factory, url=url or "<transport>", settings=settings, session_id=session_id)
        if on_event is not None:
            session.subscribe(on_event)
        try:
            session._connect(reconnect=False, timeout_s=timeout_s)
            if config is not None:
                session.configure(config, sample_rate_hz=sample_rate_hz, timeout_s=timeout_s)
        except BaseException:
            session.close()
            raise
        return session

    def __enter__(self) -> BoardSession:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- events -----------------------------------------------------------------------------

    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        """Call ``callback(event)`` for every :class:`LinkEvent` (from the I/O threads: be quick).

        Returns
        -------
        Callable[[], None]
            Unsubscribes.
        """
        with self._lock:
            self._subscribers.append(callback)

        def _unsubscribe() -> None:
            with self._lock:
                if callback in self._subscribers:
                    self._subscribers.remove(callback)

        return _unsubscribe

    def emit(self, event: LinkEvent) -> None:
        """Deliver ``event`` to the subscribers (also used by the streamer for host-side faults)."""
        with self._lock:
            subs = list(self._subscribers)
        for cb in subs:
            try:
                cb(event)
            except Exception:
                with self._lock:
                    self._tally.add("callback_errors")
                log.exception("link event subscriber %r failed on %s", cb, type(event).__name__)

    def _emit_all(self, events: list[LinkEvent]) -> None:
        for ev in events:
            self.emit(ev)

    # -- state ------------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """The link is up (handshake done, not broken)."""
        with self._lock:
            return self._conn is not None and self._conn.alive and self.capabilities is not None

    @property
    def status(self) -> Status | None:
        """The latest STATUS."""
        with self._lock:
            return self._status

    def status_snapshot(self) -> tuple[Status | None, float, int]:
        """``(status, status_time, status_count)`` read atomically."""
        with self._lock:
            return self._status, self._status_time, self._status_count

    @property
    def status_count(self) -> int:
        """STATUS frames received in this session."""
        with self._lock:
            return self._status_count

    @property
    def status_time(self) -> float:
        """``time.monotonic()`` when :attr:`status` arrived."""
        with self._lock:
            return self._status_time

    @property
    def sample_rate_hz(self) -> int:
        """The configured sample clock (Hz)."""
        if self.plan is None:
            raise ProtocolError("the board is not configured")
        return self.plan.sample_rate_hz

    def counters(self) -> LinkCounters:
        """A snapshot of :class:`LinkCounters`."""
        with self._lock:
            return self._tally.snapshot(None if self._conn is None else self._conn.endpoint)

    def _losses_now(self) -> int:
        """Frames from the board known lost so far: dropped by the decoder or missing by ``seq``."""
        total = sum(self._tally.decode_kinds.values()) + self._tally.n["frames_lost_rx"]
        if self._conn is not None:
            total += self._conn.endpoint.decoder_stats.errors + missing_frames(self._conn.endpoint)
        return total

    # -- connection management ----------------------------------------------------------------

    def _connect(self, *, reconnect: bool, timeout_s: float) -> Capabilities:
        transport = self._factory()
        with self._lock:
            if self._closing:
                transport.close()
                raise LinkClosedError(f"{self.url}: session closed")
            self._generation += 1
            conn = _Connection(transport, self.settings, self._generation)
            self._conn = conn
            # a STATUS of an earlier connection says nothing about the board now (it may have been
            # power-cycled: UNCONFIGURED, outputs at rest)
            self._status = None
            self._sensor_next = None
            self._tail = None
            self._loss_pos = self._losses_now()
        try:
            transport.write(b"\x00")  # terminate any partial garbage in the board's receive buffer
        except LinkError as exc:
            self._retire(conn)
            raise exc from None
        conn.reader = threading.Thread(target=self._reader, args=(conn,), name="piezod-link-rx", daemon=True)
        conn.writer = threading.Thread(target=self._writer, args=(conn,), name="piezod-link-tx", daemon=True)
        conn.reader.start()
        conn.writer.start()
        try:
            reply = self._request(Hello(PROTOCOL_VERSION, self.session_id), timeout_s=timeout_s, conn=conn)
        except BaseException:
            self._shutdown_connection(conn)
            raise
        if not isinstance(reply, Capabilities):  # pragma: no cover - Endpoint matches HELLO to CAPABILITIES
            self._shutdown_connection(conn)
            raise ProtocolError(f"{self.url}: HELLO answered by {type(reply).__name__}")
        try:
            check_capabilities(reply)
        except WireProtocolError as exc:
            self._shutdown_connection(conn)
            raise from_wire(exc) from exc
        with self._lock:
            broke = not conn.alive
            if not broke:
                self.capabilities = reply
                conn.hello_done = True
                conn.established = True
        if broke:
            # the reply came, then the link broke before the handshake was done: _link_failed took it
            # for a failed handshake (no reconnecting), so it fails here, where the caller sees it
            self._shutdown_connection(conn)
            raise LinkClosedError(f"{self.url}: the link broke right after the handshake")
        self.emit(LinkUp(time.monotonic(), reply, self.url))
        return reply

    def _retire(self, conn: _Connection) -> None:
        """Fold a dead connection's endpoint counters into the tally (once)."""
        with self._lock:
            if conn.retired:
                return
            conn.retired = True
            self._tally.fold(conn.endpoint)
            conn.endpoint = new_endpoint(self.settings)
            conn.alive = False
            conn.wake.set()
        with contextlib.suppress(LinkError):
            conn.transport.close()

    def _shutdown_connection(self, conn: _Connection) -> None:
        with self._lock:
            conn.alive = False
            conn.wake.set()
            reqs = list(conn.requests.values())
            conn.requests.clear()
        for r in reqs:
            if not r.done.is_set():
                r.error = LinkClosedError(f"{self.url}: connection closed")
                r.done.set()
        with contextlib.suppress(LinkError):
            conn.transport.close()  # wakes a read or write in progress
        for t in (conn.reader, conn.writer):
            if t is not None and t is not threading.current_thread():
                t.join(timeout=self.settings.write_timeout_s + 1.0)
        self._retire(conn)
        with self._lock:
            if self._conn is conn:
                self._conn = None
            self._cond.notify_all()

    def _link_failed(self, conn: _Connection, error: LinkError) -> None:
        """Called by an I/O thread when the link broke."""
        with self._lock:
            if not conn.alive or self._conn is not conn:
                return
            conn.alive = False
            conn.wake.set()
            reqs = list(conn.requests.values())
            conn.requests.clear()
            closing = self._closing or not conn.established  # a failed handshake raises in _connect
            out: list[LinkEvent] = []
            if not closing:
                self._tally.add("link_downs")
                self._down_since = time.monotonic()
                self._link_broke_in_run = self._sensor_next is not None
                if self._tail is not None:
                    # the stopped run's rows still missing would have come on this connection
                    self._close_sensor_run(self._tail[0], self._down_since, out)
            self._cond.notify_all()
        self._emit_all(out)
        for r in reqs:
            if not r.done.is_set():
                r.error = error
                r.done.set()
        if closing:
            return
        log.warning("link to the board broke: %s", error)
        self.emit(LinkDown(time.monotonic(), error))
        with self._lock:
            if self._reconnecting:
                # the reconnecting thread is still finishing (e.g. this connection is the one it just
                # made): it takes this break over instead of leaving the link down with nobody dialling
                self._pending_break = (conn, error)
                return
            self._reconnecting = True
            self._supervisor = threading.Thread(
                target=self._supervise, args=(conn, error), name="piezod-link-reconnect", daemon=True
            )
            self._supervisor.start()

    def _supervise(self, dead: _Connection, error: LinkError) -> None:
        pending: tuple[_Connection, LinkError] | None = (dead, error)
        try:
            while pending is not None:
                self._redial(*pending)
                with self._lock:
                    pending, self._pending_break = self._pending_break, None
                    if self._closing or self._dead is not None:
                        pending = None
                    if pending is None:
                        self._reconnecting = False
                        self._cond.notify_all()
        except BaseException:
            with self._lock:
                self._reconnecting = False
                self._cond.notify_all()
            raise

    def _redial(self, dead: _Connection, error: LinkError) -> None:
        """Dial until the board answers again (or the session gives up or closes)."""
        self._shutdown_connection(dead)
        if not self.settings.reconnect:
            self._give_up(error)
            return
        delay = self.settings.reconnect_initial_s
        started = time.monotonic()
        last_error: LinkError = error
        old_caps = self.capabilities
        while not self._closing:
            if self._closed_event.wait(delay):
                return
            try:
                caps = self._connect(reconnect=True, timeout_s=max(1.0, self.settings.ack_timeout_s * 8))
            except (LinkError, WireProtocolError) as exc:
                if isinstance(exc, WireProtocolError) and not isinstance(exc, LinkError):
                    self._give_up(LinkError(f"{self.url}: reconnection refused: {exc}"))
                    return
                last_error = exc
                delay = min(delay * 2.0, self.settings.reconnect_max_s)
                give_up = self.settings.reconnect_give_up_s
                if give_up is not None and time.monotonic() - started > give_up:
                    self._give_up(last_error)
                    return
                continue
            self._after_reconnect(caps, old_caps)
            return

    def _after_reconnect(self, caps: Capabilities, old: Capabilities | None) -> None:
        changed = old is not None and (
            old.board_serial != caps.board_serial or old.n_channels != caps.n_channels
        )
        with self._lock:
            conn = self._conn
            if changed:
                self._board_raw = None
                self._flags_seen = FaultFlags.NONE
            count0 = self._status_count
            wait = max(0.5, 10 * self.settings.status_period_ms / 1000.0)
            self._cond.wait_for(
                lambda: (
                    conn is None
                    or not conn.alive
                    or (self._status_count > count0 and self._conn is conn and conn.got_status)
                ),
                timeout=wait,
            )
            status = self._status if conn is not None and conn.got_status else None
            self._tally.add("reconnects")
            down = time.monotonic() - (self._down_since or time.monotonic())
            self._down_since = None
        flags = status.fault_flags if status is not None else FaultFlags.NONE
        lp = status.last_played_index if status is not None else None
        event = Reconnected(
            time.monotonic(),
            caps,
            status,
            changed,
            bool(flags & FaultFlags.WATCHDOG),
            flags,
            None if lp is None or lp == NO_INDEX else lp,
            down,
        )
        log.warning(
            "link to the board is back after %.2f s: state %s, faults %s, last played index %s",
            down,
            status.state.name if status else "unknown (no STATUS: unconfigured?)",
            flags,
            event.last_played_index,
        )
        self.emit(event)

    def _give_up(self, error: LinkError) -> None:
        with self._lock:
            self._dead = error
            self._cond.notify_all()
        log.error("giving up on the board: %s", error)
        self.emit(LinkLost(time.monotonic(), error))

    def wait_connected(self, timeout_s: float) -> bool:
        """Wait until the link is up (e.g. after :class:`LinkDown`); ``False`` on timeout.

        Raises
        ------
        LinkError
            The session gave up reconnecting.
        """
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                if self._dead is not None:
                    raise self._dead
                if self._conn is not None and self._conn.alive and self._supervisor_done():
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.05))

    def _supervisor_done(self) -> bool:
        return not self._reconnecting

    def close(self, *, ramp_to_safe: bool = False) -> None:
        """End the session (idempotent).

        Parameters
        ----------
        ramp_to_safe
            Ask the board to ramp every output to its safe value first (best effort). Otherwise
            the board keeps its state and its watchdog takes over once the host is silent.
        """
        if ramp_to_safe and self.connected:
            try:
                self.ramp_to_safe()
            except (LinkError, WireProtocolError) as exc:
                log.warning("RAMP_TO_SAFE on close failed: %s", exc)
        with self._lock:
            conn = None if self._closing else self._conn
            self._closing = True
            self._closed_event.set()
        if conn is not None:
            self._shutdown_connection(conn)
        sup = self._supervisor
        if sup is not None and sup is not threading.current_thread():
            sup.join(timeout=5.0)
        with self._lock:
            stray = self._conn
        if stray is not None:  # created by a reconnection racing with close
            self._shutdown_connection(stray)

    # -- I/O threads --------------------------------------------------------------------------

    def _reader(self, conn: _Connection) -> None:
        silence = self.settings.silence_limit_s
        while conn.alive:
            try:
                data = conn.transport.read()
            except LinkError as exc:
                self._link_failed(conn, exc)
                return
            now = time.monotonic()
            out: list[LinkEvent] = []
            with self._lock:
                if not _alive(conn):
                    return
                if data:
                    events = conn.endpoint.receive(data, now)
                    if conn.endpoint.last_rx_time is not None:
                        conn.last_rx = conn.endpoint.last_rx_time
                    for ev in events:
                        self._handle(conn, ev, now, out)
                    dec = conn.endpoint.decoder
                    if isinstance(dec, SeqWatch):
                        dec.gap_before.clear()  # e.g. before a stray reply: no event to place it at
                    self._loss_pos = self._losses_now()
                self._check_tail(now, out)
                silent = conn.got_status and now - conn.last_rx > silence
            self._emit_all(out)
            if silent:
                self._link_failed(
                    conn, LinkTimeoutError(f"{self.url}: the board sent nothing valid for {silence:g} s")
                )
                return

    def _writer(self, conn: _Connection) -> None:
        hb = self.settings.heartbeat_interval_s
        while conn.alive:
            with self._lock:
                deadline = conn.endpoint.next_deadline()
            now = time.monotonic()
            wait = conn.last_tx + hb - now if conn.hello_done else 0.05
            if deadline is not None:
                wait = min(wait, deadline - now)
            conn.wake.wait(timeout=min(max(wait, 0.0005), 0.05))
            conn.wake.clear()
            if not _alive(conn):
                return
            now = time.monotonic()
            failed: list[tuple[_Request, LinkError]] = []
            with self._lock:
                polled = conn.endpoint.poll(now)
                for ev in polled:
                    if isinstance(ev, TimedOut):
                        req = conn.requests.pop(ev.seq, None)
                        err: LinkError = LinkTimeoutError(
                            f"{self.url}: no reply to {ev.request.TYPE.name} (seq {ev.seq}) after "
                            f"{ev.attempts} attempts {self.settings.ack_timeout_s * 1000:g} ms apart"
                        )
                        if req is not None:
                            failed.append((req, err))
                data = conn.endpoint.data_to_send()
                if not data and now - conn.last_tx >= hb and conn.hello_done:
                    conn.endpoint.send(Heartbeat(time_us=int(now * 1e6) & ((1 << 64) - 1)), now)
                    self._tally.add("heartbeats_sent")
                    data = conn.endpoint.data_to_send()
            for req, err in failed:
                req.error = err
                req.done.set()
            if failed:
                self._link_failed(conn, failed[0][1])
                return
            if data:
                try:
                    conn.transport.write(data)
                except LinkError as exc:
                    self._link_failed(conn, exc)
                    return
                conn.last_tx = time.monotonic()

    # -- frame handling (under the lock, in the reader thread) ------------------------------------

    def _handle(self, conn: _Connection, ev: Any, now: float, out: list[LinkEvent]) -> None:
        if isinstance(ev, DecodeError):
            self._loss_pos += 1
        elif isinstance(ev, Frame):
            self._loss_pos += gap_before(conn.endpoint, ev.msg)
        elif isinstance(ev, Acked | Nacked):
            self._loss_pos += gap_before(conn.endpoint, ev.reply)
        if isinstance(ev, Frame):
            msg = ev.msg
            if isinstance(msg, Status):
                self._on_status(conn, msg, now, out)
            elif isinstance(msg, Sensor):
                self._on_sensor(msg, now, out)
            elif isinstance(msg, Fault):
                name = msg.code.name
                self._tally.fault_frames[name] = self._tally.fault_frames.get(name, 0) + 1
                if (
                    msg.code in (FaultCode.UNDERRUN, FaultCode.WATCHDOG)
                    and msg.index != NO_INDEX
                    and self._was_sent(msg.index)
                ):
                    self._last_played_seen = max(self._last_played_seen or 0, msg.index)
                out.append(BoardFault(now, msg))
            else:
                self._tally.add("unexpected_frames")
        elif isinstance(ev, DecodeError):
            out.append(DecodeFailure(now, ev.kind, ev.detail, ev.wire_size))
        elif isinstance(ev, Acked | Nacked):
            req = conn.requests.pop(ev.seq, None)
            if req is None:
                return
            req.status_mark = self._status_count
            if isinstance(ev, Acked):
                self._on_acked(ev, now, out)
                req.reply = ev.reply
            else:
                req.error = self._refusal(ev)
            req.done.set()

    def _refusal(self, ev: Nacked) -> ProtocolError:
        nak = ev.reply
        if nak.reason == NakReason.VERSION_MISMATCH:
            return from_wire(nak.to_error())
        what = ev.request.TYPE.name
        detail = ""
        if nak.reason in (NakReason.BAD_VALUE, NakReason.UNSUPPORTED):
            if ev.request.TYPE is MessageType.CONFIGURE:
                axes = self._pending_axes if self._pending_axes is not None else ()
                detail = f" at {describe_configure_offset(nak.detail, axes)} (frame offset {nak.detail})"
            else:
                detail = f" (field at frame offset {nak.detail})"
        elif nak.reason == NakReason.BAD_STATE:
            try:
                detail = f" (board state {BoardState(nak.detail).name})"
            except ValueError:
                detail = f" (board state {nak.detail})"
        return BoardRefusedError(
            f"{self.url}: board refused {what} (seq {ev.seq}): {nak.reason.name}{detail}", nak
        )

    def _on_acked(self, ev: Acked, now: float, out: list[LinkEvent]) -> None:
        req = ev.request
        if isinstance(req, Start):
            # the previous run's last SENSOR rows came before this ACK (flushed when its clock stopped)
            if self._last_played_seen is not None:
                self._close_sensor_run(self._last_played_seen, now, out)
            self._run_start = req.start_index
            self._sensor_next = req.start_index
            self._sensor_err_mark = self._loss_pos
            self._tail = None
            self._link_broke_in_run = False
        elif isinstance(req, Configure):
            self._sensor_stride = req.sensor_decimation
            self._flags_seen = FaultFlags.NONE
            self._sensor_next = None
            self._tail = None

    def _on_status(self, conn: _Connection, st: Status, now: float, out: list[LinkEvent]) -> None:
        prev = self._status
        self._status = st
        played_known = st.last_played_index != NO_INDEX and self._was_sent(st.last_played_index)
        if played_known:
            self._last_played_seen = st.last_played_index
        self._status_time = now
        self._status_count += 1
        conn.got_status = True
        self._tally.add("status_frames")
        raw = {src: int(getattr(st, src)) for src, _ in _BOARD_COUNTERS}
        if self._board_raw is not None:
            for src, dst in _BOARD_COUNTERS:
                delta = (raw[src] - self._board_raw[src]) % _U32
                if delta > _U32 // 2:  # the counter went down: the board restarted
                    delta = raw[src]
                if delta:
                    out.append(BoardCounter(now, src, delta, self._tally.add(dst, delta)))
        self._board_raw = raw
        raised = st.fault_flags & ~self._flags_seen
        if raised:
            if raised & FaultFlags.WATCHDOG:
                self._tally.add("watchdogs")
            out.append(FaultFlagsRaised(now, FaultFlags(raised), st))
        self._flags_seen = st.fault_flags
        was_running = prev is not None and prev.state == BoardState.RUNNING
        if (
            st.state in (BoardState.IDLE, BoardState.RAMPING)
            and (was_running or self._tail is None)
            and self._sensor_next is not None
            and played_known
        ):
            self._tail = (st.last_played_index, now + 4 * self.settings.status_period_ms / 1000.0)
        out.append(StatusUpdate(now, st))
        self._cond.notify_all()

    def _was_sent(self, index: int) -> bool:
        """Whether sample ``index`` can have been played: sent in this session (any index before the
        session's first START: the board may still run a stream of an earlier host process)."""
        return self._run_start is None or index < self._sent_hw

    def _on_sensor(self, msg: Sensor, now: float, out: list[LinkEvent]) -> None:
        n = msg.n_samples
        self._tally.add("sensor_frames")
        last = msg.first_index + (n - 1) * msg.stride
        if self._run_start is not None and (
            not self._was_sent(last)
            or msg.stride != self._sensor_stride
            or msg.n_channels != len(self._adc_scale)
        ):
            # readback of samples never sent, at another decimation or of other channels than
            # configured: a confused (or forged) frame; taken as readback it would move the run's
            # expected index (and report the rows between as lost)
            self._tally.add("unexpected_frames")
            log.warning(
                "SENSOR frame ignored: rows %d.. stride %d of %d channels, but samples sent up to %d, "
                "decimation %d, %d channels",
                msg.first_index,
                msg.stride,
                msg.n_channels,
                self._sent_hw - 1,
                self._sensor_stride,
                len(self._adc_scale),
            )
            return
        self._tally.add("sensor_rows", n)
        errors = self._loss_pos
        nxt = self._sensor_next
        end = msg.first_index + n * msg.stride
        if nxt is not None:
            if msg.first_index > nxt:
                missing = -(-(msg.first_index - nxt) // msg.stride)
                self._count_gap(nxt, missing, errors > self._sensor_err_mark, now, out)
            elif msg.first_index < nxt:
                self._tally.add("sensor_rows_duplicate", min(n, -(-(nxt - msg.first_index) // msg.stride)))
                end = max(end, nxt)  # rows already seen never restart the run's readback
        self._sensor_next = end
        self._sensor_stride = msg.stride
        self._sensor_err_mark = errors
        if self.plan is not None and msg.n_channels == len(self._adc_scale):
            out.append(
                SensorBlock(now, msg.first_index, msg.stride, msg.codes, self._adc_scale, self._adc_offset)
            )
        else:
            self._tally.add("unexpected_frames")

    def _count_gap(self, index: int, missing: int, explained: bool, now: float, out: list[LinkEvent]) -> None:
        self._tally.add("sensor_gaps")
        self._tally.add("sensor_rows_lost", missing)
        if not explained:
            self._tally.add("sensor_rows_lost_unexplained", missing)
            log.error("sensor rows %d.. (%d rows) lost without a detected frame error", index, missing)
        out.append(SensorGap(now, index, missing, explained))

    def _check_tail(self, now: float, out: list[LinkEvent]) -> None:
        if self._tail is None or now < self._tail[1]:
            return
        self._close_sensor_run(self._tail[0], now, out)

    def _close_sensor_run(self, last_played: int, now: float, out: list[LinkEvent]) -> None:
        """The clock stopped after ``last_played``: count the sensor rows of the run that never came."""
        self._tail = None
        self._cond.notify_all()
        nxt = self._sensor_next
        if nxt is not None and nxt <= last_played:
            missing = (last_played - nxt) // self._sensor_stride + 1
            explained = self._loss_pos > self._sensor_err_mark or self._link_broke_in_run
            self._count_gap(nxt, missing, explained, now, out)
        self._sensor_next = None

    # -- requests -----------------------------------------------------------------------------

    def _request(
        self, msg: Message, *, timeout_s: float | None = None, conn: _Connection | None = None
    ) -> Message:
        req = self._request_full(msg, timeout_s=timeout_s, conn=conn)
        assert req.reply is not None
        return req.reply

    def _request_full(
        self, msg: Message, *, timeout_s: float | None = None, conn: _Connection | None = None
    ) -> _Request:
        req = _Request(msg)
        with self._lock:
            if conn is None:
                conn = self._conn
                if self._dead is not None:
                    raise self._dead
                if conn is None or not conn.alive or self.capabilities is None:
                    raise LinkClosedError(f"{self.url}: the link is down")
            elif not conn.alive:
                raise LinkClosedError(f"{self.url}: the link is down")
            seq = conn.endpoint.send(msg, time.monotonic())
            conn.requests[seq] = req
        conn.wake.set()
        limit = timeout_s
        if limit is None:
            limit = self.settings.ack_timeout_s * (self.settings.max_retries + 1) + 1.0
        if not req.done.wait(limit):
            with self._lock:
                conn.requests.pop(seq, None)
                conn.endpoint.cancel(seq)
            raise LinkTimeoutError(f"{self.url}: no reply to {msg.TYPE.name} within {limit:g} s")
        if req.error is not None:
            raise req.error
        return req

    def configure(
        self,
        config: ScannerConfig | None = None,
        *,
        sample_rate_hz: float | None = None,
        settings: LinkSettings | None = None,
        timeout_s: float = 5.0,
    ) -> ChannelPlan:
        """Send CONFIGURE (from ``config``, or the last one) and wait until the board is IDLE.

        The board first finishes a ramp in progress (CONFIGURE is refused while RAMPING), then
        ramps every output to its new safe value.

        Raises
        ------
        BoardRefusedError
            NAK: the message names the field at fault (e.g. ``channels[1].code_min (axis y)``).
        ConfigError, SafetyError
            The config does not fit the board (checked before sending).
        LinkError
            No reply / the link broke.
        """
        if self.capabilities is None:
            raise LinkClosedError(f"{self.url}: not connected")
        if config is None:
            config = self._config
            if config is None:
                raise ConfigError("configure: no scanner config given and none sent before")
            sample_rate_hz = sample_rate_hz if sample_rate_hz is not None else self._sample_rate_override
        if settings is not None:
            self.settings = settings
        plan = plan_channels(config, self.capabilities, self.settings, sample_rate_hz=sample_rate_hz)
        ramp_s = self._ramp_time_s(plan)
        st = self.status
        if st is not None and st.state == BoardState.RAMPING:
            self.wait_status(lambda s: s.state != BoardState.RAMPING, timeout_s=ramp_s + timeout_s)
        with self._lock:
            self._pending_axes = plan.channel_axes
        req = self._request_full(plan.configure)
        with self._lock:
            self._config = config
            self._sample_rate_override = sample_rate_hz
            self.plan = plan
            self._adc_scale = np.array([c.adc_um_per_code for c in plan.configure.channels], dtype=np.float64)
            self._adc_offset = np.array([c.adc_offset_um for c in plan.configure.channels], dtype=np.float64)
        self.wait_status(
            lambda s: s.state == BoardState.IDLE, timeout_s=ramp_s + timeout_s, after=req.status_mark
        )
        return plan

    def _ramp_time_s(self, plan: ChannelPlan) -> float:
        caps = self.capabilities
        assert caps is not None
        return max(
            (hi - lo) / ch.ramp_v_per_s
            for (lo, hi), ch in zip(caps.amplifier_ranges_v, plan.configure.channels, strict=True)
        )

    def start(self, start_index: int, prefill_samples: int, *, timeout_s: float | None = None) -> int:
        """Send START (board must be IDLE): the clock runs once ``prefill_samples`` are queued.

        Returns
        -------
        int
            :attr:`status_count` when the ACK arrived (STATUS frames after it reflect the START).

        Raises
        ------
        BoardRefusedError
            NAK (e.g. ``BAD_STATE`` while ramping, ``BAD_VALUE`` prefill beyond the FIFO).
        """
        if self.plan is None:
            raise ProtocolError("start: the board is not configured (call configure first)")
        return self._request_full(Start(start_index, prefill_samples), timeout_s=timeout_s).status_mark

    def stop(self, after_index: int = NO_INDEX, *, timeout_s: float | None = None) -> None:
        """Send STOP: play up to and including ``after_index`` (default: now), then hold."""
        self._request(Stop(after_index), timeout_s=timeout_s)

    def ramp_to_safe(self, *, timeout_s: float | None = None) -> None:
        """Send RAMP_TO_SAFE: stop the clock and ramp every output to its safe value."""
        self._request(RampToSafe(), timeout_s=timeout_s)

    def prepare_restart(self, *, reconfigure: bool = True, timeout_s: float = 5.0) -> Status:
        """Bring the board back to IDLE after a fault or a reconnection, ready for :meth:`start`.

        Waits for a ramp in progress to end, then (``reconfigure``) sends the last configuration
        again, which also ramps the outputs to their safe values and clears the latched faults.
        """
        if self.plan is None or self._config is None:
            raise ProtocolError("prepare_restart: the board was never configured in this session")
        st = self.status
        if st is not None and st.state in (BoardState.ARMED, BoardState.RUNNING):
            try:
                self.stop()
            except BoardRefusedError as exc:
                if exc.nak.reason != NakReason.BAD_STATE:
                    raise
                log.info("STOP refused (%s): the board is not running; configuring it", exc)
        if reconfigure:
            self.configure(timeout_s=timeout_s)
        return self.wait_status(lambda s: s.state == BoardState.IDLE, timeout_s=timeout_s, fresh=False)

    def wait_status(
        self,
        predicate: Callable[[Status], bool],
        *,
        timeout_s: float,
        fresh: bool = True,
        after: int | None = None,
    ) -> Status:
        """Wait for a STATUS satisfying ``predicate``.

        ``fresh``: only one arriving after this call; ``after``: only one after the
        ``after``-th STATUS of the session (:attr:`status_count`, e.g. at a reply).

        Raises
        ------
        LinkTimeoutError
            None in time.
        LinkClosedError
            The link broke meanwhile.
        """
        deadline = time.monotonic() + timeout_s
        with self._lock:
            count0 = self._status_count if after is None else after
            if after is None and not fresh:
                count0 = -1
            conn = self._conn
            while True:
                st = self._status
                if st is not None and self._status_count > count0 and predicate(st):
                    return st
                if self._conn is not conn or conn is None or not conn.alive:
                    raise LinkClosedError(f"{self.url}: the link broke while waiting for STATUS")
                left = deadline - time.monotonic()
                if left <= 0:
                    last = f"state {st.state.name}" if st is not None else "no STATUS at all"
                    raise LinkTimeoutError(f"{self.url}: no matching STATUS within {timeout_s:g} s ({last})")
                self._cond.wait(left)

    def wait_readback_settled(self, timeout_s: float | None = None) -> bool:
        """Wait until every sensor row of the stopped run is accounted: read, or counted lost.

        The rows a stopped run's readback still lacks are counted lost 4 status periods after
        the STATUS that showed its clock stopped, when the reader next runs; on a busy machine
        that can be well after those 4 periods. Returns at once when no stopped run is open.
        ``timeout_s`` defaults to the link's silence limit (:attr:`LinkSettings.silence_limit_s`):
        a reader that has not run for that long belongs to a link that is down.

        Returns
        -------
        bool
            False when the run was still open after ``timeout_s`` (e.g. the link broke).
        """
        wait_s = self.settings.silence_limit_s if timeout_s is None else timeout_s
        with self._lock:
            return self._cond.wait_for(lambda: self._tail is None, wait_s)

    # -- streaming ------------------------------------------------------------------------------

    def send_samples(self, first_index: int, codes: CodeArray) -> int:
        """Queue one SAMPLES frame (codes ``(n, channels)`` int16); returns its sequence number.

        Does not block. The caller respects the credits (:class:`~piezod.link.streamer.Streamer`).

        Raises
        ------
        LinkClosedError
            The link is down.
        """
        msg = Samples(first_index, codes)
        with self._lock:
            conn = self._conn
            if conn is None or not conn.alive:
                raise LinkClosedError(f"{self.url}: the link is down")
            seq = conn.endpoint.send(msg, time.monotonic())
            self._sent_hw = max(self._sent_hw, first_index + msg.n_samples)
            self._tally.add("samples_frames_sent")
            self._tally.add("sample_rows_sent", msg.n_samples)
        conn.wake.set()
        return seq

    def send_sync(self, first_index: int, events: tuple[tuple[int, int, int], ...]) -> int:
        """Queue one SYNC data frame (PROTOCOL.md 4.14); returns its sequence number.

        ``events`` are ``(offset, lines, mask)`` from ``first_index``. Like SAMPLES it is not
        acknowledged: the streamer sends it with the SAMPLES of the same indices, again after a
        go-back-N rewind (the board skips events it already queued).

        Raises
        ------
        LinkClosedError
            The link is down.
        """
        msg = Sync(first_index, events)
        with self._lock:
            conn = self._conn
            if conn is None or not conn.alive:
                raise LinkClosedError(f"{self.url}: the link is down")
            seq = conn.endpoint.send(msg, time.monotonic())
        conn.wake.set()
        return seq

    def fifo_level(self) -> int | None:
        """Samples per channel in the board FIFO at the last STATUS (``None`` before one)."""
        st = self.status
        if st is None or self.capabilities is None:
            return None
        return int(self.capabilities.fifo_depth_samples - st.fifo_free_samples)


__all__ = [
    "DEFAULT_AXIS_CHANNELS",
    "BoardCounter",
    "BoardFault",
    "BoardRefusedError",
    "BoardSession",
    "ChannelPlan",
    "DecodeFailure",
    "EventQueue",
    "FaultFlagsRaised",
    "HostLimitFault",
    "LinkCounters",
    "LinkDown",
    "LinkEvent",
    "LinkLost",
    "LinkSettings",
    "LinkUp",
    "Reconnected",
    "SensorBlock",
    "SensorGap",
    "StatusUpdate",
    "describe_configure_offset",
    "plan_channels",
]
