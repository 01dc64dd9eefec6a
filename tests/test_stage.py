"""The simulated stage: configuration, physics order of magnitude, effect signatures, blocks, seeds, speed."""

from __future__ import annotations

import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from hil_sim.effects import (
    EFFECT_NAMES,
    ResonanceEffect,
    effect_spec,
    parse_effect_spec,
    random_effect,
    resonance_rest_state,
    resonance_step,
)
from hil_sim.errors import SimConfigError as ConfigError
from hil_sim.errors import SimModelError as ModelError
from hil_sim.hysteresis import CHParams, ch_rest_state, ch_step
from hil_sim.stage import Stage, StageConfig, sensor
from piezod.config import ScannerConfig, default_sim_config_path, load_config
from piezod.model.ode import hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams

SIM = default_sim_config_path()


@pytest.fixture(scope="module")
def base() -> StageConfig:
    """The default simulated stage, effects off, no sensor noise."""
    return StageConfig.from_file(SIM).model_copy(update={"sensor_noise_nm_rms": 0.0})


def _triangle(v_half: float, period_s: float, per: int, cycles: int, offset: float = 0.0) -> np.ndarray:
    phase = np.arange(1, cycles * per + 1) / per % 1.0
    out: np.ndarray = offset - v_half + 2 * v_half * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    return out


def _loop(
    cfg: StageConfig, v_half: float = 200.0, offset: float = 0.0, period_s: float = 1.0, per: int = 400
) -> tuple[np.ndarray, np.ndarray]:
    """Last of 4 loops of a triangular scan (after a ramp from rest to the lower turning point)."""
    stage = Stage(cfg, axes=("x",))
    dt = period_s / per
    stage.step(np.linspace(0.0, offset - v_half, 200), dt)
    v = _triangle(v_half, period_s, per, 4, offset)
    x = stage.step(v, dt)
    return v[-per:], x[-per:]


def _branches_at(v: np.ndarray, x: np.ndarray, v0: float) -> tuple[float, float]:
    up = np.diff(v, prepend=v[0] - 1.0) > 0
    o = np.argsort(v[up])
    x_up = float(np.interp(v0, v[up][o], x[up][o]))
    o = np.argsort(v[~up])
    x_down = float(np.interp(v0, v[~up][o], x[~up][o]))
    return x_up, x_down


# ------------------------------------------------------------------------------------------ config


def test_default_config_loads_with_the_host_and_the_simulator() -> None:
    scanner = load_config(SIM)
    assert set(scanner.axes) == {"x", "y", "z"}
    for ax in scanner.axes.values():
        assert (ax.voltage_min_v, ax.voltage_max_v, ax.safe_voltage_v) == (-230.0, 230.0, 0.0)
    stage = StageConfig.from_scanner(scanner)
    assert stage == StageConfig.from_file(SIM)
    assert stage.effects.enabled() == []
    assert stage.sensor_noise_nm_rms > 0
    # The host's model is an uncalibrated guess, not the truth.
    assert scanner.axes["x"].thesis.u_um_per_v != stage.axes["x"].u_um_per_v


def test_default_stage_is_a_medium_tube_with_monotone_branches(base: StageConfig) -> None:
    v, x = _loop(base, v_half=230.0, period_s=1.0)
    span = x.max() - x.min()
    assert 35.0 < span < 40.0  # ~37 um over 460 V p-p at 1 Hz
    assert 0.075 < span / 460.0 < 0.1
    x_up, x_down = _branches_at(v, x, 0.0)
    assert 0.10 < abs(x_down - x_up) / span < 0.20  # hysteresis width
    up = np.diff(v) > 0
    dx = np.diff(x)
    assert np.all(dx[up] > 0) and np.all(dx[~up] < 0)  # u > b/2: no backwards start after reversals
    for axis in base.axes.values():
        assert axis.b_um_per_v / 2 < axis.u_um_per_v < axis.b_um_per_v
        assert 2e-3 < axis.alpha_per_v < 4e-3


def _scanner_dict() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load(SIM.read_text())
    return data


