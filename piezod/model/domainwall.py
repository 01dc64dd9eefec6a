"""A domain-wall (Jiles-Atherton type) hysteresis law: pinned walls relaxing towards an anhysteretic curve.

The law of ferroelectric hysteresis by domain-wall motion (Smith and Ounaies' adaptation of the
Jiles-Atherton law to piezoceramics), in volt-equivalent units. The walls' displacement ``P``
(V) sees the effective field ``h = V + alpha P`` (the mean-field interaction of the walls) and
follows an anhysteretic curve, the displacement the walls would take without pinning::

    P_an(h) = a tanh((h - h_b) / a)          slope 1 at the centre h_b, saturating at +-a

Pinned walls move only while the field pushes them towards that curve, at a rate set by the
pinning energy ``k`` (V)::

    dP/d|h| = (P_an(h) - P) / k   while P_an lies ahead of P in the field's direction, else 0

The position is ``x_h = b V + w P``. Unlike a Duhem law of fixed saturation (Bouc-Wen) the
branches bend towards a curve of the voltage, so the loop's width and slope change over the
span, minor loops inside the major one take the curve's local slope, and the interaction
``alpha`` steepens the branches where the walls move.

The after-effect (:class:`piezod.model.aftereffect.AfterEffect`, thermally activated unpinning)
closes the gap ``g = P_an(h) - P`` at rest by the Eyring closed form
``tanh(g / 2 g0) -> tanh(g / 2 g0) exp(-t / tau)``, every interval, the field then settling at the
held voltage: a creep whose amount depends on how far the history left the walls from the curve,
and loops that narrow at slow drive.

Discretisation (the law *is* it, forward and inverse alike): per sample the field moves from the
last sample's to the new one; ``P_an`` is taken linear in the field across that step, so ``P``
follows the linear ODE's exact solution (:func:`piezod.model.kernels._dw_step`). The forward
solves ``h = V + alpha P(h)`` per sample by a bracketed Newton iteration; the inverse solves the
position's equation in ``h`` (increasing: ``dP/dh`` lies in ``[0, 1]`` on every reachable state)
and then ``V = h - alpha P`` explicitly: exact to rounding, bounded cost
(:func:`piezod.model.kernels.dw_loop`).

Admissible parameters: ``b > 0``, ``w >= 0`` (the walls move the stage the way the lattice
does), ``k, a > 0``, ``0 <= alpha <= MAX_INTERACTION`` (the field's slope along the voltage,
``1 / (1 - alpha dP/dh)``, stays bounded).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model import kernels
from piezod.model.aftereffect import AfterEffect

F64 = NDArray[np.float64]

#: Largest interaction ``alpha``: the field's slope along the voltage is at most ``1 / (1 - alpha)``.
MAX_INTERACTION = 0.9


@dataclass(frozen=True)
class DomainWallParams:
    """Frozen parameters of the domain-wall law.

    Attributes
    ----------
    b_um_per_v
        Lattice (reversible) slope ``b`` (um/V), > 0.
    w_um_per_v
        Weight of the walls' displacement ``w`` (um/V), >= 0.
    pinning_v
        ``k`` (V), > 0: how far the field runs while the walls close ``1 - 1/e`` of their gap.
    centre_v
        ``h_b`` (V): the anhysteretic curve's centre (the poling's bias).
    width_v
        ``a`` (V), > 0: the curve's width and saturation.
    interaction
        ``alpha`` in ``[0, MAX_INTERACTION]``.
    """

    b_um_per_v: float
    w_um_per_v: float
    pinning_v: float
    centre_v: float
    width_v: float
    interaction: float = 0.0

    def __post_init__(self) -> None:
        values = (
            self.b_um_per_v,
            self.w_um_per_v,
            self.pinning_v,
            self.centre_v,
            self.width_v,
            self.interaction,
        )
        if not all(math.isfinite(v) for v in values):
            raise ModelError("domain-wall parameters must be finite")
        if not self.b_um_per_v > 0.0:
            raise ModelError(f"domain-wall b_um_per_v must be > 0, got {self.b_um_per_v!r}")
        if not self.w_um_per_v >= 0.0:
            raise ModelError(f"domain-wall w_um_per_v must be >= 0, got {self.w_um_per_v!r}")
        if not (self.pinning_v > 0.0 and self.width_v > 0.0):
            raise ModelError("domain-wall pinning_v and width_v must be > 0")
        if not 0.0 <= self.interaction <= MAX_INTERACTION:
            raise ModelError(
                f"domain-wall interaction must lie in [0, {MAX_INTERACTION:g}], got {self.interaction!r}"
            )

    @property
    def shape(self) -> tuple[float, float, float, float]:
        """``(k, h_b, a, alpha)``: the compiled loops' law arguments."""
        return (self.pinning_v, self.centre_v, self.width_v, self.interaction)

    def anhysteretic(self, field_v: ArrayLike) -> F64:
        """``P_an`` at the fields ``field_v`` (V)."""
        h = np.asarray(field_v, dtype=np.float64)
        out: F64 = self.width_v * np.tanh((h - self.centre_v) / self.width_v)
        return out


