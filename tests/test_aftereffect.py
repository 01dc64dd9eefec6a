"""The generalised play law's after-effect: the relaxation of its memory, exact inverse, hold, fit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from family_sessions import loop_experiments, loop_session
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from piezod import calibrate_family as cf
from piezod.config import FamilyModelConfig
from piezod.errors import CalibrationError, ModelError
from piezod.model import kernels
from piezod.model.aftereffect import AfterEffect, relax
from piezod.model.family import (
    CreepSpectrum,
    FamilyParams,
    family_forward,
    family_hold,
    family_inverse,
    family_rest_state,
)
from piezod.model.gplay import GeneralisedPlayParams
from piezod.model.play import PlayState

DT = 1e-4


def _law(plays: int = 12) -> GeneralisedPlayParams:
    rng = np.random.default_rng(3)
    density = np.vstack([np.full((1, 3), 0.4), rng.uniform(0.004, 0.02, (plays, 3))])
    return GeneralisedPlayParams(
        tuple(np.linspace(3.0, 60.0, plays)), (-20.0, 50.0, 120.0), tuple(map(tuple, density))
    )


def _params(g0: float = 2.0, tau_s: float = 5.0, lag_s: float = 50e-6) -> FamilyParams:
    spec = CreepSpectrum.log_spaced(1e-3, 1e3, 2, 0.006)
    return FamilyParams(_law(), spec, lag_s, 0.01, "voltage", 0.0, AfterEffect(g0, tau_s))


@pytest.mark.parametrize("g0", [0.5, 4.0])
def test_the_closed_form_solves_the_eyring_relaxation(g0: float) -> None:
    """``tanh(g / 2 g0)`` decays as ``exp(-t / tau)``: the solution of ``dg/dt = -(g0/tau) sinh(g/g0)``;
    the compiled step is the reference's, and relaxations at a held voltage compose."""
    tau, t_end = 2.0, 7.0
    gaps = np.array([-9.0, -3.0, 0.2, 6.0])
    ode = solve_ivp(
        lambda t, g: -(g0 / tau) * np.sinh(g / g0), (0, t_end), gaps, method="Radau", rtol=1e-10, atol=1e-12
    )
    ae = AfterEffect(g0, tau)
    closed = relax(gaps + 10.0, 10.0, ae.factor(t_end), g0) - 10.0
    np.testing.assert_allclose(closed, ode.y[:, -1], rtol=1e-6, atol=1e-8)
    plays = gaps + 10.0
    kernels._relax_plays(plays, 10.0, ae.factor(3.0), g0)
    kernels._relax_plays(plays, 10.0, ae.factor(4.0), g0)
    np.testing.assert_allclose(plays - 10.0, closed, rtol=1e-12, atol=1e-12)
    linear = relax(gaps, 0.0, ae.factor(t_end), math.inf)
    np.testing.assert_allclose(linear, gaps * math.exp(-t_end / tau))


@pytest.mark.parametrize("g0", [2.0, 1e6])
def test_the_inverse_is_exact_across_blocks_and_relaxations(g0: float) -> None:
    """The compiled walk with the memory relaxing every 10 samples reproduces the voltages that
    drove the forward model, in blocks of any length (the count of samples carries over)."""
    params = _params(g0)
    t = np.arange(60_000) * DT
    v = 50.0 + 60.0 * np.sin(2 * np.pi * 0.7 * t) * np.exp(-t / 3.0)
    rest = family_rest_state(params, 0.0)
    x, end = family_forward(params, v, DT, rest)
    state, out = rest, []
    for block in np.array_split(x, 23):
        u, state = family_inverse(params, block, DT, state)
        out.append(u)
    np.testing.assert_allclose(np.concatenate(out), v, atol=1e-9)
    ae = params.after_effect
    assert ae is not None
    assert state.relax_pending == end.relax_pending == 60_000 % ae.every(DT)
    assert state.position_um == pytest.approx(end.position_um, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    step_v=st.floats(0.01, 8.0),
    g0=st.sampled_from([0.3, 3.0, 1e6]),
    tau_s=st.floats(1e-3, 1e3),
    every_ms=st.sampled_from([0.1, 1.0, 5.0]),
    splits=st.integers(1, 9),
)
def test_random_walks_through_the_relaxing_inverse_are_exact(
    seed: int, step_v: float, g0: float, tau_s: float, every_ms: float, splits: int
) -> None:
    """Random walks (steps up to 8 V a sample, reversals anywhere, relaxations every 1-50 samples,
    gaps from far below to far above ``g0``) through the forward model come back through the
    compiled inverse to 1e-8 V, over blocks split anywhere."""
    spec = CreepSpectrum.log_spaced(1e-3, 1e2, 1, 0.01)
    params = FamilyParams(_law(), spec, 0.0, 0.02, "voltage", 0.0, AfterEffect(g0, tau_s, every_ms * 1e-3))
    rng = np.random.default_rng(seed)
    v = np.clip(40.0 + np.cumsum(rng.normal(0.0, step_v, 3000)), -20.0, 120.0)
    rest = family_rest_state(params, 40.0)
    x, _ = family_forward(params, v, DT, rest)
    state, out = rest, []
    for block in np.array_split(x, splits):
        u, state = family_inverse(params, block, DT, state)
        out.append(u)
    np.testing.assert_allclose(np.concatenate(out), v, atol=1e-8)


