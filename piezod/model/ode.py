"""Exact per-sample solution of the rate-independent hysteresis ODE (2.21).

Between two samples the voltage is taken as linear (monotone), so on every step
``V_k -> V_{k+1}`` with direction ``s = sgn(V_{k+1} - V_k)`` the ODE is linear in
``V`` and its solution (2.22) is exact. With ``y = x - b V`` and
``delta = (b - u) / alpha`` one step is

    y_{k+1} = a_k y_k + s_k delta (a_k - 1),    a_k = exp(-alpha |V_{k+1} - V_k|)

a linear recurrence. With ``L_k = alpha * sum_{j<k} |dV_j|`` (the scaled total
variation) it has the closed form

    y_n = exp(-L_n) [ y_0 + delta * sum_{k<n} s_k (exp(L_k) - exp(L_{k+1})) ]

which is evaluated with cumulative sums in chunks whose ``L`` span stays far from
overflow. Cost: a handful of vectorised passes per block, independent of the
number of reversals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import ModelError
from piezod.model.lambertw import lambertw0_exp, lambertw0_exp_scalar
from piezod.model.params import HysteresisParams

#: Largest scaled total variation inside one cumulative chunk; exp(400) is far from overflow.
_CHUNK_SPAN = 400.0


@dataclass(frozen=True, slots=True)
class HysteresisState:
    """State of the hysteresis ODE after a sample.

    Attributes
    ----------
    voltage_v
        Voltage of the last sample (V).
    position_um
        Hysteretic position at that voltage (um).
    """

    voltage_v: float
    position_um: float


def relaxed_state(params: HysteresisParams, voltage_v: float = 0.0) -> HysteresisState:
    """State on the virgin curve's centre line, ``x = b V`` (a piezo at rest).

    Parameters
    ----------
    params
        Hysteresis parameters.
    voltage_v
        Voltage at which the stage rests.
    """
    return HysteresisState(voltage_v=float(voltage_v), position_um=params.b_um_per_v * float(voltage_v))


def hysteresis_step(
    params: HysteresisParams, voltage_v: ArrayLike, state: HysteresisState
) -> tuple[NDArray[np.float64], HysteresisState]:
    """Advance the ODE (2.21) exactly through a block of voltage samples.

    Parameters
    ----------
    params
        Hysteresis parameters.
    voltage_v
        Voltage samples (V), shape ``(n,)``; the first step goes from
        ``state.voltage_v`` to ``voltage_v[0]``.
    state
        State before the block.

    Returns
    -------
    position_um : ndarray
        Hysteretic position after each sample (um), shape ``(n,)``.
    state : HysteresisState
        State after the last sample, to pass to the next block.
    """
    v = np.asarray(voltage_v, dtype=np.float64)
    if v.ndim != 1:
        raise ValueError(f"voltage_v must be 1-D, got shape {v.shape}")
    if v.size == 0:
        return np.empty(0), state
    b = params.b_um_per_v
    delta = params.delta_um
    dv = np.diff(v, prepend=state.voltage_v)
    s = np.sign(dv)
    # L_{k+1}: scaled total variation after step k (L_0 = 0 before the block).
    L_next = np.cumsum(params.alpha_per_v * np.abs(dv))
    y_out = np.empty_like(v)
    y0 = state.position_um - b * state.voltage_v
    start = 0
    n = v.size
    while start < n:
        base = L_next[start - 1] if start > 0 else 0.0
        stop = int(np.searchsorted(L_next, base + _CHUNK_SPAN, side="right"))
        stop = max(stop, start + 1)
        Lk1 = L_next[start:stop] - base
        Lk = np.concatenate(([0.0], Lk1[:-1]))
        terms = s[start:stop] * (np.exp(Lk) - np.exp(Lk1))
        y_chunk = np.exp(-Lk1) * (y0 + delta * np.cumsum(terms))
        y_out[start:stop] = y_chunk
        y0 = float(y_chunk[-1])
        start = stop
    x = y_out + b * v
    return x, HysteresisState(voltage_v=float(v[-1]), position_um=float(x[-1]))


#: Up to this many monotone runs per block the runs are evaluated slice by slice.
_MAX_SLICED_RUNS = 8


def _run_starts(dx: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """First sample and direction of every monotone run of the targets.

    A run starts at a sample whose step has the opposite sign of the last
    non-zero step; zero steps belong to the run they are in.
    """
    sign = np.sign(dx)
    if sign[0] != 0.0 and np.all(sign):
        # the usual case: no held samples
        first = np.concatenate(([0], np.flatnonzero(sign[1:] != sign[:-1]) + 1))
        return first, sign[first]
    moving = np.flatnonzero(sign)
    if moving.size == 0:
        return moving, np.empty(0)
    sign = sign[moving]
    first = np.concatenate(([0], np.flatnonzero(sign[1:] != sign[:-1]) + 1))
    return moving[first], sign[first]


def hysteresis_inverse_step(
    params: HysteresisParams,
    position_um: ArrayLike,
    state: HysteresisState,
    *,
    kappa_um_per_v: float = 0.0,
) -> tuple[NDArray[np.float64], HysteresisState]:
    """Voltages whose exact forward step (:func:`hysteresis_step`) reaches the target positions.

    Inside a monotone run of the targets (direction ``s``) the voltage is
    monotone too and the ODE follows one branch ``x = b V - s delta + K exp(-s alpha V)``
    with ``K`` fixed by the state at the start of the run, so every sample of the
    run is an independent Lambert W evaluation. With ``(V_0, x_0)`` the state at
    the run start, ``eta_0 = x_0 - b V_0``, ``B = alpha (s eta_0 + delta) / b`` and
    ``A = alpha s (x - x_0) / b + B``, the scaled voltage step is

        t = alpha s (V - V_0) = A + W0(-B exp(-A))

    (``W0`` because ``x`` must move in the direction of the run). The argument
    never leaves the real branch: ``B exp(-A) <= B exp(-B) <= 1/e``.

    A first pass loops over the runs only (one scalar W per run to find the state
    at its end); a second pass evaluates all samples at once.

    Non-monotone branches: if ``B > 1`` at the start of a run (possible when
    ``b > 2 u`` and the state lies near the opposite asymptote, e.g. right after
    a long run in the other direction), the branch first moves *against* the run
    direction by up to ``b / alpha (B - 1 - ln B)`` before it turns. No monotone
    voltage can avoid that dip; the inverse returns the unique ``W0`` voltage
    beyond it, so the voltage jumps at the first sample of such a run and the
    stage passes through the dip between two samples. All targets are still
    reached exactly at the sample instants.

    Parameters
    ----------
    params
        Hysteresis parameters.
    position_um
        Target positions (um), shape ``(n,)``; the first step goes from
        ``state.position_um`` to ``position_um[0]``.
    state
        State before the block (from :func:`relaxed_state`, :func:`hysteresis_step`
        or a previous call).

    Returns
    -------
    voltage_v : ndarray
        Voltages (V), shape ``(n,)``; a sample equal to the previous target keeps
        the previous voltage.
    state : HysteresisState
        State after the last sample, to pass to the next block (either function).

    Notes
    -----
    With ``kappa_um_per_v`` the targets are ``x' = x_h + kappa V``: the hysteretic
    position plus a term linear in the voltage, the creep term of (3.8)
    (``kappa = b_hat - b``; the constant ``-kappa V_C`` is the caller's). Every
    branch keeps the form "linear + exponential" with slope ``b + kappa`` in its
    linear part, so the same Lambert W solution applies; the returned state holds
    the hysteretic position ``x_h = x' - kappa V``. For a steady triangle this is
    exactly the inverse of (3.8), and after a change of range, offset or rate the
    ODE state carries the transient of chapter 5.
    """
    x = np.asarray(position_um, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"position_um must be 1-D, got shape {x.shape}")
    if x.size == 0:
        return np.empty(0), state
    if not (math.isfinite(float(x.min())) and math.isfinite(float(x.max()))):
        bad = int(np.flatnonzero(~np.isfinite(x))[0])
        raise ModelError(f"target position {x[bad]!r} at sample {bad} is not finite")
    a, b, delta = params.alpha_per_v, params.b_um_per_v, params.delta_um
    kappa = float(kappa_um_per_v)
    bp = b + kappa
    if not (math.isfinite(bp) and bp > 0.0):
        raise ModelError(f"b + kappa = {bp!r} um/V must be > 0 for an invertible branch")
    n = x.size
    x_start = state.position_um + kappa * state.voltage_v
    dx = np.empty_like(x)
    dx[0] = x[0] - x_start
    np.subtract(x[1:], x[:-1], out=dx[1:])
    starts, signs = _run_starts(dx)
    v = np.full(n, state.voltage_v)
    if starts.size == 0:
        return v, HysteresisState(state.voltage_v, float(x[-1]) - kappa * state.voltage_v)
    n_runs = starts.size
    ends = np.append(starts[1:], n) - 1
    v0 = np.empty(n_runs)
    x0 = np.empty(n_runs)
    big_b = np.empty(n_runs)
    v_prev, x_prev = state.voltage_v, x_start
    for r in range(n_runs):
        s = float(signs[r])
        v0[r], x0[r] = v_prev, x_prev
        big_b[r] = bb = a * (s * (x_prev - bp * v_prev) + delta) / bp
        x_end = float(x[ends[r]])
        aa = a * s * (x_end - x_prev) / bp + bb
        if bb != 0.0:
            aa += lambertw0_exp_scalar(math.log(abs(bb)) - aa, negative=bb > 0.0)
        v_prev, x_prev = v_prev + s * aa / a, x_end
    # Per run, with t = A + w: y = ln|B| - A = c0 + c1 x and V = V_0 + s t / alpha = k0 + x / b' + k1 w.
    c1 = -(a / bp) * signs
    with np.errstate(divide="ignore"):
        c0 = np.log(np.abs(big_b)) - big_b - c1 * x0
    k0 = v0 + signs * big_b / a - x0 / bp
    k1 = signs / a
    neg = big_b > 0.0
    edges = np.append(starts, n)
    if n_runs <= _MAX_SLICED_RUNS:
        for r in range(n_runs):
            sl = slice(int(edges[r]), int(edges[r + 1]))
            y = x[sl] * float(c1[r])
            y += float(c0[r])
            w = lambertw0_exp(y, negative=bool(neg[r]))
            w *= float(k1[r])
            w += float(k0[r])
            w += x[sl] * (1.0 / bp)
            v[sl] = w
    else:
        first = int(starts[0])
        lengths = np.diff(edges)
        xs = x[first:]
        y = np.repeat(c1, lengths) * xs + np.repeat(c0, lengths)
        neg_s = np.repeat(neg, lengths)
        w = np.empty_like(y)
        for flag in (True, False):
            m = neg_s == flag
            if m.any():
                w[m] = lambertw0_exp(y[m], negative=flag)
        v[first:] = np.repeat(k0, lengths) + xs / bp + np.repeat(k1, lengths) * w
    return v, HysteresisState(voltage_v=float(v[-1]), position_um=float(x[-1]) - kappa * float(v[-1]))
