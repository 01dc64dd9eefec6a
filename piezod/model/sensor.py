"""The sensor path of an axis: a delay and a first-order lag between the stage and its readback.

A position sensor's demodulator, anti-alias filter and ADC pipeline show the controller the
position ``x`` late: the readback is ``y(t) = w(t - d)`` with ``w + tau w' = x`` (the effect
``delay`` of :mod:`piezod.model.registry`, with the simulated stage's order: lag, then delay).
This is a *measurement* artefact: the stage itself is where the drive put it. So the
correction is not in the drive but in the analysis of the readback: the position the stage
had at ``t`` is

    x(t) = y(t + d) + tau y'(t + d)

which needs the readback ``d`` *after* ``t`` -- available in a recording, never online. Left in,
the delay makes every loop look wider and its turning points rounded: a calibration fitted to
the raw readback puts that into the hysteresis and creep (and the drive then really is off),
and a verification scored on the raw readback reports an error the stage does not make.

A delay at the *drive* (the HV amplifier into the piezo capacitance) does move the stage late;
the family model's fitted drive lag (``lag_time_constant_s``) inverts its first-order part. From
readback alone the two are indistinguishable (a time shift commutes with a time-invariant
chain), so where a delay sits is a property of the hardware the scanner YAML states:
``extensions: {delay: {...}}`` is this sensor path.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import savgol_filter

from piezod.errors import ModelError
from piezod.model.registry import spec

F64 = NDArray[np.float64]

#: Effect ids (and their parameters) that belong to the sensor path, not the drive.
SENSOR_EFFECTS: dict[str, tuple[str, ...]] = {"delay": ("delay_s", "lag_time_constant_s")}


@dataclass(frozen=True)
class SensorPath:
    """Delay and first-order lag of the readback (both 0: the readback is the position).

    Attributes
    ----------
    delay_s
        Pure delay (s), inside the registry's physical bounds.
    lag_time_constant_s
        First-order lag (s), inside the registry's physical bounds.
    """

    delay_s: float = 0.0
    lag_time_constant_s: float = 0.0

    def __post_init__(self) -> None:
        for name in SENSOR_EFFECTS["delay"]:
            value = getattr(self, name)
            low, high = spec("delay").param(name).physical
            if not (math.isfinite(value) and low <= value <= high):
                raise ModelError(f"delay.{name} = {value!r} outside its physical range [{low}, {high}]")

    @classmethod
    def from_effects(cls, effects: Mapping[str, Mapping[str, float]]) -> SensorPath:
        """From ``{effect id: {parameter: value}}``: the sensor effects in it (others are ignored)."""
        fields: dict[str, float] = {}
        for effect, names in SENSOR_EFFECTS.items():
            for name, value in dict(effects.get(effect) or {}).items():
                if name not in names:
                    raise ModelError(f"effect {effect!r} has no parameter {name!r} ({', '.join(names)})")
                fields[name] = float(value)
        return cls(**fields)

    @property
    def identity(self) -> bool:
        """The readback is the position."""
        return self.delay_s == 0.0 and self.lag_time_constant_s == 0.0

    def align(self, t_s: F64, readback_um: F64) -> tuple[F64, F64]:
        """The stage's position at the times the readback allows: ``x(t) = y(t + d) + tau y'(t + d)``.

        The derivative is a local quadratic (Savitzky-Golay) over about ``4 tau``, so the
        sensor noise is not amplified by ``tau / dt``; a corner of the motion is rounded over
        that window.

        Parameters
        ----------
        t_s
            Sample times (s), uniform.
        readback_um
            The readback at those times.

        Returns
        -------
        t_s, position_um
            The times ``t`` with ``t + d`` inside the record (the last ``d`` of it is lost) and
            the position at them.
        """
        t = np.asarray(t_s, dtype=np.float64)
        y = np.asarray(readback_um, dtype=np.float64)
        if self.identity or t.size < 2:
            return t, y
        dt = float(np.median(np.diff(t)))
        z = y
        tau = self.lag_time_constant_s
        if tau > 0.0:
            half = self._lag_half_window(dt)
            window = min(2 * half + 1, y.size - (1 - y.size % 2))
            if window < 5:
                raise ModelError(f"too few samples ({y.size}) to undo a sensor lag of {tau:g} s")
            z = y + tau * savgol_filter(y, window, 2, deriv=1, delta=dt, mode="interp")
        keep = t + self.delay_s <= t[-1] + 1e-9 * dt
        tk = t[keep]
        x: F64 = np.interp(tk + self.delay_s, t, z)
        return tk, x

    def _lag_half_window(self, dt_s: float) -> int:
        """Half width (samples) of the local quadratic that differentiates the readback for the lag."""
        return max(2, math.ceil(2.0 * self.lag_time_constant_s / dt_s))

    def noise_gain(self, dt_s: float) -> float:
        """RMS of white readback noise after :meth:`align`, relative to before (away from the ends).

        Aligning interpolates between samples and adds a smoothed derivative, so the aligned
        readback carries less noise (a delay of half a sample: 1/sqrt(2)) or more (a lag of many
        samples) than the raw one. A noise floor measured on the raw readback is this factor off
        for residuals on the aligned one: on a 4 kS/s stage with a 2.5-sample delay the held-out
        residual of a calibrated model (2.1 nm) sat below the raw floor (2.4 nm), and no gain above
        the noise could be measured (docs/model-family.md 6.2bl).

        Parameters
        ----------
        dt_s
            The readback's sample interval (s).

        Returns
        -------
        float
            The aligned noise's RMS over the raw noise's (1 for the identity path): the RMS of the
            align filter's impulse response.
        """
        if self.identity:
            return 1.0
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ModelError(f"sample interval must be > 0 s, got {dt_s!r}")
        reach = math.ceil(self.delay_s / dt_s) + 2 * self._lag_half_window(dt_s)
        n = 4 * reach + 64
        impulse = np.zeros(n)
        impulse[n // 2] = 1.0
        _, x = self.align(np.arange(n, dtype=np.float64) * dt_s, impulse)
        return math.sqrt(float(x @ x))


__all__ = ["SENSOR_EFFECTS", "SensorPath"]