def test_a_hold_is_the_forward_model_at_the_held_voltage() -> None:
    """The hold relaxes the memory in one closed-form step: the same state as stepping through."""
    params = _params()
    t = np.arange(20_000) * DT
    _, state = family_forward(params, 40.0 + 50.0 * np.sin(2 * np.pi * t), DT, family_rest_state(params))
    held = family_hold(params, 123_457, DT, state)
    _, stepped = family_forward(params, np.full(123_457, state.voltage_v), DT, state)
    assert held.position_um == pytest.approx(stepped.position_um, abs=1e-9)
    assert held.relax_pending == stepped.relax_pending
    assert isinstance(held.law, PlayState) and isinstance(stepped.law, PlayState)
    np.testing.assert_allclose(held.law.plays_v, stepped.law.plays_v, atol=1e-9)
    # the memory relaxed: the position crept towards the anhysteretic state
    assert abs(held.position_um - state.position_um) > 1e-3


def _loop_width(params: FamilyParams, freq_hz: float) -> float:
    """Widest gap between the rising and falling branch of the third loop at ``freq_hz``."""
    per = round(1.0 / (freq_hz * DT))
    t = np.arange(3 * per) * DT
    v = 50.0 - 50.0 * np.cos(2 * np.pi * freq_hz * t)
    x, _ = family_forward(params, v, DT, family_rest_state(params))
    loop_v, loop_x = v[-per:], x[-per:]
    half = per // 2
    grid = np.linspace(10.0, 90.0, 41)
    up = np.interp(grid, loop_v[:half], loop_x[:half])
    down = np.interp(grid, loop_v[half:][::-1], loop_x[half:][::-1])
    return float(np.max(down - up))


def test_the_after_effect_makes_the_loops_depend_on_the_rate() -> None:
    """With the after-effect a slow loop differs from a fast one (the gaps relax while the voltage
    crawls: the engaged plays' narrow the loop, those left behind by a reversal keep creeping the
    old way and widen it); without it the two are the same loop."""
    no_creep = CreepSpectrum((1.0,), (0.0,))
    with_ae = FamilyParams(_law(), no_creep, 0.0, 0.0, "voltage", 0.0, AfterEffect(6.0, 50.0))
    without = FamilyParams(_law(), no_creep, 0.0, 0.0, "voltage")
    slow, fast = _loop_width(with_ae, 0.05), _loop_width(with_ae, 5.0)
    assert abs(slow - fast) > 0.1 * fast
    assert _loop_width(without, 0.05) == pytest.approx(_loop_width(without, 5.0), rel=1e-3)


def test_the_fit_discretisation_follows_the_runtime_model() -> None:
    """The calibration's play outputs at a session's sparse samples (the voltage moving linearly in
    steps of the interval between them) match the runtime model's at every sample."""
    ae = AfterEffect(1.5, 3.0)
    law = _law()
    t = np.arange(40_000) * DT
    v = 45.0 * np.sin(2 * np.pi * 0.5 * t) + 5.0 * np.sin(2 * np.pi * 3.1 * t)
    full = np.empty((law.r.size, v.size))
    kernels.relax_outputs(v, law.r, np.zeros(law.r.size), 0.0, 0, ae.every(DT), ae.factor(10 * DT), 1.5, full)
    idx = np.arange(4, v.size, 5)
    sparse = np.empty((law.r.size, idx.size))
    kernels.timed_relax_outputs(
        t[idx] + DT, v[idx], law.r, np.zeros(law.r.size), 0.0, 0.0, ae.interval_s, 3.0, 1.5, 256, sparse
    )
    x_full = law.positions(v[idx], full[:, idx])
    x_sparse = law.positions(v[idx], sparse)
    span = float(np.ptp(x_full))
    assert float(np.max(np.abs(x_full - x_sparse))) < 2e-3 * span


