"""The exceptions of the protocol package, free of any host code.

``firmware_proto`` is shared by the host (``piezod``), the simulated board (``hil_sim``) and
firmware tooling, so it defines its own small exception tree; the host mixes it into its own
root (``piezod.errors.ProtocolError`` derives from :class:`ProtocolError` below and from
``piezod.errors.PiezodError``) and translates at its link boundary
(``piezod.errors.from_wire``).

::

    WireError
    └── ProtocolError(ValueError)       malformed / unexpected frame or field
        └── VersionMismatchError        peer speaks another protocol version
"""

from __future__ import annotations


class WireError(Exception):
    """Root of every exception raised by :mod:`firmware_proto`."""


class ProtocolError(WireError, ValueError):
    """A frame or message field is malformed or unexpected."""


class VersionMismatchError(ProtocolError):
    """The peer speaks a different protocol version."""
