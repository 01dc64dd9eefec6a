"""The effect registry: ids, parameters with units, physical bounds and their sources (pure data).

One table that the audit (which effect explains a residual, is a fitted value physical), the
runtime model (which extensions a scanner YAML may carry) and the tests of the simulated stage
share. It holds data only: no numpy, no piezod imports, so any layer may import it.

Where it lives and why: ``hil_sim`` must not import ``piezod`` (the simulator stands in for
hardware and must not share the controller's code paths, or a bug in one hides in the other), so
the simulator carries its own implementation of every effect (:mod:`hil_sim.effects`) and
``tests/test_effect_registry.py`` checks that its effect ids, parameter names and realistic
magnitudes agree with this registry. The audit and the runtime model import this module.

Bounds
------
``physical`` is what a real piezo scanner can plausibly show (a fit outside it is reported as
unphysical: it absorbs something else); ``realistic`` is the typical magnitude on a lab stage, the
range :func:`hil_sim.effects.random_effect` draws from. Units are in the parameter names.

==============  ==========================================  ===================================
id              parameters                                   physical bounds
==============  ==========================================  ===================================
drift           rate_nm_per_s                                -20 ... 20 nm/s
thermal         rate_pct_per_hour                            -10 ... 10 %/h
stiffness       sensitivity_pct_per_um                       -0.5 ... 0.5 %/um
polarity        negative_sensitivity_pct                     -50 ... 50 %
resonance       f0_hz, q                                     50 ... 1e5 Hz, 0.5 ... 200
delay           delay_s, lag_time_constant_s                 0 ... 50 ms, 0 ... 50 ms
saturation      x_sat_um                                     1 ... 1e4 um
creep           pct_per_decade                               0 ... 5 %/decade
asymmetry       asymmetry_pct                                -5 ... 5 %
==============  ==========================================  ===================================
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class ParamSpec:
    """One parameter of an effect.

    Attributes
    ----------
    name
        Parameter name, unit in the name (``rate_nm_per_s``).
    unit
        The unit spelled out (``nm/s``).
    physical
        ``(low, high)``: plausible on any real piezo scanner.
    realistic
        ``(low, high)`` of the magnitude on a typical lab stage (sign free where the physical
        range is signed): what the simulator injects to test detection and correction.
    """

    name: str
    unit: str
    physical: tuple[float, float]
    realistic: tuple[float, float]


@dataclass(frozen=True, slots=True)
class EffectSpec:
    """An effect the audit can find, the runtime model can correct and the simulator can inject.

    Attributes
    ----------
    id
        Effect id (the audit's cause name).
    description
        What it does, in one line.
    law
        The equation as the runtime model and the simulator apply it.
    params
        Parameters; the first is the primary one (``NAME=VALUE`` in ``piezod sim --effect``).
    sources
        Where the bounds come from.
    """

    id: str
    description: str
    law: str
    params: tuple[ParamSpec, ...]
    sources: tuple[str, ...]

    @property
    def primary(self) -> ParamSpec:
        """The primary parameter."""
        return self.params[0]

    def param(self, name: str) -> ParamSpec:
        """The parameter ``name`` (KeyError naming the effect if it has none)."""
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"effect {self.id!r} has no parameter {name!r} ({', '.join(self.names)})")

    @property
    def names(self) -> tuple[str, ...]:
        """Parameter names."""
        return tuple(p.name for p in self.params)


_THESIS = "Sweers, thesis (seed 000_47cf08558087f297), chapter 3"
_P885 = "PI P-885.91 stack recording (piezod/data/real/pi-p885), audit in docs/audit.md"

REGISTRY: dict[str, EffectSpec] = {
    e.id: e
    for e in (
        EffectSpec(
            "drift",
            "position drifts linearly in time (mount, thermal expansion)",
            "x + r t",
            (ParamSpec("rate_nm_per_s", "nm/s", (-20.0, 20.0), (0.2, 2.0)),),
            (
                f"{_THESIS}: 0.4 nm/s on the stack scanner",
                "commercial SPM drift specs: 0.1-10 nm/s after warm-up",
            ),
        ),
        EffectSpec(
            "thermal",
            "sensitivity changes slowly over the session (warm-up of scanner and amplifier)",
            "x (1 + r t / 360000)",
            (ParamSpec("rate_pct_per_hour", "%/h", (-10.0, 10.0), (0.5, 3.0)),),
            ("PZT d33 temperature coefficient ~0.1-0.3 %/K (vendor data sheets), a few K warm-up per hour",),
        ),
        EffectSpec(
            "stiffness",
            "sensitivity depends on the position (preload spring, load)",
            "x + k x^2 / 200",
            (ParamSpec("sensitivity_pct_per_um", "%/um", (-0.5, 0.5), (0.03, 0.15)),),
            (f"{_P885}: -0.16 %/um", f"{_THESIS}: length error linear in the offset"),
        ),
        EffectSpec(
            "polarity",
            "different sensitivity for negative voltages (partially depoled ceramic)",
            "V (1 + p / 100) for V < 0",
            (ParamSpec("negative_sensitivity_pct", "%", (-50.0, 50.0), (3.0, 10.0)),),
            ("PZT under reverse field below the coercive field: d33 drops by several % (Jaffe et al. 1971)",),
        ),
        EffectSpec(
            "resonance",
            "second-order mechanical resonance, rings at turning points",
            "x'' + (w0 / Q) x' + w0^2 x = w0^2 x_static",
            (
                ParamSpec("f0_hz", "Hz", (50.0, 1e5), (300.0, 1500.0)),
                ParamSpec("q", "1", (0.5, 200.0), (5.0, 30.0)),
            ),
            ("tube scanners 0.6-10 kHz, nPoint AFM stage 665 Hz (issue #9), loaded stacks above 1 kHz",),
        ),
        EffectSpec(
            "delay",
            "sensor or amplifier lag: a pure delay and a first-order lag",
            "x(t - d) through 1 / (1 + s tau)",
            (
                ParamSpec("delay_s", "s", (0.0, 0.05), (1e-4, 1e-3)),
                ParamSpec("lag_time_constant_s", "s", (0.0, 0.05), (1e-4, 1e-3)),
            ),
            (
                f"{_P885}: one sample (5 ms) sensor lag",
                "HV amplifiers into a piezo capacitance: poles at 0.1-5 kHz",
            ),
        ),
        EffectSpec(
            "saturation",
            "compression at large excursions",
            "x_sat tanh(x / x_sat)",
            (ParamSpec("x_sat_um", "um", (1.0, 1e4), (60.0, 150.0)),),
            ("domain switching saturates the strain near the coercive field (Jaffe et al. 1971)",),
        ),
        EffectSpec(
            "creep",
            "logarithmic / power-law creep after a change of the drive",
            "sum_i w_i (1 - exp(-t / tau_i)) of the drive step",
            (ParamSpec("pct_per_decade", "%/decade", (0.0, 5.0), (3.0, 5.0)),),
            ("Jung & Gweon, Rev. Sci. Instrum. 71 (2000): 1-2 %/decade", f"{_THESIS}: creep factor (3.5)"),
        ),
        EffectSpec(
            "asymmetry",
            "asymmetric static curvature: sensitivity rises with the voltage",
            "V + (a / 100) V^2 / (2 V_r)",
            (ParamSpec("asymmetry_pct", "%", (-5.0, 5.0), (0.2, 1.0)),),
            ("unipolar vs bipolar PZT response differs by ~1 % over the range (vendor data sheets)",),
        ),
    )
}

#: Effect ids, in the order above.
EFFECT_IDS: tuple[str, ...] = tuple(REGISTRY)


def spec(effect_id: str) -> EffectSpec:
    """The registry entry of ``effect_id`` (KeyError listing the known ids)."""
    try:
        return REGISTRY[effect_id]
    except KeyError:
        raise KeyError(f"unknown effect {effect_id!r} (one of {', '.join(EFFECT_IDS)})") from None


def is_physical(effect_id: str, name: str, value: float) -> bool:
    """Whether ``value`` of parameter ``name`` of ``effect_id`` lies inside its physical bounds."""
    low, high = spec(effect_id).param(name).physical
    return low <= value <= high


__all__ = ["EFFECT_IDS", "REGISTRY", "EffectSpec", "ParamSpec", "is_physical", "spec"]