@dataclass(frozen=True, slots=True)
class DomainWallState:
    """The law's state after a sample: drive voltage, walls' displacement ``P``, field ``h``, ``x_h``."""

    voltage_v: float
    walls_v: float
    field_v: float
    position_um: float


def _state(params: DomainWallParams, walls_v: float, field_v: float) -> DomainWallState:
    v = field_v - params.interaction * walls_v
    return DomainWallState(v, walls_v, field_v, params.b_um_per_v * v + params.w_um_per_v * walls_v)


def _walls_at_gap(params: DomainWallParams, voltage_v: float, gap_v: float) -> float:
    """``P`` whose gap ``P_an(V + alpha P) - P`` is ``gap_v`` at the voltage ``V`` (it decreases in
    ``P`` at a slope of at least ``1 - alpha``: bisection on a bracket of that slope)."""
    _, _, a, al = params.shape
    centre = float(params.anhysteretic(voltage_v)) - gap_v
    lo, hi = centre - (a + abs(gap_v)) / (1.0 - al) - 1.0, centre + (a + abs(gap_v)) / (1.0 - al) + 1.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if float(params.anhysteretic(voltage_v + al * mid)) - mid > gap_v:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * (1.0 + abs(mid)):
            break
    return 0.5 * (lo + hi)


def domainwall_rest_state(params: DomainWallParams, voltage_v: float = 0.0) -> DomainWallState:
    """Rested at ``voltage_v`` for ever: the walls on the anhysteretic curve."""
    p = _walls_at_gap(params, float(voltage_v), 0.0)
    return _state(params, p, float(voltage_v) + params.interaction * p)


def domainwall_state_at(params: DomainWallParams, voltage_v: float, position_um: float) -> DomainWallState:
    """A state at ``voltage_v`` reaching ``position_um`` if the walls can be there (their gap to the
    curve within ``+-k``, as on any branch), else the nearest that can."""
    v = float(voltage_v)
    lo = _walls_at_gap(params, v, params.pinning_v)
    hi = _walls_at_gap(params, v, -params.pinning_v)
    want = (float(position_um) - params.b_um_per_v * v) / params.w_um_per_v if params.w_um_per_v > 0 else lo
    p = float(np.clip(want, lo, hi))
    return _state(params, p, v + params.interaction * p)


def _relaxation(ae: AfterEffect | None, dt_s: float) -> tuple[int, float, float]:
    """:meth:`AfterEffect.loop_args`, or ``(0, 1, inf)`` (none) without an after-effect."""
    return (0, 1.0, math.inf) if ae is None else ae.loop_args(dt_s)


def domainwall_forward(
    params: DomainWallParams,
    voltage_v: ArrayLike,
    state: DomainWallState,
    after_effect: AfterEffect | None = None,
    dt_s: float = 1.0,
    pending: int = 0,
) -> tuple[F64, DomainWallState, int]:
    """``x_h`` for a block of drive voltages, the state after, and the samples since the last
    relaxation (``after_effect``: its relaxation every interval at the sample interval ``dt_s``)."""
    v = np.ascontiguousarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise ModelError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state, pending
    walls = np.empty(v.size)
    every, factor, g0 = _relaxation(after_effect, dt_s)
    p, h, cnt = kernels.dw_forward(
        v, *params.shape, state.walls_v, state.field_v, every, pending, factor, g0, walls
    )
    x: F64 = params.b_um_per_v * v + params.w_um_per_v * walls
    return x, _state(params, float(p), float(h)), int(cnt)


