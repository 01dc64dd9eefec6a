"""Thesis-model sessions with hidden effects: test data for the audit.

A session of a *thesis-model stage*: every recorded loop follows (3.8) exactly
(:func:`piezod.model.thesis.thesis_loop`), plus at most a few physical effects applied to the
voltage or to the output, per-experiment sensor offsets, white sensor noise and quantisation.
Time runs on (settling loops included), so effects that depend on the session time see it.

Effects (names and parameters as in :mod:`hil_sim.effects`):

==============  ==============================  ==========================================
id              parameters                      applied as
==============  ==============================  ==========================================
drift           ``rate_nm_per_s``               ``x + r t``
thermal         ``rate_pct_per_hour``           ``x (1 + r t / 360000)``
stiffness       ``sensitivity_pct_per_um``      ``x + k x^2 / 200``
polarity        ``negative_sensitivity_pct``    ``V (1 + p / 100)`` for ``V < 0``, turning points too
resonance       ``f0_hz``, ``q``                exact second-order filter, from rest per experiment
delay           ``delay_s``                     ``x(t - d)``
saturation      ``x_sat_um``                    ``x_sat tanh(x / x_sat)``
creep           ``pct_per_decade``, ``law``     ``law="motion"``: the loop scaled by ``1 + c log10(f_ref/f)``;
                                                ``law="k"``: ``c log10(f_ref/f)`` added to the frequency
                                                factor of (3.5); ``law="log"``: that factor is
                                                ``const + c log10(f_ref/f)``; ``law="spread"``: its
                                                exponential averaged over ``tau/100 ... 100 tau``
                                                with amplitude ``A1 + 4 c`` (``c`` in units of 1/100)
==============  ==============================  ==========================================
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter, lfilter_zi

from piezod.audit.dynamics import _resonance_tf
from piezod.errors import ModelError
from piezod.model.params import ThesisParams
from piezod.model.thesis import hysteresis_loop, max_creep_um
from piezod.recording import Recording
from piezod.synth import PlannedExperiment

F64 = NDArray[np.float64]

#: Effects this generator knows.
HIDDEN_EFFECTS: tuple[str, ...] = (
    "drift",
    "thermal",
    "stiffness",
    "polarity",
    "resonance",
    "delay",
    "saturation",
    "creep",
)


def frame_plan(
    rng: np.random.Generator | int,
    *,
    ranges_v: Sequence[float] = (80.0, 160.0, 240.0, 320.0, 400.0),
    n_frequencies: int = 6,
    frequency_hz: tuple[float, float] = (0.02, 5.0),
    offsets_v: Sequence[float] = (-50.0, 0.0, 50.0),
    v_limit: float = 230.0,
    reference: tuple[float, float] = (240.0, 1.0),
    n_references: int = 5,
    n_loops: int = 1,
    settle_loops: int = 1,
) -> tuple[PlannedExperiment, ...]:
    """A calibration-frame-like plan: ranges x frequencies with random offsets, and a repeated reference.

    The frequencies are log-spaced over ``frequency_hz`` with a random shift; every scan gets
    an offset drawn from ``offsets_v`` that keeps it inside ``+-v_limit``. The reference scan
    (range, frequency) is run first, last and evenly in between (``n_references`` times).
    """
    g = np.random.default_rng(rng)
    lo, hi = (math.log(f) for f in frequency_hz)
    step = (hi - lo) / n_frequencies
    freqs = np.exp(lo + step * (np.arange(n_frequencies) + g.uniform(0.0, 1.0)))
    grid: list[PlannedExperiment] = []
    for r in ranges_v:
        for f in freqs:
            ok = [o for o in offsets_v if abs(o) + r / 2 <= v_limit] or [0.0]
            o = float(g.choice(ok))
            grid.append(
                PlannedExperiment(
                    f"r{r:g}_f{f:.3g}_o{o:g}", o - r / 2, o + r / 2, float(f), n_loops, settle_loops
                )
            )
    order = g.permutation(len(grid))
    grid = [grid[i] for i in order]
    if n_references <= 0:
        return tuple(grid)
    plan: list[PlannedExperiment] = []
    every = max(1, math.ceil(len(grid) / max(n_references - 1, 1)))
    k = 0
    for i, item in enumerate(grid):
        if i % every == 0:
            k += 1
            rr, ff = reference
            plan.append(PlannedExperiment(f"reference_{k:02d}", -rr / 2, rr / 2, ff, n_loops, settle_loops))
        plan.append(item)
    rr, ff = reference
    plan.append(PlannedExperiment(f"reference_{k + 1:02d}", -rr / 2, rr / 2, ff, n_loops, settle_loops))
    return tuple(plan)


@dataclass(frozen=True, eq=False)
class HiddenSession:
    """A generated session and its truth.

    Attributes
    ----------
    recording
        The data (``t, voltage, position, axis, experiment``).
    params
        The true (3.8) parameters.
    effects
        The hidden effects (id -> parameters).
    plan
        The experiments.
    """

    recording: Recording
    params: ThesisParams
    effects: Mapping[str, Mapping[str, Any]]
    plan: tuple[PlannedExperiment, ...]


def _loop_position(
    p: ThesisParams,
    v: F64,
    s: F64,
    v_min: float,
    v_max: float,
    f: float,
    creep: Mapping[str, Any] | None,
    f_ref: float,
) -> F64:
    """(3.8), optionally with a creep law other than (3.5)."""
    vh = 0.5 * (v_max - v_min)
    vc = 0.5 * (v_max + v_min)
    ff = 1.0 - p.a1 * math.exp(-1.0 / (f * p.tau_s))
    c = 0.0 if creep is None else float(creep["pct_per_decade"]) / 100.0
    law = "motion" if creep is None else str(creep.get("law", "motion"))
    if law == "k":
        ff += c * math.log10(f_ref / f)
    elif law == "log":
        # (3.5)'s exponential replaced by a logarithm of the frequency, same value at f_ref.
        ff = 1.0 - p.a1 * math.exp(-1.0 / (f_ref * p.tau_s)) + c * math.log10(f_ref / f)
    elif law == "spread":
        # A spread of relaxation times: exp(-1/(f tau)) averaged over tau / 100 ... 100 tau,
        # with an amplitude of c per decade of time.
        taus = p.tau_s * np.logspace(-2.0, 2.0, 17)
        ff = 1.0 - (p.a1 + 4.0 * c) * float(np.mean(np.exp(-1.0 / (f * taus))))
    kk = ff * (p.a2_per_v * vh + p.a3)
    b_hat = p.b_um_per_v + kk * max_creep_um(p.hysteresis, v_min, v_max) / vh
    x: F64 = hysteresis_loop(p.hysteresis, v, s, v_min, v_max) + (b_hat - p.b_um_per_v) * (v - vc)
    if law == "motion" and c:
        x = x * (1.0 + c * math.log10(f_ref / f))
    return x


def hidden_session(
    params: ThesisParams,
    plan: Sequence[PlannedExperiment],
    effects: Mapping[str, Mapping[str, Any]] | None = None,
    *,
    samples_per_loop: int = 2048,
    noise_um: float = 0.005,
    lsb_um: float | None = 0.001,
    offset_spread_um: float = 2.0,
    f_ref_hz: float = 0.3,
    seed: np.random.Generator | int = 0,
    axis: str = "x",
) -> HiddenSession:
    """Generate a thesis-model session with hidden effects.

    Parameters
    ----------
    params
        True (3.8) parameters.
    plan
        Experiments (:func:`frame_plan`, :func:`piezod.synth.random_plan`).
    effects
        Effect id -> parameters (see the module docstring); none for a clean session.
    samples_per_loop
        Samples per loop (even).
    noise_um
        White sensor noise (um rms).
    lsb_um
        Sensor quantisation step (um), None for none.
    offset_spread_um
        Per-experiment sensor offsets, uniform in +-this.
    f_ref_hz
        Reference frequency of the creep law.
    seed
        Random generator or seed.
    axis
        Axis column value.

    Raises
    ------
    ModelError
        Unknown effect or bad settings.
    """
    fx = dict(effects or {})
    unknown = [k for k in fx if k not in HIDDEN_EFFECTS]
    if unknown:
        raise ModelError(f"unknown hidden effect(s) {unknown}; choose from {HIDDEN_EFFECTS}")
    if samples_per_loop < 8 or samples_per_loop % 2:
        raise ModelError(f"samples_per_loop must be even and >= 8, got {samples_per_loop}")
    g = np.random.default_rng(seed)
    plan = tuple(plan)
    offsets = g.uniform(-offset_spread_um, offset_spread_um, len(plan))
    ts, vs, xs, labels = [], [], [], []
    t_next = 0.0
    for exp, off in zip(plan, offsets.tolist(), strict=True):
        loops = exp.settle_loops + exp.n_loops
        k = np.arange(loops * samples_per_loop + 1)
        phase = (k % samples_per_loop) / samples_per_loop
        tri = np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
        s = np.where(phase < 0.5, 1.0, -1.0)
        v = exp.v_min + exp.range_v * tri
        dt = 1.0 / (exp.frequency_hz * samples_per_loop)
        t = t_next + dt * k
        v_min, v_max = exp.v_min, exp.v_max
        if "polarity" in fx:
            fac = 1.0 + float(fx["polarity"]["negative_sensitivity_pct"]) / 100.0
            v = np.where(v < 0, v * fac, v)
            v_min = v_min * fac if v_min < 0 else v_min
            v_max = v_max * fac if v_max < 0 else v_max
        x = _loop_position(params, v, s, v_min, v_max, exp.frequency_hz, fx.get("creep"), f_ref_hz)
        if "thermal" in fx:
            x = x * (1.0 + float(fx["thermal"]["rate_pct_per_hour"]) / 100.0 / 3600.0 * t)
        if "stiffness" in fx:
            x = x + float(fx["stiffness"]["sensitivity_pct_per_um"]) / 200.0 * x * x
        if "saturation" in fx:
            xs_ = float(fx["saturation"]["x_sat_um"])
            x = xs_ * np.tanh(x / xs_)
        if "resonance" in fx:
            b, a = _resonance_tf(float(fx["resonance"]["f0_hz"]), float(fx["resonance"].get("q", 10.0)), dt)
            x, _ = lfilter(b, a, x, zi=lfilter_zi(b, a) * x[0])
        if "drift" in fx:
            x = x + float(fx["drift"]["rate_nm_per_s"]) * 1e-3 * t
        if "delay" in fx:
            x = np.interp(t - float(fx["delay"]["delay_s"]), t, x)
        start = exp.settle_loops * samples_per_loop
        ts.append(t[start:])
        vs.append((exp.v_min + exp.range_v * tri)[start:])
        xs.append(x[start:] + off)
        labels.append(np.full(t.size - start, exp.label))
        t_next = float(t[-1]) + dt
    pos = np.concatenate(xs)
    pos = pos + g.normal(0.0, noise_um, pos.size)
    if lsb_um is not None:
        pos = np.round(pos / lsb_um) * lsb_um
    n = pos.size
    rec = Recording(
        t_s=np.concatenate(ts),
        voltage_v=np.concatenate(vs),
        position_um=pos,
        axis=np.full(n, axis),
        experiment=np.concatenate(labels),
        metadata={
            "source": "piezod.audit.synthetic (thesis-model stage)",
            "effects": ",".join(fx) or "none",
            "noise_um": f"{noise_um:g}",
        },
    )
    return HiddenSession(recording=rec, params=params, effects=fx, plan=plan)
