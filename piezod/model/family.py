"""The model family: drive lag -> hysteresis law -> creep spectrum -> static map, each exactly invertible.

Per sample ``n`` (interval ``dt``)::

    V_c[n] = a V_c[n-1] + (1 - a) V[n],  a = exp(-dt / tau_lag)     amplifier pole (tau_lag = 0: none)
    x_h    = H(V_c)                                               Coleman-Hodgdon ODE (2.21) or
                                                                  Prandtl-Ishlinskii (piezod.model.play),
                                                                  generalised play (piezod.model.gplay;
                                                                  its memory may relax: after_effect,
                                                                  piezod.model.aftereffect), Bouc-Wen or
                                                                  domain-wall (piezod.model.domainwall;
                                                                  may relax too)
    x_c    = (1 + W) x_h + sum_i w_i e_i                          creep spectrum (driver: position):
                                                                  free non-negative weights on tau_i
    x_c    = x_h + s (W V_c + sum_i w_i e_i)                      or (driver: voltage) the creep of the
                                                                  drive voltage, s = the law's slope
    x      = x_c + k x_c^2 / 200                                  static stiffness map (k in %/um)

The inverse runs the chain backwards, each part exact per sample and vectorised over a block:
the static map by the quadratic formula, the creep by the modal filters of
:mod:`piezod.model.dynamic` (any non-negative weights), the hysteresis by the Lambert W step
(:func:`piezod.model.ode.hysteresis_inverse_step`) or the play inverse
(:func:`piezod.model.play.play_inverse`), the lag by its lead filter
``V[n] = (V_c[n] - a V_c[n-1]) / (1 - a)`` (an FIR: stable for any ``tau_lag``).

The creep is driven by the hysteretic position (the cascade "hysteresis, then linear
viscoelastic creep") or by the drive voltage (``creep_driver="voltage"``: the ceramic's
polarisation creeps under the applied field; ``e_i`` are then deviations of the filtered voltage
from ``V_c``, in V, and ``s`` is the law's static slope ``b (rho0 + sum w)`` or ``b``). Both use
the same first-order-hold discretisation ``e_i[n] = a_i e_i[n-1] - (1 - b0_i) (d[n] - d[n-1])``.
With the voltage driver the creep at sample ``n`` is affine in ``V_c[n]``, so the inverse solves
per sample ``H_state(V_c) + g V_c = x_c - s sum_i w_i (a_i e_i[n-1] + (1 - b0_i) V_c[n-1])`` with
``g = s sum_i w_i b0_i >= 0``: for Prandtl-Ishlinskii a play law with slope ``rho0 + g / b``
(the play inverse, exact), for Coleman-Hodgdon a monotone scalar equation (bracketed Newton).
This inverse is sequential (one sample's voltage moves the next sample's creep): a compiled
per-sample loop of bounded cost (:mod:`piezod.model.kernels`, tens of ns per sample).

The weights are data-driven (:mod:`piezod.calibrate_family` fits them by
regularised non-negative least squares), so the spectrum is whatever the stage shows: a log
law, a power law, or a few dominant times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import lfilter

from piezod.errors import ModelError
from piezod.model import kernels
from piezod.model.aftereffect import AfterEffect, relax
from piezod.model.boucwen import (
    BoucWenParams,
    BoucWenState,
    boucwen_forward,
    boucwen_inverse,
    boucwen_rest_state,
    boucwen_state_at,
)
from piezod.model.boucwen import creep_loop as bw_creep_loop
from piezod.model.domainwall import (
    DomainWallParams,
    DomainWallState,
    domainwall_forward,
    domainwall_hold,
    domainwall_inverse,
    domainwall_rest_state,
    domainwall_state_at,
)
from piezod.model.domainwall import creep_loop as dw_creep_loop
from piezod.model.dynamic import MAX_TOTAL_CREEP, _creep_forward, _creep_inverse, discretise
from piezod.model.gplay import GeneralisedPlayParams, gplay_forward, gplay_rest_state, gplay_state_at
from piezod.model.ode import HysteresisState, hysteresis_inverse_step, hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams, readonly_array
from piezod.model.play import (
    PlayParams,
    PlayState,
    play_forward,
    play_inverse,
    play_rest_state,
    play_state_at,
)

F64 = NDArray[np.float64]
HysteresisLaw = HysteresisParams | PlayParams | GeneralisedPlayParams | BoucWenParams | DomainWallParams
CREEP_DRIVERS = ("position", "voltage")
#: Largest static stiffness map the model accepts (%/um): ``x + k x^2 / 200`` changes the
#: sensitivity by ``k`` % per um, so 5 %/um is far beyond any stage (fits are bounded by it).
MAX_STIFFNESS_PCT_PER_UM = 5.0
#: Creep drivers whose per-sample inverse fits the streaming budget (<= 150 ns per sample and axis,
#: ``piezod bench inverse``): both, since the voltage-driven loop is compiled (:mod:`piezod.model.kernels`).
REALTIME_CREEP_DRIVERS = ("position", "voltage")
LawState = HysteresisState | PlayState | BoucWenState | DomainWallState


@dataclass(frozen=True)
class CreepSpectrum:
    """Non-negative weights ``w_i`` (fractions of the hysteretic motion) on relaxation times ``tau_i``.

    Attributes
    ----------
    taus: tuple of float
        Relaxation times (s), ascending, > 0.
    w: tuple of float
        Weights, >= 0, ``sum w < 0.9``.
    """

    taus: tuple[float, ...]
    w: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.taus) != len(self.w) or len(self.taus) < 1:
            raise ModelError("a creep spectrum needs relaxation times, one weight each")
        if not all(math.isfinite(t) and t > 0 for t in self.taus) or list(self.taus) != sorted(self.taus):
            raise ModelError("creep relaxation times must be finite, > 0 and ascending")
        if not all(math.isfinite(x) and x >= 0 for x in self.w):
            raise ModelError("creep weights must be finite and >= 0")
        if sum(self.w) >= MAX_TOTAL_CREEP:
            raise ModelError(f"total creep {sum(self.w):.4g} must stay below {MAX_TOTAL_CREEP}")

    @classmethod
    def log_spaced(
        cls, tau_min_s: float, tau_max_s: float, per_decade: int, weights: ArrayLike
    ) -> CreepSpectrum:
        """Weights on ``per_decade`` log-spaced times per decade from ``tau_min_s`` to ``tau_max_s``."""
        count = max(2, round(math.log10(tau_max_s / tau_min_s) * per_decade) + 1)
        taus = np.logspace(math.log10(tau_min_s), math.log10(tau_max_s), count)
        w = np.broadcast_to(np.asarray(weights, dtype=np.float64), taus.shape)
        return cls(tuple(map(float, taus)), tuple(map(float, w)))

    def pruned(self, min_weight: float = 1e-9) -> CreepSpectrum:
        """The elements that creep (weight above ``min_weight``); at least one is kept.

        Elements of zero weight contribute nothing but make the inverse's secular equation
        degenerate (a root on a pole), so a fitted spectrum is pruned before use.
        """
        keep = [i for i, w in enumerate(self.w) if w > min_weight]
        if not keep:
            return CreepSpectrum((self.taus[0],), (0.0,))
        return CreepSpectrum(tuple(self.taus[i] for i in keep), tuple(self.w[i] for i in keep))

    @cached_property
    def taus_s(self) -> F64:
        """Relaxation times (s)."""
        return readonly_array(self.taus)

    @cached_property
    def weights(self) -> F64:
        """Weights."""
        return readonly_array(self.w)

    @property
    def total_creep(self) -> float:
        """``W = sum w``."""
        return float(sum(self.w))

    def step_response(self, t_s: ArrayLike) -> F64:
        """Creep after a unit step of the hysteretic position."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        out: F64 = self.weights @ -np.expm1(-t[None, :] / self.taus_s[:, None])
        return out