@pytest.mark.parametrize(
    ("path", "value", "expected"),
    [
        (("axes", "x", "u_um_per_v"), 0.05, "simulation.axes.x: Value error, u_um_per_v (0.05) must exceed"),
        (("axes", "y", "b_um_per_v"), -1.0, "simulation.axes.y.b_um_per_v: Input should be greater than 0"),
        (("creep", "foo"), 1, "simulation.creep.foo: unknown key"),
        (("creep", "tau_max_s"), 1e-4, "simulation.creep: Value error, tau_max_s"),
        (("sensor_noise_nm_rms",), -1.0, "simulation.sensor_noise_nm_rms: Input should be greater"),
        (("effects", "resonance"), {"f0_hz": 800, "q": 0.1}, "simulation.effects.resonance.q:"),
        (("effects", "drift"), {"rate_nm_per_s": 1, "rate": 1}, "simulation.effects.drift.rate: unknown key"),
        (("effects", "wobble"), {"x": 1}, "simulation.effects.wobble: unknown key"),
        (("axes", "z", "creep_pct_per_decade"), float("nan"), "simulation.axes.z.creep_pct_per_decade"),
    ],
)
def test_config_errors_name_the_field(path: tuple[str, ...], value: object, expected: str) -> None:
    data = _scanner_dict()
    node = data["simulation"]
    for key in path[:-1]:
        node = node.setdefault(key, {})
    node[path[-1]] = value
    with pytest.raises(ConfigError) as info:
        StageConfig.from_scanner(ScannerConfig.model_validate(data))
    assert str(info.value).startswith(expected), str(info.value)


def test_config_errors_for_missing_parts() -> None:
    data = _scanner_dict()
    del data["simulation"]["axes"]["z"]
    with pytest.raises(ConfigError, match=r"^simulation.axes: missing axis 'z'"):
        StageConfig.from_scanner(ScannerConfig.model_validate(data))
    data = _scanner_dict()
    del data["simulation"]
    with pytest.raises(ConfigError, match=r"simulation: missing"):
        StageConfig.from_scanner(ScannerConfig.model_validate(data))


def test_config_file_errors_name_file_line_and_field(tmp_path: Path) -> None:
    text = SIM.read_text().replace("u_um_per_v: 0.070", "u_um_per_v: 0.030")
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    line = 1 + next(i for i, s in enumerate(text.splitlines()) if "u_um_per_v: 0.030" in s)
    with pytest.raises(ConfigError, match=rf"^{bad}:{line}: simulation.axes.y: "):
        StageConfig.from_file(bad)


def test_effect_strings_set_and_combine(base: StageConfig) -> None:
    cfg = base.with_effects("drift=0.4", "resonance=800", "resonance.q=25", "delay.at=drive", "delay=1e-4")
    assert cfg.effects.drift is not None and cfg.effects.drift.rate_nm_per_s == 0.4
    assert cfg.effects.resonance is not None and (cfg.effects.resonance.f0_hz, cfg.effects.resonance.q) == (
        800.0,
        25.0,
    )
    assert cfg.effects.delay is not None and cfg.effects.delay.at == "drive"
    assert cfg.with_effects("resonance.q=5").effects.resonance.q == 5.0  # type: ignore[union-attr]
    assert cfg.effects.enabled() == ["drift", "resonance", "delay"]
    assert cfg.without_effects().effects.enabled() == []
    creep = base.with_effects("creep=3.5", "creep.drive=voltage")
    assert {a.creep_pct_per_decade for a in creep.axes.values()} == {3.5}
    assert creep.creep.drive == "voltage"
    assert parse_effect_spec("saturation=80") == ("saturation", "x_sat_um", "80")


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("drift", "expected NAME=VALUE"),
        ("wobble=1", "unknown effect 'wobble'"),
        ("resonance.qq=3", "resonance has no field 'qq'"),
        ("drift=fast", "effect 'drift=fast': rate_nm_per_s: Input should be a valid number"),
        ("resonance.q=30", "f0_hz: Field required"),
        ("saturation=-1", "x_sat_um: Input should be greater than 0"),
        ("delay.at=nowhere", "delay.at=nowhere"),
        ("delay.at=drive", "delay needs delay_s > 0 or lag_time_constant_s > 0"),
        ("thermal=nan", "rate_pct_per_hour"),
    ],
)
def test_effect_string_errors_name_the_string(base: StageConfig, spec: str, expected: str) -> None:
    with pytest.raises(ConfigError, match=expected):
        base.with_effects(spec)


