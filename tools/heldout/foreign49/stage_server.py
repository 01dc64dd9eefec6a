#!/usr/bin/env python3
"""Held-out stage "foreign49": the real hil_sim board and protocol around a stage of foreign physics.

    PYTHONPATH=. python tools/heldout/foreign49/stage_server.py --link /tmp/foreign49/link

Serves the simulated DAC / HV-amplifier board (``hil_sim.board.Board``, unchanged) on a real pty
with ``hil_sim.server.SimServer``, keeps the symlink at ``--link``, prints the public path on
stdout once ready and logs to stderr, until SIGTERM / SIGINT. The host uses
``tools/heldout/foreign49/scanner.yaml`` (``--config``) with ``--port <link>``.

BLIND TEST: whoever runs the controller against this stage should not read below this docstring
before the run; the physics lives in this file only (not in the scanner YAML).

Options: ``--seed N`` (physics randomness: sensor noise, environment phase), ``--truth FILE``
(append the true, noise-free position of the played samples: see ``TRUTH_DTYPE``; a JSON sidecar
``FILE.json`` describes the records), ``--truth-every N`` (every N-th sample while the clock runs;
every idle step is kept), ``--config`` (scanner YAML whose axis voltage limits become the
amplifier ranges; default ``scanner.yaml`` beside this script), ``--tick-ms``, ``--fifo-depth``,
``--exit-with-stdin``, ``-v``.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import logging
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parent / ".numba-cache"))
# no BLAS thread pools: on a busy 2-core machine their spinning costs far more than tiny matrices
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from numba import njit  # noqa: E402
from scipy.signal import lfilter  # noqa: E402

from hil_sim.board import Board, BoardConfig  # noqa: E402
from hil_sim.server import SimServer  # noqa: E402
from hil_sim.stage import Stage, StageConfig  # noqa: E402

log = logging.getLogger("hil_sim.foreign49")

HERE = Path(__file__).resolve().parent
AXES: tuple[str, ...] = ("x", "y", "z")

#: Records of ``--truth``: stage time (s since power-up), ceramic voltage and true position per axis.
TRUTH_DTYPE = np.dtype([("t_s", "<f8"), ("volts", "<f4", (len(AXES),)), ("x_um", "<f4", (len(AXES),))])

# =============================================================================================
# Physics (per axis x, y, z)
#
# 1. HV amplifier: second-order low-pass (natural frequency, damping) between DAC and ceramic.
# 2. Hysteresis: a Krasnosel'skii-Pokrovskii operator. Kernels with thresholds (c - r, c + r)
#    and algebraic-sigmoid ridges of width a; a kernel's state is a play of the ceramic voltage
#    with half-width r, its output a R((p - c) / a), R(z) = z / sqrt(1 + z^2). Density
#    w(r) nu(c) over a grid of half-widths r and centres c, plus a reversible part rho0 V.
# 3. Thermal activation of the domain walls: the kernels' half-widths are r g(T) with
#    g = 1 - kappa ln(T / T_ref) (clipped), T the effective observation time of the motion,
#    dT/dt = 1 - T |dV/dt| / S_v (T -> S_v / rate while the voltage moves, T grows like t at rest):
#    wider loops at faster rates, and a logarithmic-in-time relaxation of the engaged kernels at
#    rest (a creep that depends on the hysteresis state).
# 4. Accommodation: an offset o (in volts, times b) that follows, at a rate set by the voltage's
#    path length, sigma_m m + sigma_a (A - A0), m the path-weighted mean voltage (the cycling
#    centre) and A the path-weighted mean excursion about it (the cycling amplitude): loops
#    cycled off centre or at another amplitude drift until accommodated (no wiping-out).
# 5. Creep: a regularised springpot (fractional-order element), compliance
#    J(t) = gamma ((1 + t / tau0)^beta - 1) / beta, applied directly as the hereditary integral
#    C(t) = int J'(t - s) D(s) ds of the hysteretic position D (log-time binned history, exact
#    recent history; no bank of first-order relaxations).
# 6. Environment: the head warms after power-up (first-order, tau_w) and the room's HVAC cycles
#    (sinusoid); sensitivity temperature coefficient and thermal expansion drift of the sensor
#    mount. Tube bow: z picks up kappa_bow (x^2 + y^2).
# 7. Mechanics: the tube's first mode (second order, f, Q) on the position.
# 8. Sensor: capacitive, demodulator first-order lag, white noise (nm rms); the board's ADC
#    quantises.
# =============================================================================================

PARAMS: dict[str, Any] = {
    "amp_f_hz": np.array([3200.0, 3000.0, 4500.0]),
    "amp_zeta": np.array([0.75, 0.75, 0.8]),
    "b_um_per_v": np.array([0.228, 0.221, 0.0355]),
    "rho0": np.array([0.52, 0.54, 0.57]),
    # KP grid: play half-widths (V), their weights' decay (V), centres (V), ridge width (V)
    "kp_r_v": np.array([6.0, 14.0, 24.0, 36.0, 50.0, 66.0, 85.0, 106.0, 130.0, 158.0]),
    "kp_r_decay_v": np.array([110.0, 100.0, 125.0]),
    "kp_c_v": np.array([-250.0, -165.0, -82.0, 0.0, 82.0, 165.0, 250.0]),
    "kp_a_v": np.array([95.0, 90.0, 105.0]),
    "kp_c_tilt": np.array([0.10, 0.07, -0.06]),  # nu(c) = 1 + tilt c / 250 V
    "kp_c_taper_v": np.array([330.0, 320.0, 360.0]),  # nu(c) *= exp(-(c / taper)^2)
    # thermal activation
    "ta_s_v": np.array([1.6, 1.5, 1.8]),
    "ta_kappa": np.array([0.020, 0.019, 0.017]),
    "ta_t_ref_s": 5.0e-3,
    "ta_g_min": 0.62,
    "ta_g_max": 1.22,
    "ta_t_rest_s": 3600.0,
    # accommodation
    "acc_eta_m_per_v": 1.0 / 520.0,
    "acc_eta_o_per_v": 1.0 / 6500.0,
    "acc_sigma_m": np.array([0.042, 0.038, 0.03]),
    "acc_sigma_a": np.array([0.026, 0.024, 0.02]),
    "acc_a0_v": 60.0,
    # fractional creep
    "creep_gamma": np.array([0.0040, 0.0042, 0.0033]),
    "creep_beta": np.array([0.045, 0.047, 0.040]),
    "creep_tau0_s": np.array([2.0e-3, 2.0e-3, 1.5e-3]),
    "creep_fir_samples": 512,
    "creep_bin_eps": 0.08,
    # environment
    "env_warm_k": 0.6,
    "env_warm_tau_s": 900.0,
    "env_hvac_k": 0.15,
    "env_hvac_period_s": 1080.0,
    "env_tc_per_k": np.array([2.2e-3, 2.2e-3, 3.0e-3]),
    "env_drift_um_per_k": np.array([0.035, -0.020, 0.060]),
    "bow_per_um": 2.4e-5,
    # mechanics and sensor
    "mode_f_hz": np.array([1450.0, 1420.0, 6800.0]),
    "mode_q": np.array([16.0, 17.0, 22.0]),
    "sensor_lag_s": 2.5e-5,
    "sensor_noise_nm": np.array([1.8, 1.8, 0.6]),
}


# ---------------------------------------------------------------------------------------------
# exact discretisation of the linear parts (input linear between samples)


def _second_order(f_hz: float, zeta: float) -> tuple[np.ndarray, np.ndarray]:
    w = 2.0 * math.pi * f_hz
    return np.array([[0.0, 1.0], [-w * w, -2.0 * zeta * w]]), np.array([0.0, w * w])


@njit(cache=True)
def _expm(m: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Matrix exponential of a small matrix: scaling and squaring of a 16-term Taylor series."""
    n = m.shape[0]
    norm = 0.0
    for i in range(n):
        row = 0.0
        for j in range(n):
            row += abs(m[i, j])
        norm = max(norm, row)
    sq = 0
    while norm > 0.25:
        norm *= 0.5
        sq += 1
    a = m / (2.0**sq)
    out = np.eye(n)
    term = np.eye(n)
    for k in range(1, 17):
        term = term @ a / k
        out += term
    for _ in range(sq):
        out = out @ out
    return out


