"""``python -m hil_sim``: the simulated board on a pty (see :mod:`hil_sim.server`)."""

from __future__ import annotations

import sys

from hil_sim.server import main

if __name__ == "__main__":
    sys.exit(main())
