"""Optional physical effects of the simulated stage (the audit effect ids of docs/formats.md).

Every effect is off unless configured. Each one is a small frozen pydantic model with a
physical parameter (unit in the name); the first listed field is its *primary* parameter,
the one ``NAME=VALUE`` sets (``drift=0.4`` means 0.4 nm/s); the others are set with
``NAME.FIELD=VALUE`` (``resonance.q=25``) or in the ``simulation.effects`` section of the
scanner YAML.

=============  ==============================  =============================================
id             primary parameter               what it does
=============  ==============================  =============================================
drift          ``rate_nm_per_s``               position drifts linearly in time (mount, thermal)
thermal        ``rate_pct_per_hour``           sensitivity changes slowly over the session
stiffness      ``sensitivity_pct_per_um``      sensitivity depends on position (preload spring)
polarity       ``negative_sensitivity_pct``    different sensitivity for V < 0 (partial depoling)
resonance      ``f0_hz`` (and ``q``)           second-order mechanical resonance, rings at turns
delay          ``delay_s`` (and ``lag_...``)   sensor or amplifier lag: pure delay + first order
saturation     ``x_sat_um``                    ``x_sat tanh(x / x_sat)`` compression
=============  ==============================  =============================================

``creep=VALUE`` is accepted as well: it is not an effect but replaces the creep law of every
axis (percent per decade of time), to hide a "creep law wrong" finding from the audit.

The dynamic parts (resonance, delay line) are exact discretisations with explicit state, so
a block split anywhere gives the same samples.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from scipy.linalg import expm
from scipy.signal import lfilter

from hil_sim.errors import SimConfigError as ConfigError
from hil_sim.errors import SimModelError as ModelError

# ---------------------------------------------------------------------------------------------
# Configuration


class EffectConfig(BaseModel):
    """Base of the effect models: frozen, unknown keys rejected, no inf/nan."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    #: The audit id of the effect.
    name: ClassVar[str] = ""
    #: The field that ``NAME=VALUE`` sets.
    primary: ClassVar[str] = ""


class DriftEffect(EffectConfig):
    """Linear position drift (thesis section 3.3 measured 0.4 nm/s on the stack scanner)."""

    name: ClassVar[str] = "drift"
    primary: ClassVar[str] = "rate_nm_per_s"
    rate_nm_per_s: float = Field(ge=-1e4, le=1e4, description="drift velocity of the position (nm/s)")


class ThermalEffect(EffectConfig):
    """Sensitivity changing slowly over the session (warm-up of the scanner and amplifier).

    The whole displacement is multiplied by ``1 + r t / 3600`` (``r`` in 1/100 per hour), or
    with a time constant ``1 + r tau (1 - exp(-t / tau)) / 3600``: same initial rate, levelling
    off after ``tau``. ``t`` counts from the stage reset (the start of the session).
    """

    name: ClassVar[str] = "thermal"
    primary: ClassVar[str] = "rate_pct_per_hour"
    rate_pct_per_hour: float = Field(ge=-50, le=50, description="initial sensitivity change (%/h)")
    time_constant_s: float | None = Field(
        default=None, gt=0, le=1e7, description="levelling-off time (s); none = linear in time"
    )


class StiffnessEffect(EffectConfig):
    """Position-dependent stiffness (preload spring): local sensitivity ``1 + k x`` (``k`` in %/um).

    The displacement becomes ``x + k x^2 / 200``, so a scan of range ``R`` around ``x_o`` is
    ``R (1 + k x_o / 100)`` long: the length error is linear in the offset (thesis, chapter 3).
    """

    name: ClassVar[str] = "stiffness"
    primary: ClassVar[str] = "sensitivity_pct_per_um"
    sensitivity_pct_per_um: float = Field(
        ge=-2, le=2, description="relative sensitivity change per um of position (%/um)"
    )


class PolarityEffect(EffectConfig):
    """Different sensitivity for negative voltages (partially depoled ceramic).

    The voltage seen by the ceramic is ``V (1 + p / 100)`` for ``V < 0`` and ``V`` otherwise.
    """

    name: ClassVar[str] = "polarity"
    primary: ClassVar[str] = "negative_sensitivity_pct"
    negative_sensitivity_pct: float = Field(
        gt=-90, le=100, description="sensitivity change for V < 0 relative to V > 0 (%)"
    )


