"""The sensor path (piezod.model.sensor): a readback delay is undone in the analysis, not the drive."""

from __future__ import annotations

import numpy as np
import pytest

from piezod.config import AxisConfig, ThesisModelConfig
from piezod.errors import ModelError
from piezod.extensions import adopt_findings, experiments_through_sensor
from piezod.model.sensor import SensorPath
from piezod.recording import Experiment
from piezod.service.axes import axis_model

THESIS = ThesisModelConfig(
    alpha_per_v=3e-3, b_um_per_v=0.09, u_um_per_v=0.05, tau_s=2.666, a1=0.081, a2_per_v=0.0, a3=0.6
)
D, TAU = 3.2e-4, 3.2e-4


def _stage_pair(noise: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The built-in stage with hil_sim's sensor delay and without it, driven alike: times, readback,
    position (with the sensor noise or without)."""
    from piezod.config import default_sim_config_path, load_config
    from piezod.effects_bench import StageBench, _stage

    path = default_sim_config_path()
    rate = load_config(path).sample_rate_hz
    specs = [f"delay.delay_s={D}", f"delay.lag_time_constant_s={TAU}"]
    bench = StageBench(_stage(path, specs, "x", 1), rate, truth=_stage(path, [], "x", 1))
    n = round(rate / 2.0)
    phase = (np.arange(1, 2 * n + 1) % n) / n
    tri = -200.0 + 400.0 * np.minimum(2 * phase, 2 - 2 * phase)
    volts = np.concatenate([np.linspace(0.0, -200.0, 4000), tri])
    if not noise:
        t = np.arange(1, volts.size + 1) / rate
        return t, bench.stage.step(volts, 1.0 / rate), bench.truth.step(volts, 1.0 / rate)
    t, y = bench.play(volts)
    assert bench.last_truth is not None
    return t, y, bench.last_truth


def test_align_recovers_where_the_simulated_stage_is() -> None:
    """hil_sim's own sensor lag + delay (its implementation, not piezod's): aligned, the readback is
    the position to < 20 % of the raw error at the turning points (the derivative's window), < 1 nm RMS."""
    t, y, x = _stage_pair(noise=False)
    raw = np.max(np.abs(y - x))
    assert raw > 0.1  # 120 nm at 320 um/s: what the delay does to the readback
    tk, xa = SensorPath(D, TAU).align(t, y)
    assert tk.size == t.size - int(np.ceil(D * 20000.0 - 1e-6))
    err = xa - x[: tk.size]
    assert np.max(np.abs(err)) < 0.2 * raw  # at the turning points only
    assert np.sqrt(np.mean(err**2)) < 1e-3


def test_align_does_not_amplify_the_sensor_noise() -> None:
    t, y, x = _stage_pair(noise=True)
    noise = np.std(y - np.interp(t - D - TAU, t, x))
    tk, xa = SensorPath(D, TAU).align(t, y)
    assert np.sqrt(np.mean((xa - x[: tk.size]) ** 2)) < 1.2 * noise


@pytest.mark.parametrize(
    ("delay_samples", "lag_samples", "expected"),
    [
        (0.0, 0.0, 1.0),
        (0.5, 0.0, 0.5**0.5),
        (2.5, 0.0, 0.5**0.5),
        (2.0, 0.0, 1.0),
        (1.2, 1.2, None),
        (0.0, 4.0, None),
    ],
)
def test_noise_gain_is_what_aligning_does_to_white_noise(
    delay_samples: float, lag_samples: float, expected: float | None
) -> None:
    dt = 2.5e-4
    path = SensorPath(delay_samples * dt, lag_samples * dt)
    y = np.random.default_rng(5).normal(0.0, 1.0, 200_000)
    _, x = path.align(np.arange(y.size) * dt, y)
    gain = path.noise_gain(dt)
    assert gain == pytest.approx(float(np.std(x[1000:-1000])), rel=0.01)
    if expected is not None:
        assert gain == pytest.approx(expected, rel=1e-9)


def test_the_sensor_path_is_in_the_yaml_but_not_in_the_drive() -> None:
    base = {"voltage_min_v": -230.0, "voltage_max_v": 230.0, "thesis": THESIS, "model": "thesis"}
    ax = AxisConfig(**base, extensions={"delay": {"delay_s": D, "lag_time_constant_s": TAU}})
    assert ax.sensor_path() == SensorPath(D, TAU)
    assert ax.parts().identity
    target = np.linspace(0.0, 5.0, 200)
    plain = axis_model(AxisConfig(**base))
    v1, _ = axis_model(ax).inverse(target, 1e-4, axis_model(ax).rest(0.0))
    v0, _ = plain.inverse(target, 1e-4, plain.rest(0.0))
    np.testing.assert_array_equal(v1, v0)
    with pytest.raises(ValueError, match=r"extensions: .*delay\.delay_s"):
        AxisConfig(**base, extensions={"delay": {"delay_s": 1.0}})
    with pytest.raises(ValueError, match="no parameter 'f0_hz'"):
        AxisConfig(**base, extensions={"delay": {"f0_hz": 1.0}})


def test_a_delay_finding_is_adopted_as_the_sensor_path() -> None:
    adoption = adopt_findings(
        [
            {"effect": "delay", "params": {"delay_s": D, "lag_time_constant_s": TAU}},
            {"effect": "asymmetry", "params": {"asymmetry_pct": 0.5}},
        ]
    )
    assert adoption.effects == {"delay": {"delay_s": D, "lag_time_constant_s": TAU}}
    assert "sensor path" in adoption.adopted[0] and adoption.skipped[0].startswith("asymmetry")
    far = adopt_findings([{"effect": "delay", "params": {"delay_s": 0.2, "lag_time_constant_s": 0.0}}])
    assert not far.effects and "physical range" in far.skipped[0]


def test_experiments_through_the_sensor_path_keep_their_columns_aligned() -> None:
    t = np.arange(1000) * 1e-4
    e = Experiment("e", "x", t, np.sin(t), np.sin(t) * 2.0, target_um=t.copy())
    (out,) = experiments_through_sensor([e], SensorPath(5e-4, 0.0))
    assert len(out) == 995 and out.target_um is not None and out.target_um.size == 995
    np.testing.assert_allclose(out.position_um, 2.0 * np.sin(t[:995] + 5e-4), atol=1e-7)
    with pytest.raises(ModelError, match="shorter than the sensor delay"):
        experiments_through_sensor([Experiment("s", "x", t[:3], t[:3], t[:3])], SensorPath(5e-4, 0.0))
