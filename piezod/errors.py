"""The exception tree of piezod.

Every error piezod raises derives from :class:`PiezodError` and from the builtin
exception that best describes it, so callers may catch either
(``except TimeoutError`` catches :class:`LinkTimeoutError`).

::

    PiezodError
    ├── ConfigError(ValueError)             invalid scanner YAML / settings
    ├── RecordingError(ValueError)          malformed recording CSV (file:line)
    ├── ModelError(ValueError)              model evaluation outside its domain
    │   ├── RangeUnreachableError           requested scan range needs voltages beyond the limits
    │   └── LambertWDomainError             argument leaves the real branch of W
    ├── CalibrationError(RuntimeError)      fit failed or data insufficient
    ├── ProtocolError(ValueError)           malformed / unexpected frame
    │   └── VersionMismatchError            peer speaks another protocol version
    ├── LinkError(OSError)                  transport problems
    │   ├── LinkTimeoutError(TimeoutError)  no answer in time
    │   └── LinkClosedError(ConnectionError) board unplugged / port closed
    ├── BoardFaultError(RuntimeError)       the board reported a fault
    ├── SafetyError(ValueError)             a request would leave the configured limits
    ├── EngineStateError(RuntimeError)      request does not fit the engine's state (busy, fault)
    └── ApiError(RuntimeError)              the control API answered with an error (status, detail)
        └── ApiUnreachableError(ConnectionError) no answer from the control API
"""

from __future__ import annotations

import firmware_proto.errors as _wire


class PiezodError(Exception):
    """Root of every exception raised by piezod."""


class ConfigError(PiezodError, ValueError):
    """A scanner configuration (YAML) or setting is invalid."""


class RecordingError(PiezodError, ValueError):
    """A recording file is malformed.

    Parameters
    ----------
    message
        What is wrong.
    path
        The file at fault, if known.
    line
        The 1-based line number at fault, if known.
    """

    def __init__(self, message: str, path: str | None = None, line: int | None = None) -> None:
        self.path = path
        self.line = line
        self.reason = message
        where = ""
        if path is not None:
            where = f"{path}:{line}: " if line is not None else f"{path}: "
        super().__init__(f"{where}{message}")


class ModelError(PiezodError, ValueError):
    """A model was evaluated outside its domain."""


class RangeUnreachableError(ModelError):
    """The requested scan range cannot be reached inside the voltage limits."""


class LambertWDomainError(ModelError):
    """The Lambert W argument left the real branch (z < -1/e)."""


class CalibrationError(PiezodError, RuntimeError):
    """A calibration fit failed or the data cannot determine the parameters."""


class ProtocolError(PiezodError, _wire.ProtocolError):
    """A frame is malformed or unexpected.

    Also a :class:`firmware_proto.errors.ProtocolError` (the codec's own, host-free exception):
    ``except firmware_proto.ProtocolError`` catches both, and :func:`from_wire` turns the codec's
    into this one at the host's link boundary.
    """


class VersionMismatchError(ProtocolError, _wire.VersionMismatchError):
    """The peer speaks a different protocol version."""


def from_wire(exc: _wire.ProtocolError) -> ProtocolError:
    """The host's exception for an exception raised by :mod:`firmware_proto`.

    Parameters
    ----------
    exc
        Raised (or returned, for a NAK) by the codec.

    Returns
    -------
    ProtocolError
        ``exc`` itself when it already is one of piezod's, else a :class:`ProtocolError` (or
        :class:`VersionMismatchError`) with the same message whose ``__cause__`` is ``exc``.
    """
    if isinstance(exc, ProtocolError):
        return exc
    cls = VersionMismatchError if isinstance(exc, _wire.VersionMismatchError) else ProtocolError
    new = cls(str(exc))
    new.__cause__ = exc
    return new


class LinkError(PiezodError, OSError):
    """The transport to the board failed."""


class LinkTimeoutError(LinkError, TimeoutError):
    """The board did not answer in time."""


class LinkClosedError(LinkError, ConnectionError):
    """The board went away (unplugged, port closed)."""


class BoardFaultError(PiezodError, RuntimeError):
    """The board reported a fault (underrun, limit violation, watchdog)."""


class SafetyError(PiezodError, ValueError):
    """A request would drive the stage outside its configured limits."""


class EngineStateError(PiezodError, RuntimeError):
    """The request does not fit the engine's current state (busy, in fault, not scanning).

    The control API answers it with HTTP 409.
    """


class ApiError(PiezodError, RuntimeError):
    """The daemon's control API refused a request or failed.

    Parameters
    ----------
    message
        One line: what was asked and the server's reason.
    status_code
        The HTTP status, None when no HTTP answer arrived.
    detail
        The server's reason alone.
    error
        The server-side exception name, if the server gave one.
    """

    def __init__(
        self, message: str, status_code: int | None = None, detail: str = "", error: str | None = None
    ) -> None:
        self.status_code = status_code
        self.detail = detail or message
        self.error = error
        super().__init__(message)


class ApiUnreachableError(ApiError, ConnectionError):
    """No answer from the control API (no socket, connection refused, timeout)."""