class ResonanceEffect(EffectConfig):
    """Second-order mechanical resonance ``x'' + (w0 / Q) x' + w0^2 x = w0^2 x_static``."""

    name: ClassVar[str] = "resonance"
    primary: ClassVar[str] = "f0_hz"
    f0_hz: float = Field(gt=0, le=1e6, description="undamped resonance frequency (Hz)")
    q: float = Field(default=10.0, ge=0.5, le=1e4, description="quality factor (dimensionless)")


class DelayEffect(EffectConfig):
    """Sensor or amplifier lag: a pure delay and/or a first-order lag.

    ``at: sensor`` delays the measured position (demodulator and ADC pipeline), ``at: drive``
    the voltage reaching the ceramic (amplifier driving the piezo capacitance).
    """

    name: ClassVar[str] = "delay"
    primary: ClassVar[str] = "delay_s"
    delay_s: float = Field(default=0.0, ge=0, le=10.0, description="pure delay (s)")
    lag_time_constant_s: float = Field(default=0.0, ge=0, le=10.0, description="first-order lag (s)")
    at: Literal["sensor", "drive"] = "sensor"

    @model_validator(mode="after")
    def _not_empty(self) -> DelayEffect:
        if self.delay_s == 0.0 and self.lag_time_constant_s == 0.0:
            raise ValueError("delay needs delay_s > 0 or lag_time_constant_s > 0")
        return self


class SaturationEffect(EffectConfig):
    """Compression at large excursions: ``x_sat tanh(x / x_sat)``."""

    name: ClassVar[str] = "saturation"
    primary: ClassVar[str] = "x_sat_um"
    x_sat_um: float = Field(gt=0, le=1e6, description="saturation scale (um)")


class CreepLawOverride(EffectConfig):
    """Not an effect: replaces the creep law of every axis (``creep=VALUE``)."""

    name: ClassVar[str] = "creep"
    primary: ClassVar[str] = "pct_per_decade"
    pct_per_decade: float | None = Field(
        default=None, ge=0, le=20, description="creep per decade of time (% of the motion)"
    )
    tau_min_s: float | None = Field(default=None, gt=0, description="shortest relaxation time (s)")
    tau_max_s: float | None = Field(default=None, gt=0, description="longest relaxation time (s)")
    per_decade: int | None = Field(default=None, ge=1, le=20, description="relaxation times per decade")
    drive: Literal["position", "voltage"] | None = None


#: The effects by audit id (the order in which the stage applies them is listed in :mod:`hil_sim.stage`).
EFFECTS: dict[str, type[EffectConfig]] = {
    cls.name: cls
    for cls in (
        DriftEffect,
        ThermalEffect,
        StiffnessEffect,
        PolarityEffect,
        ResonanceEffect,
        DelayEffect,
        SaturationEffect,
    )
}
#: Effect ids (the audit ids of docs/formats.md that are physical effects).
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECTS)
#: Everything ``NAME=VALUE`` accepts.
SPEC_MODELS: dict[str, type[EffectConfig]] = {**EFFECTS, CreepLawOverride.name: CreepLawOverride}


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    field = ".".join(str(p) for p in err["loc"]) or "(value)"
    msg = "unknown field" if err["type"] == "extra_forbidden" else err["msg"]
    return f"{field}: {msg}"


def parse_effect_spec(text: str) -> tuple[str, str, str]:
    """Split ``NAME=VALUE`` or ``NAME.FIELD=VALUE`` into ``(name, field, value)``.

    The field of ``NAME=VALUE`` is the effect's primary parameter.

    Raises
    ------
    ConfigError
        Naming the spec when it is malformed or the name / field is unknown.
    """
    head, sep, value = text.partition("=")
    head, value = head.strip(), value.strip()
    if not sep or not head or not value:
        raise ConfigError(f"effect {text!r}: expected NAME=VALUE or NAME.FIELD=VALUE")
    name, _, field = head.partition(".")
    model = SPEC_MODELS.get(name)
    if model is None:
        raise ConfigError(f"effect {text!r}: unknown effect {name!r} (one of {', '.join(SPEC_MODELS)})")
    field = field or model.primary
    if field not in model.model_fields:
        raise ConfigError(
            f"effect {text!r}: {name} has no field {field!r} (fields: {', '.join(model.model_fields)})"
        )
    return name, field, value


