"""The time-domain ("dynamic") scanner model and its exact per-sample inverse.

The thesis model (3.8) describes steady triangular scans at one frequency. This model
describes any voltage waveform on any axis: the rate-independent hysteresis ODE (2.21)
followed by a linear creep operator that spans many decades of time with few parameters.

Model
-----
Per sample ``n`` (interval ``dt``)::

    x_h = H(V)                                 hysteresis ODE (2.21), exact step
    z_i: tau_i dz_i/dt = x_h - z_i             creep elements, i = 1..m
    x   = x_h + sum_i w_i z_i                  position

The relaxation times ``tau_i`` are log-spaced, ``creep_per_decade`` per decade from
``creep_tau_min_s`` to ``creep_tau_max_s``; the weights follow from two parameters,

    w_i = gamma / 100 * Delta * (tau_i / 1 s)^beta / Gamma(1 - beta),   Delta = log10(tau_{i+1} / tau_i)

with ``gamma = creep_pct_per_decade`` and ``beta = creep_exponent``. After a step of the
hysteretic position by ``D`` the creep grows by ``gamma(t) D / 100`` per decade of time with
``gamma(t) = gamma (t / 1 s)^beta`` for ``tau_min << t << tau_max``: ``beta = 0`` is the
logarithmic creep law (about 1-2 % of the motion per decade for PZT), ``beta != 0`` a
fractional (power-law) creep. The elements are driven by the hysteretic position (the
cascade "hysteresis, then linear viscoelastic creep"), so creep is a fraction of the
*motion*. A stage resting at ``V`` for ever sits at ``x = (1 + W) b V``, ``W = sum w_i``;
0 um at 0 V.

Discretisation (what "exact" means here)
----------------------------------------
* The voltage is taken linear between samples: the hysteresis step is the exact ODE
  solution (:func:`piezod.model.ode.hysteresis_step`).
* The creep elements take their drive ``x_h`` linear between samples (first-order hold):
  with ``h = dt / tau``, ``a = exp(-h)``, ``b0 = 1 - (1 - a) / h``, ``b1 = 1 - a - b0``,
  ``z[n] = a z[n-1] + b0 x_h[n] + b1 x_h[n-1]``, exact for that drive and any ``dt``
  (``dt`` may change between blocks). Between samples ``x_h`` is in fact slightly curved
  (it follows the exponential branch of the ODE), an error of order ``dt^2`` per step.

The state is kept as the deviations ``e_i = z_i - x_h``, which relax to exactly 0 at rest
(``e[n] = a e[n-1] - (1 - b0) (x_h[n] - x_h[n-1])``); then ``x = (1 + W) x_h + sum w_i e_i``.
Written this way the rounding of ``a`` (``a`` is within 1e-10 of 1 for ``tau = 1e5 s`` at
100 kS/s, so ``1 - a`` carries only six significant digits) only perturbs transient decay
rates, never a steady state.

Inverse
-------
The creep inverse ``x -> x_h`` is a linear system. With the pre-state
``zeta_i[n] = a_i z_i[n-1] + b1_i x_h[n-1]`` the forward model is
``x[n] = (1 + W0) x_h[n] + w . zeta[n]``, ``zeta[n+1] = a zeta[n] + c x_h[n]``
(``W0 = sum w_i b0_i``, ``c_i = (1 - a_i)(1 - b0_i) > 0``), so the inverse has the state
matrix ``diag(a) - c w^T / (1 + W0)``: diagonal plus rank one. In rates ``r_i = 1 - a_i``
its eigenvalues ``1 - rho_k`` are the roots of the secular equation

    F(rho) = 1 + W0 + sum_i w_i c_i / (r_i - rho) = 0,

one in each interval between consecutive ``r_i`` and one above the largest (``F``
increases between its poles): real, interlaced with the element rates, each root
``rho_k = r_k + delta_k`` just above "its" element rate (``delta_k ~ w_k r_k``). They are
found by bisection on ``delta_k`` (well conditioned in rates: no ``1 - a`` is formed for
them). The eigenvectors are ``c / (rho_k - r)`` and ``w / (rho_k - r)``, so the modal
transformation is explicit and nearly diagonal. In modal coordinates, measured from their
steady state ``G_k x`` (``G_k = 1 / (F'(rho_k) rho_k)``), the inverse is

    x_h[n]   = x[n] / (1 + W) + Gs (x[n] - x[n-1]) - sum_k eps_k[n],
    eps_k[n+1] = q_k eps_k[n] - q_k G_k (x[n] - x[n-1]),    q_k = 1 - rho_k,

with ``Gs = 1/(1 + W0) - 1/(1 + W)``: ``m`` decoupled first-order filters of the target
increments (:func:`scipy.signal.lfilter` with initial conditions), exact at steady state by
construction. The hysteretic targets ``x_h`` are then inverted exactly by the Lambert W
step :func:`piezod.model.ode.hysteresis_inverse_step`. A held target keeps the position
constant while ``x_h`` (and the voltage) creeps back.

Everything is block-size invariant: the state carries exactly across blocks, offset and
range changes, pauses (:func:`dynamic_hold`) and axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import lfilter

from piezod.errors import ModelError
from piezod.model.ode import HysteresisState, hysteresis_inverse_step, hysteresis_step
from piezod.model.params import HysteresisParams

F64 = NDArray[np.float64]

#: Reference time of the creep law ``gamma(t) = gamma (t / T_REF)^beta`` (s).
T_REF_S = 1.0
#: The total creep ``W = sum w_i`` must stay below this (the inverse's modes stay stable well beyond).
MAX_TOTAL_CREEP = 0.9
#: Below this ``h = dt / tau`` the first-order-hold coefficient ``b0`` is summed as a series.
_SERIES_H = 1e-2
_BISECTION_STEPS = 110
#: A total creep below this is ignored by the inverse (it changes positions by less than 1e-12).
_NEGLIGIBLE_CREEP = 1e-12
#: Elements with ``a = exp(-dt / tau)`` below this are memoryless in the inverse.
_MEMORYLESS = 1e-10


def _require(cond: bool, what: str) -> None:
    if not cond:
        raise ModelError(what)


@lru_cache(maxsize=64)
def creep_taus(tau_min_s: float, tau_max_s: float, per_decade: int) -> F64:
    """Log-spaced relaxation times from ``tau_min_s`` to ``tau_max_s`` (both included).

    Parameters
    ----------
    tau_min_s, tau_max_s
        Shortest and longest relaxation time (s), ``0 < tau_min_s < tau_max_s``.
    per_decade
        Relaxation times per decade (>= 1); the span is rounded to whole steps.

    Returns
    -------
    ndarray
        The times (s), ascending, read-only.
    """
    _require(
        math.isfinite(tau_min_s) and math.isfinite(tau_max_s) and 0.0 < tau_min_s < tau_max_s,
        f"need 0 < creep_tau_min_s < creep_tau_max_s, got {tau_min_s!r}, {tau_max_s!r}",
    )
    _require(per_decade >= 1, f"creep_per_decade must be >= 1, got {per_decade}")
    decades = math.log10(tau_max_s / tau_min_s)
    count = max(2, round(decades * per_decade) + 1)
    taus = np.logspace(math.log10(tau_min_s), math.log10(tau_max_s), count)
    taus.setflags(write=False)
    return taus


@dataclass(frozen=True, slots=True)
class DynamicParams:
    """Parameters of the dynamic model (units in the names).

    Attributes
    ----------
    alpha_per_v, b_um_per_v, u_um_per_v
        Hysteresis ODE (2.21): transition rate (1/V), sensitivity and slope after a
        reversal (um/V) of the fast (hysteretic) response, faster than ``creep_tau_min_s``.
    creep_pct_per_decade
        ``gamma``: creep per decade of time at 1 s, in % of the hysteretic motion, >= 0.
    creep_exponent
        ``beta``: the creep per decade scales as ``(t / 1 s)^beta`` (0: logarithmic law).
    creep_tau_min_s, creep_tau_max_s
        Span of the relaxation times (s).
    creep_per_decade
        Relaxation times per decade.
    """

    alpha_per_v: float
    b_um_per_v: float
    u_um_per_v: float
    creep_pct_per_decade: float
    creep_exponent: float = 0.0
    creep_tau_min_s: float = 1e-3
    creep_tau_max_s: float = 1e5
    creep_per_decade: int = 3

    def __post_init__(self) -> None:
        HysteresisParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)
        g = self.creep_pct_per_decade
        _require(math.isfinite(g) and g >= 0.0, f"creep_pct_per_decade must be finite and >= 0, got {g!r}")
        beta = self.creep_exponent
        _require(
            math.isfinite(beta) and abs(beta) <= 0.9, f"creep_exponent must be in [-0.9, 0.9], got {beta!r}"
        )
        _require(
            isinstance(self.creep_per_decade, int) and 1 <= self.creep_per_decade <= 20,
            f"creep_per_decade must be an integer in [1, 20], got {self.creep_per_decade!r}",
        )
        creep_taus(self.creep_tau_min_s, self.creep_tau_max_s, self.creep_per_decade)
        total = float(self.weights.sum())
        _require(
            total < MAX_TOTAL_CREEP,
            f"total creep sum(w) = {total:.4g} must stay below {MAX_TOTAL_CREEP} "
            "(lower creep_pct_per_decade, creep_exponent or the tau span)",
        )

    @property
    def hysteresis(self) -> HysteresisParams:
        """The ODE (2.21) parameters."""
        return HysteresisParams(self.alpha_per_v, self.b_um_per_v, self.u_um_per_v)

    @property
    def taus_s(self) -> F64:
        """Relaxation times (s), ascending."""
        return creep_taus(self.creep_tau_min_s, self.creep_tau_max_s, self.creep_per_decade)

    @property
    def weights(self) -> F64:
        """Element weights ``w_i`` (fraction of the hysteretic position), same order as :attr:`taus_s`."""
        return creep_weights(self.taus_s, self.creep_pct_per_decade, self.creep_exponent)

    @property
    def total_creep(self) -> float:
        """``W = sum w_i``: creep after infinite time as a fraction of the hysteretic motion."""
        return float(self.weights.sum())

    @property
    def static_sensitivity_um_per_v(self) -> float:
        """``(1 + W) b``: slope of the rest position over the voltage."""
        return (1.0 + self.total_creep) * self.b_um_per_v

    def step_response(self, t_s: ArrayLike) -> F64:
        """Creep after a unit step of the hysteretic position: ``sum_i w_i (1 - exp(-t / tau_i))``."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        out: F64 = self.weights @ -np.expm1(-t[None, :] / self.taus_s[:, None])
        return out


