"""Sans-I/O connection state shared by the host link and the (simulated) board.

:class:`Endpoint` numbers outgoing frames, keeps control requests until they are answered,
retransmits them on the caller's clock, matches ACK / NAK / CAPABILITIES replies to requests and
answers retransmitted requests from a reply cache instead of applying them twice. It never
reads a clock and never does I/O: the caller passes ``now`` (seconds, any monotonic origin),
writes :meth:`Endpoint.data_to_send` to its transport and feeds what it reads to
:meth:`Endpoint.receive`.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

from .codec import DecodeError, DecoderStats, Frame, FrameDecoder, encode
from .errors import ProtocolError, VersionMismatchError
from .messages import (
    CONTROL_TYPES,
    PROTOCOL_VERSION,
    Ack,
    Capabilities,
    Message,
    MessageType,
    Nak,
    NakReason,
)

DEFAULT_ACK_TIMEOUT_S = 0.1
"""Retransmit a control request not answered within this time (s)."""
DEFAULT_MAX_RETRIES = 5
"""Retransmissions before a request is given up (:class:`TimedOut`)."""


@dataclass(frozen=True, slots=True)
class PendingRequest:
    """A control request awaiting its reply."""

    seq: int
    msg: Message
    wire: bytes
    deadline: float
    attempts: int


@dataclass(frozen=True, slots=True)
class Acked:
    """A control request was answered with ACK (or, for HELLO, CAPABILITIES)."""

    seq: int
    request: Message
    reply: Ack | Capabilities


@dataclass(frozen=True, slots=True)
class Nacked:
    """A control request was refused."""

    seq: int
    request: Message
    reply: Nak

    def error(self) -> ProtocolError:
        """The exception to raise for this refusal (:class:`VersionMismatchError` for versions)."""
        return self.reply.to_error()


@dataclass(frozen=True, slots=True)
class TimedOut:
    """A control request got no reply after all retransmissions."""

    seq: int
    request: Message
    attempts: int


Event = Frame | DecodeError | Acked | Nacked | TimedOut
"""What :meth:`Endpoint.receive` and :meth:`Endpoint.poll` return."""


@dataclass(slots=True)
class EndpointStats:
    """Counters of an :class:`Endpoint` (monotonic)."""

    frames_sent: int = 0
    bytes_sent: int = 0
    retransmits: int = 0
    timeouts: int = 0
    stray_replies: int = 0
    duplicate_requests: int = 0


def check_capabilities(caps: Capabilities) -> None:
    """Raise :class:`VersionMismatchError` unless the board speaks :data:`PROTOCOL_VERSION`."""
    if caps.protocol_version != PROTOCOL_VERSION:
        raise VersionMismatchError(
            f"board speaks protocol version {caps.protocol_version}, this host speaks {PROTOCOL_VERSION}"
        )


class Endpoint:
    """One side of a link (host or board), sans I/O.

    Parameters
    ----------
    ack_timeout_s
        Time (s, on the caller's clock) after which an unanswered control request is sent again.
    max_retries
        Retransmissions before the request is reported as :class:`TimedOut`.
    initial_seq
        Sequence number of the first frame sent.
    reply_cache_size
        How many recent replies are kept to answer retransmitted requests.
    """

    def __init__(
        self,
        *,
        ack_timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
        max_retries: int = DEFAULT_MAX_RETRIES,
        initial_seq: int = 0,
        reply_cache_size: int = 16,
    ) -> None:
        if ack_timeout_s <= 0 or max_retries < 0 or reply_cache_size < 1:
            raise ValueError("ack_timeout_s must be > 0, max_retries >= 0, reply_cache_size >= 1")
        self.ack_timeout_s = ack_timeout_s
        self.max_retries = max_retries
        self.decoder = FrameDecoder()
        self.stats = EndpointStats()
        self.last_rx_time: float | None = None
        self._seq = initial_seq & 0xFFFFFFFF
        self._pending: dict[int, PendingRequest] = {}
        self._replies: OrderedDict[tuple[int, int], bytes] = OrderedDict()
        self._reply_cache_size = reply_cache_size
        self._outbox: list[bytes] = []

    # -- sending ---------------------------------------------------------------------------

    @property
    def next_seq(self) -> int:
        """Sequence number the next frame will carry."""
        return self._seq

    @property
    def pending(self) -> dict[int, PendingRequest]:
        """Control requests awaiting a reply, by sequence number (a copy)."""
        return dict(self._pending)

    @property
    def decoder_stats(self) -> DecoderStats:
        """Counters of the receive side."""
        return self.decoder.stats

    def _take_seq(self) -> int:
        seq = self._seq
        self._seq = (seq + 1) & 0xFFFFFFFF
        return seq

    def _queue(self, wire: bytes) -> None:
        self._outbox.append(wire)
        self.stats.frames_sent += 1
        self.stats.bytes_sent += len(wire)

    def send(self, msg: Message, now: float) -> int:
        """Queue ``msg``; control requests are kept for retransmission until answered.

        Returns
        -------
        int
            The sequence number used.
        """
        seq = self._take_seq()
        wire = encode(msg, seq)
        self._queue(wire)
        if msg.TYPE in CONTROL_TYPES:
            self._pending[seq] = PendingRequest(seq, msg, wire, now + self.ack_timeout_s, 1)
        return seq

    def reply(self, request: Frame | DecodeError, msg: Ack | Nak | Capabilities) -> int:
        """Queue the answer to a control request and remember it for retransmitted copies.

        ``request`` may be a :class:`DecodeError` with a valid CRC (e.g. unknown type) to NAK it.
        """
        if request.seq is None or request.msg_type is None:
            raise ProtocolError("cannot reply to a frame whose header is unknown (bad COBS / CRC)")
        seq = self._take_seq()
        wire = encode(msg, seq)
        self._queue(wire)
        key = (request.seq, request.msg_type)
        self._replies[key] = wire
        self._replies.move_to_end(key)
        while len(self._replies) > self._reply_cache_size:
            self._replies.popitem(last=False)
        return seq

    def ack(self, request: Frame) -> int:
        """Queue an ACK of ``request``."""
        return self.reply(request, Ack(request.seq, request.msg_type))

    def nak(self, request: Frame | DecodeError, reason: NakReason, detail: int = 0) -> int:
        """Queue a NAK of ``request``."""
        if request.seq is None or request.msg_type is None:
            raise ProtocolError("cannot NAK a frame whose header is unknown (bad COBS / CRC)")
        return self.reply(request, Nak(request.seq, request.msg_type, reason, detail))

    def data_to_send(self) -> bytes:
        """Everything queued since the last call, ready to write to the transport."""
        if not self._outbox:
            return b""
        out = b"".join(self._outbox)
        self._outbox.clear()
        return out

    # -- timers ----------------------------------------------------------------------------

    def next_deadline(self) -> float | None:
        """Earliest time :meth:`poll` has work (a retransmission or a give-up), or ``None``."""
        return min((p.deadline for p in self._pending.values()), default=None)

    def poll(self, now: float) -> list[Event]:
        """Retransmit overdue requests; report those out of retries as :class:`TimedOut`."""
        events: list[Event] = []
        for seq, p in list(self._pending.items()):
            if p.deadline > now:
                continue
            if p.attempts > self.max_retries:
                del self._pending[seq]
                self.stats.timeouts += 1
                events.append(TimedOut(seq, p.msg, p.attempts))
            else:
                self._queue(p.wire)
                self.stats.retransmits += 1
                self._pending[seq] = PendingRequest(
                    seq, p.msg, p.wire, now + self.ack_timeout_s, p.attempts + 1
                )
        return events

    def cancel(self, seq: int) -> None:
        """Forget a pending request (no more retransmissions)."""
        self._pending.pop(seq, None)

    # -- receiving -------------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> list[Event]:
        """Feed received bytes; return events in stream order.

        Replies matching a pending request come as :class:`Acked` / :class:`Nacked`;
        retransmitted control requests already answered are re-answered from the cache and not
        delivered; every other valid frame comes as a :class:`Frame`, every dropped one as a
        :class:`DecodeError`.
        """
        events: list[Event] = []
        for item in self.decoder.feed(data):
            if isinstance(item, DecodeError):
                events.append(item)
                continue
            self.last_rx_time = now
            msg = item.msg
            if isinstance(msg, Ack | Nak | Capabilities):
                matched = self._match_reply(msg)
                if matched is not None:
                    events.append(matched)
                    continue
                self.stats.stray_replies += 1
            elif item.ack_requested:
                if msg.TYPE is MessageType.HELLO:
                    self._replies.clear()  # a new session: its sequence numbers may repeat old ones
                else:
                    cached = self._replies.get((item.seq, item.msg_type))
                    if cached is not None:
                        self.stats.duplicate_requests += 1
                        self._queue(cached)
                        continue
            events.append(item)
        return events

    def _match_reply(self, msg: Ack | Nak | Capabilities) -> Acked | Nacked | None:
        if isinstance(msg, Ack):
            seq, typ = msg.acked_seq, msg.acked_type
        elif isinstance(msg, Nak):
            seq, typ = msg.nacked_seq, msg.nacked_type
        else:
            seq, typ = msg.reply_to_seq, int(MessageType.HELLO)
        p = self._pending.get(seq)
        if p is None or int(p.msg.TYPE) != typ:
            return None
        if isinstance(msg, Ack) and p.msg.TYPE is MessageType.HELLO:
            return None  # HELLO is answered by CAPABILITIES, not ACK
        del self._pending[seq]
        if isinstance(msg, Nak):
            return Nacked(seq, p.msg, msg)
        return Acked(seq, p.msg, msg)


__all__ = [
    "DEFAULT_ACK_TIMEOUT_S",
    "DEFAULT_MAX_RETRIES",
    "Acked",
    "Endpoint",
    "EndpointStats",
    "Event",
    "Nacked",
    "PendingRequest",
    "TimedOut",
    "check_capabilities",
]