def build_effect(name: str, fields: Mapping[str, Any], source: str | None = None) -> EffectConfig:
    """Validate the fields of effect ``name``.

    Parameters
    ----------
    name
        Effect id (or ``creep``).
    fields
        Field values (strings are converted).
    source
        What to name in the error (defaults to the effect name).

    Raises
    ------
    ConfigError
        ``effect <source>: <field>: <reason>``.
    """
    model = SPEC_MODELS.get(name)
    if model is None:
        raise ConfigError(f"unknown effect {name!r} (one of {', '.join(SPEC_MODELS)})")
    try:
        return model.model_validate(dict(fields))
    except ValidationError as exc:
        raise ConfigError(f"effect {source or name}: {_first_error(exc)}") from exc


def effect_spec(effect: EffectConfig) -> list[str]:
    """The ``NAME.FIELD=VALUE`` strings reproducing ``effect`` (inverse of :func:`parse_effect_spec`)."""
    return [
        f"{effect.name}.{key}={value}"
        for key, value in effect.model_dump(exclude_none=True).items()
        if key in type(effect).model_fields
    ]


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.uniform(low, high) * rng.choice((-1.0, 1.0)))


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(np.exp(rng.uniform(np.log(low), np.log(high))))


def random_effect(name: str, rng: np.random.Generator) -> EffectConfig:
    """Draw effect ``name`` with a realistic, clearly detectable magnitude and a random sign.

    Ranges (for the ~37 um default stage scanned for minutes): drift 0.2-2 nm/s; thermal
    0.5-3 %/h; stiffness 0.03-0.15 %/um; polarity 3-10 %; resonance 300-1500 Hz with Q 5-30;
    delay 0.1-1 ms at the sensor; saturation x_sat 60-150 um; creep 3-5 %/decade (2-3x the
    default stage's law).

    Parameters
    ----------
    name
        Effect id (or ``creep``).
    rng
        Random generator (the draw is deterministic given its state).
    """
    draws: dict[str, Any]
    if name == "drift":
        draws = {"rate_nm_per_s": _signed(rng, 0.2, 2.0)}
    elif name == "thermal":
        draws = {"rate_pct_per_hour": _signed(rng, 0.5, 3.0)}
    elif name == "stiffness":
        draws = {"sensitivity_pct_per_um": _signed(rng, 0.03, 0.15)}
    elif name == "polarity":
        draws = {"negative_sensitivity_pct": _signed(rng, 3.0, 10.0)}
    elif name == "resonance":
        draws = {"f0_hz": _log_uniform(rng, 300.0, 1500.0), "q": float(rng.uniform(5.0, 30.0))}
    elif name == "delay":
        draws = {"delay_s": _log_uniform(rng, 1e-4, 1e-3)}
    elif name == "saturation":
        draws = {"x_sat_um": float(rng.uniform(60.0, 150.0))}
    elif name == "creep":
        draws = {"pct_per_decade": float(rng.uniform(3.0, 5.0))}
    else:
        raise ConfigError(f"unknown effect {name!r} (one of {', '.join(SPEC_MODELS)})")
    return build_effect(name, draws)


# ---------------------------------------------------------------------------------------------
# Dynamic parts: exact discrete second-order resonance and a delay line


@dataclass(frozen=True, slots=True, eq=False)
class ResonanceState:
    """State of the resonance after a sample.

    Attributes
    ----------
    position_um, velocity_um_per_s
        Mechanical state per channel, shape ``(channels,)``.
    input_um
        Last quasi-static input per channel, shape ``(channels,)``.
    """

    position_um: NDArray[np.float64]
    velocity_um_per_s: NDArray[np.float64]
    input_um: NDArray[np.float64]