@dataclass(frozen=True)
class FamilyParams:
    """Frozen parameters of one axis's model of the family.

    Attributes
    ----------
    hysteresis
        The rate-independent law: Coleman-Hodgdon (:class:`HysteresisParams`),
        Prandtl-Ishlinskii (:class:`PlayParams`), the generalised play (Preisach) law
        (:class:`piezod.model.gplay.GeneralisedPlayParams`), Bouc-Wen
        (:class:`piezod.model.boucwen.BoucWenParams`) or the domain-wall law
        (:class:`piezod.model.domainwall.DomainWallParams`).
    creep
        The creep spectrum (elements of zero weight are dropped).
    lag_time_constant_s
        Drive pole (s), >= 0.
    stiffness_pct_per_um
        Static map ``x + k x^2 / 200`` (%/um).
    creep_driver
        ``position`` (the creep of the hysteretic position) or ``voltage`` (of the drive voltage).
    offset_um
        Where the position sensor reads the model's zero (um), added after the static map: the
        calibration's frame is fitted with an offset per scan (or one for the sensor), and the
        runtime parts around the model, which act on the absolute position, were fitted in the
        sensor's frame (:func:`piezod.calibrate_family.fit_family` sets it).
    after_effect
        The after-effect of the generalised play law's memory or of the domain-wall law's walls
        (:mod:`piezod.model.aftereffect`): it relaxes towards the voltage (the anhysteretic curve)
        at rest. None: the law is rate independent.
    """

    hysteresis: HysteresisLaw
    creep: CreepSpectrum
    lag_time_constant_s: float = 0.0
    stiffness_pct_per_um: float = 0.0
    creep_driver: str = "position"
    offset_um: float = 0.0
    after_effect: AfterEffect | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "creep", self.creep.pruned())
        if self.after_effect is not None and not (
            isinstance(self.hysteresis, GeneralisedPlayParams | DomainWallParams)
            and self.creep_driver == "voltage"
        ):
            # a creep of the hysteretic position would follow the relaxing memory: no closed-form hold
            raise ModelError(
                "an after-effect needs the generalised play or domain-wall law with voltage-driven creep"
            )
        if self.creep_driver not in CREEP_DRIVERS:
            raise ModelError(
                f"creep_driver must be one of {', '.join(CREEP_DRIVERS)}, got {self.creep_driver!r}"
            )
        if not math.isfinite(self.offset_um):
            raise ModelError(f"offset_um must be finite, got {self.offset_um!r}")
        if not (math.isfinite(self.lag_time_constant_s) and 0.0 <= self.lag_time_constant_s <= 1.0):
            raise ModelError(f"lag_time_constant_s must lie in [0, 1] s, got {self.lag_time_constant_s!r}")
        limit = MAX_STIFFNESS_PCT_PER_UM
        if not (math.isfinite(self.stiffness_pct_per_um) and abs(self.stiffness_pct_per_um) <= limit):
            raise ModelError(
                f"stiffness_pct_per_um must lie in [-{limit:g}, {limit:g}], got {self.stiffness_pct_per_um!r}"
            )

    @property
    def law(self) -> str:
        """``coleman-hodgdon``, ``prandtl-ishlinskii``, ``generalised-play``, ``bouc-wen`` or
        ``domain-wall``."""
        if isinstance(self.hysteresis, DomainWallParams):
            return "domain-wall"
        if isinstance(self.hysteresis, BoucWenParams):
            return "bouc-wen"
        if isinstance(self.hysteresis, GeneralisedPlayParams):
            return "generalised-play"
        return "prandtl-ishlinskii" if isinstance(self.hysteresis, PlayParams) else "coleman-hodgdon"

    @property
    def law_slope_um_per_v(self) -> float:
        """``s``: the law's rest slope (um/V; at 0 V for the generalised play law), the scale of
        voltage-driven creep."""
        h = self.hysteresis
        if isinstance(h, GeneralisedPlayParams | BoucWenParams | DomainWallParams):
            return h.b_um_per_v
        return h.b_um_per_v * (h.total_weight if isinstance(h, PlayParams) else 1.0)

    @property
    def b_um_per_v(self) -> float:
        """Sensitivity of the hysteresis law (um/V)."""
        return self.hysteresis.b_um_per_v

    @property
    def static_sensitivity_um_per_v(self) -> float:
        """Slope of the rest position over the voltage near 0 V (um/V)."""
        return self.law_slope_um_per_v * (1.0 + self.creep.total_creep)


