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

The bound is for lines in a row. After a pause the sensitivity may have moved further than a
few lines' steps: a model fitted on a frame an hour ago on a stage warming 1 %/h is 1 % off at
the first corrected line, and 0.05 % per line took twelve lines to follow it (session 21: the
first verification points of a held-out tube stage +0.60 % and +0.19 % long). So the tracker also
carries how uncertain its estimate is (a scalar Kalman filter on the scale): the uncertainty grows
with the time since the last line at ``drift_per_s`` (the fastest drift the lab expects) from the
age of the model's data when a model is switched in, and shrinks with every line taken, whose own
scatter is ``scatter``. While the filter's weight ``P / (P + scatter**2)`` is below ``gain`` a line
is taken as above (``gain``, at most ``max_step``); above it, with that weight, moving the estimate
by at most ``max(max_step, 3 sqrt(P))``. So within a scan, where the uncertainty is small, the
bounded slow update stays as it was; after an hour's pause the first line counts almost fully, the next ones
average with it. The scale a line was scanned with is the one rendered for it (the host computes
ahead, so the line just measured may not have had the present estimate yet): its measurement is
taken relative to that scale, never counted twice. A line whose readback reached the position
sensor's full scale is never given to the tracker (the recorder does not score it: the ADC's end
code is not a position, and its length error would be the sensor's range, not the stage's).
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
    drift_per_s
        The fastest relative sensitivity drift expected (1/s; 0: the estimate never grows
        uncertain, every line is weighed by ``gain``).
    scatter
        Line-to-line scatter of one line's relative length error (noise, model error).
    variance
        Variance of the estimate (relative, squared) at ``t_s``.
    t_s
        When ``variance`` was last brought up to date (s, any monotonic clock; ``None``: not yet).
    """

    gain: float = 0.25
    max_step: float = 5e-4
    limit: float = 0.03
    outlier: float = 0.05
    drift_per_s: float = 0.0
    scatter: float = 5e-4
    variance: float = 0.0
    t_s: float | None = None
    scale: float = 1.0
    lines_used: int = 0
    lines_ignored: int = 0
    lines_too_fast: int = 0

    def restarted(self, age_s: float | None = 0.0, t_s: float | None = None) -> SensitivityTracker:
        """The same settings from scale 1, no lines counted (a new model: the scale is relative to one).

        Parameters
        ----------
        age_s
            How long before ``t_s`` the new model's data were measured: the estimate starts as
            uncertain as a drift at ``drift_per_s`` makes it over that time; ``None`` (unknown)
            starts it as uncertain as ``limit`` allows.
        t_s
            Now, on the clock later updates give.
        """
        sd = self.limit if age_s is None else min(self.limit, self.drift_per_s * max(0.0, age_s))
        return SensitivityTracker(
            gain=self.gain,
            max_step=self.max_step,
            limit=self.limit,
            outlier=self.outlier,
            drift_per_s=self.drift_per_s,
            scatter=self.scatter,
            variance=sd * sd,
            t_s=t_s,
        )

    def sd_at(self, t_s: float | None) -> float:
        """Standard deviation of the estimate at ``t_s``: it grows linearly with the time since
        the last line (a drift is a trend, not a random walk), at most to ``limit``."""
        sd = math.sqrt(self.variance)
        if t_s is not None and self.t_s is not None:
            sd += self.drift_per_s * max(0.0, t_s - self.t_s)
        return min(sd, self.limit)

    def update(
        self,
        measured_over_nominal: float,
        line_s: float = math.inf,
        min_line_s: float | None = None,
        *,
        rendered: float | None = None,
        t_s: float | None = None,
    ) -> float:
        """Take one line's ``measured / nominal``; return the scale.

        Parameters
        ----------
        measured_over_nominal
            The line's measured length over its nominal one.
        line_s
            The line's duration (s); one shorter than :data:`LINE_TOLERANCE` times
            ``min_line_s`` is not taken.
        min_line_s
            The shortest calibrated line (s; ``None``: no bound).
        rendered
            The scale the line was scanned with (``None``: the present one).
        t_s
            When the line ended (s, the clock of :meth:`restarted`; ``None``: no time passes).
        """
        if min_line_s is not None and line_s < LINE_TOLERANCE * min_line_s:
            self.lines_too_fast += 1
            return self.scale
        seen = self.scale if rendered is None else rendered
        err = seen * measured_over_nominal / self.scale - 1.0
        if not math.isfinite(err) or abs(err) > self.outlier:
            self.lines_ignored += 1
            return self.scale
        sd = self.sd_at(t_s)
        prior = sd * sd
        r = self.scatter * self.scatter
        k = prior / (prior + r)
        # more uncertain than the steady, bounded update: the filter's weight and a wider bound
        bound = max(self.max_step, 3.0 * sd)
        if k <= self.gain:
            k, bound = self.gain, self.max_step
        step = max(-bound, min(bound, k * err))
        self.scale = max(1.0 - self.limit, min(1.0 + self.limit, self.scale * (1.0 + step)))
        self.variance = (1.0 - k) ** 2 * prior + k * k * r
        if t_s is not None:
            self.t_s = t_s
        self.lines_used += 1
        return self.scale