@pytest.mark.parametrize("name", [*EFFECT_NAMES, "creep"])
def test_random_effects_are_valid_deterministic_and_applicable(base: StageConfig, name: str) -> None:
    draws = [random_effect(name, np.random.default_rng(s)) for s in range(12)]
    assert random_effect(name, np.random.default_rng(3)) == draws[3]
    assert len({d.model_dump_json() for d in draws}) == 12
    cfg = base.with_effects(draws[0])
    if name == "creep":
        assert cfg.axes["x"].creep_pct_per_decade == draws[0].model_dump()["pct_per_decade"]
    else:
        assert cfg.effects.enabled() == [name]
        assert base.with_effects(*effect_spec(draws[0])) == cfg
    signed = {
        "drift": "rate_nm_per_s",
        "thermal": "rate_pct_per_hour",
        "stiffness": "sensitivity_pct_per_um",
        "polarity": "negative_sensitivity_pct",
    }
    if name in signed:
        values = [getattr(d, signed[name]) for d in draws]
        assert min(values) < 0 < max(values)
    with pytest.raises(ConfigError):
        random_effect("none", np.random.default_rng(0))


# ----------------------------------------------------------------------------------------- effects


def test_drift_is_linear_in_time(base: StageConfig) -> None:
    cfg = base.with_effects("drift=0.4")
    v = _triangle(150.0, 2.0, 200, 5)
    x = Stage(cfg, axes=("x",)).step(v, 0.01)
    x0 = Stage(base, axes=("x",)).step(v, 0.01)
    t = 0.01 * np.arange(1, v.size + 1)
    np.testing.assert_allclose(x - x0, 0.4e-3 * t, rtol=0, atol=1e-12)
    held = Stage(cfg, axes=("x",)).step(np.zeros(1000), 0.1)
    np.testing.assert_allclose(held, 0.4e-3 * 0.1 * np.arange(1, 1001), rtol=1e-12)


def _thermal_ratio(cfg: StageConfig, base: StageConfig, hold_s: float) -> float:
    def last_loop_span(c: StageConfig) -> float:
        stage = Stage(c, axes=("x",))
        stage.step(_triangle(200.0, 1.0, 100, 3), 0.01)
        stage.step(np.full(int(hold_s), -200.0), 1.0)
        x = stage.step(_triangle(200.0, 1.0, 100, 3), 0.01)[-100:]
        return float(x.max() - x.min())

    return last_loop_span(cfg) / last_loop_span(base)


def test_thermal_changes_sensitivity_by_the_configured_amount(base: StageConfig) -> None:
    ratio = _thermal_ratio(base.with_effects("thermal=1.5"), base, 3600.0)
    assert ratio - 1.0 == pytest.approx(0.015 * (3600 + 6) / 3600, rel=1e-3)
    ratio = _thermal_ratio(base.with_effects("thermal=-2", "thermal.time_constant_s=1800"), base, 3600.0)
    t = 3606.0
    assert ratio - 1.0 == pytest.approx(-0.02 * 1800 * (1 - np.exp(-t / 1800)) / 3600, rel=1e-3)


def test_stiffness_makes_the_sensitivity_depend_on_the_offset(base: StageConfig) -> None:
    kappa = 0.08  # %/um
    cfg = base.with_effects(f"stiffness={kappa}")
    gains, centres = [], []
    for offset in (-150.0, -50.0, 50.0, 150.0):
        _, x = _loop(cfg, v_half=50.0, offset=offset)
        _, x0 = _loop(base, v_half=50.0, offset=offset)
        gains.append((x.max() - x.min()) / (x0.max() - x0.min()) - 1.0)
        centres.append(0.5 * (x0.max() + x0.min()))
    slope, intercept = np.polyfit(centres, gains, 1)
    assert slope == pytest.approx(kappa / 100, rel=1e-6)  # length error linear in the offset
    assert abs(intercept) < 1e-6


def test_polarity_makes_the_two_voltage_polarities_differ(base: StageConfig) -> None:
    def asymmetry(c: StageConfig) -> float:
        v, x = _loop(c, v_half=200.0)
        x_up, x_down = _branches_at(v, x, 0.0)
        mid = 0.5 * (x_up + x_down)
        return float((mid - x.min()) / (x.max() - mid) - 1.0)

    assert abs(asymmetry(base)) < 1e-3
    for pct in (-8.0, 5.0):
        assert asymmetry(base.with_effects(f"polarity={pct}")) == pytest.approx(pct / 100, rel=0.05)