@dataclass(frozen=True, slots=True, eq=False)
class FamilyState:
    """State after a sample.

    Attributes
    ----------
    voltage_v
        Commanded voltage of the last sample (V).
    drive_v
        Voltage at the ceramic after the lag (V).
    law
        State of the hysteresis law (at ``drive_v``).
    creep_um
        Creep element deviations ``e_i`` (um for the position driver, V for the voltage driver).
    creep_position_um
        ``x_c``: position before the static map (um).
    position_um
        ``x``: the model's position (um).
    relax_pending
        Samples since the after-effect last relaxed the law's memory.
    """

    voltage_v: float
    drive_v: float
    law: LawState
    creep_um: F64
    creep_position_um: float
    position_um: float
    relax_pending: int = 0


def _static(params: FamilyParams, xc: F64) -> F64:
    kappa = params.stiffness_pct_per_um / 200.0
    if kappa == 0.0 and params.offset_um == 0.0:
        return xc
    out: F64 = xc + kappa * xc * xc + params.offset_um
    return out


def _static_inverse(params: FamilyParams, x: F64) -> F64:
    kappa = params.stiffness_pct_per_um / 200.0
    x = x - params.offset_um
    if kappa == 0.0:
        return x
    disc = np.maximum(1.0 + 4.0 * kappa * x, 0.0)
    out: F64 = 2.0 * x / (1.0 + np.sqrt(disc))
    return out