def creep_weights(taus_s: F64, pct_per_decade: float, exponent: float) -> F64:
    """Weights of log-spaced elements: ``gamma / 100 * Delta * (tau / 1 s)^beta / Gamma(1 - beta)``.

    With a weight density ``c tau^beta`` per decade the creep grows by ``c Gamma(1 - beta) t^beta``
    per decade of ``t``, so the ``Gamma`` normalisation makes ``gamma`` the creep per decade at
    1 s for any ``beta``.

    Parameters
    ----------
    taus_s
        Log-spaced relaxation times (s), ascending, at least two.
    pct_per_decade
        ``gamma`` (% per decade at 1 s).
    exponent
        ``beta``, ``|beta| < 1``.
    """
    step = math.log10(float(taus_s[1] / taus_s[0]))
    scale = pct_per_decade / 100.0 * step / math.gamma(1.0 - exponent)
    w: F64 = scale * (taus_s / T_REF_S) ** exponent
    return w


# --------------------------------------------------------------------------------------------- state


@dataclass(frozen=True, slots=True, eq=False)
class DynamicState:
    """State of the dynamic model after a sample (shared by the forward model and the inverse).

    Attributes
    ----------
    hysteresis
        ODE state: the last voltage and the hysteretic position ``x_h`` there.
    position_um
        Position ``x`` after the last sample (um).
    creep_um
        Element deviations ``e_i = z_i - x_h`` (um), order of :attr:`DynamicParams.taus_s`
        (read-only).
    """

    hysteresis: HysteresisState
    position_um: float
    creep_um: F64

    def __post_init__(self) -> None:
        e = np.array(self.creep_um, dtype=np.float64)
        if e.ndim != 1:
            raise ModelError(f"creep_um must be 1-D, got shape {e.shape}")
        e.setflags(write=False)
        object.__setattr__(self, "creep_um", e)

    @property
    def voltage_v(self) -> float:
        """The last voltage (V)."""
        return self.hysteresis.voltage_v

    @property
    def hysteretic_um(self) -> float:
        """The hysteretic position ``x_h`` (um)."""
        return self.hysteresis.position_um


