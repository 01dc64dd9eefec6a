#!/usr/bin/env python3
"""Held-out stage "foreign51": the real hil_sim board and protocol around a stage of foreign physics.

    PYTHONPATH=. python tools/heldout/foreign51/stage_server.py --link /tmp/foreign51/link

Serves the simulated DAC / HV-amplifier board (``hil_sim.board.Board``, unchanged) on a real pty
with ``hil_sim.server.SimServer``, keeps the symlink at ``--link``, prints the public path on
stdout once ready and logs to stderr, until SIGTERM / SIGINT. The host uses
``tools/heldout/foreign51/scanner.yaml`` (``--config``) with ``--port <link>``.

BLIND TEST: whoever runs the controller against this stage should not read below this docstring
before the run; the physics lives in this file only (not in the scanner YAML).

Options: ``--seed N`` (physics randomness: sensor noise, environment phases), ``--truth FILE``
(append the true, noise-free position of the played samples: see ``TRUTH_DTYPE``; a JSON sidecar
``FILE.json`` describes the records), ``--truth-every N`` (every N-th sample while the clock runs;
every idle step is kept), ``--config`` (scanner YAML: its axes must be x, y, z and its voltage
limits must lie inside the amplifier's output range), ``--tick-ms``, ``--fifo-depth``,
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
from scipy.linalg import expm  # noqa: E402

from hil_sim.board import Board, BoardConfig  # noqa: E402
from hil_sim.server import SimServer  # noqa: E402
from hil_sim.stage import Stage, StageConfig  # noqa: E402

log = logging.getLogger("hil_sim.foreign51")

HERE = Path(__file__).resolve().parent
AXES: tuple[str, ...] = ("x", "y", "z")

#: Records of ``--truth``: stage time (s since power-up), ceramic voltage and true position per axis.
TRUTH_DTYPE = np.dtype([("t_s", "<f8"), ("volts", "<f4", (len(AXES),)), ("x_um", "<f4", (len(AXES),))])

# =============================================================================================
# Physics: a parallel-kinematic XY flexure nanopositioner with a Z stage (optical microscopy
# insert). Each axis: a multilayer stack (x, y with a flexure lever, z direct), a capacitive
# position sensor. Per axis, in this order:
#
# 1. HV amplifier: its output resistance and the stack's capacitance form a one-pole low-pass
#    (exact for a drive linear between samples); the output current is limited, so the ceramic
#    voltage slews at most I_max / C.
# 2. Hysteresis: a Jiles-Atherton-type domain-wall law adapted to a poled ceramic (Smith and
#    Ounaies). Wall displacement P (volt-equivalent units) in an effective field
#    H = V + alpha P (mean-field interaction of the walls); anhysteretic P_an = Ms L((H - H_b) / a)
#    (Langevin, biased by the poling); the irreversible part P_i moves towards P_an only while
#    the field moves towards it, dP_i = (P_an - P_i) |dH| / k (pinning energy k; clamped: never
#    away from P_an); reversible bowing P = P_i + c (P_an - P_i). Position
#    b_int V (1 + e2 V) (lattice, electrostrictive curvature) + b_dw (P - P_rest).
# 3. Creep: thermally activated unpinning (magnetic-viscosity-like after-effect) of the walls:
#    the gap g = P_an - P_i closes at rest as dg/dt = -(g0 / tau) sinh(g / g0) (Eyring rate;
#    exact closed form over each sample): a logarithmic creep whose window and amount depend
#    on how far the history left the walls from equilibrium (nonlinear, hereditary through g).
#    The same process narrows the loops at slow drive.
# 4. Temperature: the room warms slowly (linear ramp) and an illumination / incubator heater
#    switches on once (first-order step at a seeded time); the stacks self-heat with the
#    dielectric loss of the drive (pi/2 tan(delta) C |dV/dt| |V - V_mid|, first-order thermal
#    time constant). Stack temperature scales the sensitivity, lowers the pinning energy and
#    raises g0; room and stack temperatures expand the stage (drift in sensor coordinates).
# 5. Parallel kinematics: static cross-coupling of the axes (x <-> y, parasitic z from x and y,
#    and a z bow with the square of the lateral position).
# 6. Mechanics: x, y two modes (carriage translation and a rocking mode, weights summing to 1);
#    z one mode.
# 7. Sensor: capacitive, pure electronics delay (interpolated) and a one-pole lag, slow
#    electronic drift (deterministic, seeded phases), white noise; the board's ADC quantises.
# =============================================================================================

PARAMS: dict[str, Any] = {
    # amplifier
    "amp_tau_s": np.array([5.6e-5, 5.4e-5, 3.2e-5]),
    "amp_i_max_a": np.array([0.075, 0.075, 0.075]),
    "stack_c_f": np.array([3.1e-6, 3.1e-6, 1.6e-6]),
    "amp_range_v": ((-30.0, 135.0), (-30.0, 135.0), (-30.0, 135.0)),
    # domain-wall hysteresis (volt-equivalent units)
    "dw_a_v": np.array([62.0, 66.0, 58.0]),
    "dw_ms_v": np.array([170.0, 178.0, 160.0]),
    "dw_hb_v": np.array([38.0, 42.0, 35.0]),
    "dw_alpha": np.array([0.30, 0.28, 0.32]),
    "dw_k_v": np.array([30.0, 28.0, 32.0]),
    "dw_c": np.array([0.22, 0.25, 0.2]),
    "dw_max_step_v": 0.5,
    "b_int_um_per_v": np.array([0.40, 0.39, 0.080]),
    "b_dw_um_per_v": np.array([0.225, 0.23, 0.045]),
    "e2_per_v": np.array([4.0e-4, 3.0e-4, 5.0e-4]),
    # after-effect (creep)
    "ae_g0_v": np.array([1.45, 1.5, 1.6]),
    "ae_tau_s": np.array([2.0e4, 2.4e4, 1.6e4]),
    # temperature
    "amb_ramp_k_per_s": 0.35 / 3600.0,
    "amb_step_k": 0.25,
    "amb_step_tau_s": 420.0,
    "amb_step_window_s": (200.0, 800.0),
    "self_tan_delta": 0.04,
    "self_rth_k_per_w": 12.0,
    "self_tau_s": 180.0,
    "self_v_mid_v": 50.0,
    "t_ref_k": 295.0,
    "tc_sens_per_k": np.array([1.2e-3, 1.2e-3, 1.0e-3]),
    "tc_pin_per_k": np.array([6.0e-3, 6.0e-3, 6.0e-3]),
    "exp_amb_um_per_k": np.array([-0.045, 0.030, 0.110]),
    "exp_self_um_per_k": np.array([0.15, 0.14, 0.05]),
    # parallel kinematics: rows are the output axes, columns the actuators' displacement
    "couple": np.array([[1.0, -0.004, 0.0], [0.007, 1.0, 0.0], [3.0e-4, -2.0e-4, 1.0]]),
    "z_bow_per_um": 4.0e-6,
    # mechanics
    "mode1_f_hz": np.array([480.0, 440.0, 1250.0]),
    "mode1_q": np.array([14.0, 16.0, 22.0]),
    "mode2_f_hz": np.array([2150.0, 1900.0, 3000.0]),
    "mode2_q": np.array([30.0, 28.0, 30.0]),
    "mode2_weight": np.array([0.03, 0.035, 0.0]),
    # sensor
    "sensor_delay_s": 7.0e-5,
    "sensor_lag_s": 4.5e-5,
    "sensor_noise_nm": np.array([1.2, 1.2, 0.5]),
    "sensor_drift_nm": np.array([0.8, 0.8, 0.4]),
    "sensor_drift_periods_s": (600.0, 3000.0),
}


# ---------------------------------------------------------------------------------------------
# exact discretisation of the linear parts (input linear between samples)


def _second_order(f_hz: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    w = 2.0 * math.pi * f_hz
    return np.array([[0.0, 1.0], [-w * w, -w / q]]), np.array([0.0, w * w])


def _foh(a_mat: np.ndarray, b_vec: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x_{k+1} = phi x_k + g0 u_k + g1 u_{k+1} for x' = A x + B u, u linear over the step."""
    n = a_mat.shape[0]
    m = np.zeros((n + 2, n + 2))
    m[:n, :n] = a_mat
    m[:n, n] = b_vec
    m[n, n + 1] = 1.0
    e = np.asarray(expm(m * dt))
    phi = e[:n, :n]
    e12 = e[:n, n]
    e13 = e[:n, n + 1] / dt
    return phi, e12 - e13, e13


