"""The host link to the board: transports, the protocol session, the sample streamer.

Layers (each usable alone):

- :mod:`piezod.link.transport`: byte transports chosen by URL (serial device / pty opened
  exclusively, pyserial URLs, ``unix://``, ``usb://`` through :mod:`piezod.link.usb`), errors
  mapped onto :class:`~piezod.errors.LinkError` / ``LinkTimeoutError`` / ``LinkClosedError``;
- :mod:`piezod.link.session`: :class:`BoardSession` (handshake, CONFIGURE from the scanner
  config, control requests with retransmission, heartbeat, STATUS / SENSOR / FAULT handling,
  typed events, counters, reconnection);
- :mod:`piezod.link.streamer`: :class:`Streamer` keeps the board FIFO filled ahead from a block
  source, within the credits, and matches the sensor readback to sample indices;
- :mod:`piezod.link.bench`: ``piezod bench stream``.
"""

from __future__ import annotations

from piezod.link.session import (
    BoardCounter,
    BoardFault,
    BoardRefusedError,
    BoardSession,
    ChannelPlan,
    DecodeFailure,
    EventQueue,
    FaultFlagsRaised,
    HostLimitFault,
    LinkCounters,
    LinkDown,
    LinkEvent,
    LinkLost,
    LinkSettings,
    LinkUp,
    Reconnected,
    SensorBlock,
    SensorGap,
    StatusUpdate,
    plan_channels,
)
from piezod.link.streamer import (
    BlockSource,
    CodeConverter,
    MatchedBlock,
    RunRecord,
    Streamer,
    StreamStats,
    TriangleSource,
)
from piezod.link.transport import LinkUrl, Transport, open_transport, parse_url

__all__ = [
    "BlockSource",
    "BoardCounter",
    "BoardFault",
    "BoardRefusedError",
    "BoardSession",
    "ChannelPlan",
    "CodeConverter",
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
    "LinkUrl",
    "MatchedBlock",
    "Reconnected",
    "RunRecord",
    "SensorBlock",
    "SensorGap",
    "StatusUpdate",
    "StreamStats",
    "Streamer",
    "Transport",
    "TriangleSource",
    "open_transport",
    "parse_url",
    "plan_channels",
]