def _ring(cfg: StageConfig, base: StageConfig, fs: float, duration_s: float) -> np.ndarray:
    v = np.full(int(duration_s * fs), 50.0)
    ring: np.ndarray = Stage(cfg, axes=("x",)).step(v, 1 / fs) - Stage(base, axes=("x",)).step(v, 1 / fs)
    return ring


def test_resonance_rings_at_f0_with_the_configured_q(base: StageConfig) -> None:
    f0, q, fs = 800.0, 15.0, 200_000.0
    ring = _ring(base.with_effects(f"resonance={f0}", f"resonance.q={q}"), base, fs, 0.03)
    t = np.arange(1, ring.size + 1) / fs
    sign = np.signbit(ring[10:])
    crossings = np.flatnonzero(sign[1:] != sign[:-1]) + 10
    # Linear interpolation of the zero crossings.
    tc = t[crossings] - ring[crossings] * (t[crossings + 1] - t[crossings]) / (
        ring[crossings + 1] - ring[crossings]
    )
    f_d = 0.5 / np.mean(np.diff(tc))
    assert f_d == pytest.approx(f0 * np.sqrt(1 - 1 / (4 * q * q)), rel=1e-3)
    peaks = np.array([np.abs(ring[a:b]).max() for a, b in itertools.pairwise(crossings)])
    delta = 2 * np.mean(np.log(peaks[:-1] / peaks[1:]))  # log decrement per period
    assert np.sqrt(4 * np.pi**2 + delta**2) / (2 * delta) == pytest.approx(q, rel=0.01)
    assert np.abs(ring).max() > 0.5 * 50.0 * 0.115  # a real overshoot, not numerical noise


def test_resonance_is_exact_for_changing_sample_intervals() -> None:
    from scipy.signal import lsim

    effect = ResonanceEffect(f0_hz=1000.0, q=8.0)
    dt = 1e-5
    u = np.sin(np.arange(1500) * 0.02)[None, :]
    a, state = resonance_step(effect, u[:, :1000], dt, resonance_rest_state([0.0]))
    b, _ = resonance_step(effect, u[:, 1000:], 2 * dt, state)
    t_coarse = np.concatenate([[0.0], np.arange(1, 1001) * dt, 1000 * dt + np.arange(1, 501) * 2 * dt])
    fine = np.arange(0, 8001) * dt / 4
    w0 = 2 * np.pi * 1000.0
    _, y, _ = lsim(([w0**2], [1, w0 / 8, w0**2]), np.interp(fine, t_coarse, np.r_[0.0, u[0]]), fine)
    idx = np.round(t_coarse[1:] / (dt / 4)).astype(int)
    np.testing.assert_allclose(np.concatenate([a[0], b[0]]), y[idx], atol=1e-9)


def test_a_resonance_faster_than_the_sample_rate_is_stepped_exactly(base: StageConfig) -> None:
    """Steps longer than a quarter period are sub-stepped (an idle hold of the board is one ~0.1 s
    step); until session 7 they were refused. Exactness: tests/test_stage_physics.py."""
    x = Stage(base.with_effects("resonance=2000"), axes=("x",)).step(np.zeros(10), 1e-3)
    np.testing.assert_allclose(x, 0.0, atol=1e-12)


def test_sensor_delay_shifts_by_the_delay(base: StageConfig) -> None:
    dt = 1e-3
    v = _triangle(200.0, 0.5, 500, 3)
    x0 = Stage(base, axes=("x",)).step(v, dt)
    x = Stage(base.with_effects(f"delay={5 * dt}"), axes=("x",)).step(v, dt)
    np.testing.assert_allclose(x[5:], x0[:-5], rtol=0, atol=1e-12)
    np.testing.assert_allclose(x[:5], 0.0, atol=1e-12)
    x = Stage(base.with_effects(f"delay={2.5 * dt}"), axes=("x",)).step(v, dt)
    np.testing.assert_allclose(x[3:], 0.5 * (x0[1:-2] + x0[:-3]), rtol=0, atol=1e-9)


