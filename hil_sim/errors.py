"""The exception tree of hil_sim (the simulator does not import the host's :mod:`piezod`).

Every error hil_sim raises derives from :class:`SimError` and from the builtin exception that
best describes it, so callers may catch either (``except ValueError`` catches
:class:`SimConfigError`).

::

    SimError
    ├── SimConfigError(ValueError)   invalid ``simulation:`` section, preset or effect string
    ├── SimModelError(ValueError)    stage evaluation outside its domain (shapes, non-finite input)
    ├── SimSafetyError(ValueError)   an offline session plan leaves the voltage limits it was given
    └── SimLinkError(OSError)        the simulator's pty / socket / process cannot be served or reached
        ├── SimLinkClosedError(ConnectionError)   the peer is gone (unplugged, refused)
        └── SimLinkTimeoutError(TimeoutError)     nothing answered in time

The host (:mod:`piezod.simulator`) turns these into its own link errors.
"""

from __future__ import annotations


class SimError(Exception):
    """Root of every exception raised by the simulated stage."""


class SimConfigError(SimError, ValueError):
    """The ``simulation:`` section of a scanner YAML, a preset or an effect string is invalid."""


class SimModelError(SimError, ValueError):
    """The stage was asked to evaluate something outside its domain."""


class SimSafetyError(SimError, ValueError):
    """An offline session plan (:mod:`hil_sim.session`) leaves the voltage limits it was given."""


class SimLinkError(SimError, OSError):
    """The simulator's pty, USB socket or process cannot be served or reached."""


class SimLinkClosedError(SimLinkError, ConnectionError):
    """The other end is gone (an unplugged simulated device, a refused connection)."""


class SimLinkTimeoutError(SimLinkError, TimeoutError):
    """Nothing answered in time (no simulated device, no path printed)."""


__all__ = [
    "SimConfigError",
    "SimError",
    "SimLinkClosedError",
    "SimLinkError",
    "SimLinkTimeoutError",
    "SimModelError",
    "SimSafetyError",
]
