"""piezod: online hysteresis + creep linearisation of SPM piezo scanners.

The package is layered: :mod:`piezod.model` is pure numpy (no I/O); recordings,
calibration, audit and linearity analysis read and write files; the link and
service layers talk to the board.
"""

from piezod.errors import PiezodError

__all__ = ["PiezodError", "__version__"]
__version__ = "0.1.0"
