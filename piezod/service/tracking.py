"""Sensitivity tracking: follow slow sensitivity drift from the readback of normal scans.

The thesis saw the instrument's sensitivity drift by about 1 % over hours (warm-up, section 4.4);
a model calibrated in the morning then scans 1 % too long in the afternoon. During every
corrected scan the sensor says how long each line really was: the regression slope of the
measured position on the commanded target, ``g = measured / nominal`` ((4.14)-(4.15)). The
tracker turns those per-line measurements into a slowly adapting gain estimate and the engine
divides the fast-axis travel by it, so the stage scans the nominal length again.

Adaptation is deliberately bounded: each line moves the estimate by at most
``max_step`` (relative) towards ``gain`` times the line's error, and the total correction
never exceeds ``limit``; a measurement that is far off (a fault, a resonance, a wrong line) is
ignored rather than followed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class SensitivityTracker:
    """Bounded, slow estimate of the stage's sensitivity relative to the model.

    Parameters
    ----------
    gain
        Fraction of a line's relative length error taken per line (0 < gain <= 1).
    max_step
        Largest relative change of the estimate per line.
    limit
        Largest relative deviation of the estimate from 1.
    outlier
        Line errors larger than this (relative) are ignored.
    """

    gain: float = 0.25
    max_step: float = 5e-4
    limit: float = 0.03
    outlier: float = 0.05
    scale: float = 1.0
    lines_used: int = 0
    lines_ignored: int = 0

    def update(self, measured_over_nominal: float) -> float:
        """Take one line's ``measured / nominal`` (with the current correction applied); return the scale."""
        err = measured_over_nominal - 1.0
        if not math.isfinite(err) or abs(err) > self.outlier:
            self.lines_ignored += 1
            return self.scale
        step = max(-self.max_step, min(self.max_step, self.gain * err))
        self.scale = max(1.0 - self.limit, min(1.0 + self.limit, self.scale * (1.0 + step)))
        self.lines_used += 1
        return self.scale