def dynamic_rest_state(params: DynamicParams, voltage_v: float = 0.0) -> DynamicState:
    """A stage that has rested at ``voltage_v`` for ever: ``x_h = b V``, creep relaxed.

    Parameters
    ----------
    params
        Model parameters.
    voltage_v
        The rest voltage (V).
    """
    v = float(voltage_v)
    _require(math.isfinite(v), f"rest voltage must be finite, got {voltage_v!r}")
    xh = params.b_um_per_v * v
    return DynamicState(HysteresisState(v, xh), (1.0 + params.total_creep) * xh, np.zeros(params.taus_s.size))


def _check_state(params: DynamicParams, state: DynamicState) -> None:
    if state.creep_um.size != params.taus_s.size:
        raise ModelError(
            f"state has {state.creep_um.size} creep elements, the parameters {params.taus_s.size}"
        )


def _check_dt(dt_s: float) -> float:
    dt = float(dt_s)
    _require(math.isfinite(dt) and dt > 0.0, f"dt_s must be finite and > 0, got {dt_s!r}")
    return dt


def _block(values: ArrayLike, name: str) -> F64:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 1:
        raise ModelError(f"{name} must be 1-D, got shape {a.shape}")
    if a.size and not (math.isfinite(float(a.min())) and math.isfinite(float(a.max()))):
        bad = int(np.flatnonzero(~np.isfinite(a))[0])
        raise ModelError(f"{name}[{bad}] = {a[bad]!r} is not finite")
    return a


