"""Creep of the simulated stage: a bank of first-order relaxations with log-spaced time constants.

Real PZT creeps logarithmically, ``x(t) = x_0 (1 + gamma log10(t / t_0))`` with ``gamma``
about 1-2 % of the motion per decade of time, over many decades (milliseconds to days).
One or two time constants cannot produce that. A bank of first-order relaxations

    x = d + sum_i w_i z_i,     tau_i dz_i/dt = d - z_i

with ``n`` time constants per decade between ``tau_min`` and ``tau_max`` and equal weights
``w_i = gamma / n`` does: after a step of the drive ``d`` by ``D`` the creep
``D sum_i w_i (1 - exp(-t / tau_i))`` grows by ``gamma D`` per decade of ``t`` for
``tau_min << t << tau_max`` (the kernel ``(t/tau) exp(-t/tau)`` integrates to exactly one
decade per decade of log-spaced ``tau``), with a ripple far below 1e-3 of ``gamma`` for
``n >= 3``. It is the Kelvin-Voigt chain of the linear creep operator of Croft, Shed and
Devasia (2001), cascaded after the rate-independent hysteresis.

Each element is discretised exactly for an input that is linear between samples (the same
assumption as the hysteresis ODE step): with ``h = dt / tau`` and ``a = exp(-h)``

    z_{k+1} = a z_k + b0 d_{k+1} + b1 d_k,   b0 = 1 - (1 - a) / h,   b1 = (1 - a) - b0

for any ``dt`` (the state is the physical ``z`` and the last drive sample, so ``dt`` may
change between blocks), evaluated with :func:`scipy.signal.lfilter` over a whole block.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import lfilter

from hil_sim.errors import SimModelError as ModelError

#: Below this ``h = dt / tau`` the FOH coefficient ``b0`` is summed as a series (no cancellation).
_SERIES_H = 1e-2


def log_spaced_taus(tau_min_s: float, tau_max_s: float, per_decade: int) -> NDArray[np.float64]:
    """Time constants from ``tau_min_s`` to ``tau_max_s`` (inclusive), ``per_decade`` per decade.

    Parameters
    ----------
    tau_min_s, tau_max_s
        Shortest and longest relaxation time (s), ``0 < tau_min_s < tau_max_s``.
    per_decade
        Number of time constants per decade (>= 1); the span is rounded to whole steps.

    Returns
    -------
    ndarray
        The time constants (s), ascending.
    """
    if not (np.isfinite(tau_min_s) and np.isfinite(tau_max_s) and 0.0 < tau_min_s < tau_max_s):
        raise ModelError(f"need 0 < tau_min_s < tau_max_s, got {tau_min_s!r}, {tau_max_s!r}")
    if per_decade < 1:
        raise ModelError(f"per_decade must be >= 1, got {per_decade}")
    decades = np.log10(tau_max_s / tau_min_s)
    count = max(2, round(decades * per_decade) + 1)
    return np.logspace(np.log10(tau_min_s), np.log10(tau_max_s), count)


def foh_lowpass_coefficients(
    tau_s: ArrayLike, dt_s: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Exact discrete coefficients ``(a, b0, b1)`` of ``tau dz/dt = d - z`` for linear-in-time input.

    ``z_{k+1} = a z_k + b0 d_{k+1} + b1 d_k``; accurate to rounding for ``dt / tau`` from 1e-15 to
    1e15 (``b0`` is summed as a series for small ``dt / tau``).

    Parameters
    ----------
    tau_s
        Time constants (s), > 0.
    dt_s
        Sample interval (s), > 0.
    """
    tau = np.asarray(tau_s, dtype=np.float64)
    h = dt_s / tau
    a = np.exp(-h)
    one_minus_a = -np.expm1(-h)
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = 1.0 - one_minus_a / h
    # 1 - (1 - e^-h)/h = h/2 - h^2/6 + h^3/24 - h^4/120 + h^5/720 - h^6/5040
    series = h * (1 / 2 - h * (1 / 6 - h * (1 / 24 - h * (1 / 120 - h * (1 / 720 - h / 5040)))))
    b0 = np.where(h < _SERIES_H, series, direct)
    b1 = one_minus_a - b0
    return a, b0, b1


def lowpass_block(
    tau_s: float,
    drive: NDArray[np.float64],
    dt_s: float,
    z_last: NDArray[np.float64],
    d_last: NDArray[np.float64],
) -> NDArray[np.float64]:
    """One exact first-order lowpass through a block, rows = channels.

    Parameters
    ----------
    tau_s
        Time constant (s).
    drive
        Input, shape ``(channels, n)``, ``n >= 1``.
    dt_s
        Sample interval (s).
    z_last, d_last
        Output and input at the sample before the block, shape ``(channels,)``.

    Returns
    -------
    ndarray
        Output, shape ``(channels, n)``; its last column is the new ``z_last``.
    """
    a, b0, b1 = (float(c) for c in foh_lowpass_coefficients(tau_s, dt_s))
    zi = (b1 * d_last + a * z_last)[:, None]
    out, _ = lfilter([b0, b1], [1.0, -a], drive, axis=-1, zi=zi)
    result: NDArray[np.float64] = out
    return result


