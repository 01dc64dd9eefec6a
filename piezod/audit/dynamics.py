"""Linear time-invariant output dynamics of the audit candidates, exact for piecewise-linear signals.

All filters act on one experiment sampled at a constant interval ``dt`` and use a first-order
hold (the signal is linear between samples), like the exact ODE step of the model. The state
before the first sample is either a periodic steady state (the caller prepends the samples one
period later, see :func:`history`) or rest at the first sample.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm
from scipy.signal import lfilter

F64 = NDArray[np.float64]


def history(x: F64, period: int, m: int) -> F64:
    """``m`` samples before ``x[0]``: one period later (periodic signal) or ``x[0]`` repeated.

    Parameters
    ----------
    x
        The signal of one experiment.
    period
        Samples per period (0: not periodic).
    m
        Samples wanted.
    """
    if m <= 0:
        return np.empty(0)
    if 0 < period <= x.size:
        reps = math.ceil(m / period)
        one = x[:period]
        ext = np.tile(one, reps)[-m:] if reps > 1 else one[period - m :]
        return np.asarray(ext, dtype=np.float64)
    return np.full(m, x[0])


def _run_with_history(b: F64, a: F64, x: F64, period: int, m: int) -> F64:
    pre = history(x, period, m)
    xx = np.concatenate((pre, x))
    zi = _rest_state_of(b, a) * xx[0]
    y, _ = lfilter(b, a, xx, zi=zi)
    out: F64 = y[pre.size :]
    return out


def _rest_state_of(b: F64, a: F64) -> F64:
    """Filter state of a steady unit input (every filter here has DC gain 1)."""
    if a.size == 2:
        # First order, DC gain 1: the direct-form-II-transposed state is b1 - a1.
        return np.array([b[1] - a[1]])
    # Second order: z0 = b1 + b2 - a1 - a2, z1 = b2 - a2.
    return np.array([b[1] + b[2] - a[1] - a[2], b[2] - a[2]])


def lag_coefficients(tau_s: float, dt_s: float) -> tuple[F64, F64]:
    """Exact first-order-hold discretisation of ``tau y' = x - y`` (DC gain 1)."""
    a = math.exp(-dt_s / tau_s)
    r = tau_s / dt_s * (1.0 - a)
    return np.array([1.0 - r, r - a]), np.array([1.0, -a])


def first_order_lag(x: F64, dt_s: float, tau_s: float, period: int) -> F64:
    """``x`` through a first-order lag of time constant ``tau_s`` (exact for linear segments)."""
    if tau_s <= 0.0:
        return x
    b, a = lag_coefficients(tau_s, dt_s)
    m = period if period else 0
    if not m:
        m = min(x.size, max(1, math.ceil(10.0 * tau_s / dt_s)))
    return _run_with_history(b, a, x, period, m)


@functools.lru_cache(maxsize=4096)
def _resonance_tf(f0_hz: float, q: float, dt_s: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """First-order-hold discretisation of ``x'' + (w0/Q) x' + w0^2 x = w0^2 u`` as a transfer function.

    State ``s = (x, x')``, ``s' = A s + B u`` with ``u`` linear between samples:
    ``s_{k+1} = Phi s_k + (G0 - G1) u_k + G1 u_{k+1}`` with ``Phi = exp(A h)``,
    ``G0 = A^-1 (Phi - I) B`` and ``G1 = (A^-2 (Phi - I) - h A^-1) B / h``. ``Phi`` of the 2 x 2
    matrix in closed form (``mu = tr A / 2``, ``nu^2 = mu^2 - det A``, complex when underdamped).
    """
    w0 = 2.0 * math.pi * f0_hz
    h = dt_s
    a_mat = np.array([[0.0, 1.0], [-(w0**2), -w0 / q]])
    mu = -0.5 * w0 / q
    nu = complex(mu * mu - w0 * w0) ** 0.5
    ch = complex(np.cosh(nu * h))
    sh = complex(np.sinh(nu * h) / nu) if abs(nu * h) > 1e-8 else h
    em = math.exp(mu * h)
    phi = em * (ch.real * np.eye(2) + sh.real * (a_mat - mu * np.eye(2)))
    a_inv = np.array([[-1.0 / q / w0, -1.0 / w0**2], [1.0, 0.0]])
    bvec = np.array([0.0, w0**2])
    pm = phi - np.eye(2)
    g0 = a_inv @ pm @ bvec
    g1 = (a_inv @ a_inv @ pm @ bvec - h * (a_inv @ bvec)) / h
    bd = phi @ g1 + g0 - g1
    d = g1[0]
    tr = phi[0, 0] + phi[1, 1]
    det = phi[0, 0] * phi[1, 1] - phi[0, 1] * phi[1, 0]
    b = (float(d), float(bd[0] - d * tr), float(phi[0, 1] * bd[1] - phi[1, 1] * bd[0] + d * det))
    return b, (1.0, float(-tr), float(det))


@functools.lru_cache(maxsize=4096)
def _resonance_arrays(f0_hz: float, q: float, dt_s: float) -> tuple[F64, F64]:
    bt, at = _resonance_tf(f0_hz, q, dt_s)
    return np.asarray(bt), np.asarray(at)


def _resonance_tf_expm(f0_hz: float, q: float, dt_s: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Reference implementation of :func:`_resonance_tf` through the matrix exponential (tests)."""
    w0 = 2.0 * math.pi * f0_hz
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
    b = (float(d), float(bd[0] - d * tr), float(phi[0, 1] * bd[1] - phi[1, 1] * bd[0] + d * det))
    return b, (1.0, float(-tr), float(det))


def resonance(x: F64, dt_s: float, f0_hz: float, q: float, period: int) -> F64:
    """``x`` through a unit-gain second-order resonance ``(f0, Q)`` (exact for linear segments)."""
    b, a = _resonance_arrays(float(f0_hz), float(q), float(dt_s))
    m = period
    if not m:
        decay = max(q, 0.5) / (math.pi * f0_hz)
        m = min(x.size, max(2, math.ceil(8.0 * decay / dt_s)))
    return _run_with_history(b, a, x, period, m)


def pure_delay(x: F64, dt_s: float, delay_s: float, period: int) -> F64:
    """``x`` delayed by ``delay_s`` (linear interpolation between samples)."""
    if delay_s <= 0.0:
        return x
    shift = delay_s / dt_s
    whole = math.floor(shift)
    frac = shift - whole
    m = whole + 1
    pre = history(x, period, m)
    xx = np.concatenate((pre, x))
    k = np.arange(x.size) + pre.size - whole
    out: F64 = (1.0 - frac) * xx[k] + frac * xx[k - 1]
    return out