def test_drive_delay_delays_the_voltage(base: StageConfig) -> None:
    dt = 1e-3
    v = _triangle(200.0, 0.5, 500, 2)
    x = Stage(base.with_effects("delay.at=drive", f"delay={3 * dt}"), axes=("x",)).step(v, dt)
    x0 = Stage(base, axes=("x",)).step(np.r_[0.0, 0.0, 0.0, v[:-3]], dt)
    np.testing.assert_allclose(x, x0, rtol=0, atol=1e-9)


def test_first_order_lag_delays_a_ramp_by_its_time_constant(base: StageConfig) -> None:
    tau, dt = 2e-3, 1e-4
    v = np.linspace(0.0, 200.0, 4000)[1:]
    x0 = Stage(base, axes=("x",)).step(v, dt)
    x = Stage(base.with_effects("delay.lag_time_constant_s=0.002"), axes=("x",)).step(v, dt)
    t = dt * np.arange(1, v.size + 1)
    late = t > 20 * tau
    shifted = np.interp(t[late] - tau, t, x0)
    assert np.abs(x[late] - shifted).max() < 1e-3 * np.abs(x0[late] - shifted).max()


def test_saturation_compresses_large_excursions(base: StageConfig) -> None:
    v = _triangle(230.0, 1.0, 400, 3)
    x0 = Stage(base, axes=("x",)).step(v, 1 / 400)
    x = Stage(base.with_effects("saturation=60"), axes=("x",)).step(v, 1 / 400)
    np.testing.assert_allclose(x, 60.0 * np.tanh(x0 / 60.0), rtol=1e-12)
    compression = 1.0 - (x.max() - x.min()) / (x0.max() - x0.min())
    assert compression == pytest.approx((x0.max() / 60.0) ** 2 / 3, rel=0.1)
    small = np.abs(x0) < 1.0
    np.testing.assert_allclose(x[small], x0[small], atol=1e-3)


# --------------------------------------------------------------------------- blocks, seeds, shapes


def _everything(base: StageConfig, at: str) -> StageConfig:
    return base.with_effects(
        "drift=0.7",
        "thermal=2",
        "stiffness=0.05",
        "polarity=-6",
        "resonance=900",
        "resonance.q=12",
        f"delay.at={at}",
        "delay=1.7e-4",
        "delay.lag_time_constant_s=3e-4",
        "saturation=90",
    )


@pytest.mark.parametrize("at", ["sensor", "drive"])
def test_one_block_equals_many_small_blocks(base: StageConfig, at: str) -> None:
    cfg = _everything(base, at)
    rng = np.random.default_rng(11)
    n, dt = 6000, 5e-5
    v = np.clip(np.cumsum(rng.normal(0, 4.0, (3, n)), axis=1), -230, 230)
    whole = Stage(cfg).step(v, dt)
    stage = Stage(cfg)
    cuts = np.unique(np.r_[0, rng.integers(1, n, 25), 1, 2, n])
    parts = [stage.step(v[:, a:b], dt) for a, b in itertools.pairwise(cuts)]
    np.testing.assert_allclose(np.concatenate(parts, axis=1), whole, rtol=0, atol=1e-9)
    assert stage.time_s == pytest.approx(n * dt)


def test_noise_is_deterministic_given_a_seed_and_snapshots_restore(base: StageConfig) -> None:
    cfg = base.model_copy(update={"sensor_noise_nm_rms": 3.0})
    v = np.tile(_triangle(100.0, 0.1, 200, 2), (3, 1))
    a, b, c = Stage(cfg, seed=5), Stage(cfg, seed=5), Stage(cfg, seed=6)
    ra, rb, rc = (s.sense(s.step(v, 5e-4)) for s in (a, b, c))
    np.testing.assert_array_equal(ra, rb)
    assert np.abs(ra - rc).max() > 0
    noise = ra - Stage(cfg).step(v, 5e-4)
    assert np.std(noise) == pytest.approx(3e-3, rel=0.05)
    snap = a.snapshot()
    first = a.sense(a.step(v, 5e-4))
    a.restore(snap)
    np.testing.assert_array_equal(a.sense(a.step(v, 5e-4)), first)
    a.reset()
    np.testing.assert_array_equal(a.sense(a.step(v, 5e-4)), ra)