# -------------------------------------------------------------------------------------- discretisation


def foh_coefficients(taus_s: F64, dt_s: float) -> tuple[F64, F64, F64]:
    """``(a, r, b0)`` of ``tau dz/dt = d - z`` for a drive linear between samples.

    ``a = exp(-h)``, ``r = 1 - a`` (computed without cancellation), ``b0 = 1 - r / h``
    (summed as a series for small ``h = dt / tau``).
    """
    h = dt_s / taus_s
    a = np.exp(-h)
    r = -np.expm1(-h)
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = 1.0 - r / h
    series = h * (1 / 2 - h * (1 / 6 - h * (1 / 24 - h * (1 / 120 - h * (1 / 720 - h / 5040)))))
    b0: F64 = np.where(h < _SERIES_H, series, direct)
    return a, r, b0


@dataclass(frozen=True, eq=False)
class CreepDiscretisation:
    """The creep operator of a parameter set at one sample interval, with its modal inverse.

    Attributes
    ----------
    a, one_minus_b0
        Element recursion ``e[n] = a e[n-1] - (1 - b0) (x_h[n] - x_h[n-1])``.
    w, total, total_b0
        Weights, ``W = sum w``, ``W0 = sum w b0``.
    q, gain
        Inverse modes: ``eps_k[n+1] = q_k eps_k[n] - q_k gain_k (x[n] - x[n-1])``.
    gain_sum
        ``Gs = 1 / (1 + W0) - 1 / (1 + W)``.
    to_modes
        ``(m, m)``: modal deviations from element deviations, ``eps[0] = to_modes @ e`` plus
        a term in ``(1 + W) x_h - x`` (zero for a consistent state).
    to_elements
        ``(m, m)``: element deviations from modal deviations.
    rates
        ``rho_k`` (the inverse's mode rates), for diagnostics.
    memoryless
        Elements treated as memoryless (``a < 1e-10``): merged into one mode of rate 1.
    """

    a: F64
    one_minus_b0: F64
    w: F64
    total: float
    total_b0: float
    q: F64
    gain: F64
    gain_sum: float
    to_modes: F64
    to_elements: F64
    rates: F64
    memoryless: NDArray[np.bool_]


