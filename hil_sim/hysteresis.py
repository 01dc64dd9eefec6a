"""Rate-independent hysteresis laws of the simulated stage (hil_sim's own implementations).

Four laws, chosen per axis in the ``simulation:`` section:

``coleman-hodgdon``
    The ODE ``dx/dV = alpha sgn(dV) (b V - x) + u`` (thesis eq. 2.21), stepped exactly for a
    voltage linear between samples. It is the law the controller's default model assumes, so a
    stage built from it measures self-consistency. Its minor loops do not close: a repeated
    small loop drifts towards the centre line.
``prandtl-ishlinskii``
    ``x = b (rho0 V + sum_i w_i P_{r_i}[V])``: a weighted sum of play (backlash) operators with
    thresholds ``r_i`` (Prandtl-Ishlinskii). It is rate independent, has wiping-out memory and
    its minor loops close after one period; the branch slope after a reversal rises from
    ``b rho0`` to ``b`` in steps as the voltage change passes ``2 r_i``. It is not the
    controller's default law: a stage built from it is *other physics*.
``preisach``
    A continuum of relay hysterons with a closed-form Everett function whose density depends on
    the relay centre as well as its width (:class:`PreisachParams`): asymmetric loops, minor loops
    that close but are not congruent. Neither law the controller fits: the held-out stage
    ``configs/sim-preisach-stage.yaml`` uses it to check generality.

``bouc-wen``
    A rate-independent Bouc-Wen law (:class:`BoucWenParams`): a Duhem-type ODE in the voltage
    whose relaxation rate depends on the direction and on the sign of the hysteretic part. Not a
    law the controller fits: the second held-out stage ``configs/sim-boucwen-stage.yaml``.

All are evaluated over whole blocks with state carried across blocks; a block split anywhere
gives the same samples (the play operator is exact at the sample instants for a voltage that is
monotone between samples). The Coleman-Hodgdon step is an independent copy of the closed form
used by the host (``tests/test_stage.py`` checks that both agree).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil_sim.errors import SimModelError

#: Largest scaled total variation inside one cumulative chunk; exp(400) is far from overflow.
_CHUNK_SPAN = 400.0


# ---------------------------------------------------------------------------------------------
# Coleman-Hodgdon ODE


@dataclass(frozen=True, slots=True)
class CHParams:
    """Parameters of the Coleman-Hodgdon ODE ``dx/dV = alpha sgn(dV) (b V - x) + u``.

    Attributes
    ----------
    alpha_per_v
        Transition rate (1/V), > 0.
    b_um_per_v
        Sensitivity (slope of the asymptote) (um/V), > 0.
    u_um_per_v
        Slope right after a reversal from the asymptote (um/V), > 0.
    """

    alpha_per_v: float
    b_um_per_v: float
    u_um_per_v: float

    def __post_init__(self) -> None:
        for name in ("alpha_per_v", "b_um_per_v", "u_um_per_v"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise SimModelError(f"{name} must be finite and > 0, got {value!r}")


@dataclass(frozen=True, slots=True)
class CHState:
    """Voltage (V) and hysteretic position (um) of the last sample."""

    voltage_v: float
    position_um: float


def ch_rest_state(params: CHParams, voltage_v: float = 0.0) -> CHState:
    """At rest on the centre line ``x = b V``."""
    return CHState(float(voltage_v), params.b_um_per_v * float(voltage_v))


def ch_step(params: CHParams, voltage_v: ArrayLike, state: CHState) -> tuple[NDArray[np.float64], CHState]:
    """Advance the ODE exactly through a block (closed form with chunked cumulative sums).

    With ``y = x - b V``, ``delta = (b - u) / alpha`` and ``L`` the scaled total variation
    ``alpha sum |dV|``: ``y_n = exp(-L_n) [y_0 + delta sum_k s_k (exp(L_k) - exp(L_{k+1}))]``.

    Parameters
    ----------
    params
        The law's parameters.
    voltage_v
        Voltages (V), shape ``(n,)``; the first step goes from ``state.voltage_v``.
    state
        State before the block.

    Returns
    -------
    position_um : ndarray
        Hysteretic position after each sample (um).
    state : CHState
        State after the block.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise SimModelError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state
    b = params.b_um_per_v
    delta = (params.b_um_per_v - params.u_um_per_v) / params.alpha_per_v
    dv = np.diff(v, prepend=state.voltage_v)
    s = np.sign(dv)
    l_next = np.cumsum(params.alpha_per_v * np.abs(dv))
    y_out = np.empty_like(v)
    y0 = state.position_um - b * state.voltage_v
    start, n = 0, v.size
    while start < n:
        base = l_next[start - 1] if start > 0 else 0.0
        stop = max(int(np.searchsorted(l_next, base + _CHUNK_SPAN, side="right")), start + 1)
        lk1 = l_next[start:stop] - base
        lk = np.concatenate(([0.0], lk1[:-1]))
        y_chunk = np.exp(-lk1) * (y0 + delta * np.cumsum(s[start:stop] * (np.exp(lk) - np.exp(lk1))))
        y_out[start:stop] = y_chunk
        y0 = float(y_chunk[-1])
        start = stop
    x = y_out + b * v
    return x, CHState(float(v[-1]), float(x[-1]))