def resonance_rest_state(position_um: ArrayLike) -> ResonanceState:
    """At rest at ``position_um`` (per channel)."""
    p = np.array(position_um, dtype=np.float64, ndmin=1)
    return ResonanceState(position_um=p.copy(), velocity_um_per_s=np.zeros_like(p), input_um=p.copy())


@dataclass(frozen=True, slots=True)
class _ResonanceDiscrete:
    phi: tuple[tuple[float, float], tuple[float, float]]
    phi_inv: tuple[tuple[float, float], tuple[float, float]]
    gamma0_minus_gamma1: tuple[float, float]
    gamma1: tuple[float, float]
    bd: tuple[float, float]
    b: tuple[float, float, float]
    a: tuple[float, float, float]


def _damped_rad_per_s(f0_hz: float, q: float) -> float:
    """The resonator's damped angular frequency (rad/s)."""
    return 2.0 * math.pi * f0_hz * math.sqrt(max(0.0, 1.0 - 1.0 / (4.0 * q * q)))


@functools.lru_cache(maxsize=64)
def _resonance_discrete(f0_hz: float, q: float, dt_s: float) -> _ResonanceDiscrete:
    """First-order-hold discretisation of the resonator (exact for input linear between samples).

    ``s_{k+1} = Phi s_k + (G0 - G1) u_k + G1 u_{k+1}``; with ``xi = s - G1 u`` the system
    ``xi_{k+1} = Phi xi_k + Bd u_k``, ``y = xi_0 + G1_0 u`` has the transfer function ``b / a``
    that :func:`scipy.signal.lfilter` runs.
    """
    w0 = 2.0 * math.pi * f0_hz
    w_d = _damped_rad_per_s(f0_hz, q)
    if w_d * dt_s >= 0.9 * math.pi:
        raise ModelError(
            f"resonance f0_hz={f0_hz:g} needs a sample rate above {2.0 * w_d / (0.9 * 2.0 * math.pi):.4g} Hz"
            f" (got {1.0 / dt_s:.4g} Hz)"
        )
    m = np.zeros((4, 4))
    m[0, 1] = 1.0
    m[1, 0] = -(w0**2)
    m[1, 1] = -w0 / q
    m[1, 2] = w0**2
    m[2, 3] = 1.0
    e = expm(m * dt_s)
    phi = e[:2, :2]
    g0 = e[:2, 2]
    g1 = e[:2, 3] / dt_s
    bd = phi @ g1 + g0 - g1
    d = g1[0]
    tr = phi[0, 0] + phi[1, 1]
    det = phi[0, 0] * phi[1, 1] - phi[0, 1] * phi[1, 0]
    b = (d, bd[0] - d * tr, phi[0, 1] * bd[1] - phi[1, 1] * bd[0] + d * det)
    phi_inv = np.linalg.inv(phi)
    return _ResonanceDiscrete(
        phi=((phi[0, 0], phi[0, 1]), (phi[1, 0], phi[1, 1])),
        phi_inv=((phi_inv[0, 0], phi_inv[0, 1]), (phi_inv[1, 0], phi_inv[1, 1])),
        gamma0_minus_gamma1=(g0[0] - g1[0], g0[1] - g1[1]),
        gamma1=(g1[0], g1[1]),
        bd=(bd[0], bd[1]),
        b=(float(b[0]), float(b[1]), float(b[2])),
        a=(1.0, float(-tr), float(det)),
    )