@lru_cache(maxsize=64)
def discretise(params: DynamicParams, dt_s: float) -> CreepDiscretisation:
    """The creep operator of ``params`` at the sample interval ``dt_s`` and its modal inverse (cached).

    Elements much faster than the sample interval (``a < 1e-10``) have no memory beyond the
    previous drive sample; they share the rate ``r = 1`` and enter the inverse as one element.

    Raises
    ------
    ModelError
        When the inverse has a mode outside the unit circle (total creep too large for so
        coarse a ``dt``), or ``dt_s`` is not a positive finite number.
    """
    dt = _check_dt(dt_s)
    taus = params.taus_s
    w = params.weights
    a, r, b0 = foh_coefficients(taus, dt)
    one_b0 = 1.0 - b0
    c = r * one_b0
    total = float(w.sum())
    total_b0 = float(w @ b0)
    m = taus.size
    memoryless = a < _MEMORYLESS
    if total < _NEGLIGIBLE_CREEP:
        zeros = np.zeros((m, m))
        return CreepDiscretisation(
            a, one_b0, w, total, total_b0, 1.0 - r, np.zeros(m), 0.0, zeros, zeros, r, memoryless
        )
    # The inverse's elements: the memoryless ones merged (rate 1), then the others; rates descend
    # (taus ascend), root k lies in (r_k, r_{k-1}), root 0 above r_0.
    dyn = ~memoryless
    merged = bool(memoryless.any())
    r_red = np.concatenate(([1.0] if merged else [], r[dyn]))
    wc = np.concatenate(([float((w * c)[memoryless].sum())] if merged else [], (w * c)[dyn]))
    n_red = r_red.size
    diff = r_red[:, None] - r_red[None, :]  # diff[i, k] = r_i - r_k
    gap = np.empty(n_red)
    gap[1:] = r_red[:-1] - r_red[1:]
    gap[0] = float(wc.sum()) / (1.0 + total_b0) * 2.0
    lo = np.minimum(gap, wc) * 1e-30  # F < 0 there: -w_k c_k / delta dominates
    hi = gap.copy()
    one_w0 = 1.0 + total_b0
    cols = np.arange(n_red)

    def secular(delta: F64) -> F64:
        den = diff - delta[None, :]
        den[cols, cols] = -delta
        out: F64 = one_w0 + wc @ (1.0 / den)
        return out

    for _ in range(_BISECTION_STEPS):
        mid = np.sqrt(lo) * np.sqrt(hi)
        neg = secular(mid) < 0.0
        lo = np.where(neg, mid, lo)
        hi = np.where(neg, hi, mid)
    delta = np.sqrt(lo) * np.sqrt(hi)
    rho = r_red + delta
    den = diff - delta[None, :]
    den[cols, cols] = -delta  # den[i, k] = r_i - rho_k
    inv_den = 1.0 / den
    fprime = wc @ inv_den**2
    q = 1.0 - rho
    if not np.all(np.abs(q) < 1.0):
        raise ModelError(
            f"creep inverse unstable at dt = {dt:g} s (mode factor {q[np.argmax(np.abs(q))]:.6g}); "
            "lower the creep or the sample interval"
        )
    gain = 1.0 / (fprime * rho)
    gain_sum = 1.0 / (1.0 + total_b0) - 1.0 / (1.0 + total)
    rows = np.flatnonzero(dyn)
    first = 1 if merged else 0
    # eta_k = sum_i w_i zeta_i / (rho_k - r_i) / F'_k with zeta_i = a_i e_i + (1 - b0_i) x_h
    # (memoryless elements: a_i = 0, nothing of their state survives a sample)
    to_modes = np.zeros((n_red, m))
    to_modes[:, rows] = -(inv_den[first:].T) * (w * a)[rows][None, :] / fprime[:, None]
    # zeta_i = sum_k c_i eta_k / (rho_k - r_i) for the other elements
    to_elements = np.zeros((m, n_red))
    to_elements[rows] = -inv_den[first:] * c[rows][:, None]
    return CreepDiscretisation(
        a=a,
        one_minus_b0=one_b0,
        w=w,
        total=total,
        total_b0=total_b0,
        q=q,
        gain=gain,
        gain_sum=gain_sum,
        to_modes=to_modes,
        to_elements=to_elements,
        rates=rho,
        memoryless=memoryless,
    )