class _Discrete:
    """Cached FOH coefficients per dt of the two modes and the sensor lag (all channels)."""

    def __init__(self, p: dict[str, Any]) -> None:
        self._p = p
        self._cache: dict[float, tuple[np.ndarray, ...]] = {}

    def get(self, dt: float) -> tuple[np.ndarray, ...]:
        hit = self._cache.get(dt)
        if hit is not None:
            return hit
        p = self._p
        C = len(AXES)
        phis = np.zeros((C, 2, 2, 2))  # channel, mode, 2 x 2
        gs = np.zeros((C, 2, 2, 2))  # channel, mode, [g0, g1], state
        for c in range(C):
            for m, (f, q) in enumerate(
                ((p["mode1_f_hz"][c], p["mode1_q"][c]), (p["mode2_f_hz"][c], p["mode2_q"][c]))
            ):
                a, b = _second_order(float(f), float(q))
                phi, g0, g1 = _foh(a, b, dt)
                phis[c, m], gs[c, m, 0], gs[c, m, 1] = phi, g0, g1
        tl = p["sensor_lag_s"]
        phi, g0, g1 = _foh(np.array([[-1.0 / tl]]), np.array([1.0 / tl]), dt)
        lag = np.array([phi[0, 0], g0[0], g1[0]])
        out = (phis, gs, lag)
        if len(self._cache) > 64:
            self._cache.clear()
        self._cache[dt] = out
        return out