# ---------------------------------------------------------------------------------------------
# Prandtl-Ishlinskii (play operators)


@dataclass(frozen=True, slots=True, eq=False)
class PIParams:
    """A Prandtl-Ishlinskii law ``x = b (rho0 V + sum_i w_i P_{r_i}[V])``.

    Attributes
    ----------
    b_um_per_v
        Slope once every play operator moves (um/V), > 0.
    rho0
        Fraction of ``b`` that follows the voltage without play (the slope right after a
        reversal, as a fraction of ``b``), in (0, 1].
    thresholds_v
        Play half-widths ``r_i`` (V), shape ``(m,)``, > 0, ascending.
    weights
        Weights ``w_i``, shape ``(m,)``, >= 0, summing to ``1 - rho0``.
    """

    b_um_per_v: float
    rho0: float
    thresholds_v: NDArray[np.float64]
    weights: NDArray[np.float64]

    def __post_init__(self) -> None:
        r = np.array(self.thresholds_v, dtype=np.float64)
        w = np.array(self.weights, dtype=np.float64)
        if not (math.isfinite(self.b_um_per_v) and self.b_um_per_v > 0.0):
            raise SimModelError(f"b_um_per_v must be finite and > 0, got {self.b_um_per_v!r}")
        if not 0.0 < self.rho0 <= 1.0:
            raise SimModelError(f"rho0 must lie in (0, 1], got {self.rho0!r}")
        if r.ndim != 1 or r.shape != w.shape or not np.all(np.isfinite(r) & (r > 0)):
            raise SimModelError("thresholds_v must be finite, > 0, one per weight")
        if not np.all(np.isfinite(w) & (w >= 0)):
            raise SimModelError("weights must be finite and >= 0")
        r.setflags(write=False)
        w.setflags(write=False)
        object.__setattr__(self, "thresholds_v", r)
        object.__setattr__(self, "weights", w)

    @classmethod
    def from_shape(
        cls, b_um_per_v: float, rho0: float, span_v: float, operators: int, decay_v: float | None
    ) -> PIParams:
        """A law whose branch slope rises from ``b rho0`` to ``b`` over a voltage change ``span_v``.

        Thresholds ``r_i = (i / m) span_v / 2`` for ``i = 1..m``; weights proportional to
        ``exp(-2 r_i / decay_v)`` (uniform when ``decay_v`` is None), scaled to sum to ``1 - rho0``.
        """
        if operators < 1:
            raise SimModelError(f"operators must be >= 1, got {operators}")
        if not (math.isfinite(span_v) and span_v > 0.0):
            raise SimModelError(f"span_v must be finite and > 0, got {span_v!r}")
        r = 0.5 * span_v * np.arange(1, operators + 1) / operators
        shape = np.ones(operators) if decay_v is None else np.exp(-2.0 * r / decay_v)
        w = (1.0 - rho0) * shape / shape.sum()
        return cls(float(b_um_per_v), float(rho0), r, w)


@dataclass(frozen=True, slots=True, eq=False)
class PIState:
    """Voltage of the last sample (V) and the output of every play operator (V), shape ``(m,)``."""

    voltage_v: float
    plays_v: NDArray[np.float64]