def test_sensor_helper_adds_noise_and_quantises() -> None:
    x = np.linspace(-10, 10, 20001)
    y = sensor(x, np.random.default_rng(0), 5.0, lsb_um=0.01)
    assert np.allclose(y / 0.01, np.round(y / 0.01))
    assert np.std(y - x) == pytest.approx(np.sqrt(5e-3**2 + 0.01**2 / 12), rel=0.05)
    np.testing.assert_array_equal(sensor(x, np.random.default_rng(0), 0.0), x)
    with pytest.raises(ModelError):
        sensor(x, np.random.default_rng(0), -1.0)


def test_rest_voltage_shapes_and_bad_input(base: StageConfig) -> None:
    stage = Stage(base, rest_voltage_v=[10.0, 0.0, -10.0])
    out = stage.step({"x": [10.0, 10.0], "y": [0.0, 0.0], "z": [-10.0, -10.0]}, 1e-3)
    assert out.shape == (3, 2)
    assert out[0, 0] == pytest.approx(out[0, 1]) and out[0, 0] > 0 > out[2, 0]  # at rest: no motion
    one = Stage(base, axes=("y",))
    assert one.step(np.zeros(4), 1e-3).shape == (4,)
    with pytest.raises(ModelError):
        stage.step(np.zeros(4), 1e-3)
    with pytest.raises(ModelError):
        stage.step(np.zeros((3, 4)), 0.0)
    with pytest.raises(ModelError):
        stage.step(np.full((3, 4), np.nan), 1e-3)
    with pytest.raises(ModelError):
        stage.step({"x": [0.0]}, 1e-3)
    with pytest.raises(ConfigError):
        Stage(base, axes=("q",))  # type: ignore[arg-type]
    assert stage.step(np.zeros((3, 0)), 1e-3).shape == (3, 0)


# ------------------------------------------------------------------------------------------- speed


def _best_of(fn: Any, repeats: int = 3) -> float:
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return float(best)


def test_benchmark_stage_step(benchmark: Any, base: StageConfig) -> None:
    """3 channels x 100 kS/s: ns per sample and channel, default stage and all effects, vs the plain ODE."""
    fs, n = 100_000.0, 100_000
    v = np.tile(_triangle(200.0, 0.01, 1000, n // 1000), (3, 1))
    default = Stage(base)
    benchmark(default.step, v, 1 / fs)
    params = [default.model.hysteresis[i] for i in range(3)]
    assert all(isinstance(p, CHParams) for p in params)

    def ode() -> None:
        for p, row in zip(params, v, strict=True):
            assert isinstance(p, CHParams)
            ch_step(p, row, ch_rest_state(p))

    t_ode = _best_of(ode)
    t_default = _best_of(lambda: default.step(v, 1 / fs))
    everything = Stage(_everything(base, "sensor"))
    t_all = _best_of(lambda: everything.step(v, 1 / fs))
    per = 1e9 / (3 * n)
    print(
        f"\nstage step, 3 ch x {n} samples: plain ODE {t_ode * per:.1f} ns/sample/ch; "
        f"default stage {t_default * per:.1f} ns/sample/ch ({t_default / t_ode:.1f}x ODE); "
        f"all effects {t_all * per:.1f} ns/sample/ch ({t_all / t_ode:.1f}x ODE); "
        f"real-time load at 3 x 100 kS/s: {t_default:.3f} / {t_all:.3f} core-seconds per second"
    )


def test_sim_coleman_hodgdon_step_matches_the_hosts_ode() -> None:
    """hil_sim carries its own copy of the ODE (it must not import piezod): both agree to rounding."""
    rng = np.random.default_rng(5)
    v = np.cumsum(rng.normal(0.0, 3.0, 4000))
    sim = CHParams(3.0e-3, 0.115, 0.072)
    host = HysteresisParams(3.0e-3, 0.115, 0.072)
    x_sim, s_sim = ch_step(sim, v, ch_rest_state(sim, 1.0))
    x_host, s_host = hysteresis_step(host, v, relaxed_state(host, 1.0))
    np.testing.assert_allclose(x_sim, x_host, rtol=0, atol=1e-12)
    assert s_sim.position_um == pytest.approx(s_host.position_um, abs=1e-12)