def _law_rest(h: HysteresisLaw, v: float) -> LawState:
    if isinstance(h, DomainWallParams):
        return domainwall_rest_state(h, v)
    if isinstance(h, BoucWenParams):
        return boucwen_rest_state(h, v)
    if isinstance(h, GeneralisedPlayParams):
        return gplay_rest_state(h, v)
    return play_rest_state(h, v) if isinstance(h, PlayParams) else relaxed_state(h, v)


def family_rest_state(params: FamilyParams, voltage_v: float = 0.0) -> FamilyState:
    """Rested at ``voltage_v`` for ever: lag settled, hysteresis relaxed, creep relaxed."""
    v = float(voltage_v)
    if not math.isfinite(v):
        raise ModelError(f"rest voltage must be finite, got {voltage_v!r}")
    law = _law_rest(params.hysteresis, v)
    xc = _relaxed_creep_position(params, law.position_um, v)
    x = float(_static(params, np.array([xc]))[0])
    return FamilyState(v, v, law, np.zeros(len(params.creep.taus)), xc, x)


def _relaxed_creep_position(params: FamilyParams, xh: float, drive_v: float) -> float:
    """``x_c`` with every creep element relaxed."""
    total = params.creep.total_creep
    if params.creep_driver == "voltage":
        return xh + params.law_slope_um_per_v * total * drive_v
    return (1.0 + total) * xh


def family_adopt_state(params: FamilyParams, voltage_v: float, position_um: float) -> FamilyState:
    """A state at ``voltage_v`` (lag settled, creep relaxed) whose position is ``position_um`` if the
    hysteresis can hold it there (else the nearest position the loop allows)."""
    v = float(voltage_v)
    xc = float(_static_inverse(params, np.array([float(position_um)]))[0])
    if params.creep_driver == "voltage":
        xh = xc - params.law_slope_um_per_v * params.creep.total_creep * v
    else:
        xh = xc / (1.0 + params.creep.total_creep)
    h = params.hysteresis
    law: LawState
    if isinstance(h, DomainWallParams):
        law = domainwall_state_at(h, v, xh)
    elif isinstance(h, BoucWenParams):
        law = boucwen_state_at(h, v, xh)
    elif isinstance(h, GeneralisedPlayParams):
        law = _gplay_adopt(h, v, xh)
    elif isinstance(h, PlayParams):
        spread = float(h.w @ h.r)
        c = 0.0 if spread == 0.0 else (xh / h.b_um_per_v - h.total_weight * v) / spread
        law = play_state_at(h, v, v + float(np.clip(c, -1.0, 1.0)) * h.r)
    else:
        law = HysteresisState(v, xh)
    xc = _relaxed_creep_position(params, law.position_um, v)
    return FamilyState(
        v, v, law, np.zeros(len(params.creep.taus)), xc, float(_static(params, np.array([xc]))[0])
    )


def _gplay_adopt(h: GeneralisedPlayParams, v: float, xh: float) -> PlayState:
    """Plays at ``v + c r``, ``c`` in [-1, 1], reaching ``xh`` (bisection: the position grows with ``c``)."""
    lo, hi = -1.0, 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if gplay_state_at(h, v, v + mid * h.r).position_um < xh:
            lo = mid
        else:
            hi = mid
    return gplay_state_at(h, v, v + 0.5 * (lo + hi) * h.r)


