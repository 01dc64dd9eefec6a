"""What a board session reports: typed link events, sensor blocks, refusals and counters.

Delivered by :class:`~piezod.link.session.BoardSession` to its subscribers (from its I/O
threads); the engine, the streamer and the tests consume them.
"""

from __future__ import annotations

import logging
import queue
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Protocol

import numpy as np
import numpy.typing as npt

from firmware_proto import (
    Capabilities,
    CodeArray,
    Endpoint,
    ErrorKind,
    Fault,
    FaultCode,
    FaultFlags,
    Nak,
    Status,
)
from piezod.errors import (
    LinkError,
    ProtocolError,
)
from piezod.link.seqwatch import missing_frames

log = logging.getLogger("piezod.link.session")

_U32 = 1 << 32


# ---------------------------------------------------------------------------------------------
# events


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """Base of everything a session reports. ``time`` is ``time.monotonic()`` at detection."""

    time: float


@dataclass(frozen=True, slots=True)
class LinkUp(LinkEvent):
    """The handshake succeeded (first connection or a reconnection)."""

    capabilities: Capabilities
    url: str


@dataclass(frozen=True, slots=True)
class LinkDown(LinkEvent):
    """The link broke; a reconnection follows when enabled."""

    error: LinkError


@dataclass(frozen=True, slots=True)
class Reconnected(LinkEvent):
    """The link is back after :class:`LinkDown`; nothing was restarted.

    Attributes
    ----------
    capabilities
        The board's CAPABILITIES now.
    status
        The first STATUS after the handshake (``None``: the board sent none, i.e. it is
        unconfigured, for instance after a power cycle).
    board_changed
        Another board (serial number / channels) answered.
    watchdog_fired
        The board latched WATCHDOG: it ramped the outputs to their safe values.
    fault_flags
        Everything latched since the last START / CONFIGURE.
    last_played_index
        The last sample the board applied (``None`` if none).
    downtime_s
        From :class:`LinkDown` to now.
    """

    capabilities: Capabilities
    status: Status | None
    board_changed: bool
    watchdog_fired: bool
    fault_flags: FaultFlags
    last_played_index: int | None
    downtime_s: float


@dataclass(frozen=True, slots=True)
class LinkLost(LinkEvent):
    """Reconnection was given up (or disabled); the session is dead."""

    error: LinkError


@dataclass(frozen=True, slots=True)
class StatusUpdate(LinkEvent):
    """A STATUS frame."""

    status: Status


@dataclass(frozen=True, slots=True)
class BoardFault(LinkEvent):
    """A FAULT frame (best effort; :class:`FaultFlagsRaised` and the counters are the reliable record)."""

    fault: Fault

    @property
    def code(self) -> FaultCode:
        """What happened."""
        return self.fault.code


@dataclass(frozen=True, slots=True)
class FaultFlagsRaised(LinkEvent):
    """STATUS shows newly latched fault flags (also when their FAULT frame was lost)."""

    raised: FaultFlags
    status: Status


@dataclass(frozen=True, slots=True)
class BoardCounter(LinkEvent):
    """A board counter in STATUS increased (``name`` is the STATUS field)."""

    name: str
    delta: int
    total: int


@dataclass(frozen=True, slots=True)
class DecodeFailure(LinkEvent):
    """The host dropped a damaged frame."""

    kind: ErrorKind
    detail: str
    wire_size: int


@dataclass(frozen=True, slots=True)
class SensorGap(LinkEvent):
    """Sensor rows missing in the readback.

    Attributes
    ----------
    expected_index
        First missing sample index.
    missing_rows
        Rows lost.
    explained
        A dropped frame (counted by the decoder) or a link break can account for them.
    """

    expected_index: int
    missing_rows: int
    explained: bool


@dataclass(frozen=True, slots=True)
class HostLimitFault(LinkEvent):
    """The host clamped samples that left the configured voltage limits (reported by the streamer)."""

    channel: int
    axis: str | None
    first_index: int
    count: int
    worst_v: float


@dataclass(frozen=True, slots=True, eq=False)
class SensorBlock(LinkEvent):
    """One SENSOR frame, with its sample indices and the configured scaling.

    Attributes
    ----------
    first_index
        Sample index of the first row.
    stride
        Index step between rows.
    codes
        ADC codes, shape ``(n, channels)``.
    um_per_code, offset_um
        Per-channel scaling from the configuration in force.
    """

    first_index: int
    stride: int
    codes: CodeArray
    um_per_code: npt.NDArray[np.float64]
    offset_um: npt.NDArray[np.float64]

    @property
    def n_samples(self) -> int:
        """Rows in this block."""
        return int(self.codes.shape[0])

    @property
    def indices(self) -> npt.NDArray[np.int64]:
        """Sample index of every row."""
        return self.first_index + self.stride * np.arange(self.n_samples, dtype=np.int64)

    @property
    def positions_um(self) -> npt.NDArray[np.float64]:
        """Sensor positions (um), shape ``(channels, n)``."""
        out: npt.NDArray[np.float64] = self.offset_um[:, None] + self.um_per_code[
            :, None
        ] * self.codes.T.astype(np.float64)
        return out


class BoardRefusedError(ProtocolError):
    """The board answered a control request with NAK.

    Attributes
    ----------
    nak
        The NAK.
    """

    def __init__(self, message: str, nak: Nak) -> None:
        super().__init__(message)
        self.nak = nak


# ---------------------------------------------------------------------------------------------
# counters