def test_the_after_effect_is_written_and_read_back() -> None:
    """The config section carries the after-effect; a half-given one and one on another law or
    with position-driven creep are refused."""
    params = _params()
    section = cf.family_model_config(params)
    assert section.params().after_effect == params.after_effect
    fields = section.model_dump()
    with pytest.raises(ValueError, match="both ae_fluctuation_v and ae_time_s"):
        FamilyModelConfig(**{**fields, "ae_time_s": None})
    with pytest.raises(ValueError, match="voltage-driven creep"):
        FamilyModelConfig(**{**fields, "creep_driver": "position"})
    with pytest.raises(ModelError, match="generalised play or domain-wall law"):
        FamilyParams(_law(), params.creep, creep_driver="position", after_effect=AfterEffect(1.0, 1.0))
    with pytest.raises(ModelError, match="fluctuation_v"):
        AfterEffect(0.0, 1.0)
    with pytest.raises(ModelError, match="time_s"):
        AfterEffect(1.0, math.inf)


def test_the_choice_adopts_the_after_effect_where_the_memory_relaxes() -> None:
    """Self-consistency: on a session of the law with its after-effect the fit finds it (the
    held-out data 5x better than without) and the choice names the member with it."""
    truth = _params(2.0, 20.0, lag_s=0.0)
    data = loop_session(truth)
    train = cf.holdout_mask(data.n_experiments, 3)
    without = cf.fit_family(data, "generalised-play", train=train, creep_driver="voltage", plays=12)
    fitted = cf.fit_family(
        data, "generalised-play", train=train, creep_driver="voltage", plays=12, after_effect=True
    )
    assert fitted.params.after_effect is not None
    assert fitted.heldout_rms_um < 0.2 * without.heldout_rms_um
    choice = cf.choose_model(
        data, laws=("generalised-play",), creep_drivers=("voltage",), holdout_every=3, plays=16
    )
    assert cf.member_after_effect(choice.chosen), choice.table()
    assert choice.fit is not None and choice.fit.params.after_effect is not None
    with pytest.raises(CalibrationError, match="after-effect needs"):
        cf.fit_family(data, "bouc-wen", creep_driver="voltage", after_effect=True)


def test_a_saturated_gap_relaxes_to_a_finite_one_and_no_time_leaves_it() -> None:
    """A gap far beyond ``g0`` (tanh at 1.0 in floating point) relaxes to the finite gap the closed
    form gives; a step too short to change ``exp(-t / tau)`` from 1 leaves every play where it is."""
    plays = np.array([100.0, -100.0, 0.5])
    kernels._relax_plays(plays, 0.0, 1.0, 1.0)
    np.testing.assert_array_equal(plays, [100.0, -100.0, 0.5])
    kernels._relax_plays(plays, 0.0, 1.0 - 1e-7, 1.0)
    assert np.all(np.isfinite(plays))
    # the log law: tanh(g / 2) = 1 - 2 exp(-g) times 1 - eps leaves g = ln(2 / eps)
    assert plays[0] == pytest.approx(2.0 * 0.5 * math.log(2.0 / 1e-7), rel=1e-6)
    np.testing.assert_allclose(relax(np.array([100.0]), 0.0, 1.0 - 1e-7, 1.0), plays[:1])


def test_the_recordings_path_tries_the_after_effect_and_writes_it() -> None:
    """``piezod calibrate FILES`` (the held-out comparison of recordings) tries the after-effect on
    a best generalised play member with voltage creep, names it best when it predicts better, and
    the written refit holds it."""
    from piezod.cli.calibrate import _written
    from piezod.family_heldout import compare_family

    truth = _params(2.0, 20.0, lag_s=0.0)
    exps = loop_experiments(truth)
    family = compare_family(
        exps, laws=("generalised-play",), creep_drivers=("voltage",), plays=12, parts=False, after_effect=True
    )
    best = family.best
    assert best is not None and cf.member_after_effect(best.name), family.table()
    written = _written(exps, best, family.skip_s, refit=True)
    assert best.params is not None and written.after_effect == best.params.after_effect
    plain = compare_family(
        exps, laws=("generalised-play",), creep_drivers=("voltage",), plays=12, parts=False
    )
    assert not any(cf.member_after_effect(m.name) for m in plain.members)