def _lag_coefficient(params: FamilyParams, dt_s: float) -> float:
    if params.lag_time_constant_s == 0.0:
        return 0.0
    return math.exp(-dt_s / params.lag_time_constant_s)


def _check(values: ArrayLike, name: str, dt_s: float) -> F64:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 1:
        raise ModelError(f"{name} must be 1-D, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ModelError(f"{name} contains non-finite samples")
    if not (math.isfinite(dt_s) and dt_s > 0.0):
        raise ModelError(f"dt_s must be finite and > 0, got {dt_s!r}")
    return a


def family_forward(
    params: FamilyParams, voltage_v: ArrayLike, dt_s: float, state: FamilyState
) -> tuple[F64, FamilyState]:
    """Positions for a block of commanded voltages (exact per sample for the model's discretisation).

    Parameters
    ----------
    params
        The model.
    voltage_v
        Commanded voltages (V), shape ``(n,)``.
    dt_s
        Sample interval (s).
    state
        State before the block.
    """
    v = _check(voltage_v, "voltage_v", dt_s)
    if v.size == 0:
        return np.empty(0), state
    a = _lag_coefficient(params, dt_s)
    vc = v if a == 0.0 else lfilter([1.0 - a], [1.0, -a], v, zi=[a * state.drive_v])[0]
    h = params.hysteresis
    xh: F64
    law: LawState
    pending = state.relax_pending
    if isinstance(h, DomainWallParams):
        assert isinstance(state.law, DomainWallState)
        xh, law, pending = domainwall_forward(h, vc, state.law, params.after_effect, dt_s, pending)
    elif isinstance(h, BoucWenParams):
        assert isinstance(state.law, BoucWenState)
        xh, law = boucwen_forward(h, vc, state.law)
    elif isinstance(h, GeneralisedPlayParams):
        assert isinstance(state.law, PlayState)
        if params.after_effect is not None:
            xh, law, pending = _relaxing_forward(h, params.after_effect, vc, dt_s, state)
        else:
            xh, law = gplay_forward(h, vc, state.law)
    elif isinstance(h, PlayParams):
        assert isinstance(state.law, PlayState)
        xh, law = play_forward(h, vc, state.law)
    else:
        assert isinstance(state.law, HysteresisState)
        xh, law = hysteresis_step(h, vc, state.law)
    disc = discretise(params.creep, dt_s)
    if params.creep_driver == "voltage":
        creep, e_end = _creep_forward(params.creep, dt_s, disc, vc, state.drive_v, state.creep_um)  # type: ignore[arg-type]
        xc = xh + params.law_slope_um_per_v * (disc.total * vc + creep)
    else:
        creep, e_end = _creep_forward(params.creep, dt_s, disc, xh, state.law.position_um, state.creep_um)  # type: ignore[arg-type]
        xc = (1.0 + disc.total) * xh + creep
    x = _static(params, xc)
    return x, FamilyState(float(v[-1]), float(vc[-1]), law, e_end, float(xc[-1]), float(x[-1]), pending)


def _relaxing_forward(
    h: GeneralisedPlayParams, ae: AfterEffect, vc: F64, dt_s: float, state: FamilyState
) -> tuple[F64, PlayState, int]:
    """The generalised play law with its after-effect through a block: positions, state, count."""
    assert isinstance(state.law, PlayState)
    plays = np.array(state.law.plays_v, dtype=np.float64)
    out = np.empty((plays.size, vc.size))
    every, factor, g0 = ae.loop_args(dt_s)
    pending = kernels.relax_outputs(
        vc, h.r, plays, state.law.voltage_v, state.relax_pending, every, factor, g0, out
    )
    xh = h.positions(vc, out)
    return xh, PlayState(float(vc[-1]), plays, float(xh[-1])), int(pending)


def family_inverse(
    params: FamilyParams, target_um: ArrayLike, dt_s: float, state: FamilyState
) -> tuple[F64, FamilyState]:
    """Commanded voltages whose forward model reaches the targets at every sample.

    Parameters
    ----------
    params
        The model.
    target_um
        Target positions (um), shape ``(n,)``.
    dt_s
        Sample interval (s).
    state
        State before the block.
    """
    x = _check(target_um, "target_um", dt_s)
    if x.size == 0:
        return np.empty(0), state
    xc = _static_inverse(params, x)
    if params.creep_driver == "voltage":
        vc_v, law_v, e_v = _voltage_creep_inverse(params, xc, dt_s, state)
        return _lag_inverse(params, vc_v, xc, x, dt_s, state, law_v, e_v)
    disc = discretise(params.creep, dt_s)
    xh, e_end = _creep_inverse(
        params.creep,  # type: ignore[arg-type]
        dt_s,
        disc,
        xc,
        state.creep_position_um,
        state.law.position_um,
        state.creep_um,
    )
    h = params.hysteresis
    vc: F64
    law: LawState
    if isinstance(h, DomainWallParams):
        assert isinstance(state.law, DomainWallState)
        vc, law, _ = domainwall_inverse(h, xh, state.law)
    elif isinstance(h, BoucWenParams):
        assert isinstance(state.law, BoucWenState)
        vc, law = boucwen_inverse(h, xh, state.law)
    elif isinstance(h, GeneralisedPlayParams):
        assert isinstance(state.law, PlayState)
        vc, law = _gplay_inverse(h, xh, state.law, _relaxation(params, dt_s, state))
    elif isinstance(h, PlayParams):
        assert isinstance(state.law, PlayState)
        vc, law = play_inverse(h, xh, state.law)
    else:
        assert isinstance(state.law, HysteresisState)
        vc, law = hysteresis_inverse_step(h, xh, state.law)
    return _lag_inverse(params, vc, xc, x, dt_s, state, law, e_end)


def _relaxation(params: FamilyParams, dt_s: float, state: FamilyState) -> tuple[int, int, float, float]:
    """The compiled walk's after-effect arguments: samples per relaxation (0: none), samples since
    the last one, the relaxation factor, the fluctuation voltage."""
    ae = params.after_effect
    if ae is None:
        return 0, 0, 1.0, math.inf
    every, factor, g0 = ae.loop_args(dt_s)
    return every, int(state.relax_pending), factor, g0


def _gplay_inverse(
    h: GeneralisedPlayParams, xh: F64, state: PlayState, relaxation: tuple[int, int, float, float]
) -> tuple[F64, PlayState]:
    """The generalised play law's exact inverse: the compiled walk without creep."""
    plays = np.array(state.plays_v, dtype=np.float64)
    vc = np.empty(xh.size)
    none = np.empty(0)
    u, x_end = kernels.gpi_loop(
        xh,
        h.r,
        h.c,
        h.mu,
        h.zero,
        0.0,
        none,
        0.0,
        none,
        none,
        none,
        plays,
        state.voltage_v,
        state.position_um,
        vc,
        *relaxation,
    )
    return vc, PlayState(u, plays, x_end)


def _lag_inverse(
    params: FamilyParams, vc: F64, xc: F64, x: F64, dt_s: float, state: FamilyState, law: LawState, e_end: F64
) -> tuple[F64, FamilyState]:
    a = _lag_coefficient(params, dt_s)
    if a == 0.0:
        v = vc
    else:
        prev = np.concatenate(([state.drive_v], vc[:-1]))
        v = (vc - a * prev) / (1.0 - a)
    pending = state.relax_pending
    if params.after_effect is not None:
        pending = (pending + vc.size) % params.after_effect.every(dt_s)
    return v, FamilyState(float(v[-1]), float(vc[-1]), law, e_end, float(xc[-1]), float(x[-1]), pending)


def family_hold(params: FamilyParams, samples: int, dt_s: float, state: FamilyState) -> FamilyState:
    """The state after holding the last commanded voltage for ``samples`` samples.

    The lag settles (simulated sample by sample for ``20 tau_lag``), then the creep elements
    relax in closed form, ``e_i -> e_i exp(-T / tau_i)``, and so does an after-effect's memory
    (one step over every relaxation interval that ends in the hold: at a held voltage they compose).
    """
    if samples < 0:
        raise ModelError(f"samples must be >= 0, got {samples}")
    if samples == 0:
        return state
    settle = 0
    if params.lag_time_constant_s > 0.0:
        settle = min(samples, math.ceil(20.0 * params.lag_time_constant_s / dt_s) + 1)
        _, state = family_forward(params, np.full(settle, state.voltage_v), dt_s, state)
    rest = samples - settle
    if rest == 0:
        return state
    e = state.creep_um * np.exp(-(rest * dt_s) / params.creep.taus_s)
    law, pending = state.law, state.relax_pending
    ae = params.after_effect
    if ae is not None and isinstance(params.hysteresis, DomainWallParams):
        assert isinstance(law, DomainWallState)
        law, pending = domainwall_hold(params.hysteresis, law, ae, dt_s, rest, pending)
    elif ae is not None and isinstance(params.hysteresis, GeneralisedPlayParams):
        assert isinstance(law, PlayState)
        # at a held voltage the relaxations compose: one step over all the intervals that end
        every = ae.every(dt_s)
        times, pending = divmod(pending + rest, every)
        plays = relax(law.plays_v, state.drive_v, ae.factor(times * every * dt_s), ae.fluctuation_v)
        law = gplay_state_at(params.hysteresis, state.drive_v, plays)
    scale = params.law_slope_um_per_v if params.creep_driver == "voltage" else 1.0
    xc = _relaxed_creep_position(params, law.position_um, state.drive_v) + scale * float(
        params.creep.weights @ e
    )
    x = float(_static(params, np.array([xc]))[0])
    return FamilyState(state.voltage_v, state.drive_v, law, e, xc, x, pending)


def _voltage_creep_inverse(
    params: FamilyParams, xc: F64, dt_s: float, state: FamilyState
) -> tuple[F64, LawState, F64]:
    """Drive voltages ``V_c`` giving ``x_c`` with voltage-driven creep: the compiled per-sample loop."""
    disc = discretise(params.creep, dt_s)
    w = params.creep.weights
    s = params.law_slope_um_per_v
    ob0 = disc.one_minus_b0
    g = s * float(w @ (1.0 - ob0))
    wa, wb = s * (w * disc.a), s * float(w @ ob0)
    e = np.array(state.creep_um, dtype=np.float64)
    vc = np.empty(xc.size)
    creep = (g, wa, wb, disc.a, ob0, e)
    h = params.hysteresis
    relaxation = _relaxation(params, dt_s, state)
    law: LawState
    if isinstance(h, DomainWallParams):
        assert isinstance(state.law, DomainWallState)
        law, _ = dw_creep_loop(h, xc, creep, state.law, vc, params.after_effect, dt_s, state.relax_pending)
    elif isinstance(h, BoucWenParams):
        assert isinstance(state.law, BoucWenState)
        u, hv = bw_creep_loop(h, xc, *creep, state.drive_v, state.law.h_v, vc)
        law = BoucWenState(u, hv, h.b_um_per_v * u + h.c_um_per_v * hv)
    elif isinstance(h, GeneralisedPlayParams | PlayParams):
        assert isinstance(state.law, PlayState)
        plays = np.array(state.law.plays_v, dtype=np.float64)
        if isinstance(h, GeneralisedPlayParams):
            u, xh = kernels.gpi_loop(
                xc,
                h.r,
                h.c,
                h.mu,
                h.zero,
                *creep,
                plays,
                state.drive_v,
                state.law.position_um,
                vc,
                *relaxation,
            )
        else:
            pi_args = (h.b_um_per_v, h.rho0, h.r, h.w)
            u, xh = kernels.pi_loop(xc, *pi_args, *creep, plays, state.drive_v, state.law.position_um, vc)
        law = PlayState(u, plays, xh)
    else:
        assert isinstance(state.law, HysteresisState)
        ch_args = (h.b_um_per_v, h.alpha_per_v, h.delta_um)
        u, xh = kernels.ch_loop(xc, *ch_args, *creep, state.drive_v, state.law.position_um, vc)
        law = HysteresisState(u, xh)
    return vc, law, e


__all__ = [
    "CREEP_DRIVERS",
    "CreepSpectrum",
    "FamilyParams",
    "FamilyState",
    "family_adopt_state",
    "family_forward",
    "family_hold",
    "family_inverse",
    "family_rest_state",
]