def _foh(a_mat: np.ndarray, b_vec: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x_{k+1} = phi x_k + g0 u_k + g1 u_{k+1} for x' = A x + B u, u linear over the step."""
    n = a_mat.shape[0]
    m = np.zeros((n + 2, n + 2))
    m[:n, :n] = a_mat
    m[:n, n] = b_vec
    m[n, n + 1] = 1.0
    e = _expm(m * dt)
    phi = e[:n, :n]
    e12 = e[:n, n]
    e13 = e[:n, n + 1] / dt
    return phi, e12 - e13, e13


class _Discrete:
    """Cached FOH coefficients per dt of the amplifier, the mode and the sensor lag (all channels)."""

    def __init__(self, p: dict[str, Any]) -> None:
        self._p = p
        self._cache: dict[float, tuple[np.ndarray, ...]] = {}

    def get(self, dt: float) -> tuple[np.ndarray, ...]:
        hit = self._cache.get(dt)
        if hit is not None:
            return hit
        p = self._p
        C = len(AXES)
        amp_phi = np.zeros((C, 2, 2))
        amp_g = np.zeros((C, 2, 2))  # [:, 0] = g0, [:, 1] = g1
        mode_phi = np.zeros((C, 2, 2))
        mode_g = np.zeros((C, 2, 2))
        for c in range(C):
            a, b = _second_order(p["amp_f_hz"][c], p["amp_zeta"][c])
            phi, g0, g1 = _foh(a, b, dt)
            amp_phi[c], amp_g[c, 0], amp_g[c, 1] = phi, g0, g1
            a, b = _second_order(p["mode_f_hz"][c], 1.0 / (2.0 * p["mode_q"][c]))
            phi, g0, g1 = _foh(a, b, dt)
            mode_phi[c], mode_g[c, 0], mode_g[c, 1] = phi, g0, g1
        phi, g0, g1 = _foh(np.array([[-1.0 / p["sensor_lag_s"]]]), np.array([1.0 / p["sensor_lag_s"]]), dt)
        lag = np.array([phi[0, 0], g0[0], g1[0]])
        out = (amp_phi, amp_g, mode_phi, mode_g, lag)
        if len(self._cache) > 64:
            self._cache.clear()
        self._cache[dt] = out
        return out


# ---------------------------------------------------------------------------------------------
# compiled kernels


@njit(cache=True)
def _lin2(
    u: np.ndarray, phi: np.ndarray, g: np.ndarray, st: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Second-order FOH filter of one channel; st = [y, y', u_prev]; out = y."""
    y0, y1, up = st[0], st[1], st[2]
    p00, p01, p10, p11 = phi[0, 0], phi[0, 1], phi[1, 0], phi[1, 1]
    a0, a1, b0, b1 = g[0, 0], g[0, 1], g[1, 0], g[1, 1]
    for k in range(u.shape[0]):
        uk = u[k]
        n0 = p00 * y0 + p01 * y1 + a0 * up + b0 * uk
        n1 = p10 * y0 + p11 * y1 + a1 * up + b1 * uk
        y0, y1, up = n0, n1, uk
        out[k] = y0
    st[0], st[1], st[2] = y0, y1, up


@njit(cache=True)
def _hysteresis(
    v: np.ndarray,
    dt: float,
    r: np.ndarray,
    w_r: np.ndarray,
    cents: np.ndarray,
    nu: np.ndarray,
    a: float,
    rho0: float,
    b: float,
    s_v: float,
    kappa: float,
    t_ref: float,
    g_min: float,
    g_max: float,
    eta_m: float,
    eta_o: float,
    sig_m: float,
    sig_a: float,
    a0: float,
    p: np.ndarray,
    contrib: np.ndarray,
    st: np.ndarray,
    out_d: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """KP hysteresis with thermally activated half-widths and accommodation, one channel.

    st = [T, v_prev, m, A, o, offset0]; p, contrib: per half-width play state / KP output.
    out_d: hysteretic position (um) relative to the rest position, accommodation included.
    """
    T, vp, m, amp, o, off0 = st[0], st[1], st[2], st[3], st[4], st[5]
    nr = r.shape[0]
    nc = cents.shape[0]
    total = 0.0
    for i in range(nr):
        total += contrib[i]
    for k in range(v.shape[0]):
        vk = v[k]
        dv = abs(vk - vp)
        # effective observation time of the motion (thermal activation)
        rate = dv / (s_v * dt)
        x = rate * dt
        if x > 1e-12:
            e = math.exp(-x)
            T = T * e + (1.0 - e) / rate
        else:
            T = T + dt
        g = 1.0 - kappa * math.log(T / t_ref)
        if g < g_min:
            g = g_min
        elif g > g_max:
            g = g_max
        # KP kernels (plays shared over centres)
        for i in range(nr):
            ri = r[i] * g
            pi = p[i]
            lo = vk - ri
            hi = vk + ri
            if pi < lo:
                pi = lo
            elif pi > hi:
                pi = hi
            if pi != p[i]:
                p[i] = pi
                s = 0.0
                for j in range(nc):
                    z = (pi - cents[j]) / a
                    s += nu[j] * z / math.sqrt(1.0 + z * z)
                s *= w_r[i] * a
                total += s - contrib[i]
                contrib[i] = s
        # accommodation (path-length driven)
        if dv > 0.0:
            em = math.exp(-eta_m * dv)
            m = m * em + (1.0 - em) * vk
            amp = amp * em + (1.0 - em) * abs(vk - m)
            eo = math.exp(-eta_o * dv)
            o = o * eo + (1.0 - eo) * (sig_m * m + sig_a * (amp - a0))
        vp = vk
        out_d[k] = b * (rho0 * vk + total + o) - off0
    st[0], st[1], st[2], st[3], st[4] = T, vp, m, amp, o


@njit(cache=True)
def _jc(t: float, gamma: float, beta: float, tau0: float) -> float:  # pragma: no cover - compiled
    """Creep compliance J(t) (fraction of the motion), 0 for t <= 0."""
    if t <= 0.0:
        return 0.0
    return gamma * (math.exp(beta * math.log1p(t / tau0)) - 1.0) / beta


@njit(cache=True)
def _bins_at(
    t: float,
    bs: np.ndarray,
    be: np.ndarray,
    bd: np.ndarray,
    lo: int,
    hi: int,
    gamma: float,
    beta: float,
    tau0: float,
) -> float:  # pragma: no cover - compiled
    s = 0.0
    for q in range(lo, hi):
        s += bd[q] * (_jc(t - bs[q], gamma, beta, tau0) - _jc(t - be[q], gamma, beta, tau0))
    return s


@njit(cache=True)
def _creep_block(
    d: np.ndarray,
    t0: float,
    dt: float,
    gamma: float,
    beta: float,
    tau0: float,
    fir: np.ndarray,
    nfir: int,
    bs: np.ndarray,
    be: np.ndarray,
    bd: np.ndarray,
    nb: int,
    out_c: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Creep of one channel over a block: C_k = int J'(t_k - s) D(s) ds (D held over each sample).

    History: bins [bs, be) of mean D (oldest first, nb of them) up to the FIR buffer's start, then
    the FIR buffer fir[:nfir] (samples at this dt, oldest first, the last ending at t0), then the
    block d. Bins at least two block lengths old are summed at 4 nodes and interpolated (cubic).
    """
    n = d.shape[0]
    L = n * dt
    taps = np.empty(n + nfir)
    jprev = 0.0
    for mm in range(n + nfir):
        jn = _jc((mm + 1) * dt, gamma, beta, tau0)
        taps[mm] = jn - jprev
        jprev = jn
    # split bins by age at the block start
    split = 0
    for q in range(nb):
        if t0 - be[q] >= 2.0 * L:
            split = q + 1
        else:
            break
    # smooth part
    smooth = np.zeros(n)
    if split > 0:
        if n <= 8:
            for k in range(n):
                smooth[k] = _bins_at(t0 + (k + 1) * dt, bs, be, bd, 0, split, gamma, beta, tau0)
        else:
            xs = np.empty(4)
            ys = np.empty(4)
            for q in range(4):
                # Chebyshev-Lobatto nodes over [1, n]
                xs[q] = 1.0 + 0.5 * (n - 1) * (1.0 - math.cos(math.pi * q / 3.0))
                ys[q] = _bins_at(t0 + xs[q] * dt, bs, be, bd, 0, split, gamma, beta, tau0)
            for k in range(n):
                xk = k + 1.0
                s = 0.0
                for q in range(4):
                    lq = 1.0
                    for r_ in range(4):
                        if r_ != q:
                            lq *= (xk - xs[r_]) / (xs[q] - xs[r_])
                    s += lq * ys[q]
                smooth[k] = s
    for k in range(n):
        tk = t0 + (k + 1) * dt
        s = smooth[k]
        if split < nb:
            s += _bins_at(tk, bs, be, bd, split, nb, gamma, beta, tau0)
        # FIR buffer: its newest sample ends at t0, i.e. lag k + 1 samples -> taps[k + 1 + age]
        for q in range(nfir):
            s += taps[k + nfir - q] * fir[q]
        # the block itself
        for j in range(k + 1):
            s += taps[k - j] * d[j]
        out_c[k] = s


@njit(cache=True)
def _merge_bins(
    t_now: float, eps: float, bs: np.ndarray, be: np.ndarray, bd: np.ndarray, nb: int
) -> int:  # pragma: no cover - compiled
    """Merge neighbouring bins (from the newest) while a group spans at most eps x its age."""
    if nb <= 1:
        return nb
    # work from the newest bin backwards, writing groups from the end
    w = nb - 1
    gs, ge, gsum = bs[nb - 1], be[nb - 1], bd[nb - 1] * (be[nb - 1] - bs[nb - 1])
    for q in range(nb - 2, -1, -1):
        if ge - bs[q] <= eps * (t_now - ge):
            gsum += bd[q] * (be[q] - bs[q])
            gs = bs[q]
        else:
            bs[w], be[w], bd[w] = gs, ge, gsum / (ge - gs)
            w -= 1
            gs, ge, gsum = bs[q], be[q], bd[q] * (be[q] - bs[q])
    bs[w], be[w], bd[w] = gs, ge, gsum / (ge - gs)
    count = nb - w
    for q in range(count):
        bs[q], be[q], bd[q] = bs[w + q], be[w + q], bd[w + q]
    return count


# ---------------------------------------------------------------------------------------------
# the stage


@dataclasses.dataclass
class _State:
    time_s: float
    amp: np.ndarray  # (C, 3)
    mode: np.ndarray  # (C, 3)
    lag: np.ndarray  # (C, 2): output, input
    plays: np.ndarray  # (C, nr)
    contrib: np.ndarray  # (C, nr)
    hyst: np.ndarray  # (C, 6)
    fir: np.ndarray  # (C, M)
    nfir: int
    fir_dt: float
    bs: np.ndarray  # (C, cap)
    be: np.ndarray
    bd: np.ndarray
    nb: np.ndarray  # (C,) int64
    env_phase: float


def _placeholder_config() -> StageConfig:
    """A valid StageConfig for code that reads ``stage.config`` (only the microscope does; this
    stage has none). It is NOT this stage's physics."""
    axis = {"alpha_per_v": 3.0e-3, "b_um_per_v": 0.2, "u_um_per_v": 0.13}
    return StageConfig.model_validate({"axes": {a: axis for a in AXES}, "seed": 0})


class ForeignStage(Stage):
    """The foreign-physics stage, with the interface the board uses (step, sense, axes, channels,
    config, time_s, reset, snapshot / restore)."""

    BIN_CAPACITY = 8192
    MAX_CHUNK = 256

    def __init__(self, seed: int = 0, truth: str | None = None, truth_every: int = 10) -> None:
        self._p = PARAMS
        self._seed = int(seed)
        self._disc = _Discrete(self._p)
        p = self._p
        C = len(AXES)
        self._r = np.asarray(p["kp_r_v"], dtype=np.float64)
        self._c = np.asarray(p["kp_c_v"], dtype=np.float64)
        self._w_r = np.empty((C, self._r.size))
        self._nu = np.empty((C, self._c.size))
        grid = np.linspace(-200.0, 200.0, 401)
        for ch in range(C):
            w = np.exp(-self._r / p["kp_r_decay_v"][ch])
            taper = np.exp(-((self._c / p["kp_c_taper_v"][ch]) ** 2))
            nu = (1.0 + p["kp_c_tilt"][ch] * self._c / 250.0) * taper
            # normalise: the KP part's mean small-signal slope over +-200 V is 1 - rho0
            a = p["kp_a_v"][ch]
            z = (grid[:, None] - self._c[None, :]) / a
            slope = ((1.0 + z * z) ** -1.5 * nu[None, :]).sum(axis=1).mean()
            self._w_r[ch] = w / w.sum() * (1.0 - p["rho0"][ch]) / slope
            self._nu[ch] = nu
        self._truth_every = max(1, int(truth_every))
        self._truth_fh = None
        self._truth_count = 0
        if truth:
            self._truth_fh = open(truth, "ab")  # noqa: SIM115
            side = {
                "dtype": [("t_s", "<f8"), ("volts", "<f4", [len(AXES)]), ("x_um", "<f4", [len(AXES)])],
                "axes": list(AXES),
                "meaning": "t_s: stage time since power-up; volts: at the ceramic (after the amplifier); "
                "x_um: true position, noise-free, before the sensor's lag and noise (sensor coordinates, "
                "0 = rest at 0 V at power-up)",
                "every": self._truth_every,
            }
            Path(truth + ".json").write_text(json.dumps(side, indent=1), encoding="utf-8")
        self._config = _placeholder_config()
        self.reset()

    # -- the Stage interface --------------------------------------------------------------------

    @property
    def config(self) -> StageConfig:
        return self._config

    @property
    def axes(self) -> tuple[str, ...]:  # type: ignore[override]
        return AXES

    @property
    def channels(self) -> int:
        return len(AXES)

    @property
    def time_s(self) -> float:
        return self._s.time_s

    @property
    def model(self) -> Any:
        raise AttributeError("the foreign stage has no hil_sim StageModel")

    def reset(self, rest_voltage_v: Any = None) -> None:
        if rest_voltage_v is not None and np.any(np.asarray(rest_voltage_v) != 0.0):
            raise ValueError("the foreign stage rests at 0 V")
        p = self._p
        C = len(AXES)
        nr = self._r.size
        plays = np.zeros((C, nr))
        contrib = np.zeros((C, nr))
        for ch in range(C):
            a = p["kp_a_v"][ch]
            z = (0.0 - self._c) / a
            contrib[ch] = self._w_r[ch] * a * (self._nu[ch] * z / np.sqrt(1.0 + z * z)).sum()
        hyst = np.zeros((C, 6))
        hyst[:, 0] = p["ta_t_rest_s"]
        hyst[:, 3] = p["acc_a0_v"]
        hyst[:, 5] = p["b_um_per_v"] * contrib.sum(axis=1)  # rest position 0
        M = int(p["creep_fir_samples"])
        cap = self.BIN_CAPACITY
        rng = np.random.default_rng(self._seed)
        self._s = _State(
            time_s=0.0,
            amp=np.zeros((C, 3)),
            mode=np.zeros((C, 3)),
            lag=np.zeros((C, 2)),
            plays=plays,
            contrib=contrib,
            hyst=hyst,
            fir=np.zeros((C, M)),
            nfir=0,
            fir_dt=0.0,
            bs=np.zeros((C, cap)),
            be=np.zeros((C, cap)),
            bd=np.zeros((C, cap)),
            nb=np.zeros(C, dtype=np.int64),
            env_phase=float(rng.uniform(0.0, 2.0 * math.pi)),
        )
        self._rng = np.random.default_rng([self._seed, 49])

    def snapshot(self) -> Any:
        return (copy.deepcopy(self._s), copy.deepcopy(self._rng.bit_generator.state))

    def restore(self, snapshot: Any) -> None:
        self._s = copy.deepcopy(snapshot[0])
        self._rng = np.random.default_rng()
        self._rng.bit_generator.state = copy.deepcopy(snapshot[1])

    def sense(self, position_um: Any, lsb_um: float | None = None) -> np.ndarray:
        x = np.array(position_um, dtype=np.float64)
        noise = self._p["sensor_noise_nm"] * 1e-3
        if x.ndim == 2:
            x = x + self._rng.normal(0.0, 1.0, size=x.shape) * noise[: x.shape[0], None]
        else:
            x = x + self._rng.normal(0.0, noise[0], size=x.shape)
        if lsb_um is not None:
            x = np.round(x / lsb_um) * lsb_um
        return x

    def step(self, voltage_v: Any, dt_s: float) -> np.ndarray:
        if isinstance(voltage_v, Mapping):
            v = np.stack([np.asarray(voltage_v[a], dtype=np.float64) for a in AXES])
        else:
            v = np.asarray(voltage_v, dtype=np.float64)
        v = np.ascontiguousarray(v)
        if v.ndim == 1:
            raise ValueError("the foreign stage has 3 channels: voltage of shape (3, n)")
        if v.shape[0] != len(AXES):
            raise ValueError(f"voltage_v must have shape (3, n), got {v.shape}")
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s must be finite and > 0, got {dt_s!r}")
        if not np.all(np.isfinite(v)):
            raise ValueError("voltage_v contains non-finite samples")
        n = v.shape[1]
        if n == 0:
            return np.empty_like(v)
        # long holds: sub-step so that the thermal-activation clock and the filters see the time pass
        if n == 1 and dt_s > 0.02:
            k = math.ceil(dt_s / 0.02)
            s = self._s
            vp = s.amp[:, 2]
            frac = np.arange(1, k + 1) / k
            vv = vp[:, None] + (v[:, :1] - vp[:, None]) * frac[None, :]
            x = self._step(vv, dt_s / k)
            return x[:, -1:]
        if n <= self.MAX_CHUNK:
            return self._step(v, dt_s)
        # a long block (the board caught up after a stall): the same physics in chunks
        return np.concatenate(
            [self._step(v[:, k : k + self.MAX_CHUNK], dt_s) for k in range(0, n, self.MAX_CHUNK)], axis=1
        )

    # -- the physics ---------------------------------------------------------------------------

    def _step(self, v: np.ndarray, dt: float) -> np.ndarray:
        p = self._p
        s = self._s
        C, n = v.shape
        amp_phi, amp_g, mode_phi, mode_g, lag = self._disc.get(dt)
        t0 = s.time_s
        t = t0 + dt * np.arange(1, n + 1)
        # 1. amplifier
        vc = np.empty_like(v)
        for ch in range(C):
            _lin2(v[ch], amp_phi[ch], amp_g[ch], s.amp[ch], vc[ch])
        # 2-4. hysteresis
        d = np.empty_like(v)
        for ch in range(C):
            _hysteresis(
                vc[ch],
                dt,
                self._r,
                self._w_r[ch],
                self._c,
                self._nu[ch],
                p["kp_a_v"][ch],
                p["rho0"][ch],
                p["b_um_per_v"][ch],
                p["ta_s_v"][ch],
                p["ta_kappa"][ch],
                p["ta_t_ref_s"],
                p["ta_g_min"],
                p["ta_g_max"],
                p["acc_eta_m_per_v"],
                p["acc_eta_o_per_v"],
                p["acc_sigma_m"][ch],
                p["acc_sigma_a"][ch],
                p["acc_a0_v"],
                s.plays[ch],
                s.contrib[ch],
                s.hyst[ch],
                d[ch],
            )
        # 5. creep
        c = self._creep(d, t0, dt)
        x = d + c
        # 6. environment (sensitivity) and tube bow
        dT = self._temperature(t)
        x = x * (1.0 + p["env_tc_per_k"][:, None] * dT[None, :])
        x[2] += p["bow_per_um"] * (x[0] * x[0] + x[1] * x[1])
        # 7. mechanics
        xm = np.empty_like(x)
        for ch in range(C):
            _lin2(x[ch], mode_phi[ch], mode_g[ch], s.mode[ch], xm[ch])
        xm += p["env_drift_um_per_k"][:, None] * dT[None, :]
        # 8. sensor lag
        a, g0, g1 = lag
        y: np.ndarray = np.empty_like(xm)
        for ch in range(C):
            z, up = s.lag[ch]
            zi = np.array([g0 * up + a * z])
            y[ch], _ = lfilter([g1, g0], [1.0, -a], xm[ch], zi=zi)
            s.lag[ch] = (y[ch, -1], xm[ch, -1])
        s.time_s = float(t[-1])
        self._record(t, vc, xm)
        return y

    def _temperature(self, t: np.ndarray) -> np.ndarray:
        p = self._p
        ph = self._s.env_phase
        w = 2.0 * math.pi / p["env_hvac_period_s"]
        temp: np.ndarray = p["env_warm_k"] * -np.expm1(-t / p["env_warm_tau_s"]) + p["env_hvac_k"] * (
            np.sin(w * t + ph) - math.sin(ph)
        )
        return temp

    def _creep(self, d: np.ndarray, t0: float, dt: float) -> np.ndarray:
        p = self._p
        s = self._s
        C, n = d.shape
        M = s.fir.shape[1]
        if s.nfir and abs(s.fir_dt - dt) > 1e-12 * max(dt, s.fir_dt):
            self._fir_to_bins(s.nfir, t0)
        out = np.empty_like(d)
        for ch in range(C):
            _creep_block(
                d[ch],
                t0,
                dt,
                p["creep_gamma"][ch],
                p["creep_beta"][ch],
                p["creep_tau0_s"][ch],
                s.fir[ch],
                s.nfir,
                s.bs[ch],
                s.be[ch],
                s.bd[ch],
                int(s.nb[ch]),
                out[ch],
            )
        # the block joins the FIR buffer; what falls out of it joins the bins
        s.fir_dt = dt
        t_end = t0 + n * dt
        total = s.nfir + n
        if total > M:
            spill = total - M
            from_fir = min(spill, s.nfir)
            if from_fir:
                self._fir_to_bins(from_fir, t0)
            from_blk = spill - from_fir
            if from_blk:
                self._samples_to_bins(d[:, :from_blk], t0, dt)
            keep = d[:, from_blk:]
            s.fir[:, s.nfir : s.nfir + keep.shape[1]] = keep
            s.nfir += keep.shape[1]
        else:
            s.fir[:, s.nfir : total] = d
            s.nfir = total
        eps = p["creep_bin_eps"]
        for ch in range(C):
            s.nb[ch] = _merge_bins(t_end, eps, s.bs[ch], s.be[ch], s.bd[ch], int(s.nb[ch]))
        return out

    def _fir_to_bins(self, count: int, t_fir_end: float) -> None:
        """Move the oldest ``count`` FIR samples (the buffer ends at ``t_fir_end``) into the bins."""
        s = self._s
        dt = s.fir_dt
        start = t_fir_end - s.nfir * dt
        self._samples_to_bins(s.fir[:, :count], start, dt)
        s.fir[:, : s.nfir - count] = s.fir[:, count : s.nfir].copy()
        s.nfir -= count

    def _samples_to_bins(self, vals: np.ndarray, t_start: float, dt: float) -> None:
        step = 1024
        if vals.shape[1] > step:
            eps = self._p["creep_bin_eps"]
            s = self._s
            for k in range(0, vals.shape[1], step):
                part = vals[:, k : k + step]
                self._samples_to_bins(part, t_start + k * dt, dt)
                t_part_end = t_start + (k + part.shape[1]) * dt
                for ch in range(vals.shape[0]):
                    s.nb[ch] = _merge_bins(t_part_end, eps, s.bs[ch], s.be[ch], s.bd[ch], int(s.nb[ch]))
            return
        s = self._s
        k = vals.shape[1]
        edges = t_start + dt * np.arange(k + 1)
        for ch in range(vals.shape[0]):
            nb = int(s.nb[ch])
            if nb + k > s.bs.shape[1]:
                s.nb[ch] = nb = _merge_bins(edges[0], 0.5, s.bs[ch], s.be[ch], s.bd[ch], nb)
                if nb + k > s.bs.shape[1]:
                    raise RuntimeError("creep history overflow")
            s.bs[ch, nb : nb + k] = edges[:-1]
            s.be[ch, nb : nb + k] = edges[1:]
            s.bd[ch, nb : nb + k] = vals[ch]
            s.nb[ch] = nb + k

    def _record(self, t: np.ndarray, vc: np.ndarray, x: np.ndarray) -> None:
        if self._truth_fh is None:
            return
        n = t.size
        idx = self._truth_count + np.arange(n)
        self._truth_count += n
        sel = idx % self._truth_every == 0
        if n == 1 or (t.size > 1 and t[1] - t[0] > 5e-4):
            sel[:] = True  # idle steps: keep all
        if not sel.any():
            return
        rec = np.empty(int(sel.sum()), dtype=TRUTH_DTYPE)
        rec["t_s"] = t[sel]
        rec["volts"] = vc[:, sel].T
        rec["x_um"] = x[:, sel].T
        self._truth_fh.write(rec.tobytes())

    def flush_truth(self) -> None:
        if self._truth_fh is not None:
            self._truth_fh.flush()

    def close(self) -> None:
        if self._truth_fh is not None:
            self._truth_fh.close()
            self._truth_fh = None


# ---------------------------------------------------------------------------------------------
# the server


def _voltage_limits(path: Path) -> tuple[tuple[float, float], ...]:
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    axes = data["axes"]
    if list(axes) != list(AXES):
        raise SystemExit(f"{path}: axes must be {', '.join(AXES)} in this order (the board's channels)")
    return tuple((float(axes[a]["voltage_min_v"]), float(axes[a]["voltage_max_v"])) for a in AXES)


def _setup_logging(verbose: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s foreign49[%(process)d] %(levelname)s: %(message)s"))
    root = logging.getLogger("hil_sim")
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    root.propagate = False


def warm_up(stage: ForeignStage) -> float:
    """Compile the kernels (on a throw-away copy of the state); returns the seconds it took."""
    t = time.monotonic()
    snap = stage.snapshot()
    count = stage._truth_count
    fh, stage._truth_fh = stage._truth_fh, None
    try:
        v = np.zeros((3, 3000))
        v[:, :] = np.linspace(0.0, 1.0, 3000)[None, :]
        stage.step(v, 5e-5)
        stage.step(np.asfortranarray(v[:, :200]), 5e-5)
        stage.step(v[:, :1], 0.1)
        stage.step(v[:, :7], 1e-3)
    finally:
        stage.restore(snap)
        stage._truth_fh = fh
        stage._truth_count = count
    return time.monotonic() - t


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="held-out foreign-physics stage on a pty (hil_sim board)")
    parser.add_argument("--link", metavar="PATH", help="keep a symlink PATH -> the current pty")
    parser.add_argument("--config", default=str(HERE / "scanner.yaml"), metavar="F", help="scanner YAML")
    parser.add_argument("--seed", type=int, default=49, metavar="N")
    parser.add_argument("--truth", metavar="FILE", help="append the true position records here")
    parser.add_argument("--truth-every", type=int, default=10, metavar="N")
    parser.add_argument("--tick-ms", type=float, default=2.0, metavar="MS")
    parser.add_argument("--fifo-depth", type=int, default=BoardConfig().fifo_depth_samples, metavar="N")
    parser.add_argument("--exit-with-stdin", action="store_true")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    ranges = _voltage_limits(Path(args.config))
    stage = ForeignStage(seed=args.seed, truth=args.truth, truth_every=args.truth_every)
    log.info("compiled the stage in %.1f s", warm_up(stage))
    clock = time.monotonic
    cfg = BoardConfig(
        amplifier_ranges_v=ranges,
        fifo_depth_samples=args.fifo_depth,
        seed=args.seed,
        board_serial=0x51A0_F049,
    )
    board = Board(stage, cfg, now=clock())
    server = SimServer(
        board,
        link=args.link,
        tick_s=args.tick_ms * 1e-3,
        clock=clock,
        parent_fd=sys.stdin.fileno() if args.exit_with_stdin else None,
    )
    if args.truth:
        # flush the truth file about once a second (cheap), whatever the loop does
        step = server.step
        last = [clock()]

        def step_and_flush() -> None:
            step()
            if clock() - last[0] > 1.0:
                stage.flush_truth()
                last[0] = clock()

        server.step = step_and_flush  # type: ignore[method-assign]
    log.info(
        "board %d channels (%s), serial 0x%08x, FIFO %d, amplifier ranges %s",
        stage.channels,
        "".join(stage.axes),
        board.capabilities.board_serial,
        board.capabilities.fifo_depth_samples,
        ranges,
    )

    def ready(path: str) -> None:
        sys.stdout.write(path + "\n")
        sys.stdout.flush()

    try:
        return server.serve_forever(ready)
    finally:
        stage.close()


if __name__ == "__main__":
    sys.exit(main())