def pi_rest_state(params: PIParams, voltage_v: float = 0.0) -> PIState:
    """At rest at ``voltage_v`` with every play centred on it (the demagnetised, relaxed state)."""
    return PIState(float(voltage_v), np.full(params.thresholds_v.shape, float(voltage_v)))


def _runs(v: NDArray[np.float64], v_last: float) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """First sample and direction (+1 / -1) of every monotone run of ``v`` (held samples join a run)."""
    sign = np.sign(np.diff(v, prepend=v_last))
    moving = np.flatnonzero(sign)
    if moving.size == 0:
        return np.zeros(1, dtype=np.intp), np.zeros(1)
    sm = sign[moving]
    change = np.concatenate(([0], np.flatnonzero(sm[1:] != sm[:-1]) + 1))
    starts = moving[change]
    starts[0] = 0
    return starts, sm[change]


def play_step(
    thresholds_v: NDArray[np.float64], voltage_v: NDArray[np.float64], state: PIState
) -> tuple[NDArray[np.float64], PIState]:
    """Outputs of the play operators through a block, shape ``(m, n)``.

    On a rising run ``p = max(p_start, V - r)``, on a falling one ``p = min(p_start, V + r)``:
    one vectorised pass per monotone run (a scan line has two).
    """
    v = voltage_v
    r = thresholds_v[:, None]
    out = np.empty((thresholds_v.size, v.size))
    p = state.plays_v.copy()
    starts, dirs = _runs(v, state.voltage_v)
    bounds = np.append(starts, v.size)
    for k, direction in enumerate(dirs):
        seg = v[bounds[k] : bounds[k + 1]][None, :]
        if direction > 0:
            block = np.maximum(p[:, None], seg - r)
        elif direction < 0:
            block = np.minimum(p[:, None], seg + r)
        else:
            block = np.repeat(p[:, None], seg.shape[1], axis=1)
        out[:, bounds[k] : bounds[k + 1]] = block
        p = block[:, -1].copy()
    return out, PIState(float(v[-1]), p)


