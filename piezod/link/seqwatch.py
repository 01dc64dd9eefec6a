"""Frames lost whole, found by the board's sequence numbers (PROTOCOL.md 5.2).

:class:`SeqWatch` is the session's frame decoder: besides decoding, it counts the frames missing
from the peer's ``seq`` (damaged beyond recognition, merged by a damaged delimiter, or dropped)
and where in the stream each loss happened, so the session can explain a later sensor gap. A
reply re-sent from the board's duplicate cache (5.3) carries its old ``seq``: it is counted
apart and never taken for a rewind.
"""

from __future__ import annotations

from firmware_proto import Ack, Capabilities, DecodeError, Endpoint, Frame, FrameDecoder, Message, Nak
from piezod.link.plan import LinkSettings


class SeqWatch(FrameDecoder):
    """A :class:`FrameDecoder` that also counts frames missing from the peer's sequence numbers.

    Every frame the board sends carries the next ``seq``; a jump reveals frames lost on the way
    (damaged beyond recognition, merged by a damaged delimiter, or dropped), replies included.

    A reply the board answers from its duplicate cache (PROTOCOL.md 5.3: a retransmitted request
    whose first reply was lost) is re-sent byte-identical, so it carries its *old* ``seq``. It is
    counted in :attr:`resent_replies` and leaves the expected ``seq`` alone: taking it as the new
    position would count every frame sent since the first reply as missing once the next frame
    arrives. Any other frame behind the expected ``seq`` (a board that restarted its counter)
    re-synchronises the count.
    """

    def __init__(self) -> None:
        super().__init__()
        self.expected: int | None = None
        self.missing = 0
        self.out_of_order = 0
        self.resent_replies = 0
        # frames missing right before a frame, by id() of its message: the session places each
        # loss at its position in the stream (a batch of bytes may hold a loss after a SENSOR)
        self.gap_before: dict[int, int] = {}

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame | DecodeError]:
        items = super().feed(data)
        for item in items:
            if isinstance(item, Frame):
                if self.expected is not None and item.seq != self.expected:
                    gap = (item.seq - self.expected) & 0xFFFFFFFF
                    if gap < 1 << 31:
                        self.missing += gap
                        self.gap_before[id(item.msg)] = gap
                    elif isinstance(item.msg, Ack | Nak | Capabilities):
                        self.resent_replies += 1
                        continue
                    else:
                        self.out_of_order += 1
                self.expected = (item.seq + 1) & 0xFFFFFFFF
        return items


def new_endpoint(settings: LinkSettings) -> Endpoint:
    ep = Endpoint(ack_timeout_s=settings.ack_timeout_s, max_retries=settings.max_retries)
    ep.decoder = SeqWatch()
    return ep


def missing_frames(ep: Endpoint) -> int:
    dec = ep.decoder
    return dec.missing if isinstance(dec, SeqWatch) else 0


def gap_before(ep: Endpoint, msg: Message) -> int:
    dec = ep.decoder
    return dec.gap_before.pop(id(msg), 0) if isinstance(dec, SeqWatch) else 0


__all__ = ["SeqWatch", "gap_before", "missing_frames", "new_endpoint"]