@dataclass(frozen=True, slots=True, eq=False)
class CreepBank:
    """Frozen parameters of the creep operator for a set of channels.

    Attributes
    ----------
    taus_s
        Relaxation times (s), shape ``(m,)``, shared by all channels.
    weights
        Weight of each element per channel, shape ``(channels, m)``; ``gamma / per_decade``
        for a creep of ``gamma`` (fraction of the drive) per decade of time.
    """

    taus_s: NDArray[np.float64]
    weights: NDArray[np.float64]

    def __post_init__(self) -> None:
        taus = np.array(self.taus_s, dtype=np.float64)
        weights = np.atleast_2d(np.array(self.weights, dtype=np.float64))
        if taus.ndim != 1 or taus.size == 0 or not np.all(np.isfinite(taus) & (taus > 0)):
            raise ModelError("taus_s must be a non-empty 1-D array of finite times > 0")
        if weights.shape[1] != taus.size:
            raise ModelError(f"weights must have shape (channels, {taus.size}), got {weights.shape}")
        if not np.all(np.isfinite(weights) & (weights >= 0)):
            raise ModelError("creep weights must be finite and >= 0")
        taus.setflags(write=False)
        weights.setflags(write=False)
        object.__setattr__(self, "taus_s", taus)
        object.__setattr__(self, "weights", weights)

    @classmethod
    def from_law(
        cls,
        pct_per_decade: ArrayLike,
        tau_min_s: float,
        tau_max_s: float,
        per_decade: int,
        spectrum_exponent: float = 0.0,
    ) -> CreepBank:
        """A bank creeping ``pct_per_decade`` percent of the drive per decade of time, per channel.

        Parameters
        ----------
        pct_per_decade
            Creep per decade of time (% of the drive step) at ``t = 1 s``, one value per channel.
        tau_min_s, tau_max_s, per_decade
            Span and density of the relaxation times, see :func:`log_spaced_taus`.
        spectrum_exponent
            ``beta`` of a power-law relaxation spectrum: weights ``proportional to tau^beta``, so
            the step response grows like ``t^beta`` (a power law, Findley / Jung-Gweon) instead
            of ``log t``; the creep per decade is ``pct_per_decade (t / 1 s)^beta``. 0 gives
            the logarithmic law (equal weights).
        """
        taus = log_spaced_taus(tau_min_s, tau_max_s, per_decade)
        gamma = np.atleast_1d(np.asarray(pct_per_decade, dtype=np.float64)) / 100.0
        # Equal weights per element: with log-spaced taus the density is exactly per_decade per decade.
        step = np.log10(taus[1] / taus[0])
        shape = taus**spectrum_exponent
        weights = (gamma * step)[:, None] * shape[None, :]
        return cls(taus, weights)

    @property
    def channels(self) -> int:
        """Number of channels."""
        return int(self.weights.shape[0])

    @property
    def total_weight(self) -> NDArray[np.float64]:
        """Creep after infinite time as a fraction of the drive, per channel."""
        total: NDArray[np.float64] = self.weights.sum(axis=1)
        return total

    def step_response(self, t_s: ArrayLike) -> NDArray[np.float64]:
        """Creep ``sum_i w_i (1 - exp(-t / tau_i))`` after a unit drive step, shape ``(channels, n)``."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        kernel = -np.expm1(-t[None, :] / self.taus_s[:, None])
        out: NDArray[np.float64] = self.weights @ kernel
        return out


@dataclass(frozen=True, slots=True, eq=False)
class CreepState:
    """State of the creep bank after a sample.

    Attributes
    ----------
    drive
        Last drive sample per channel, shape ``(channels,)``.
    z
        Output of every element per channel, shape ``(m, channels)``.
    """

    drive: NDArray[np.float64]
    z: NDArray[np.float64]


def creep_rest_state(bank: CreepBank, drive: ArrayLike) -> CreepState:
    """Fully relaxed state at a constant drive (every element equal to the drive).

    Parameters
    ----------
    bank
        The creep bank.
    drive
        Drive per channel (scalar broadcasts), in the unit of the drive (um).
    """
    d = np.broadcast_to(np.asarray(drive, dtype=np.float64), (bank.channels,)).copy()
    z = np.repeat(d[None, :], bank.taus_s.size, axis=0)
    return CreepState(drive=d, z=z)


def creep_step(
    bank: CreepBank, drive: ArrayLike, dt_s: float, state: CreepState
) -> tuple[NDArray[np.float64], CreepState]:
    """Advance the creep bank exactly through a block.

    Parameters
    ----------
    bank
        The creep bank.
    drive
        Drive samples, shape ``(channels, n)``; the first step goes from ``state.drive``.
    dt_s
        Sample interval (s), > 0.
    state
        State before the block.

    Returns
    -------
    creep : ndarray
        The creep ``sum_i w_i z_i`` after each sample, shape ``(channels, n)`` (add it to the drive).
    state : CreepState
        State after the block.
    """
    d = np.asarray(drive, dtype=np.float64)
    if d.ndim != 2 or d.shape[0] != bank.channels:
        raise ModelError(f"drive must have shape ({bank.channels}, n), got {d.shape}")
    if not (np.isfinite(dt_s) and dt_s > 0.0):
        raise ModelError(f"dt_s must be finite and > 0, got {dt_s!r}")
    if d.shape[1] == 0:
        return np.zeros_like(d), state
    a, b0, b1 = foh_lowpass_coefficients(bank.taus_s, dt_s)
    total = np.zeros_like(d)
    z_new = np.empty_like(state.z)
    for i in range(bank.taus_s.size):
        zi = (b1[i] * state.drive + a[i] * state.z[i])[:, None]
        z_i, _ = lfilter([b0[i], b1[i]], [1.0, -a[i]], d, axis=-1, zi=zi)
        z_new[i] = z_i[:, -1]
        np.multiply(z_i, bank.weights[:, i : i + 1], out=z_i)
        total += z_i
    return total, CreepState(drive=d[:, -1].copy(), z=z_new)