def pi_step(params: PIParams, voltage_v: ArrayLike, state: PIState) -> tuple[NDArray[np.float64], PIState]:
    """Advance the Prandtl-Ishlinskii law through a block.

    Parameters
    ----------
    params
        The law's parameters.
    voltage_v
        Voltages (V), shape ``(n,)``.
    state
        State before the block.

    Returns
    -------
    position_um : ndarray
        Hysteretic position after each sample (um).
    state : PIState
        State after the block.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise SimModelError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state
    plays, new = play_step(params.thresholds_v, v, state)
    x = params.b_um_per_v * (params.rho0 * v + params.weights @ plays)
    return x, new


# ---------------------------------------------------------------------------------------------
# Preisach (Everett function), the held-out law


@dataclass(frozen=True, slots=True, eq=False)
class PreisachParams:
    """A Preisach law with a closed-form Everett function (the held-out law of ``sim-preisach-stage``).

    ``x = b (rho0 V + E-part)``: the hysteretic part is a continuum of relay hysterons with
    switching voltages ``alpha >= beta`` in ``[-V_s, V_s]`` and density
    ``mu(alpha, beta) = k exp(-(alpha - beta) / u0) (1 + eps (alpha + beta) / (2 V_s))``: the
    width density of a Prandtl-Ishlinskii law times a factor of the relay centre, so the loops
    are asymmetric and minor loops at different offsets are *not* congruent (a
    Prandtl-Ishlinskii law cannot represent it exactly). Its Everett function is closed form,
    ``E(a, b) = k f(a - b) (1 + eps (a + b) / (2 V_s))`` with ``f(u) = u0^2 (exp(-u / u0) - 1 + u / u0)``;
    ``k`` scales the major loop's excursion to ``(1 - rho0) 2 V_s`` (mean major slope ``b``).
    The slope right after every reversal is ``b rho0``. Minor loops close (wiping-out memory).
    Voltages beyond ``+-V_s`` switch no more relays (the reversible part still follows).

    Attributes
    ----------
    b_um_per_v
        Sensitivity (um/V), > 0.
    rho0
        Reversible fraction, in (0, 1].
    width_v
        ``u0``: decay of the density over the relay width (V), > 0.
    asymmetry
        ``eps``: centre dependence of the density, ``|eps| < 0.5`` (keeps every branch increasing).
    saturation_v
        ``V_s`` (V), > 0.
    """

    b_um_per_v: float
    rho0: float
    width_v: float
    asymmetry: float
    saturation_v: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.b_um_per_v) and self.b_um_per_v > 0.0):
            raise SimModelError(f"b_um_per_v must be finite and > 0, got {self.b_um_per_v!r}")
        if not 0.0 < self.rho0 <= 1.0:
            raise SimModelError(f"rho0 must lie in (0, 1], got {self.rho0!r}")
        if not (math.isfinite(self.width_v) and self.width_v > 0.0):
            raise SimModelError(f"width_v must be finite and > 0, got {self.width_v!r}")
        if not abs(self.asymmetry) < 0.5:
            raise SimModelError(f"asymmetry must lie in (-0.5, 0.5), got {self.asymmetry!r}")
        if not (math.isfinite(self.saturation_v) and self.saturation_v > 0.0):
            raise SimModelError(f"saturation_v must be finite and > 0, got {self.saturation_v!r}")

    def _f(self, u: NDArray[np.float64]) -> NDArray[np.float64]:
        u0 = self.width_v
        out: NDArray[np.float64] = u0 * u0 * (np.expm1(-u / u0) + u / u0)
        return out

    @property
    def _k(self) -> float:
        vs = self.saturation_v
        return (1.0 - self.rho0) * 2.0 * vs / float(self._f(np.array([2.0 * vs]))[0])

    def everett(self, a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
        """``E(a, b)`` (V): the hysteretic change when the relays between ``b`` and ``a`` switch."""
        av = np.asarray(a, dtype=np.float64)
        bv = np.asarray(b, dtype=np.float64)
        g = 1.0 + self.asymmetry * (av + bv) / (2.0 * self.saturation_v)
        out: NDArray[np.float64] = self._k * self._f(av - bv) * g
        return out


@dataclass(frozen=True, slots=True, eq=False)
class PreisachState:
    """The memory of a Preisach law.

    Attributes
    ----------
    voltage_v, hyst_v
        The last (clipped) voltage and the hysteretic part there (V).
    direction
        Direction of the run that reached it (+1, -1).
    turns_v, turns_x
        The dominant turning points (alternating maxima and minima, the first one positive
        saturation ``+V_s``), the last one where the current run started, and the hysteretic
        part at each.
    """

    voltage_v: float
    hyst_v: float
    direction: int
    turns_v: NDArray[np.float64]
    turns_x: NDArray[np.float64]


def _preisach_runs(
    params: PreisachParams, u: NDArray[np.float64], state: PreisachState
) -> tuple[NDArray[np.float64], PreisachState]:
    """Hysteretic part (V) for clipped voltages ``u`` (one vectorised pass per monotone run)."""
    out = np.empty_like(u)
    tv, tx = state.turns_v, state.turns_x
    v_cur, h_cur, d_cur = state.voltage_v, state.hyst_v, state.direction
    starts, dirs = _runs(u, v_cur)
    bounds = np.append(starts, u.size)
    for k, direction in enumerate(dirs):
        seg = u[bounds[k] : bounds[k + 1]]
        if direction == 0:
            out[bounds[k] : bounds[k + 1]] = h_cur
            continue
        d = int(direction)
        if d != d_cur:
            tv, tx = np.append(tv, v_cur), np.append(tx, h_cur)
        top = tv.size - 1
        # the opposite turning points below the base, nearest first: wiped out once passed
        opp = tv[top - 1 :: -2] if top >= 1 else np.empty(0)
        base = top - 2 * np.searchsorted(d * opp, d * seg, side="left")
        h = tx[base] + d * params.everett(np.maximum(seg, tv[base]), np.minimum(seg, tv[base]))
        out[bounds[k] : bounds[k + 1]] = h
        last = int(base[-1])
        tv, tx = tv[: last + 1], tx[: last + 1]
        v_cur, h_cur, d_cur = float(seg[-1]), float(h[-1]), d
    return out, PreisachState(v_cur, h_cur, d_cur, tv, tx)


def preisach_rest_state(params: PreisachParams, voltage_v: float = 0.0) -> PreisachState:
    """Demagnetised at ``voltage_v``: from negative saturation, alternating extremes decaying onto it."""
    vs = params.saturation_v
    v0 = float(np.clip(voltage_v, -vs, vs))
    top = float(params.everett(vs, -vs))
    state = PreisachState(-vs, 0.0, -1, np.array([vs]), np.array([top]))
    amp = min(vs - v0, vs + v0)
    extremes = []
    sign = 1.0
    while amp > 1e-6 * vs:
        extremes.append(v0 + sign * amp)
        sign, amp = -sign, 0.8 * amp
    extremes.append(v0)
    _, state = _preisach_runs(params, np.array(extremes), state)
    return state


def preisach_step(
    params: PreisachParams, voltage_v: ArrayLike, state: PreisachState
) -> tuple[NDArray[np.float64], PreisachState]:
    """Advance the Preisach law through a block; positions (um) relative to the demagnetised state at 0 V.

    Parameters
    ----------
    params
        The law's parameters.
    voltage_v
        Voltages (V), shape ``(n,)``.
    state
        State before the block.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise SimModelError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state
    u = np.clip(v, -params.saturation_v, params.saturation_v)
    h, new = _preisach_runs(params, u, state)
    x = params.b_um_per_v * (params.rho0 * v + h - _preisach_zero(params))
    return x, new


