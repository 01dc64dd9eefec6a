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
ignored rather than followed. So is a line much faster than the calibration measured
(``min_line_s``, the axis's ``tracking_min_line_s``): its length error is the model's rate error
there (a lag, a mode, short-time creep the frame did not pin), the same at every sensitivity.
Followed, it had moved the scale of the next, slower scans: on a held-out nPoint-like stage a
scan of 20 Hz lines (0.7 % short from the stage's lags) left the scale 0.4 % high, and the next
1 Hz scan 0.41 % long.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: A line is taken while it lasts at least this fraction of the shortest calibrated line (a scan a
#: little faster than the frame's fastest still tracks; ten times faster does not).
LINE_TOLERANCE = 0.8


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
    lines_too_fast: int = 0

    def restarted(self) -> SensitivityTracker:
        """The same settings from scale 1, no lines counted (a new model: the scale is relative to one)."""
        return SensitivityTracker(self.gain, self.max_step, self.limit, self.outlier)

    def update(
        self, measured_over_nominal: float, line_s: float = math.inf, min_line_s: float | None = None
    ) -> float:
        """Take one line's ``measured / nominal`` (with the current correction applied); return the scale.

        A line shorter than :data:`LINE_TOLERANCE` times ``min_line_s`` (seconds) is not taken.
        """
        if min_line_s is not None and line_s < LINE_TOLERANCE * min_line_s:
            self.lines_too_fast += 1
            return self.scale
        err = measured_over_nominal - 1.0
        if not math.isfinite(err) or abs(err) > self.outlier:
            self.lines_ignored += 1
            return self.scale
        step = max(-self.max_step, min(self.max_step, self.gain * err))
        self.scale = max(1.0 - self.limit, min(1.0 + self.limit, self.scale * (1.0 + step)))
        self.lines_used += 1
        return self.scale
