"""The creep operator of the simulated stage: exact discretisation, log law, loop tilt vs frequency."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.signal import cont2discrete

from hil_sim.creep import (
    CreepBank,
    creep_rest_state,
    creep_step,
    foh_lowpass_coefficients,
    log_spaced_taus,
)
from hil_sim.errors import SimModelError as ModelError
from hil_sim.stage import Stage, StageConfig

X_AXIS = {"alpha_per_v": 3e-3, "b_um_per_v": 0.115, "u_um_per_v": 0.072}


def _stage(pct: float = 1.5, **creep: object) -> Stage:
    cfg = StageConfig.model_validate({"axes": {"x": {**X_AXIS, "creep_pct_per_decade": pct}}, "creep": creep})
    return Stage(cfg)


def test_log_spaced_taus_span_and_density() -> None:
    taus = log_spaced_taus(1e-3, 1e5, 3)
    assert taus.size == 25
    assert taus[0] == pytest.approx(1e-3) and taus[-1] == pytest.approx(1e5)
    np.testing.assert_allclose(np.diff(np.log10(taus)), 1 / 3)
    with pytest.raises(ModelError):
        log_spaced_taus(1.0, 1.0, 3)
    with pytest.raises(ModelError):
        log_spaced_taus(1.0, 10.0, 0)


@pytest.mark.parametrize("h", [1e-3, 0.05, 1.0, 7.0])
def test_foh_coefficients_match_scipy_first_order_hold(h: float) -> None:
    tau, dt = 0.5, 0.5 * h
    a, b0, b1 = foh_lowpass_coefficients(tau, dt)
    num, den, _ = cont2discrete(([1.0], [tau, 1.0]), dt, method="foh")
    np.testing.assert_allclose([b0, b1], np.ravel(num)[:2], rtol=1e-9)
    assert den[1] == pytest.approx(-a, rel=1e-12)


def test_foh_coefficients_stay_accurate_for_tiny_steps() -> None:
    h = np.array([1e-15, 1e-10, 1e-6, 9.9e-3, 1.01e-2])
    a, b0, b1 = foh_lowpass_coefficients(1.0, h)  # type: ignore[arg-type]
    # Exact series: b0 = sum (-1)^(k+1) h^k / (k+1)!, b1 = sum (-1)^(k+1) k h^k / (k+1)!.
    k = np.arange(1, 20)[:, None]
    fact = np.cumprod(np.arange(2, 21, dtype=np.float64))[:, None]  # (k+1)!
    sign = (-1.0) ** (k + 1)
    np.testing.assert_allclose(b0, (sign * h**k / fact).sum(axis=0), rtol=1e-14)
    np.testing.assert_allclose(b1, (sign * k * h**k / fact).sum(axis=0), rtol=1e-13)
    np.testing.assert_allclose(a + b0 + b1, 1.0, rtol=0, atol=1e-15)


def test_bank_is_exact_for_a_step_with_any_sample_intervals() -> None:
    bank = CreepBank.from_law([1.5, 2.0], 1e-3, 1e5, 3)
    state = creep_rest_state(bank, 0.0)
    dt0 = 1e-5
    out, state = creep_step(bank, np.array([[1.0], [2.0]]), dt0, state)  # linear 0 -> D within dt0
    times, values = [dt0], [out[:, 0]]
    t = dt0
    rng = np.random.default_rng(3)
    for dt in np.geomspace(1e-5, 300.0, 40):
        n = int(rng.integers(1, 5))
        out, state = creep_step(bank, np.tile([[1.0], [2.0]], n), float(dt), state)
        t_block = t + dt * np.arange(1, n + 1)
        times += list(t_block)
        values += list(out.T)
        t = float(t_block[-1])
    tt = np.array(times)
    got = np.array(values).T
    # Exact response of tau z' = d - z to d rising linearly to D over dt0, then constant.
    kernel = 1.0 - bank.taus_s[:, None] / dt0 * np.expm1(dt0 / bank.taus_s[:, None]) * np.exp(
        -tt[None, :] / bank.taus_s[:, None]
    )
    expected = (bank.weights @ kernel) * np.array([[1.0], [2.0]])
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-14)


def test_step_creep_is_linear_in_log_time_at_the_configured_rate() -> None:
    """Voltage step on the full stage: creep grows by pct_per_decade of the motion per decade of time."""
    pct = 1.5
    stage = _stage(pct)
    x0 = stage.step(np.array([[200.0]]), 1e-6)[0, 0]  # the fast (hysteretic) response
    probes = np.logspace(-1, 4, 11)
    t, got = 1e-6, []
    for t_next in probes:
        n = 50
        dt = (t_next - t) / n
        got.append(stage.step(np.full((1, n), 200.0), dt)[0, -1])
        t = t_next
    creep = np.array(got) - x0
    slope, intercept = np.polyfit(np.log10(probes), creep, 1)
    assert slope / x0 == pytest.approx(pct / 100, rel=0.01)
    residual = creep - (slope * np.log10(probes) + intercept)
    assert np.abs(residual).max() < 0.01 * (creep[-1] - creep[0])  # log-linear over 5 decades


def test_a_narrow_bank_is_not_log_linear() -> None:
    """The linearity check above can fail: two time constants give a saturating, not logarithmic, creep."""
    stage = _stage(1.5, tau_min_s=1.0, tau_max_s=10.0, per_decade=1)
    x0 = stage.step(np.array([[200.0]]), 1e-6)[0, 0]
    probes = np.logspace(-1, 4, 11)
    t, got = 1e-6, []
    for t_next in probes:
        got.append(stage.step(np.full((1, 50), 200.0), (t_next - t) / 50)[0, -1])
        t = t_next
    creep = np.array(got) - x0
    slope, intercept = np.polyfit(np.log10(probes), creep, 1)
    residual = creep - (slope * np.log10(probes) + intercept)
    assert np.abs(residual).max() > 0.05 * (creep[-1] - creep[0])


def _loop_range(stage: Stage, period_s: float, v_half: float = 200.0, cycles: int = 5) -> float:
    per = 400
    dt = period_s / per
    stage.step(np.linspace(0.0, -v_half, 100)[None, :], dt)
    phase = np.arange(1, cycles * per + 1) / per % 1.0
    v = -v_half + 2 * v_half * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    x = stage.step(v[None, :], dt)[0, -per:]
    return float(x.max() - x.min())


def test_loop_range_grows_with_period_like_the_creep_law() -> None:
    """Thesis chapter 3: slower scans cover more. Per decade of period the range grows ~gamma ln(10)."""
    pct = 1.5
    periods = np.array([0.1, 1.0, 10.0, 100.0])
    ranges = np.array([_loop_range(_stage(pct), p) for p in periods])
    assert np.all(np.diff(ranges) > 0)
    growth = np.diff(ranges) / ranges[:-1]  # per decade of period
    np.testing.assert_allclose(growth, pct / 100, rtol=0.2)
    no_creep = np.array([_loop_range(_stage(0.0), p) for p in periods])
    np.testing.assert_allclose(no_creep, no_creep[0], rtol=1e-9)  # the ODE alone is rate-independent


def test_bank_validation() -> None:
    with pytest.raises(ModelError):
        CreepBank(np.array([1.0, 2.0]), np.array([[0.1]]))
    with pytest.raises(ModelError):
        CreepBank(np.array([1.0, -2.0]), np.array([[0.1, 0.1]]))
    with pytest.raises(ModelError):
        CreepBank(np.array([1.0, 2.0]), np.array([[0.1, -0.1]]))
    bank = CreepBank.from_law([1.0], 1e-3, 1.0, 2)
    with pytest.raises(ModelError):
        creep_step(bank, np.zeros((2, 3)), 1e-3, creep_rest_state(bank, 0.0))
    with pytest.raises(ModelError):
        creep_step(bank, np.zeros((1, 3)), 0.0, creep_rest_state(bank, 0.0))


@given(st.lists(st.integers(1, 400), min_size=1, max_size=6), st.floats(1e-6, 10.0))
def test_bank_blocks_compose(splits: list[int], dt: float) -> None:
    bank = CreepBank.from_law([1.2, 1.8, 0.7], 1e-3, 1e5, 3)
    rng = np.random.default_rng(len(splits))
    d = np.cumsum(rng.normal(0, 1.0, (3, 1000)), axis=1)
    whole, end = creep_step(bank, d, dt, creep_rest_state(bank, 0.0))
    parts, state, i = [], creep_rest_state(bank, 0.0), 0
    for n in [*splits, 1000]:
        if i >= 1000:
            break
        out, state = creep_step(bank, d[:, i : i + n], dt, state)
        parts.append(out)
        i += n
    np.testing.assert_allclose(np.concatenate(parts, axis=1), whole, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.z, end.z, rtol=0, atol=1e-12)


def test_voltage_driven_creep_is_a_fraction_of_b_v_and_linear_in_v() -> None:
    """``creep.drive: voltage``: the creep term is the bank applied to ``b V`` (thesis (3.3): linear in V)."""
    position = _stage(1.5)
    voltage = _stage(1.5, drive="voltage")
    none = _stage(0.0)
    b = X_AXIS["b_um_per_v"]
    v = np.concatenate([np.linspace(0, 200, 50), np.full(2000, 200.0)])
    dt = 1e-3
    x_h = none.step(v[None, :], dt)[0]
    x_v = voltage.step(v[None, :], dt)[0]
    x_p = position.step(v[None, :], dt)[0]
    bank = voltage.model.creep
    creep_v, _ = creep_step(bank, b * v[None, :], dt, creep_rest_state(bank, 0.0))
    creep_p, _ = creep_step(bank, x_h[None, :], dt, creep_rest_state(bank, 0.0))
    np.testing.assert_allclose(x_v - x_h, creep_v[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(x_p - x_h, creep_p[0], rtol=0, atol=1e-12)
    # b V exceeds the virgin-curve position, so the voltage-driven stage creeps more.
    assert (x_v[-1] - x_h[-1]) / (x_p[-1] - x_h[-1]) == pytest.approx(b * 200.0 / x_h[-1], rel=0.02)