def creep_loop(
    params: DomainWallParams,
    xc: F64,
    creep: tuple[float, F64, float, F64, F64, F64],
    state: DomainWallState,
    out: F64,
    after_effect: AfterEffect | None = None,
    dt_s: float = 1.0,
    pending: int = 0,
) -> tuple[DomainWallState, int]:
    """The compiled inverse of the law plus voltage creep (:func:`piezod.model.kernels.dw_loop`;
    ``creep = (g, wa, wb, a, ob0, e)``, ``e`` updated in place): the state after and the count."""
    every, factor, g0 = _relaxation(after_effect, dt_s)
    p, h, cnt = kernels.dw_loop(
        xc,
        params.b_um_per_v,
        params.w_um_per_v,
        *params.shape,
        *creep,
        state.walls_v,
        state.field_v,
        out,
        every,
        pending,
        factor,
        g0,
    )
    return _state(params, float(p), float(h)), int(cnt)


def domainwall_inverse(
    params: DomainWallParams,
    position_um: ArrayLike,
    state: DomainWallState,
    after_effect: AfterEffect | None = None,
    dt_s: float = 1.0,
    pending: int = 0,
) -> tuple[F64, DomainWallState, int]:
    """Drive voltages whose forward law reaches ``position_um`` at every sample (exact), the state
    after and the count."""
    x = np.ascontiguousarray(position_um, dtype=np.float64)
    if x.ndim != 1:
        raise ModelError(f"position_um must be 1-D, got shape {x.shape}")
    if x.size == 0:
        return np.empty(0), state, pending
    out = np.empty(x.size)
    none = np.empty(0)
    after, cnt = creep_loop(
        params, x, (0.0, none, 0.0, none, none, np.empty(0)), state, out, after_effect, dt_s, pending
    )
    return out, after, cnt


def domainwall_hold(
    params: DomainWallParams,
    state: DomainWallState,
    after_effect: AfterEffect,
    dt_s: float,
    samples: int,
    pending: int,
) -> tuple[DomainWallState, int]:
    """The state after holding the drive voltage ``samples`` samples (the relaxations that end in
    the hold, exactly as :func:`domainwall_forward` takes them), and the count."""
    every, factor, g0 = _relaxation(after_effect, dt_s)
    times, left = divmod(pending + samples, every)
    p, h = kernels.dw_hold(state.walls_v, state.field_v, times, factor, g0, *params.shape[1:])
    return _state(params, float(p), float(h)), int(left)


def session_walls(
    params: DomainWallParams,
    times_s: F64,
    voltage_v: F64,
    rest_voltage_v: float,
    after_effect: AfterEffect | None = None,
    max_steps: int = 256,
) -> F64:
    """``P`` at a calibration session's samples (any spacing, at the times ``times_s`` from rest at
    ``rest_voltage_v``), the after-effect relaxing between them as the runtime model does."""
    v = np.ascontiguousarray(voltage_v, dtype=np.float64)
    out = np.empty(v.size)
    rest = domainwall_rest_state(params, rest_voltage_v)
    interval, tau, g0 = (1.0, math.inf, math.inf)
    if after_effect is not None:
        interval, tau, g0 = after_effect.interval_s, after_effect.time_s, after_effect.fluctuation_v
    kernels.dw_timed_forward(
        np.ascontiguousarray(times_s, dtype=np.float64),
        v,
        *params.shape,
        rest.walls_v,
        rest.field_v,
        0.0,
        interval,
        tau,
        g0,
        max_steps,
        out,
    )
    return out


__all__ = [
    "MAX_INTERACTION",
    "DomainWallParams",
    "DomainWallState",
    "creep_loop",
    "domainwall_forward",
    "domainwall_hold",
    "domainwall_inverse",
    "domainwall_rest_state",
    "domainwall_state_at",
    "session_walls",
]
