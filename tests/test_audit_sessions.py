"""Session generators for the audit tests, and tests of the generators themselves.

Two kinds of stages hide effects from the audit:

* a *thesis-model stage* (:func:`piezod.audit.synthetic.hidden_session`): every recorded loop
  follows (3.8) exactly, plus effects, sensor offsets, white noise and quantisation (what the
  acceptance checker generates);
* the *simulated stage* (:mod:`hil_sim.session`): the hysteresis ODE with a log creep bank
  (relaxation times 1 ms ... 1e5 s), i.e. memory and a creep law that (3.8) only approximates.

Effect magnitudes come from :func:`hil_sim.effects.random_effect` (realistic ranges, random sign).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest

from hil_sim.effects import random_effect
from hil_sim.session import PlanItem, Triangle, run_session
from hil_sim.stage import StageConfig
from piezod.audit.synthetic import frame_plan, hidden_session
from piezod.config import default_sim_config_path
from piezod.model.thesis import thesis_loop
from piezod.recording import Experiment, Recording, split_experiments
from piezod.synth import random_params

EFFECT_IDS = ("drift", "thermal", "stiffness", "polarity", "resonance", "delay", "saturation", "creep")


def draw_effects(names: Sequence[str], rng: np.random.Generator) -> dict[str, dict[str, Any]]:
    """Random realistic magnitudes (and signs) for the effects ``names``."""
    out: dict[str, dict[str, Any]] = {}
    for name in names:
        fields = random_effect(name, rng).model_dump(exclude_none=True)
        if name == "creep":
            fields["law"] = str(rng.choice(["motion", "k"]))
        out[name] = fields
    return out


def thesis_session(
    effects: Sequence[str],
    seed: int,
    *,
    small: bool = False,
    noise_um: float = 0.005,
) -> tuple[list[Experiment], dict[str, dict[str, Any]]]:
    """A thesis-model session with ``effects`` hidden (random magnitudes); ``small`` for fast tests.

    Full size: 5 ranges x 6 frequencies (0.02-5 Hz) with offsets and 6 references, 2048 samples
    per loop (~36 experiments, ~74k samples). Small: 3 ranges x 3 frequencies (0.1-5 Hz) and
    3 references, 512 samples per loop (12 experiments, ~6k samples).
    """
    rng = np.random.default_rng(seed)
    fx = draw_effects(effects, rng)
    params = random_params(rng)
    if small:
        plan = frame_plan(
            rng,
            ranges_v=(120.0, 260.0, 400.0),
            n_frequencies=3,
            frequency_hz=(0.1, 5.0),
            n_references=3,
        )
        spl = 512
    else:
        plan = frame_plan(rng, n_references=6)
        spl = 2048
    session = hidden_session(params, plan, fx, samples_per_loop=spl, noise_um=noise_um, seed=rng)
    return split_experiments(session.recording), fx


def sim_session(
    effects: Sequence[str],
    seed: int,
    *,
    n_frequencies: int = 6,
    frequency_hz: tuple[float, float] = (0.02, 5.0),
    ranges_v: Sequence[float] = (80.0, 160.0, 240.0, 320.0, 400.0),
    samples_per_loop: int = 2048,
    sample_rate_hz: float = 10240.0,
    noise_nm: float = 5.0,
    lsb_um: float = 0.001,
) -> tuple[list[Experiment], dict[str, dict[str, Any]]]:
    """A session of the simulated stage with ``effects`` hidden: a calibration frame with offsets
    and a repeated reference, simulated at ``sample_rate_hz`` and recorded at ``samples_per_loop``.
    """
    rng = np.random.default_rng(seed)
    specs = [random_effect(name, rng) for name in effects]
    fx = {s.name: s.model_dump(exclude_none=True) for s in specs}
    cfg = StageConfig.from_file(default_sim_config_path()).with_effects(*specs)
    cfg = cfg.model_copy(update={"sensor_noise_nm_rms": noise_nm})
    lo, hi = (math.log(f) for f in frequency_hz)
    step = (hi - lo) / n_frequencies
    freqs = np.exp(lo + step * (np.arange(n_frequencies) + rng.uniform()))
    grid: list[Triangle] = []
    for r in ranges_v:
        for f in freqs:
            offsets = [o for o in (-50.0, 0.0, 50.0) if abs(o) + r / 2 <= 230.0]
            grid.append(Triangle(r, float(f), float(rng.choice(offsets)), cycles=1, settle_cycles=1))
    grid = [grid[i] for i in rng.permutation(len(grid))]
    plan: list[PlanItem] = []
    ref = 0
    for i, item in enumerate(grid):
        if i % 8 == 0:
            ref += 1
            plan.append(Triangle(240.0, 1.0, cycles=1, settle_cycles=1, label=f"reference_{ref:02d}"))
        plan.append(item)
    plan.append(Triangle(240.0, 1.0, cycles=1, settle_cycles=1, label=f"reference_{ref + 1:02d}"))
    res = run_session(cfg, plan, sample_rate_hz=sample_rate_hz, seed=seed, lsb_um=lsb_um)
    ts, vs, xs, labels = [], [], [], []
    for rec, item in zip(res.experiments, plan, strict=True):
        assert isinstance(item, Triangle)
        k = max(1, round(sample_rate_hz / (item.frequency_hz * samples_per_loop)))
        ts.append(rec.t_s[::k])
        vs.append(rec.voltage_v[::k])
        xs.append(rec.position_um[::k])
        labels.append(np.full(rec.t_s[::k].size, rec.label))
    recording = Recording(
        t_s=np.concatenate(ts),
        voltage_v=np.concatenate(vs),
        position_um=np.concatenate(xs),
        experiment=np.concatenate(labels),
    )
    return split_experiments(recording), fx


# ------------------------------------------------------------------------------ tests of the generators


def test_clean_thesis_session_is_the_thesis_loop_plus_offsets_and_noise() -> None:
    rng = np.random.default_rng(3)
    params = random_params(rng)
    plan = frame_plan(rng, ranges_v=(100.0, 300.0), n_frequencies=2, n_references=2)
    s = hidden_session(params, plan, None, samples_per_loop=64, noise_um=0.0, lsb_um=None, seed=4)
    for e, item in zip(split_experiments(s.recording), s.plan, strict=True):
        info = e.require_scan()
        x = thesis_loop(params, e.voltage_v, info.direction, item.v_min, item.v_max, item.frequency_hz)
        d = e.position_um - x
        assert np.ptp(d) < 1e-9  # a constant offset only
        assert abs(float(d[0])) <= 2.0


@pytest.mark.parametrize("effect", EFFECT_IDS)
def test_every_hidden_effect_changes_the_data(effect: str) -> None:
    rng = np.random.default_rng(5)
    params = random_params(rng)
    plan = frame_plan(rng, ranges_v=(100.0, 300.0), n_frequencies=3, n_references=2)
    fx = draw_effects([effect], np.random.default_rng(6))
    kw: dict[str, Any] = {"samples_per_loop": 2048, "noise_um": 0.0, "lsb_um": None}
    clean = hidden_session(params, plan, None, seed=7, **kw).recording.position_um
    hidden = hidden_session(params, plan, fx, seed=7, **kw).recording.position_um
    assert np.max(np.abs(hidden - clean)) > 0.005  # above the 5 nm noise of the tests


def test_sim_session_records_a_frame_with_references() -> None:
    exps, fx = sim_session(
        ["drift"],
        1,
        n_frequencies=2,
        frequency_hz=(1.0, 4.0),
        ranges_v=(100.0, 200.0),
        samples_per_loop=256,
        sample_rate_hz=2048.0,
    )
    labels = [e.label for e in exps]
    assert labels[0] == "reference_01" and labels[-1].startswith("reference_")
    assert len(exps) == 4 + 2
    assert set(fx) == {"drift"}
    assert all(e.scan().is_scan for e in exps)