def resonance_step(
    effect: ResonanceEffect, x_um: NDArray[np.float64], dt_s: float, state: ResonanceState
) -> tuple[NDArray[np.float64], ResonanceState]:
    """Pass the quasi-static position through the resonator (exact, state carried).

    Parameters
    ----------
    effect
        Resonance parameters.
    x_um
        Quasi-static position, shape ``(channels, n)``, ``n >= 1``.
    dt_s
        Sample interval (s).
    state
        State before the block.

    Returns
    -------
    position_um : ndarray
        Dynamic position, shape ``(channels, n)``.
    state : ResonanceState
        State after the block.
    """
    w_d = _damped_rad_per_s(effect.f0_hz, effect.q)
    if w_d * dt_s >= 0.5 * math.pi:
        # a step too long for the discretisation's state recovery (an idle hold of the board):
        # the same first-order hold on sub-steps, the input linear between the samples
        k = math.ceil(w_d * dt_s / (0.25 * math.pi))
        xs = np.concatenate([np.asarray(state.input_um, dtype=np.float64)[:, None], x_um], axis=1)
        frac = np.arange(1, k + 1, dtype=np.float64) / k
        up = xs[:, :-1, None] + (xs[:, 1:, None] - xs[:, :-1, None]) * frac
        y_up, after = resonance_step(effect, up.reshape(x_um.shape[0], -1), dt_s / k, state)
        return y_up[:, k - 1 :: k], after
    c = _resonance_discrete(effect.f0_hz, effect.q, dt_s)
    (p00, p01), (p10, p11) = c.phi
    p0, v0, u0 = state.position_um, state.velocity_um_per_s, state.input_um
    # xi of the first sample of the block, from the physical state at the sample before it.
    xi0 = p00 * p0 + p01 * v0 + c.gamma0_minus_gamma1[0] * u0
    xi1 = p10 * p0 + p11 * v0 + c.gamma0_minus_gamma1[1] * u0
    s1 = xi0
    s2 = p01 * xi1 - p11 * xi0
    zi = np.stack([s1, s2], axis=-1)
    y, zf = lfilter(c.b, c.a, x_um, axis=-1, zi=zi)
    # zf is xi of the sample after the block; step it back to the physical state at the last sample.
    n_xi0 = zf[:, 0]
    n_xi1 = (zf[:, 1] + p11 * zf[:, 0]) / p01
    u_last = x_um[:, -1]
    r0 = n_xi0 - c.bd[0] * u_last
    r1 = n_xi1 - c.bd[1] * u_last
    (q10, q11) = c.phi_inv[1]
    last_xi1 = q10 * r0 + q11 * r1
    # The position is taken from the filter output itself (no round trip through Phi^-1).
    new = ResonanceState(
        position_um=y[:, -1].copy(),
        velocity_um_per_s=last_xi1 + c.gamma1[1] * u_last,
        input_um=u_last.copy(),
    )
    out: NDArray[np.float64] = y
    return out, new


@dataclass(frozen=True, slots=True, eq=False)
class DelayState:
    """History of a pure delay line.

    Attributes
    ----------
    times_s
        Times of the kept samples (s), ascending, shape ``(m,)``.
    values
        Kept samples per channel, shape ``(channels, m)``.
    """

    times_s: NDArray[np.float64]
    values: NDArray[np.float64]


def delay_rest_state(value: ArrayLike, time_s: float, delay_s: float) -> DelayState:
    """A delay line that has seen the constant ``value`` (per channel) up to ``time_s``."""
    v = np.array(value, dtype=np.float64, ndmin=1)
    times = np.array([time_s - delay_s - 1.0, time_s])
    return DelayState(times_s=times, values=np.repeat(v[:, None], 2, axis=1))


def delay_step(
    delay_s: float, x: NDArray[np.float64], t_s: NDArray[np.float64], state: DelayState
) -> tuple[NDArray[np.float64], DelayState]:
    """Delay ``x`` sampled at ``t_s`` by ``delay_s``, interpolating linearly between samples.

    Exact for a signal linear between samples, for any (also changing) sample interval.

    Parameters
    ----------
    delay_s
        The delay (s), >= 0.
    x
        Samples, shape ``(channels, n)``, ``n >= 1``.
    t_s
        Their times (s), ascending, all after ``state.times_s[-1]``.
    state
        History before the block.
    """
    times = np.concatenate([state.times_s, t_s])
    values = np.concatenate([state.values, x], axis=1)
    query = t_s - delay_s
    out = np.empty_like(x)
    for ch in range(x.shape[0]):
        out[ch] = np.interp(query, times, values[ch])
    keep = max(0, int(np.searchsorted(times, t_s[-1] - delay_s, side="right")) - 1)
    return out, DelayState(times_s=times[keep:].copy(), values=values[:, keep:].copy())
