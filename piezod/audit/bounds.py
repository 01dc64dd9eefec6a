"""Physical plausibility bounds of every audit effect: a fit outside them is not a cause.

A least-squares term fitted to a residual it does not describe takes any value that lowers the
residual: a "stiffness" of -7e10 %/um, a "drift" of -1.4e4 nm/s, a "resonance" at 0.2 Hz.
Such a fit says that the term absorbed something else, not that the stage has that property.
Every effect therefore has bounds a real piezo stage, its amplifier and its sensor stay inside;
a candidate whose fitted magnitude lies outside them is reported as *implausible* and is never
named as the cause.

The bounds are deliberately wide (about 10x the largest values reported for the instrument
class) so that no real effect is rejected; they exclude only what no stage of the class does.
Sources (also in ``docs/audit.md``):

* creep of PZT actuators: about 1-2 % of the last step per decade of time (PI, *Piezoelectrics in
  Positioning*, "Creep"; Jung & Gweon, Rev. Sci. Instrum. 71, 1896 (2000)); bound 20 %/decade;
* drift of SPM stages and interferometers: thermal drift of SPM scanners is of order
  0.01-1 nm/s after warm-up, a few nm/s during warm-up (Marinello et al., Meas. Sci. Technol. 22,
  094016 (2011)); a HeNe interferometer in air drifts ~1e-6 of its path per kelvin; bound 50 nm/s;
* sensitivity vs temperature: d33 of PZT changes ~0.1-0.5 %/K (PI, "Temperature dependence"),
  a lab changes by less than a few K/h; bound 10 %/h;
* stiffness / position-dependent sensitivity: the open-loop nonlinearity of piezo stacks and
  tubes is ~10-15 % of the stroke (PI, "Nonlinearity"); bound: a sensitivity change of 30 %
  over the largest excursion of the data;
* polarity (sensitivity below 0 V): a partially depoled ceramic differs by up to tens of per cent;
  bound 50 %;
* saturation: ``x_sat`` below the largest excursion would compress the stroke by more than 24 %;
* resonance: the first mechanical resonance of piezo stages and actuators lies between ~100 Hz
  (loaded long-travel stages) and ~100 kHz (bare stacks) (PI P-611: 350 Hz, P-885: >70 kHz);
  a fitted ``f0`` must be above 5 Hz and above the 5th harmonic of the fastest scan (else the
  "resonance" is the scan itself), with ``0.5 <= Q <= 300``;
* delay / lag: sensors and HV amplifiers have bandwidths of >= 10 Hz (lag <= 16 ms) with a
  capacitive load; bound: delay + lag <= 0.1 s and <= 10 % of the shortest scan period.

The model package's effect registry (:mod:`piezod.model.registry`, issue #9) landed with
other ``physical`` bounds (drift 20 nm/s, creep 5 %/decade, stiffness 0.5 %/um absolute,
resonance >= 50 Hz, delay <= 50 ms). They are not used here yet: a 5 %/decade bound on a
*fitted* creep rejects the realistic 3-5 %/decade effects the checks hide, and the audit's
stiffness and resonance bounds depend on the data (excursion, scan harmonics). The two tables
are to be unified in the registry (fit bounds vs realistic magnitudes); until then the audit
reads its bounds through :func:`implausible` only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from piezod.audit.candidates import Scales


@dataclass(frozen=True)
class Bound:
    """Absolute bounds of one public parameter.

    Attributes
    ----------
    param
        Public name (unit in the name).
    lo, hi
        Plausible interval (inclusive).
    source
        Where the bound comes from.
    """

    param: str
    lo: float
    hi: float
    source: str


#: Absolute bounds per effect (relative ones, which depend on the data, are in :func:`implausible`).
BOUNDS: dict[str, tuple[Bound, ...]] = {
    "drift": (Bound("rate_nm_per_s", -50.0, 50.0, "SPM/interferometer drift <= a few nm/s (x10)"),),
    "thermal": (Bound("rate_pct_per_hour", -10.0, 10.0, "d33(T) ~0.1-0.5 %/K, lab <= a few K/h"),),
    "stiffness": (),
    "polarity": (Bound("negative_sensitivity_pct", -50.0, 50.0, "partially depoled ceramic"),),
    "resonance": (
        Bound("f0_hz", 5.0, 1e6, "first resonance of piezo stages 100 Hz - 100 kHz"),
        Bound("q", 0.5, 300.0, "mechanical Q of stages"),
    ),
    "delay": (
        Bound("delay_s", 0.0, 0.1, "sensor/amplifier bandwidth >= 10 Hz"),
        Bound("lag_time_constant_s", 0.0, 0.1, "sensor/amplifier bandwidth >= 10 Hz"),
    ),
    "saturation": (),
    "creep": (
        Bound("creep_pct_per_decade", 0.0, 20.0, "PZT creep 1-2 %/decade (x10)"),
        Bound("motion_pct_per_decade", -20.0, 20.0, "PZT creep 1-2 %/decade (x10)"),
    ),
}

#: Largest sensitivity change over the largest excursion for ``stiffness`` (fraction).
STIFFNESS_MAX_CHANGE = 0.30
#: Lowest harmonic of the fastest scan a resonance must lie above.
RESONANCE_HARMONIC = 5.0


def implausible(effect: str, params: dict[str, float], sc: Scales) -> str:
    """Empty when the fitted ``params`` of ``effect`` are physically plausible, else why not.

    Parameters
    ----------
    effect
        Audit id.
    params
        Public parameters of the fit.
    sc
        Scales of the training data (largest excursion, line frequencies, periods).
    """
    for b in BOUNDS.get(effect, ()):
        if b.param not in params:
            continue
        v = params[b.param]
        if not math.isfinite(v) or not (b.lo <= v <= b.hi):
            return f"implausible: {b.param} = {v:.4g} outside [{b.lo:g}, {b.hi:g}] ({b.source})"
    if effect == "stiffness":
        k = params.get("sensitivity_pct_per_um", 0.0)
        change = abs(k) / 100.0 * sc.x_scale_um
        if not math.isfinite(change) or change > STIFFNESS_MAX_CHANGE:
            return (
                f"implausible: sensitivity_pct_per_um = {k:.4g} changes the sensitivity by "
                f"{100.0 * change:.3g} % over the {sc.x_scale_um:.3g} um excursion "
                f"(open-loop nonlinearity of piezo stages is <= 15 %)"
            )
    elif effect == "saturation":
        xs = params.get("x_sat_um", math.inf)
        if xs < sc.x_scale_um:
            return (
                f"implausible: x_sat_um = {xs:.4g} below the largest excursion {sc.x_scale_um:.3g} um "
                "(the stroke would be compressed by more than 24 %)"
            )
    elif effect == "resonance":
        f0 = params.get("f0_hz", math.inf)
        f_min = RESONANCE_HARMONIC * sc.max_line_hz
        if f0 < f_min:
            return (
                f"implausible: f0_hz = {f0:.4g} is not above the {RESONANCE_HARMONIC:g}th harmonic of the "
                f"fastest scan ({f_min:.4g} Hz)"
            )
    elif effect == "delay":
        total = params.get("delay_s", 0.0) + params.get("lag_time_constant_s", 0.0)
        if total > 0.1 * sc.min_period_s:
            return (
                f"implausible: delay + lag = {total:.4g} s is more than 10 % of the shortest period "
                f"{sc.min_period_s:.4g} s"
            )
    return ""