# ------------------------------------------------------------------------------------------- creep


def creep_element_deviations(
    taus_s: F64, dt_s: float, drive_um: F64, drive_prev_um: float, deviations_um: F64
) -> F64:
    """Unweighted element deviations ``e_i[n] = z_i[n] - d[n]`` for a drive block, shape ``(n, m)``.

    The building block of the forward model (``x = (1 + W) d + e @ w``), exposed for
    calibration, where the weights are fitted: ``e`` is linear in the drive and the initial
    deviations and does not depend on the weights.

    Parameters
    ----------
    taus_s
        Relaxation times (s), shape ``(m,)``.
    dt_s
        Sample interval (s).
    drive_um
        Drive ``d`` (the hysteretic position), shape ``(n,)``.
    drive_prev_um
        Drive at the sample before the block.
    deviations_um
        Deviations after that sample, shape ``(m,)``.
    """
    dt = _check_dt(dt_s)
    a, _, b0 = foh_coefficients(np.asarray(taus_s, dtype=np.float64), dt)
    d = np.asarray(drive_um, dtype=np.float64)
    e0 = np.asarray(deviations_um, dtype=np.float64)
    n, m = d.size, a.size
    out = np.empty((n, m))
    if n == 0:
        return out
    dd = np.diff(d, prepend=drive_prev_um)
    one_b0 = 1.0 - b0
    if n == 1:
        out[0] = a * e0 - one_b0 * dd[0]
        return out
    for i in range(m):
        out[:, i], _ = lfilter([-one_b0[i]], [1.0, -a[i]], dd, zi=[a[i] * e0[i]])
    return out


#: Blocks are processed in chunks of at most this many samples by the filter-bank tables.
_CHUNK = 2048


@dataclass(frozen=True, eq=False)
class _BankTables:
    """Tables of a bank of first-order filters ``y_k[n] = p_k y_k[n-1] + g_k u[n]`` for ``n`` samples.

    ``sum_k o_k y_k[j] = init[j] @ s + (K * u)[j]`` with ``K[l] = sum_k o_k g_k p_k^l`` (a causal
    convolution, by FFT) and ``y_k[n-1] = p_k^n s_k + end[k] @ u`` for the initial states ``s``.
    """

    n: int
    nfft: int
    kernel_f: NDArray[np.complex128]
    init: F64
    end: F64
    p_n: F64


