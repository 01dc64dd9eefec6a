"""The time-domain model: forward, per-sample inverse, state, config and the axis driver."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hil_sim.stage import Stage, StageConfig
from piezod.config import (
    AxisConfig,
    DynamicModelConfig,
    ThesisModelConfig,
    default_sim_config_path,
    dump_config,
    load_config,
)
from piezod.errors import ConfigError, ModelError
from piezod.model.axis_model import DynamicAxisModel
from piezod.model.dynamic import (
    DynamicParams,
    DynamicState,
    creep_element_deviations,
    discretise,
    dynamic_forward,
    dynamic_hold,
    dynamic_inverse,
    dynamic_rest_state,
    foh_coefficients,
)
from piezod.model.ode import hysteresis_inverse_step, hysteresis_step, relaxed_state
from piezod.service.axes import AxisDriver

#: The simulated stage's x axis (configs/sim-stage.yaml) as a dynamic model.
SIM_X = DynamicParams(3.0e-3, 0.115, 0.072, 1.5)
THESIS = ThesisModelConfig(
    alpha_per_v=3.23e-3, b_um_per_v=0.081, u_um_per_v=0.016, tau_s=2.666, a1=0.081, a2_per_v=2.78e-3, a3=0.872
)


def _reference_forward(
    p: DynamicParams, v: np.ndarray, dt: float | np.ndarray, state: DynamicState
) -> np.ndarray:
    """Per-sample loop: the ODE step sample by sample and the creep elements' FOH recursion."""
    z = state.creep_um + state.hysteretic_um
    h = state.hysteresis
    out = np.empty(v.size)
    dts = np.broadcast_to(np.asarray(dt, dtype=np.float64), v.shape)
    for n, vn in enumerate(v):
        a, r, b0 = foh_coefficients(p.taus_s, float(dts[n]))
        b1 = r - b0
        xh, h2 = hysteresis_step(p.hysteresis, np.array([vn]), h)
        z = a * z + b0 * xh[0] + b1 * h.position_um
        h = h2
        out[n] = xh[0] + p.weights @ z
    return out


