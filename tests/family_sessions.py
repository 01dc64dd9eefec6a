"""A calibration session simulated on a family model: loops at three rates and two ranges."""

from __future__ import annotations

import numpy as np

from piezod.calibrate_dynamic import DynamicCalibrationData, prepare_dynamic
from piezod.model.family import FamilyParams, family_forward, family_rest_state
from piezod.recording import Experiment


def loop_experiments(params: FamilyParams, rate_hz: float = 500.0) -> list[Experiment]:
    """Loops at 0.1, 1 and 10 Hz over 35 and 60 V around 50 V, each after a 2 s pause at the
    sample before its start, with 5 nm of sensor noise."""
    rng = np.random.default_rng(11)
    dt = 1.0 / rate_hz
    state = family_rest_state(params)
    exps, t0 = [], 0.0
    for freq in (0.1, 1.0, 10.0):
        for amp in (35.0, 60.0):
            n = round(2.0 / (freq * dt)) if freq < 1.0 else round(3.0 / (freq * dt))
            t = np.arange(n) * dt
            v = 50.0 - amp * np.cos(2 * np.pi * freq * t)
            # as the session's layout has it: a jump to the start (one sample before it), held
            gap = round(2.0 / dt)
            _, state = family_forward(params, np.full(gap, 2.0 * v[0] - v[1]), dt, state)
            t0 += gap * dt
            x, state = family_forward(params, v, dt, state)
            x = x + rng.normal(0.0, 0.005, x.size)
            times = np.asarray(t0 + t, dtype=np.float64)
            exps.append(Experiment(f"{amp:g}V {freq:g}Hz", "x", times, np.asarray(v, np.float64), x))
            t0 += n * dt
    return exps


def loop_session(params: FamilyParams) -> DynamicCalibrationData:
    """:func:`loop_experiments` as a calibration session (128 samples a loop, from rest at 0 V)."""
    return prepare_dynamic(
        loop_experiments(params),
        max_samples_per_loop=128,
        slew_rate_v_per_s=1e9,
        rest_voltage_v=0.0,
        max_preroll_loops=0,
    )