def _bank_tables(log_abs_p: F64, neg_p: NDArray[np.bool_], g: F64, o: F64, n: int) -> _BankTables:
    ell = np.arange(n + 1, dtype=np.float64)
    powers = np.exp(np.outer(ell, log_abs_p))  # (n + 1, m): |p_k|^l
    if neg_p.any():
        odd = (np.arange(n + 1) % 2 == 1)[:, None]
        powers = np.where(odd & neg_p[None, :], -powers, powers)
    kernel = powers[:n] @ (o * g)
    nfft = 1 << max(1, (2 * n - 1).bit_length())
    kernel_f = np.fft.rfft(kernel, nfft)
    init = powers[1:] * o[None, :]
    end = (powers[n - 1 :: -1] * g[None, :]).T.copy()
    return _BankTables(n, nfft, kernel_f, init, end, powers[n].copy())


@dataclass(frozen=True, eq=False)
class _Bank:
    """A bank of first-order filters with cached tables per block length."""

    log_abs_p: F64
    neg_p: NDArray[np.bool_]
    g: F64
    o: F64

    def tables(self, n: int) -> _BankTables:
        return _tables_cached(self, n)

    def run(self, u: F64, s: F64) -> tuple[F64, F64]:
        """``sum_k o_k y_k[j]`` for every sample and ``y_k`` after the last one."""
        out = np.empty_like(u)
        for start in range(0, u.size, _CHUNK):
            chunk = u[start : start + _CHUNK]
            tab = self.tables(chunk.size)
            conv = np.fft.irfft(np.fft.rfft(chunk, tab.nfft) * tab.kernel_f, tab.nfft)[: chunk.size]
            out[start : start + chunk.size] = tab.init @ s + conv
            s = tab.p_n * s + tab.end @ chunk
        return out, s


@lru_cache(maxsize=16)  # at most ~1.2 MB each
def _tables_cached(bank: _Bank, n: int) -> _BankTables:
    return _bank_tables(bank.log_abs_p, bank.neg_p, bank.g, bank.o, n)


@lru_cache(maxsize=64)
def _banks(params: DynamicParams, dt_s: float) -> tuple[_Bank, _Bank]:
    """The forward (elements) and inverse (modes) filter banks of ``params`` at ``dt_s``."""
    disc = discretise(params, dt_s)
    h = dt_s / params.taus_s
    fwd = _Bank(-h, np.zeros(h.size, dtype=bool), -disc.one_minus_b0, disc.w)
    rho = disc.rates
    log_q = np.log(np.maximum(np.abs(disc.q), 1e-300))
    inv = _Bank(log_q, disc.q < 0.0, -disc.q * disc.gain, np.ones(rho.size))
    return fwd, inv


def _creep_forward(
    params: DynamicParams, dt: float, disc: CreepDiscretisation, d: F64, d_prev: float, e0: F64
) -> tuple[F64, F64]:
    """``sum_i w_i e_i[n]`` for a drive block and the deviations after its last sample."""
    fwd, _ = _banks(params, dt)
    # bank state s = e[-1]: y = e (p = a, g = -(1 - b0), o = w)
    return fwd.run(np.diff(d, prepend=d_prev), e0)


def _creep_inverse(
    params: DynamicParams, dt: float, disc: CreepDiscretisation, x: F64, x_prev: float, d_prev: float, e0: F64
) -> tuple[F64, F64]:
    """Hysteretic positions ``x_h`` that give the positions ``x``, and the deviations after the block."""
    n = x.size
    inv_total = 1.0 / (1.0 + disc.total)
    if disc.total < _NEGLIGIBLE_CREEP:
        return x * inv_total, np.zeros_like(e0)
    dx = np.diff(x, prepend=x_prev)
    eps0 = disc.to_modes @ e0 + disc.gain * ((1.0 + disc.total) * d_prev - x_prev)
    d = x * inv_total
    d += disc.gain_sum * dx
    d[0] -= float(eps0.sum())
    eps_last = eps0
    if n > 1:
        # y_k[j] = eps_k[j + 1] = q_k eps_k[j] - q_k G_k dx[j]; sample j + 1 needs y[j]
        _, inv = _banks(params, dt)
        sums, eps_last = inv.run(dx[:-1], eps0)
        d[1:] -= sums
    x_before_last = float(x[-2]) if n > 1 else x_prev
    d_before_last = float(d[-2]) if n > 1 else d_prev
    e_end = disc.to_elements @ eps_last + disc.one_minus_b0 * (x_before_last * inv_total - float(d[-1]))
    if disc.memoryless.any():
        ml = disc.memoryless
        e_end[ml] = -disc.one_minus_b0[ml] * (float(d[-1]) - d_before_last)
    return d, e_end