def _wave(n: int, dt: float, seed: int = 0) -> np.ndarray:
    """A target with a fast scan, a slow drift and reversals of every size."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    slow = np.cumsum(rng.normal(0.0, 0.05, n))
    out: np.ndarray = 12.0 * np.sin(2 * np.pi * 3.0 * t) + 2.0 * np.sin(2 * np.pi * 41.0 * t) + slow
    return out


# --------------------------------------------------------------------------------------- parameters


def test_parameters_are_validated() -> None:
    assert SIM_X.taus_s.size == 25
    assert SIM_X.total_creep == pytest.approx(0.015 * 25 / 3)  # 25 elements, a third of a decade each
    for bad in (
        {"creep_pct_per_decade": -0.1},
        {"creep_pct_per_decade": math.nan},
        {"creep_exponent": 1.5},
        {"creep_tau_min_s": 10.0, "creep_tau_max_s": 1.0},
        {"creep_per_decade": 0},
        {"creep_pct_per_decade": 15.0},  # total creep beyond 0.9
        {"u_um_per_v": -1.0},
    ):
        kw: dict[str, Any] = {
            "alpha_per_v": 3e-3,
            "b_um_per_v": 0.1,
            "u_um_per_v": 0.07,
            "creep_pct_per_decade": 1.0,
            **bad,
        }
        with pytest.raises(ModelError):
            DynamicParams(**kw)


def test_step_response_is_the_log_law_and_its_power_law_tilt() -> None:
    t = np.logspace(-1, 2, 7)
    per_decade = np.diff(100 * SIM_X.step_response(t)) / np.diff(np.log10(t))
    np.testing.assert_allclose(per_decade, 1.5, rtol=2e-3)
    tilted = DynamicParams(3e-3, 0.1, 0.07, 1.5, creep_exponent=0.1)
    per_decade = np.diff(100 * tilted.step_response(t)) / np.diff(np.log10(t))
    mid = np.sqrt(t[1:] * t[:-1])
    np.testing.assert_allclose(per_decade, 1.5 * mid**0.1, rtol=0.01)


# ------------------------------------------------------------------------------------------ forward


def test_forward_equals_a_per_sample_reference_loop() -> None:
    dt = 1e-3
    v = 200.0 * np.sin(np.linspace(0, 9, 1500)) + np.linspace(0, 30, 1500)
    p = DynamicParams(3e-3, 0.115, 0.072, 1.5, creep_exponent=0.05, creep_tau_min_s=1e-4)
    state = dynamic_rest_state(p, 20.0)
    x, _ = dynamic_forward(p, v, dt, state)
    np.testing.assert_allclose(x, _reference_forward(p, v, dt, state), rtol=0, atol=1e-11)


def test_rest_state_stays_put_and_the_creep_follows_a_step() -> None:
    dt = 1e-3
    rest = dynamic_rest_state(SIM_X, 50.0)
    assert rest.position_um == pytest.approx(1.125 * 0.115 * 50.0)
    x, _ = dynamic_forward(SIM_X, np.full(500, 50.0), dt, rest)
    np.testing.assert_allclose(x, rest.position_um, rtol=0, atol=1e-12)
    # a voltage step from rest, then hold: creep of 1.5 % of the hysteretic step per decade
    x, st_ = dynamic_forward(SIM_X, np.full(100_000, 150.0), dt, rest)
    x_h = st_.hysteretic_um
    step = x_h - rest.hysteretic_um
    t = np.arange(1, x.size + 1) * dt
    i1, i10 = np.searchsorted(t, [1.0, 10.0])
    assert (x[i10] - x[i1]) / step == pytest.approx(0.015, rel=2e-3)


def test_hold_is_the_forward_model_at_constant_voltage() -> None:
    dt = 1e-4
    _, state = dynamic_forward(SIM_X, np.linspace(0, 180, 3000), dt, dynamic_rest_state(SIM_X))
    _, by_forward = dynamic_forward(SIM_X, np.full(20_000, 180.0), dt, state)
    held = dynamic_hold(SIM_X, 20_000, dt, state)
    assert held.position_um == pytest.approx(by_forward.position_um, abs=1e-12)
    np.testing.assert_allclose(held.creep_um, by_forward.creep_um, atol=1e-12)
    assert dynamic_hold(SIM_X, 0, dt, state) is state


def test_block_size_and_interval_changes_are_exact() -> None:
    dt = 1e-4
    v = 150.0 * np.sin(np.linspace(0, 30, 20_000))
    x_all, s_all = dynamic_forward(SIM_X, v, dt, dynamic_rest_state(SIM_X))
    rng = np.random.default_rng(3)
    cuts = np.sort(rng.choice(np.arange(1, v.size), 40, replace=False))
    state = dynamic_rest_state(SIM_X)
    parts = []
    for blk in np.split(v, cuts):
        xb, state = dynamic_forward(SIM_X, blk, dt, state)
        parts.append(xb)
    np.testing.assert_allclose(np.concatenate(parts), x_all, rtol=0, atol=1e-11)
    np.testing.assert_allclose(state.creep_um, s_all.creep_um, atol=1e-12)
    # dt may change between blocks
    v2 = v[:600]
    xa, sa = dynamic_forward(SIM_X, v2[:250], dt, state)
    xb, _ = dynamic_forward(SIM_X, v2[250:], 7 * dt, sa)
    ref = _reference_forward(SIM_X, v2, np.where(np.arange(600) < 250, dt, 7 * dt), state)
    np.testing.assert_allclose(np.concatenate([xa, xb]), ref, rtol=0, atol=1e-11)


# ------------------------------------------------------------------------------------------ inverse


def test_inverse_modes_interlace_with_the_element_rates() -> None:
    for dt in (1e-5, 1e-3, 0.1):
        disc = discretise(SIM_X, dt)
        _, r, _ = foh_coefficients(SIM_X.taus_s, dt)
        r = r[~disc.memoryless]
        if disc.memoryless.any():  # elements far faster than dt merge into one of rate 1
            assert dt == 0.1 and r.size < SIM_X.taus_s.size
            r = np.concatenate(([1.0], r))
        rho = disc.rates
        assert np.all(rho > r)
        assert np.all(rho[1:] < r[:-1])  # one mode between consecutive element rates
        assert np.all(np.abs(disc.q) < 1.0)
        # steady state: the modal gains add up to 1/(1 + W0) - 1/(1 + W)
        assert disc.gain.sum() == pytest.approx(disc.gain_sum, rel=1e-12)
    # at 100 kS/s the slowest element has 1 - a = 1e-10: the modes are still resolved
    disc = discretise(SIM_X, 1e-5)
    assert disc.rates.min() > 1e-10


def test_round_trip_over_long_blocks_and_block_boundaries() -> None:
    dt = 1e-5  # 100 kS/s: the slowest element is within 1e-10 of 1
    x = _wave(400_000, dt)
    span = float(np.ptp(x))
    rest = dynamic_rest_state(SIM_X, 10.0)
    rng = np.random.default_rng(5)
    cuts = np.sort(rng.choice(np.arange(1, x.size), 60, replace=False))
    state = rest
    volts = []
    for blk in np.split(x, cuts):
        vb, state = dynamic_inverse(SIM_X, blk, dt, state)
        volts.append(vb)
    v = np.concatenate(volts)
    back, fstate = dynamic_forward(SIM_X, v, dt, rest)
    assert np.max(np.abs(back - x)) <= 1e-9 * span
    assert state.position_um == pytest.approx(float(x[-1]), abs=1e-9 * span)
    np.testing.assert_allclose(state.creep_um, fstate.creep_um, atol=1e-9 * span)
    v_one, _ = dynamic_inverse(SIM_X, x, dt, rest)
    assert np.max(np.abs(v_one - v)) <= 1e-9 * np.ptp(v)


@given(
    seed=st.integers(0, 2**31),
    gamma=st.floats(0.0, 4.0),
    beta=st.floats(-0.2, 0.2),
    log_dt=st.floats(-5.0, -1.0),
    tau_min=st.sampled_from([1e-4, 1e-3, 1e-2]),
    per_decade=st.integers(1, 5),
    n_blocks=st.integers(1, 6),
)
def test_round_trip_property(
    seed: int, gamma: float, beta: float, log_dt: float, tau_min: float, per_decade: int, n_blocks: int
) -> None:
    p = DynamicParams(3e-3, 0.1, 0.065, gamma, beta, tau_min, 1e5, per_decade)
    dt = 10.0**log_dt
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(0.0, 0.5, 1200)) + rng.uniform(-5, 5)
    x[rng.integers(0, x.size, 50)] += rng.normal(0.0, 3.0, 50)  # jumps
    state0 = dynamic_rest_state(p, rng.uniform(-100, 100))
    state = state0
    volts = []
    for blk in np.array_split(x, n_blocks):
        vb, state = dynamic_inverse(p, blk, dt, state)
        volts.append(vb)
    back, _ = dynamic_forward(p, np.concatenate(volts), dt, state0)
    assert np.max(np.abs(back - x)) <= 1e-9 * max(float(np.ptp(x)), 1.0)


def test_pause_keeps_the_position_while_the_voltage_creeps_back() -> None:
    dt = 1e-3
    up = np.linspace(0.0, 30.0, 2000)
    v_up, state = dynamic_inverse(SIM_X, up, dt, dynamic_rest_state(SIM_X))
    n = 300_000  # five minutes
    v_hold, end = dynamic_inverse(SIM_X, np.full(n, 30.0), dt, state)
    x_hold, _ = dynamic_forward(SIM_X, v_hold, dt, state)
    assert np.max(np.abs(x_hold - 30.0)) <= 1e-9 * 30.0
    assert np.all(np.diff(v_hold) <= 1e-12)  # monotone creep back
    assert v_up[-1] - v_hold[-1] > 5.0  # volts, clearly visible
    assert end.position_um == 30.0


def test_a_held_target_keeps_the_voltage_and_nothing_moves_at_rest() -> None:
    rest = dynamic_rest_state(SIM_X, 40.0)
    v, _ = dynamic_inverse(SIM_X, np.full(1000, rest.position_um), 1e-3, rest)
    np.testing.assert_allclose(v, 40.0, atol=1e-9)


def test_zero_creep_is_the_ode_inverse() -> None:
    p = DynamicParams(3e-3, 0.115, 0.072, 0.0)
    x = _wave(5000, 1e-4)
    v, _ = dynamic_inverse(p, x, 1e-4, dynamic_rest_state(p))
    v_ode, _ = hysteresis_inverse_step(p.hysteresis, x, relaxed_state(p.hysteresis))
    np.testing.assert_allclose(v, v_ode, atol=1e-9)


def test_bad_input_is_refused() -> None:
    rest = dynamic_rest_state(SIM_X)
    with pytest.raises(ModelError, match="not finite"):
        dynamic_inverse(SIM_X, np.array([1.0, np.nan]), 1e-3, rest)
    with pytest.raises(ModelError, match="dt_s"):
        dynamic_forward(SIM_X, np.ones(3), 0.0, rest)
    with pytest.raises(ModelError, match="1-D"):
        dynamic_forward(SIM_X, np.ones((2, 3)), 1e-3, rest)
    other = DynamicParams(3e-3, 0.115, 0.072, 1.5, creep_per_decade=2)
    with pytest.raises(ModelError, match="creep elements"):
        dynamic_inverse(other, np.ones(3), 1e-3, rest)
    assert dynamic_inverse(SIM_X, np.empty(0), 1e-3, rest)[1] is rest


def test_element_deviations_are_the_unweighted_creep() -> None:
    dt = 1e-3
    v = np.linspace(0.0, 100.0, 400)
    rest = dynamic_rest_state(SIM_X)
    x, _ = dynamic_forward(SIM_X, v, dt, rest)
    xh, _ = hysteresis_step(SIM_X.hysteresis, v, rest.hysteresis)
    e = creep_element_deviations(SIM_X.taus_s, dt, xh, 0.0, np.zeros(SIM_X.taus_s.size))
    np.testing.assert_allclose((1 + SIM_X.total_creep) * xh + e @ SIM_X.weights, x, atol=1e-12)


# ------------------------------------------------------------------------------------ on the stage


def test_inverse_drives_the_simulated_stage_exactly_through_any_trajectory() -> None:
    """True stage parameters: offset and range changes, a pause, a stepped slow axis."""
    fs = 2000.0
    stage_cfg = StageConfig.from_scanner(load_config(default_sim_config_path()))
    p = SIM_X  # configs/sim-stage.yaml, axis x: the stage's own structure and values
    t = np.arange(int(4 * fs)) / fs
    tri = 2 * np.abs((t * 2.0) % 1.0 - 0.5)
    pieces = [
        np.linspace(0.0, -8.0, 500),
        -8.0 + 10.0 * tri,  # a scan around -3 um
        np.full(int(60 * fs), -8.0),  # a minute's pause
        5.0 + 20.0 * tri,  # offset and range change
        np.repeat(np.arange(5.0, 25.0, 2.0), 400),  # slow-axis staircase
        3.0 + 0.5 * np.sin(2 * np.pi * 17.0 * t),  # a fast small wobble
    ]
    target = np.concatenate(pieces)
    stage = Stage(stage_cfg, axes=("x",))
    state = dynamic_rest_state(p)
    measured = []
    for blk in np.array_split(target, 97):
        v, state = dynamic_inverse(p, blk, 1.0 / fs, state)
        measured.append(stage.step(v, 1.0 / fs))
    err = np.concatenate(measured) - target
    assert np.max(np.abs(err)) <= 1e-6 * np.ptp(target)


# -------------------------------------------------------------------------------------- config, axis


def test_config_section_and_validator(tmp_path: Any) -> None:
    section = DynamicModelConfig(
        alpha_per_v=3e-3, b_um_per_v=0.115, u_um_per_v=0.072, creep_pct_per_decade=1.5
    )
    assert section.params() == SIM_X
    with pytest.raises(ValueError, match="model: dynamic needs a dynamic: section"):
        AxisConfig(voltage_min_v=-1, voltage_max_v=1, model="dynamic", thesis=THESIS)
    with pytest.raises(ValueError, match="total creep"):
        DynamicModelConfig(alpha_per_v=3e-3, b_um_per_v=0.1, u_um_per_v=0.07, creep_pct_per_decade=15.0)
    cfg = load_config(default_sim_config_path())
    ax = cfg.axes["x"].model_copy(update={"model": "dynamic", "dynamic": section})
    out = tmp_path / "c.yaml"
    dump_config(cfg.model_copy(update={"axes": {**cfg.axes, "x": ax}}), out)
    again = load_config(out)
    assert again.axes["x"].model == "dynamic" and again.axes["x"].dynamic == section
    text = out.read_text().replace("creep_pct_per_decade: 1.5", "creep_pct_per_decade: -1")
    out.write_text(text)
    with pytest.raises(ConfigError, match=r"c.yaml:\d+: axes.x.dynamic.creep_pct_per_decade"):
        load_config(out)


def _driver(slew: float = 1e9, fs: float = 1000.0) -> AxisDriver:
    section = DynamicModelConfig(
        alpha_per_v=3e-3, b_um_per_v=0.115, u_um_per_v=0.072, creep_pct_per_decade=1.5
    )
    cfg = AxisConfig(
        voltage_min_v=-230,
        voltage_max_v=230,
        slew_rate_v_per_s=slew,
        model="dynamic",
        thesis=THESIS,
        dynamic=section,
    )
    return AxisDriver("x", cfg, fs)


def test_axis_driver_uses_the_dynamic_inverse_with_carried_state() -> None:
    d = _driver()
    assert d.model == DynamicAxisModel(SIM_X) and d.position_um == 0.0
    targets = _wave(3000, 1e-3)
    assert isinstance(d.state, DynamicState)
    v = np.concatenate([d.corrected(b).voltage_v for b in np.array_split(targets, 7)])
    x, _ = dynamic_forward(SIM_X, v, 1e-3, dynamic_rest_state(SIM_X))
    np.testing.assert_allclose(x, targets, atol=1e-9 * np.ptp(targets))
    assert d.position_um == pytest.approx(targets[-1], abs=1e-9)
    # holding the voltage: the stage creeps on, and the driver knows it
    before = d.position_um
    out = d.hold(5000)
    assert np.all(out.voltage_v == d.voltage_v)
    assert abs(d.position_um - before) > 1e-3
    # a later corrected block starts from the crept state
    v2 = d.corrected(np.full(10, before)).voltage_v
    assert d.position_um == pytest.approx(before, abs=1e-9)
    assert abs(v2[-1] - out.voltage_v[-1]) > 1e-3


def test_axis_driver_limits_and_slew_follow_the_forward_model() -> None:
    d = _driver(slew=1000.0)
    out = d.corrected(np.array([40.0, 40.0, 40.0]))
    assert out.slew_limited > 0
    assert np.all(np.abs(np.diff(out.voltage_v, prepend=0.0)) <= 1.0 + 1e-12)
    x, _ = dynamic_forward(SIM_X, out.voltage_v, 1e-3, dynamic_rest_state(SIM_X))
    assert d.position_um == pytest.approx(float(x[-1]), abs=1e-12)
    d.reset(20.0)
    assert d.voltage_v == 20.0 and d.position_um == pytest.approx(dynamic_rest_state(SIM_X, 20.0).position_um)
    ramp = d.ramp_to(0.0, 200.0, 1000.0)
    assert ramp[-1] == 0.0 and d.voltage_v == 0.0
    # an adopted state (another driver's voltage and position) restarts the creep at rest
    adopted = d.model.adopt(10.0, 1.2)
    assert adopted.position_um == 1.2 and not adopted.creep_um.any()
    assert adopted.hysteretic_um == pytest.approx(1.2 / (1 + SIM_X.total_creep))


# ---------------------------------------------------------------------------------------- benchmark


def test_benchmark_dynamic_inverse_block(benchmark: Any) -> None:
    """pytest-benchmark: 2048-sample blocks at 100 kS/s, 25 creep elements (disabled by default).

    Prints ns per sample next to the ODE inverse alone (same targets, same process). Run with
    ``python -m pytest tests/test_dynamic_model.py -k benchmark -s --benchmark-enable``.
    """
    dt = 1e-5
    t = np.arange(2048 * 40) * dt
    x = 30.0 * np.abs((t * 10.0) % 1.0 - 0.5)  # 10 lines/s over 15 um, as the engine streams it
    blocks = np.split(x, 40)
    state0 = dynamic_rest_state(SIM_X)
    dynamic_inverse(SIM_X, blocks[0], dt, state0)  # tables for this block length

    def run_dynamic() -> None:
        s = state0
        for b in blocks:
            _, s = dynamic_inverse(SIM_X, b, dt, s)

    def run_ode() -> None:
        s = relaxed_state(SIM_X.hysteresis)
        for b in blocks:
            _, s = hysteresis_inverse_step(SIM_X.hysteresis, b / 1.12, s)

    best = {}
    for name, fn in (("dynamic", run_dynamic), ("ode", run_ode)):
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        best[name] = min(times) / x.size * 1e9
    print(
        f"\ndynamic inverse {best['dynamic']:.0f} ns/sample, ODE inverse alone {best['ode']:.0f} ns/sample "
        f"(ratio {best['dynamic'] / best['ode']:.2f}), {SIM_X.taus_s.size} creep elements"
    )
    v, _ = benchmark(dynamic_inverse, SIM_X, blocks[0], dt, state0)
    assert v.size == blocks[0].size


def test_a_dynamic_driver_adopts_the_state_of_the_one_it_replaces() -> None:
    old = _driver()
    old.corrected(np.linspace(0.0, 20.0, 800))
    old.hold(300)
    new = _driver()
    new.adopt_state(old)
    assert new.voltage_v == old.voltage_v
    assert new.position_um == pytest.approx(old.position_um, abs=1e-12)  # the stage is where it was
    thesis = AxisDriver("x", AxisConfig(voltage_min_v=-230, voltage_max_v=230, thesis=THESIS), 1000.0)
    thesis.corrected(np.linspace(0.0, 5.0, 300))
    new.adopt_state(thesis)
    assert new.voltage_v == thesis.voltage_v
    state = new.state
    assert isinstance(state, DynamicState) and not state.creep_um.any()  # creep restarts relaxed
    assert new.position_um == pytest.approx(thesis.position_um, abs=1e-12)
    v = new.corrected(np.full(5, new.position_um)).voltage_v
    np.testing.assert_allclose(v, thesis.voltage_v, atol=1e-9)  # nothing moves at the adopted point
