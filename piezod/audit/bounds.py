"""Physical plausibility bounds of every audit effect: a fit outside them is not a cause.

A least-squares term fitted to a residual it does not describe takes any value that lowers the
residual: a "stiffness" of -7e10 %/um, a "drift" of -1.4e4 nm/s, a "resonance" at 0.2 Hz.
Such a fit says that the term absorbed something else, not that the stage has that property.
Every effect therefore has bounds a real piezo stage, its amplifier and its sensor stay inside;
a candidate whose fitted magnitude lies outside them is reported as *implausible* and is never
named as the cause.

The bounds exclude only what no stage of the class does. Sources (also in ``docs/audit.md``):

* creep of PZT actuators: about 1-2 % of the last step per decade of time (PI, *Piezoelectrics in
  Positioning*, "Creep"; Jung & Gweon, Rev. Sci. Instrum. 71, 1896 (2000)); bound 20 %/decade;
* drift, thermal, polarity, resonance ``f0`` and ``Q``, delay and lag: the effect registry's
  physical intervals and sources (20 nm/s; 10 %/h; 50 %; 50 Hz - 100 kHz, 0.5 - 200; 50 ms);
* stiffness / position-dependent sensitivity: the open-loop nonlinearity of piezo stacks and
  tubes is ~10-15 % of the stroke (PI, "Nonlinearity"); bound: a sensitivity change of 30 %
  over the largest excursion of the data;
* saturation: ``x_sat`` below the largest excursion would compress the stroke by more than 24 %;
* resonance, relative: above the 5th harmonic of the fastest scan (else the "resonance" is the
  scan itself);
* delay, relative: delay + lag <= 10 % of the shortest scan period.

Where the audit and the model package's effect registry (:mod:`piezod.model.registry`) name
the same parameter of the same effect, the registry's ``physical`` interval *is* the audit's
bound (:data:`REGISTRY_SHARED`, imported, not copied): drift, thermal, polarity, resonance
(``f0_hz``, ``q``) and delay (``delay_s``, ``lag_time_constant_s``). The rest stays the audit's
own, because it is a different quantity: the audit's creep is ``creep_pct_per_decade`` of its
log-creep operator and ``motion_pct_per_decade`` of (3.8), not the registry's ``pct_per_decade``
of the drive step (a fitted creep also absorbs lag and drift, so its bound is the literature's
1-2 %/decade x10); stiffness and saturation are bounded relative to the data's largest excursion
(a 10 % nonlinearity is 0.01 %/um on a 1 mm stroke and 10 %/um on a 1 um ceramic disc), where the
registry's absolute %/um and um intervals presuppose a lab stage's stroke. The resonance must
also lie above the scan's harmonics, the delay below 10 % of the shortest period.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from piezod.audit.candidates import Scales
from piezod.model import registry


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


#: (effect, parameter) whose bound is the registry's ``physical`` interval.
REGISTRY_SHARED: tuple[tuple[str, str], ...] = (
    ("drift", "rate_nm_per_s"),
    ("thermal", "rate_pct_per_hour"),
    ("polarity", "negative_sensitivity_pct"),
    ("resonance", "f0_hz"),
    ("resonance", "q"),
    ("delay", "delay_s"),
    ("delay", "lag_time_constant_s"),
)


def _from_registry(effect: str, name: str) -> Bound:
    s = registry.spec(effect)
    lo, hi = s.param(name).physical
    return Bound(name, lo, hi, "effect registry: " + "; ".join(s.sources))


#: Absolute bounds per effect (relative ones, which depend on the data, are in :func:`implausible`).
BOUNDS: dict[str, tuple[Bound, ...]] = {
    effect: tuple(_from_registry(e, n) for e, n in REGISTRY_SHARED if e == effect)
    for effect in ("drift", "thermal", "stiffness", "polarity", "resonance", "delay", "saturation")
}
BOUNDS["creep"] = (
    Bound("creep_pct_per_decade", 0.0, 20.0, "PZT creep 1-2 %/decade of the last step (x10)"),
    Bound("motion_pct_per_decade", -20.0, 20.0, "PZT creep 1-2 %/decade of the last step (x10)"),
)

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