# ----------------------------------------------------------------------------------------- public API


def dynamic_forward(
    params: DynamicParams, voltage_v: ArrayLike, dt_s: float, state: DynamicState
) -> tuple[F64, DynamicState]:
    """Positions of the model for a block of voltages (exact per sample, see the module docstring).

    Parameters
    ----------
    params
        Model parameters.
    voltage_v
        Voltages (V), shape ``(n,)``; the first sample is ``dt_s`` after the state's.
    dt_s
        Sample interval (s); may change between blocks.
    state
        State before the block (:func:`dynamic_rest_state` or a previous call of either
        direction).

    Returns
    -------
    position_um : ndarray
        Position after each sample (um).
    state : DynamicState
        State after the block.
    """
    v = _block(voltage_v, "voltage_v")
    _check_state(params, state)
    if v.size == 0:
        return np.empty(0), state
    disc_dt = _check_dt(dt_s)
    disc = discretise(params, disc_dt)
    d, hstate = hysteresis_step(params.hysteresis, v, state.hysteresis)
    creep, e_end = _creep_forward(params, disc_dt, disc, d, state.hysteretic_um, state.creep_um)
    x = (1.0 + disc.total) * d + creep
    return x, DynamicState(hstate, float(x[-1]), e_end)


def dynamic_inverse(
    params: DynamicParams, target_um: ArrayLike, dt_s: float, state: DynamicState
) -> tuple[F64, DynamicState]:
    """Voltages whose forward model (:func:`dynamic_forward`) reaches the targets at every sample.

    The creep inverse (modal filters, see the module docstring) gives the hysteretic
    targets, the Lambert W step of the ODE the voltages.

    Parameters
    ----------
    params
        Model parameters.
    target_um
        Target positions (um), shape ``(n,)``.
    dt_s
        Sample interval (s).
    state
        State before the block.

    Returns
    -------
    voltage_v : ndarray
        Voltages (V).
    state : DynamicState
        State after the block (positions equal to the targets).
    """
    x = _block(target_um, "target_um")
    _check_state(params, state)
    if x.size == 0:
        return np.empty(0), state
    dt = _check_dt(dt_s)
    disc = discretise(params, dt)
    d, e_end = _creep_inverse(params, dt, disc, x, state.position_um, state.hysteretic_um, state.creep_um)
    v, hstate = hysteresis_inverse_step(params.hysteresis, d, state.hysteresis)
    return v, DynamicState(hstate, float(x[-1]), e_end)


def dynamic_hold(params: DynamicParams, samples: int, dt_s: float, state: DynamicState) -> DynamicState:
    """The state after holding the last voltage for ``samples`` samples (closed form, O(m)).

    The hysteretic position stays, the creep elements relax: ``e_i -> e_i exp(-T / tau_i)``.
    """
    _check_state(params, state)
    if samples < 0:
        raise ModelError(f"samples must be >= 0, got {samples}")
    if samples == 0:
        return state
    decay = np.exp(-(samples * _check_dt(dt_s)) / params.taus_s)
    e = state.creep_um * decay
    x = (1.0 + params.total_creep) * state.hysteretic_um + float(params.weights @ e)
    return DynamicState(state.hysteresis, x, e)


__all__ = [
    "T_REF_S",
    "CreepDiscretisation",
    "DynamicParams",
    "DynamicState",
    "creep_element_deviations",
    "creep_taus",
    "creep_weights",
    "discretise",
    "dynamic_forward",
    "dynamic_hold",
    "dynamic_inverse",
    "dynamic_rest_state",
    "foh_coefficients",
]