def preisach_position(params: PreisachParams, voltage_v: float, state: PreisachState) -> float:
    """The position (um) of a state reached at ``voltage_v`` (the unclipped voltage)."""
    return params.b_um_per_v * (params.rho0 * voltage_v + state.hyst_v - _preisach_zero(params))


def _preisach_zero(params: PreisachParams) -> float:
    return _zero(params.rho0, params.width_v, params.asymmetry, params.saturation_v)


@functools.lru_cache(maxsize=64)
def _zero(rho0: float, width_v: float, asymmetry: float, saturation_v: float) -> float:
    return preisach_rest_state(PreisachParams(1.0, rho0, width_v, asymmetry, saturation_v), 0.0).hyst_v


# ---------------------------------------------------------------------------------------------
# Bouc-Wen (rate independent, exponent 1 or 2), the held-out laws


@dataclass(frozen=True, slots=True)
class BoucWenParams:
    """A rate-independent Bouc-Wen law of exponent 1 or 2 (the held-out laws of the Bouc-Wen presets).

    ``x = b (V - h)`` with the hysteretic voltage ``h`` obeying
    ``dh = A dV - beta |dV| |h|^(n-1) h - gamma dV |h|^n`` (the Bouc-Wen form used for piezo
    stacks). With ``n = 1`` ``h`` relaxes exponentially along a monotone run towards
    ``+-A / (beta + gamma)`` at a rate that depends on the direction *and* on the sign of ``h``
    (``beta + gamma`` or ``beta - gamma``); with ``n = 2`` it follows ``tanh`` (``h`` and ``dV``
    of one sign) or ``tan`` (opposite signs) towards ``+-sqrt(A / (beta + gamma))``: a sharper
    knee. Neither is a sum of plays nor the Coleman-Hodgdon ODE; repeated minor loops do not
    close exactly (no wiping-out memory).

    Attributes
    ----------
    b_um_per_v
        Sensitivity (um/V), > 0.
    a
        ``A``, in (0, 1).
    beta_per_v, gamma_per_v
        ``beta > |gamma|`` (1/V^n); the branch stays increasing (``2 A beta / (beta + gamma) < 1``).
    exponent
        ``n``, 1 or 2.
    """

    b_um_per_v: float
    a: float
    beta_per_v: float
    gamma_per_v: float
    exponent: int = 1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.b_um_per_v) and self.b_um_per_v > 0.0):
            raise SimModelError(f"b_um_per_v must be finite and > 0, got {self.b_um_per_v!r}")
        if not 0.0 < self.a < 1.0:
            raise SimModelError(f"bouc-wen A must lie in (0, 1), got {self.a!r}")
        if not (math.isfinite(self.beta_per_v) and self.beta_per_v > abs(self.gamma_per_v)):
            raise SimModelError("bouc-wen needs beta_per_v > |gamma_per_v|")
        if not 2.0 * self.a * self.beta_per_v / (self.beta_per_v + self.gamma_per_v) < 1.0:
            raise SimModelError("bouc-wen branch would run backwards: need 2 A beta / (beta + gamma) < 1")
        if self.exponent not in (1, 2):
            raise SimModelError(f"bouc-wen exponent must be 1 or 2, got {self.exponent!r}")


