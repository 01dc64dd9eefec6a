"""Stand-ins for kinds of real recordings (generated in process for the tests and ``piezod bench audit``).

None of these is built from the audit's own candidate terms alone: positions come from the
hysteresis ODE (2.21) with a log creep after every voltage step (a spread of relaxation
times), a polarization-switching ferroelectric, a sensor lag, white noise and a quantised
sensor, at the sample rates and durations of the instruments described in issue #10:

* :func:`pnzt_hold_session`: a PNZT ceramic disc measured by an interferometer: triangles at
  three rates, then a voltage hold of 1355 s with a known linear (interferometer) drift;
* :func:`actuator_5khz`: a +-150 V actuator driven by a 1 Hz sine, sampled at 5 kHz, with an
  amplifier lag; :func:`decimate` makes the 200 Hz version;
* :func:`butterfly_session`: a ferroelectric cycled above its coercive voltage (butterfly);
* :func:`pnzt_holds`: hold-only recordings (one file per voltage hold, up to 1355 s), the
  creep of the step before each a spread of relaxation times (not the audit's log law), an
  interferometer with white noise, a slow random walk (air, temperature) and 0.3 nm steps;
* :func:`one_period_triangles`: one-period triangles at 1, 0.1 and 0.01 Hz, one per block
  (the way many instruments export);
* :func:`preset_session`: a small calibration frame (and optionally a voltage hold) on a
  simulated stage of other physics, the presets of ``piezod sim --stage NAME``
  (``configs/sim-pi-stage.yaml``: Prandtl-Ishlinskii hysteresis, voltage-driven power-law creep,
  asymmetric curvature, amplifier pole; ``configs/sim-p885-stage.yaml``: the P-885 loop shape
  and creep rate, sensor lag), run in process through :mod:`piezod.simulator`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from piezod.model.ode import hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams
from piezod.recording import Experiment
from piezod.simulator import simulated_session

F64 = NDArray[np.float64]


def _triangle(t: F64, f: float, lo: float, hi: float) -> F64:
    ph = (t * f) % 1.0
    out: F64 = lo + (hi - lo) * np.where(ph < 0.5, 2.0 * ph, 2.0 - 2.0 * ph)
    return out


def _log_creep(t: F64, v: F64, pct_per_decade: float, b: float, tau0: float = 0.05) -> F64:
    """Creep after every voltage change: a superposition of ``c log10(1 + (t - t_k)/tau0)`` steps."""
    dv = np.diff(v, prepend=v[0])
    out = np.zeros_like(t)
    for k in np.flatnonzero(np.abs(dv) > 0).tolist():
        out[k:] += dv[k] * np.log10(1.0 + (t[k:] - t[k]) / tau0)
    res: F64 = out * b * pct_per_decade / 100.0
    return res


def pnzt_hold_session(
    drift_nm_per_s: float = 0.63,
    *,
    hold_s: float = 1355.0,
    rate_hz: float = 10.0,
    seed: int = 0,
) -> list[Experiment]:
    """A PNZT disc: 2 loops each at 0.1 and 0.05 Hz (+-400 V), then a hold at +400 V for ``hold_s``.

    Interferometer: 2 nm noise, quantised to 0.3 nm, drifting linearly at ``drift_nm_per_s``
    through the whole session; the ceramic creeps 2 %/decade after every voltage change.
    """
    rng = np.random.default_rng(seed)
    p = HysteresisParams(alpha_per_v=4e-3, b_um_per_v=2.4e-3, u_um_per_v=1.9e-3)
    dt = 1.0 / rate_hz
    parts: list[tuple[str, F64]] = []
    for f in (0.1, 0.05):
        t = np.arange(round(2.0 / f * rate_hz), dtype=np.float64) * dt
        parts.append((f"triangle_{f:g}Hz", _triangle(t + 0.25 / f, f, -400.0, 400.0)))
    n_hold = round(hold_s * rate_hz)
    parts.append(("hold_400V", np.full(n_hold, 400.0)))
    v_all = np.concatenate([v for _, v in parts])
    t_all = np.arange(v_all.size, dtype=np.float64) * dt
    x, _ = hysteresis_step(p, v_all, relaxed_state(p, float(v_all[0])))
    x = x + _log_creep(t_all, v_all, 2.0, p.b_um_per_v)
    x = x + drift_nm_per_s * 1e-3 * t_all
    x = x + rng.normal(0.0, 2e-3, x.size)
    x = np.round(x / 3e-4) * 3e-4
    out, k = [], 0
    for label, v in parts:
        sl = slice(k, k + v.size)
        out.append(Experiment(label, None, t_all[sl], v_all[sl], x[sl]))
        k += v.size
    return out


def pnzt_holds(
    drift_nm_per_s: float = 0.63,
    *,
    volts: tuple[float, ...] = (400.0,),
    hold_s: float = 1355.0,
    rate_hz: float = 10.0,
    walk_nm_per_sqrt_s: float = 0.05,
    seed: int = 4,
) -> list[Experiment]:
    """Hold-only recordings of a PNZT disc: one experiment per hold at each of ``volts``.

    Before each hold the voltage stepped there 5 s before the recording started. The creep is a
    spread of relaxations (24 times, 1 ms to 1e5 s, weights growing as ``tau^0.05``: about
    2 %/decade of the step, not a pure log law); the interferometer adds 2 nm white noise, a
    random walk of ``walk_nm_per_sqrt_s`` and 0.3 nm quantisation; a linear drift of
    ``drift_nm_per_s`` runs through the session. The voltage monitor reads 0.05 V noise.
    """
    rng = np.random.default_rng(seed)
    b = 2.4e-3
    taus = np.geomspace(1e-3, 1e5, 24)
    w = taus**0.05
    w *= 0.02 * 8.0 / w.sum()  # ~2 % of the step per decade over the 8 decades
    out, t0, v_prev = [], 0.0, 0.0
    for k, volt in enumerate(volts):
        t = np.arange(round(hold_s * rate_hz)) / rate_hz
        since = t + 5.0
        creep = (volt - v_prev) * b * ((1.0 - np.exp(-since[:, None] / taus[None, :])) @ w)
        x = b * volt + creep + drift_nm_per_s * 1e-3 * (t + t0)
        x = x + np.cumsum(rng.normal(0.0, walk_nm_per_sqrt_s * 1e-3 / math.sqrt(rate_hz), t.size))
        x = np.round((x + rng.normal(0.0, 2e-3, t.size)) / 3e-4) * 3e-4
        v = volt + rng.normal(0.0, 0.05, t.size)
        out.append(Experiment(f"hold_{volt:g}V_{k}", None, t + t0, v, x))
        t0 += hold_s + 60.0
        v_prev = volt
    return out


def actuator_5khz(*, seconds: float = 12.0, lag_s: float = 2e-3, seed: int = 1) -> Experiment:
    """A +-150 V actuator, 1 Hz sine, 5 kHz sampling, first-order amplifier lag ``lag_s``, 3 nm noise."""
    rng = np.random.default_rng(seed)
    rate = 5000.0
    t = np.arange(round(seconds * rate)) / rate
    amp = 150.0 * np.minimum(1.0, 0.4 + 0.6 * t / seconds)  # growing amplitude: minor loops
    v = amp * np.sin(2 * np.pi * 1.0 * t)
    p = HysteresisParams(alpha_per_v=6e-3, b_um_per_v=0.12, u_um_per_v=0.095)
    # The lag acts on the voltage the stack sees (amplifier driving a capacitance).
    a = math.exp(-1.0 / (rate * lag_s))
    v_seen = lfilter([1.0 - a], [1.0, -a], v, zi=[a * v[0]])[0]
    x, _ = hysteresis_step(p, v_seen, relaxed_state(p, float(v_seen[0])))
    x = x + rng.normal(0.0, 3e-3, x.size)
    return Experiment("actuator_1Hz", None, t, v, x)


def decimate(e: Experiment, factor: int) -> Experiment:
    """Every ``factor``-th sample (what a slower logger records; the metadata are kept)."""
    sl = slice(None, None, factor)
    return Experiment(e.label, e.axis, e.t_s[sl], e.voltage_v[sl], e.position_um[sl], metadata=e.metadata)


def butterfly_session(
    *,
    v_max: float = 1400.0,
    v_c: float = 600.0,
    f_hz: float = 0.05,
    rate_hz: float = 50.0,
    loss: float = 0.77,
    seed: int = 2,
) -> list[Experiment]:
    """A ferroelectric cycled to +-``v_max`` above its coercive voltage ``v_c``: a butterfly strain loop.

    First two loops at +-0.3 ``v_max`` (below ``v_c``: an ordinary piezo loop), then two loops
    at +-``v_max``: the polarization switches where ``|V|`` passes ``v_c`` against it; then the
    small loops again with the sensitivity reduced by ``loss`` (partly depoled).
    """
    rng = np.random.default_rng(seed)
    p = HysteresisParams(alpha_per_v=2e-3, b_um_per_v=1.2e-3, u_um_per_v=0.9e-3)
    out = []
    t0 = 0.0
    plan = (
        ("small_loops", 0.3 * v_max, 1.0),
        ("large_loops", v_max, 1.0),
        ("small_loops_after", 0.3 * v_max, 1.0 - loss),
    )
    for label, amp, d in plan:
        t = np.arange(round(2.0 / f_hz * rate_hz)) / rate_hz
        v = amp * np.sin(2 * np.pi * f_hz * t)
        # The strain follows the field along the polarization: the hysteretic actuator response
        # to pol * V, where pol flips when |V| passes v_c against it (re-poled at the end).
        pol = np.ones_like(v)
        state = 1.0
        for k, vk in enumerate(v):
            if vk <= -v_c and state > 0:
                state = -1.0
            elif vk >= v_c and state < 0:
                state = 1.0
            pol[k] = state
        x, _ = hysteresis_step(p, pol * v, relaxed_state(p, float(pol[0] * v[0])))
        x = d * x + rng.normal(0.0, 2e-3, x.size)
        out.append(Experiment(label, None, t + t0, v, x))
        t0 += float(t[-1]) + 1.0 / rate_hz
    return out


def one_period_triangles(
    freqs_hz: tuple[float, ...] = (1.0, 0.1, 0.01),
    *,
    samples_per_period: int = 400,
    v_pp: float = 200.0,
    seed: int = 3,
) -> list[Experiment]:
    """One triangle period per experiment (0 -> +V -> 0 -> -V -> 0) at each frequency, with creep."""
    rng = np.random.default_rng(seed)
    p = HysteresisParams(alpha_per_v=5e-3, b_um_per_v=0.01, u_um_per_v=0.008)
    out, t0 = [], 0.0
    for f in freqs_hz:
        n = samples_per_period
        t = np.arange(n + 1) / (n * f)
        v = _triangle(t + 0.25 / f, f, -v_pp / 2, v_pp / 2)  # 0 -> +V -> 0 -> -V -> 0
        x, _ = hysteresis_step(p, v, relaxed_state(p, float(v[0])))
        x = x + _log_creep(t, v, 3.0, p.b_um_per_v) + rng.normal(0.0, 1e-3, n + 1)
        out.append(Experiment(f"triangle_{f:g}Hz", None, t + t0, v, x))
        t0 += float(t[-1]) + 1.0
    return out


def preset_session(
    stage: str,
    effects: tuple[str, ...] = (),
    *,
    rate_hz: float = 1000.0,
    hold_s: float = 0.0,
    seed: int = 0,
) -> list[Experiment]:
    """A small frame on a preset stage: 3 ranges (120-400 V) x 3 line rates (0.1-5 Hz), then a hold.

    The frame is what a user records to calibrate (a settling loop before each scan, one or two
    recorded loops); ``hold_s > 0`` adds a voltage hold at +100 V (creep and drift). ``effects``
    are ``piezod sim --effect`` specs (``drift=1.0``, ``resonance=700``, ...).
    """
    plan: list[tuple[object, ...]] = [
        ("triangle", r, f, 0.0, 1 if f < 1.0 else 2, 1)
        for r in (120.0, 260.0, 400.0)
        for f in (0.1, 1.0, 5.0)
    ]
    if hold_s > 0:
        plan.append(("hold", 100.0, hold_s))
    return [
        Experiment(label, None, t, v, x)
        for label, t, v, x in simulated_session(
            stage, plan, effects=effects, sample_rate_hz=rate_hz, seed=seed
        )
    ]