@dataclass(frozen=True, slots=True)
class LinkCounters:
    """Cumulative counts of a session (all connections).

    Board counters are increments since the session's first STATUS (wrap- and reset-aware),
    including increments that happened while the link was down. ``frames_lost_rx`` counts the
    board's frames that never arrived intact, from the gaps in their sequence numbers (this
    includes frames the decoder dropped, and frames lost whole).
    """

    frames_sent: int = 0
    bytes_sent: int = 0
    samples_frames_sent: int = 0
    sample_rows_sent: int = 0
    heartbeats_sent: int = 0
    retransmits: int = 0
    request_timeouts: int = 0
    frames_received: int = 0
    bytes_received: int = 0
    decode_errors: int = 0
    crc_errors_host: int = 0
    decode_errors_by_kind: Mapping[str, int] = field(default_factory=dict)
    frames_lost_rx: int = 0
    status_frames: int = 0
    sensor_frames: int = 0
    sensor_rows: int = 0
    sensor_rows_lost: int = 0
    sensor_rows_lost_unexplained: int = 0
    sensor_gaps: int = 0
    sensor_rows_duplicate: int = 0
    unexpected_frames: int = 0
    stray_replies: int = 0
    link_downs: int = 0
    reconnects: int = 0
    callback_errors: int = 0
    crc_errors_board: int = 0
    frames_dropped_board: int = 0
    underruns: int = 0
    clamped_samples: int = 0
    index_gaps: int = 0
    overflows: int = 0
    watchdogs: int = 0
    fault_frames: Mapping[str, int] = field(default_factory=dict)

    @property
    def crc_errors(self) -> int:
        """CRC errors detected on both sides."""
        return self.crc_errors_host + self.crc_errors_board


#: The counts :class:`LinkCounters` derives from the decode errors rather than keeps.
_DERIVED = frozenset({"decode_errors", "crc_errors_host", "decode_errors_by_kind", "fault_frames"})


class LinkTally:
    """The session's running counts, keyed by the names of :class:`LinkCounters`' fields (an unknown
    name cannot be tallied), with the endpoint counts of retired connections folded in (:meth:`fold`);
    :meth:`snapshot` is the counters."""

    __slots__ = ("decode_kinds", "fault_frames", "n")

    def __init__(self) -> None:
        self.n: dict[str, int] = {f.name: 0 for f in fields(LinkCounters) if f.name not in _DERIVED}
        self.decode_kinds: dict[str, int] = {}
        self.fault_frames: dict[str, int] = {}

    def add(self, name: str, count: int = 1) -> int:
        """Count ``count`` more of ``name`` (a :class:`LinkCounters` field); returns the new total."""
        self.n[name] += count  # KeyError for a name LinkCounters does not have
        return self.n[name]

    def fold(self, endpoint: Endpoint) -> None:
        """Add a connection's endpoint counts (frames, bytes, retransmissions, decode errors, losses)."""
        es, ds = endpoint.stats, endpoint.decoder_stats
        for name, count in (
            ("frames_sent", es.frames_sent),
            ("bytes_sent", es.bytes_sent),
            ("retransmits", es.retransmits),
            ("request_timeouts", es.timeouts),
            ("stray_replies", es.stray_replies),
            ("frames_received", ds.frames_ok),
            ("bytes_received", ds.bytes_in),
            ("frames_lost_rx", missing_frames(endpoint)),
        ):
            self.add(name, count)
        for kind in ErrorKind:
            self.decode_kinds[kind.value] = self.decode_kinds.get(kind.value, 0) + ds.count(kind)

    def snapshot(self, live: Endpoint | None = None) -> LinkCounters:
        """The counters, with the live connection's endpoint (if any) counted too."""
        t = LinkTally()
        t.n, t.decode_kinds, t.fault_frames = dict(self.n), dict(self.decode_kinds), dict(self.fault_frames)
        if live is not None:
            t.fold(live)
        kinds = t.decode_kinds
        return LinkCounters(
            **t.n,
            decode_errors=sum(kinds.values()),
            crc_errors_host=kinds.get(ErrorKind.BAD_CRC.value, 0),
            decode_errors_by_kind={k: v for k, v in kinds.items() if v},
            fault_frames=t.fault_frames,
        )


class Subscribable(Protocol):
    """What :class:`EventQueue` needs of a session: ``subscribe`` returning the unsubscribe call."""

    def subscribe(self, callback: Callable[[LinkEvent], None]) -> Callable[[], None]: ...


class EventQueue:
    """A bounded queue of a session's events, for a consumer that polls instead of a callback.

    Parameters
    ----------
    session
        The session to subscribe to (:class:`piezod.link.session.BoardSession`).
    kinds
        Event classes kept (e.g. ``(SensorBlock,)``); others are ignored.
    maxsize
        Events kept at most; when the consumer falls behind, new events are counted in
        :attr:`dropped` (and logged once) instead of growing without bound.
    """

    def __init__(
        self,
        session: Subscribable,
        kinds: tuple[type[LinkEvent], ...] = (LinkEvent,),
        maxsize: int = 10_000,
    ) -> None:
        self.kinds = kinds
        self.dropped = 0
        self._q: queue.Queue[LinkEvent] = queue.Queue(maxsize)
        self._unsubscribe = session.subscribe(self._put)

    def _put(self, ev: LinkEvent) -> None:
        if not isinstance(ev, self.kinds):
            return
        try:
            self._q.put_nowait(ev)
        except queue.Full:
            if not self.dropped:
                log.error("event queue full (%d): the consumer falls behind; counting drops", self._q.maxsize)
            self.dropped += 1

    def get(self, timeout_s: float | None = None) -> LinkEvent:
        """The next event; raises :class:`queue.Empty` after ``timeout_s``."""
        return self._q.get(timeout=timeout_s)

    def drain(self) -> list[LinkEvent]:
        """Every event queued now."""
        out: list[LinkEvent] = []
        while True:
            try:
                out.append(self._q.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        """Stop collecting."""
        self._unsubscribe()