@dataclass(frozen=True, slots=True)
class BoucWenState:
    """Voltage of the last sample (V) and the hysteretic voltage ``h`` (V)."""

    voltage_v: float
    h_v: float


def boucwen_rest_state(params: BoucWenParams, voltage_v: float = 0.0) -> BoucWenState:
    """Relaxed at ``voltage_v``: ``h = 0`` (the demagnetised state, ``x = b V``)."""
    return BoucWenState(float(voltage_v), 0.0)


def _bw_rising(params: BoucWenParams, dv: NDArray[np.float64], h0: float) -> NDArray[np.float64]:
    """``h`` after rising by ``dv >= 0`` from ``h0`` (closed form, one sign change of ``h`` at most)."""
    if params.exponent == 2:
        return _bw2_rising(params, dv, h0)
    a, kp, km = params.a, params.beta_per_v + params.gamma_per_v, params.beta_per_v - params.gamma_per_v
    if h0 >= 0.0:
        out: NDArray[np.float64] = a / kp + (h0 - a / kp) * np.exp(-kp * dv)
        return out
    d0 = math.log1p(-h0 * km / a) / km  # where h crosses 0
    below = a / km + (h0 - a / km) * np.exp(-km * np.minimum(dv, d0))
    above = -(a / kp) * np.expm1(-kp * np.maximum(dv - d0, 0.0))
    return np.where(dv <= d0, below, above)


def _bw2_rising(params: BoucWenParams, dv: NDArray[np.float64], h0: float) -> NDArray[np.float64]:
    """Exponent 2: ``dh/dV = A - kp h^2`` for ``h >= 0``, ``A + km h^2`` for ``h < 0``."""
    a, kp, km = params.a, params.beta_per_v + params.gamma_per_v, params.beta_per_v - params.gamma_per_v
    s, r = math.sqrt(a / kp), math.sqrt(a * kp)
    if h0 >= 0.0:
        # |h| cannot pass s from below; clipping keeps a rounding excess on the fixed point
        return s * np.tanh(r * dv + math.atanh(min(h0 / s, 1.0 - 1e-15)))
    q, w = math.sqrt(a / km), math.sqrt(a * km)
    d0 = -math.atan(h0 / q) / w  # where h crosses 0
    below = q * np.tan(w * np.minimum(dv, d0) + math.atan(h0 / q))
    above = s * np.tanh(r * np.maximum(dv - d0, 0.0))
    return np.where(dv <= d0, below, above)


def boucwen_step(
    params: BoucWenParams, voltage_v: ArrayLike, state: BoucWenState
) -> tuple[NDArray[np.float64], BoucWenState]:
    """Advance the Bouc-Wen law through a block (exact for a voltage monotone between samples).

    A falling run is a rising run of ``(-V, -h)`` (the law is odd), so both use one closed form.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise SimModelError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state
    h = np.empty_like(v)
    v0, h0 = state.voltage_v, state.h_v
    starts, dirs = _runs(v, v0)
    bounds = np.append(starts, v.size)
    for k, direction in enumerate(dirs):
        seg = v[bounds[k] : bounds[k + 1]]
        if direction == 0:
            h[bounds[k] : bounds[k + 1]] = h0
        else:
            sgn = 1.0 if direction > 0 else -1.0
            h[bounds[k] : bounds[k + 1]] = sgn * _bw_rising(params, sgn * (seg - v0), sgn * h0)
        v0, h0 = float(seg[-1]), float(h[bounds[k + 1] - 1])
    x = params.b_um_per_v * (v - h)
    return x, BoucWenState(v0, h0)


__all__ = [
    "BoucWenParams",
    "BoucWenState",
    "CHParams",
    "CHState",
    "PIParams",
    "PIState",
    "PreisachParams",
    "PreisachState",
    "boucwen_rest_state",
    "boucwen_step",
    "ch_rest_state",
    "ch_step",
    "pi_rest_state",
    "pi_step",
    "play_step",
    "preisach_position",
    "preisach_rest_state",
    "preisach_step",
]