# ---------------------------------------------------------------------------------------------
# compiled kernels


@njit(cache=True)
def _amplifier(
    u: np.ndarray, dt: float, tau: float, slew: float, st: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover - compiled
    """Current-limited one-pole amplifier of one channel; st = [v, u_prev]; out = ceramic voltage."""
    v, up = st[0], st[1]
    e = math.exp(-dt / tau)
    dv_max = slew * dt
    for k in range(u.shape[0]):
        uk = u[k]
        r = (uk - up) / dt
        vn = (uk - r * tau) + (v - up + r * tau) * e
        dv = vn - v
        if dv > dv_max:
            dv = dv_max
        elif dv < -dv_max:
            dv = -dv_max
        v += dv
        up = uk
        out[k] = v
    st[0], st[1] = v, up


@njit(cache=True)
def _langevin(z: float) -> float:  # pragma: no cover - compiled
    if abs(z) < 1e-4:
        return z / 3.0
    return 1.0 / math.tanh(z) - 1.0 / z


@njit(cache=True)
def _domain_walls(
    v: np.ndarray,
    dt: float,
    a: float,
    ms: float,
    hb: float,
    alpha: float,
    k: float,
    c: float,
    g0: float,
    tau: float,
    max_step: float,
    st: np.ndarray,
    out_p: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Domain-wall hysteresis with its thermal after-effect, one channel.

    st = [P_i, P, H_prev, V_prev]; out_p: wall displacement P (volt-equivalent).
    """
    pi, p, hp, vp = st[0], st[1], st[2], st[3]
    decay = math.exp(-dt / tau)
    for kk in range(v.shape[0]):
        vk = v[kk]
        dv = vk - vp
        pan = 0.0
        if dv != 0.0:
            nsub = math.ceil(abs(dv) / max_step)
            if nsub > 4000:
                nsub = 4000
            for j in range(nsub):
                vs = vp + dv * (j + 1) / nsub
                h = vs + alpha * p
                pan = ms * _langevin((h - hb) / a)
                gap = pan - pi
                if gap * dv > 0.0:
                    pi += gap * (1.0 - math.exp(-abs(h - hp) / k))
                p = pi + c * (pan - pi)
                hp = h
        else:
            h = vk + alpha * p
            pan = ms * _langevin((h - hb) / a)
        # thermal after-effect over the sample (anhysteretic frozen): exact Eyring relaxation
        gap = pan - pi
        if gap != 0.0:
            th = math.tanh(gap / (2.0 * g0)) * decay
            if th > 0.999999999999:
                th = 0.999999999999
            elif th < -0.999999999999:
                th = -0.999999999999
            pi = pan - 2.0 * g0 * math.atanh(th)
        p = pi + c * (pan - pi)
        hp = vk + alpha * p
        vp = vk
        out_p[kk] = p
    st[0], st[1], st[2], st[3] = pi, p, hp, vp


@njit(cache=True)
def _output_chain(
    x: np.ndarray,
    phis: np.ndarray,
    gs: np.ndarray,
    w2: float,
    lag: np.ndarray,
    delay_frac: float,
    delay_int: int,
    st: np.ndarray,
    hist: np.ndarray,
    out_m: np.ndarray,
    out_y: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Two modes (weights 1 - w2, w2), then the sensor's delay (history hist, newest last) and lag.

    st = [m1, m1', m2, m2', x_prev, lag, lag_in_prev]; out_m: mechanical position, out_y: sensed.
    """
    a10, a11, a12, a13 = phis[0, 0, 0], phis[0, 0, 1], phis[0, 1, 0], phis[0, 1, 1]
    b10, b11, c10, c11 = gs[0, 0, 0], gs[0, 0, 1], gs[0, 1, 0], gs[0, 1, 1]
    a20, a21, a22, a23 = phis[1, 0, 0], phis[1, 0, 1], phis[1, 1, 0], phis[1, 1, 1]
    b20, b21, c20, c21 = gs[1, 0, 0], gs[1, 0, 1], gs[1, 1, 0], gs[1, 1, 1]
    m1, m1d, m2, m2d, xp, z, zp = st[0], st[1], st[2], st[3], st[4], st[5], st[6]
    la, lg0, lg1 = lag[0], lag[1], lag[2]
    nh = hist.shape[0]
    for k in range(x.shape[0]):
        xk = x[k]
        n1 = a10 * m1 + a11 * m1d + b10 * xp + c10 * xk
        n1d = a12 * m1 + a13 * m1d + b11 * xp + c11 * xk
        m1, m1d = n1, n1d
        if w2 != 0.0:
            n2 = a20 * m2 + a21 * m2d + b20 * xp + c20 * xk
            n2d = a22 * m2 + a23 * m2d + b21 * xp + c21 * xk
            m2, m2d = n2, n2d
        xp = xk
        m = (1.0 - w2) * m1 + w2 * m2
        out_m[k] = m
        # delay line: hist holds the last nh mechanical positions, newest last
        for q in range(nh - 1):
            hist[q] = hist[q + 1]
        hist[nh - 1] = m
        i0 = nh - 1 - delay_int
        d = hist[i0] + delay_frac * (hist[i0 - 1] - hist[i0])
        z = la * z + lg0 * zp + lg1 * d
        zp = d
        out_y[k] = z
    st[0], st[1], st[2], st[3], st[4], st[5], st[6] = m1, m1d, m2, m2d, xp, z, zp


# ---------------------------------------------------------------------------------------------
# the stage


@dataclasses.dataclass
class _State:
    time_s: float
    amp: np.ndarray  # (C, 2): v, u_prev
    walls: np.ndarray  # (C, 4): P_i, P, H_prev, V_prev
    chain: np.ndarray  # (C, 7)
    hist: np.ndarray  # (C, H)
    t_self: np.ndarray  # (C,) stack self-heating (K)
    amb_step_t_s: float
    drift_phase: np.ndarray  # (C, 3)
    drift_period_s: np.ndarray  # (C, 3)


def _placeholder_config() -> StageConfig:
    """A valid StageConfig for code that reads ``stage.config`` (only the microscope does; this
    stage has none). It is NOT this stage's physics."""
    axis = {"alpha_per_v": 3.0e-3, "b_um_per_v": 0.7, "u_um_per_v": 0.45}
    return StageConfig.model_validate({"axes": {a: axis for a in AXES}, "seed": 0})


class ForeignStage(Stage):
    """The foreign-physics stage, with the interface the board uses (step, sense, axes, channels,
    config, time_s, reset, snapshot / restore)."""

    MAX_CHUNK = 256
    HIST = 16

    def __init__(self, seed: int = 0, truth: str | None = None, truth_every: int = 10) -> None:
        self._p = PARAMS
        self._seed = int(seed)
        self._disc = _Discrete(self._p)
        self._truth_every = max(1, int(truth_every))
        self._truth_fh = None
        self._truth_count = 0
        if truth:
            self._truth_fh = open(truth, "ab")  # noqa: SIM115
            side = {
                "dtype": [("t_s", "<f8"), ("volts", "<f4", [len(AXES)]), ("x_um", "<f4", [len(AXES)])],
                "axes": list(AXES),
                "meaning": "t_s: stage time since power-up; volts: at the ceramic (after the amplifier); "
                "x_um: true position, noise-free, before the sensor's delay, lag, drift and noise (sensor "
                "coordinates, 0 = rest at 0 V at power-up)",
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
        walls = np.zeros((C, 4))
        self._p_rest = np.zeros(C)
        for ch in range(C):
            # virgin state at 0 V: the walls at the (self-consistent) anhysteretic
            pw = 0.0
            a, ms, hb, alpha = p["dw_a_v"][ch], p["dw_ms_v"][ch], p["dw_hb_v"][ch], p["dw_alpha"][ch]
            for _ in range(200):
                pw = ms * _langevin((alpha * pw - hb) / a)
            walls[ch] = (pw, pw, p["dw_alpha"][ch] * pw, 0.0)
            self._p_rest[ch] = pw
        rng = np.random.default_rng([self._seed, 5100])
        lo, hi = p["amb_step_window_s"]
        plo, phi = p["sensor_drift_periods_s"]
        self._s = _State(
            time_s=0.0,
            amp=np.zeros((C, 2)),
            walls=walls,
            chain=np.zeros((C, 7)),
            hist=np.zeros((C, self.HIST)),
            t_self=np.zeros(C),
            amb_step_t_s=float(rng.uniform(lo, hi)),
            drift_phase=rng.uniform(0.0, 2.0 * math.pi, size=(C, 3)),
            drift_period_s=np.exp(rng.uniform(math.log(plo), math.log(phi), size=(C, 3))),
        )
        self._rng = np.random.default_rng([self._seed, 51])

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
        # long holds: sub-step so that the amplifier, the after-effect and the filters see the time pass
        if n == 1 and dt_s > 0.02:
            k = math.ceil(dt_s / 0.02)
            s = self._s
            up = s.amp[:, 1]
            frac = np.arange(1, k + 1) / k
            vv = up[:, None] + (v[:, :1] - up[:, None]) * frac[None, :]
            x = self._long(vv, dt_s / k)
            return x[:, -1:]
        if n <= self.MAX_CHUNK:
            return self._step(v, dt_s)
        return self._long(v, dt_s)

    def _long(self, v: np.ndarray, dt_s: float) -> np.ndarray:
        """A long block (the board caught up after a stall, a long hold): the same physics in chunks."""
        n = v.shape[1]
        return np.concatenate(
            [
                self._step(np.ascontiguousarray(v[:, k : k + self.MAX_CHUNK]), dt_s)
                for k in range(0, n, self.MAX_CHUNK)
            ],
            axis=1,
        )

    # -- the physics ---------------------------------------------------------------------------

    def _ambient(self, t: np.ndarray) -> np.ndarray:
        p = self._p
        ts = self._s.amb_step_t_s
        on = np.maximum(t - ts, 0.0)
        amb: np.ndarray = p["amb_ramp_k_per_s"] * t + p["amb_step_k"] * -np.expm1(-on / p["amb_step_tau_s"])
        return amb

    def _step(self, u: np.ndarray, dt: float) -> np.ndarray:
        p = self._p
        s = self._s
        C, n = u.shape
        phis, gs, lag = self._disc.get(dt)
        t0 = s.time_s
        t = t0 + dt * np.arange(1, n + 1)
        # 1. amplifier
        vc = np.empty_like(u)
        slew = p["amp_i_max_a"] / p["stack_c_f"]
        for ch in range(C):
            _amplifier(u[ch], dt, p["amp_tau_s"][ch], slew[ch], s.amp[ch], vc[ch])
        # 4a. stack self-heating over the block (dielectric loss of the drive), constant over a block
        prev = np.concatenate((s.walls[:, 3:4], vc[:, :-1]), axis=1)
        dvdt = np.abs(vc - prev) / dt
        power = (
            0.5
            * math.pi
            * p["self_tan_delta"]
            * p["stack_c_f"]
            * np.mean(dvdt * np.abs(vc - p["self_v_mid_v"]), axis=1)
        )
        ef = math.exp(-n * dt / p["self_tau_s"])
        s.t_self = p["self_rth_k_per_w"] * power + (s.t_self - p["self_rth_k_per_w"] * power) * ef
        amb = self._ambient(t)
        t_stack = s.t_self[:, None] + amb[None, :]
        t_blk = s.t_self + amb[-1]
        # 2-3. hysteresis and creep
        pw = np.empty_like(vc)
        for ch in range(C):
            _domain_walls(
                vc[ch],
                dt,
                p["dw_a_v"][ch],
                p["dw_ms_v"][ch],
                p["dw_hb_v"][ch],
                p["dw_alpha"][ch],
                p["dw_k_v"][ch] * max(0.5, 1.0 - p["tc_pin_per_k"][ch] * t_blk[ch]),
                p["dw_c"][ch],
                p["ae_g0_v"][ch] * (1.0 + t_blk[ch] / p["t_ref_k"]),
                p["ae_tau_s"][ch],
                p["dw_max_step_v"],
                s.walls[ch],
                pw[ch],
            )
        d = p["b_int_um_per_v"][:, None] * vc * (1.0 + p["e2_per_v"][:, None] * vc) + p["b_dw_um_per_v"][
            :, None
        ] * (pw - self._p_rest[:, None])
        d *= 1.0 + p["tc_sens_per_k"][:, None] * t_stack
        # 5. parallel kinematics
        x = p["couple"] @ d
        x[2] += p["z_bow_per_um"] * (d[0] * d[0] + d[1] * d[1])
        # 4b. thermal expansion of the stage and the stacks
        x += p["exp_amb_um_per_k"][:, None] * amb[None, :]
        x += p["exp_self_um_per_k"][:, None] * s.t_self[:, None]
        # 6-7. mechanics and sensor
        dpos = p["sensor_delay_s"] / dt
        dint = min(int(dpos), self.HIST - 2)
        dfrac = min(dpos - dint, 1.0)
        xm = np.empty_like(x)
        y: np.ndarray = np.empty_like(x)
        x = np.ascontiguousarray(x)
        for ch in range(C):
            _output_chain(
                x[ch],
                phis[ch],
                gs[ch],
                p["mode2_weight"][ch],
                lag,
                dfrac,
                dint,
                s.chain[ch],
                s.hist[ch],
                xm[ch],
                y[ch],
            )
        drift = (
            p["sensor_drift_nm"][:, None]
            * 1e-3
            * np.sin(
                2.0 * math.pi * t[None, None, :] / s.drift_period_s[:, :, None] + s.drift_phase[:, :, None]
            ).sum(axis=1)
        )
        y += drift - p["sensor_drift_nm"][:, None] * 1e-3 * np.sin(s.drift_phase).sum(axis=1)[:, None]
        s.time_s = float(t[-1])
        self._record(t, vc, xm)
        return y

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


def _amplifier_ranges(path: Path) -> tuple[tuple[float, float], ...]:
    """The amplifier's output ranges; the scanner YAML's voltage limits must lie inside them."""
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    axes = data["axes"]
    if list(axes) != list(AXES):
        raise SystemExit(f"{path}: axes must be {', '.join(AXES)} in this order (the board's channels)")
    ranges: tuple[tuple[float, float], ...] = tuple(PARAMS["amp_range_v"])
    for a, (lo, hi) in zip(AXES, ranges, strict=True):
        vmin, vmax = float(axes[a]["voltage_min_v"]), float(axes[a]["voltage_max_v"])
        if not lo <= vmin < vmax <= hi:
            raise SystemExit(
                f"{path}: axes.{a} limits [{vmin}, {vmax}] V outside the amplifier's [{lo}, {hi}] V"
            )
    return ranges


def _setup_logging(verbose: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s foreign51[%(process)d] %(levelname)s: %(message)s"))
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
        stage.step(v, 1e-4)
        stage.step(np.asfortranarray(v[:, :200]), 1e-4)
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
    parser.add_argument("--seed", type=int, default=51, metavar="N")
    parser.add_argument("--truth", metavar="FILE", help="append the true position records here")
    parser.add_argument("--truth-every", type=int, default=10, metavar="N")
    parser.add_argument("--tick-ms", type=float, default=2.0, metavar="MS")
    parser.add_argument("--fifo-depth", type=int, default=BoardConfig().fifo_depth_samples, metavar="N")
    parser.add_argument("--exit-with-stdin", action="store_true")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    ranges = _amplifier_ranges(Path(args.config))
    stage = ForeignStage(seed=args.seed, truth=args.truth, truth_every=args.truth_every)
    log.info("compiled the stage in %.1f s", warm_up(stage))
    clock = time.monotonic
    cfg = BoardConfig(
        amplifier_ranges_v=ranges,
        fifo_depth_samples=args.fifo_depth,
        seed=args.seed,
        board_serial=0x51A0_F051,
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
