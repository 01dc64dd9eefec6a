"""Offline calibration of the model (3.8): recovery of known parameters from synthetic frames."""

from __future__ import annotations

import dataclasses
import os
import time

import numpy as np
import pytest

from piezod.calibrate import (
    PARAM_NAMES,
    CalibrationData,
    CalibrationResult,
    _model,
    _to_z,
    auto_start,
    calibrate,
    calibrated_config,
    fit,
    fit_errors,
    model_positions,
    prepare,
    result_json,
)
from piezod.config import AxisConfig, ScannerConfig, ThesisModelConfig, dump_config, load_config
from piezod.errors import CalibrationError, RecordingError
from piezod.model import ThesisParams, thesis_loop
from piezod.recording import Experiment, split_experiments
from piezod.synth import (
    MEDIUM_TUBE,
    PlannedExperiment,
    calibration_plan,
    random_params,
    random_plan,
    synth_session,
)


def _frame(
    seed: int,
    n_exp: int = 12,
    spl: int = 1024,
    noise_um: float = 0.005,
    params: ThesisParams | None = None,
    offsets_v: tuple[float, float] = (-30.0, 30.0),
) -> tuple[ThesisParams, CalibrationData]:
    truth = params if params is not None else random_params(seed)
    plan = random_plan(seed, n_exp, offset_v=offsets_v)
    session = synth_session(truth, plan, samples_per_loop=spl, noise_um=noise_um, seed=seed)
    return truth, prepare(split_experiments(session.recording))


def _check_recovery(truth: ThesisParams, data: CalibrationData, res: CalibrationResult) -> None:
    assert res.success, res.message
    assert res.fixed == () and res.at_bounds == ()
    for k in PARAM_NAMES:
        err = getattr(res.params, k) - getattr(truth, k)
        assert abs(err) < 4.0 * res.stderr[k], (k, err, res.stderr[k])
    floor = float(fit_errors(data, truth)[0].max())  # noise only: the true parameters
    assert 0.95 * floor < res.fit_error_pct < 1.3 * floor


def test_model_is_thesis_loop_with_offsets() -> None:
    plan = calibration_plan((80.0, 300.0), (0.05, 2.0), (-20.0, 35.0))
    s = synth_session(MEDIUM_TUBE, plan, samples_per_loop=256, noise_um=0.0, offset_spread_um=0.0)
    data = prepare(split_experiments(s.recording))
    np.testing.assert_allclose(model_positions(data, MEDIUM_TUBE), data.position_um, atol=1e-9)
    e = plan[3]
    v = np.linspace(e.v_min, e.v_max, 7)
    ref = thesis_loop(MEDIUM_TUBE, v, 1, e.v_min, e.v_max, e.frequency_hz)
    assert ref.shape == (7,)


def test_jacobian_matches_finite_differences() -> None:
    _, data = _frame(4, n_exp=6, spl=64)
    p = ThesisParams(2.9e-3, 0.09, 0.02, 1.7, 0.2, 1.5e-3, 0.6)
    scale = 150.0
    z = _to_z(p, scale)
    _, J = _model(data, z, scale, jac=True)
    assert J is not None
    for j in range(7):
        h = 1e-6 * max(1.0, abs(z[j]))
        zp, zm = z.copy(), z.copy()
        zp[j] += h
        zm[j] -= h
        fd = (_model(data, zp, scale, False)[0] - _model(data, zm, scale, False)[0]) / (2 * h)
        np.testing.assert_allclose(
            J[:, j], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max(), err_msg=PARAM_NAMES[j]
        )


def test_noise_free_frame_is_recovered_exactly() -> None:
    truth, data = _frame(5, n_exp=12, spl=512, noise_um=0.0)
    res = fit(data)
    for k in PARAM_NAMES:
        assert getattr(res.params, k) == pytest.approx(getattr(truth, k), rel=1e-6), k
    assert res.fit_error_pct < 1e-6


@pytest.mark.parametrize("seed", [1, 2])
def test_recovers_random_parameters_within_standard_errors(seed: int) -> None:
    truth, data = _frame(seed)
    _check_recovery(truth, data, fit(data))


def test_offsets_are_recovered() -> None:
    truth = random_params(7)
    plan = random_plan(7, 10, offset_v=(-40.0, 40.0))
    s = synth_session(truth, plan, samples_per_loop=512, noise_um=0.002, seed=7)
    res = calibrate(split_experiments(s.recording))
    # the fitted offset also absorbs -(b_hat - b) V_C of an offset scan (3.8)
    for e, c, pe in zip(res.experiments, s.position_offsets_um, plan, strict=True):
        assert e.label == pe.label
        assert e.frequency_hz == pytest.approx(pe.frequency_hz, rel=1e-9)
        assert e.offset_v == pytest.approx(pe.offset_v, abs=1e-9)
        b_hat = thesis_loop(truth, np.array([pe.offset_v]), 1, pe.v_min, pe.v_max, pe.frequency_hz)
        centre_line = thesis_loop(truth, np.array([pe.offset_v]), -1, pe.v_min, pe.v_max, pe.frequency_hz)
        assert e.position_offset_um == pytest.approx(c, abs=0.05 + abs(b_hat[0] - centre_line[0]))
        assert e.n == 512 + 1


def test_auto_start_finds_the_hysteresis_shape() -> None:
    truth, data = _frame(3)
    start = auto_start(data)
    assert start.alpha_per_v == pytest.approx(truth.alpha_per_v, rel=0.01)
    delta = (start.b_um_per_v - start.u_um_per_v) / start.alpha_per_v
    assert delta == pytest.approx(truth.hysteresis.delta_um, rel=0.02)


def test_config_start_and_auto_start_reach_the_same_minimum() -> None:
    _, data = _frame(2)
    a = fit(data)
    b = fit(data, start=MEDIUM_TUBE)
    for k in PARAM_NAMES:
        assert getattr(a.params, k) == pytest.approx(getattr(b.params, k), abs=0.05 * a.stderr[k]), k


def test_robust_loss_resists_outliers() -> None:
    truth, data = _frame(1)
    rng = np.random.default_rng(1)
    x = data.position_um.copy()
    hit = rng.random(x.size) < 0.005
    x[hit] += rng.choice([-2.0, 2.0], int(hit.sum()))
    spiky = dataclasses.replace(data, position_um=x)
    plain = fit(spiky)
    robust = fit(spiky, loss="soft_l1")
    worst_plain = max(abs(getattr(plain.params, k) / getattr(truth, k) - 1) for k in PARAM_NAMES)
    worst_robust = max(abs(getattr(robust.params, k) / getattr(truth, k) - 1) for k in PARAM_NAMES)
    assert worst_robust < 0.2 * worst_plain
    for k in PARAM_NAMES:
        assert abs(getattr(robust.params, k) - getattr(truth, k)) < 4.0 * robust.stderr[k], k
    assert any("soft_l1" in w for w in robust.warnings)


def test_single_frequency_holds_tau_and_a1() -> None:
    plan = calibration_plan((100.0, 200.0, 300.0, 400.0), (0.5,))
    s = synth_session(MEDIUM_TUBE, plan, samples_per_loop=512, noise_um=0.005, seed=3)
    data = prepare(split_experiments(s.recording))
    res = fit(data)
    assert set(res.fixed) == {"tau_s", "a1"}
    assert res.stderr["tau_s"] == 0.0 and res.params.a1 == 0.0
    assert any("tau_s held" in w for w in res.warnings)
    # one frequency: (1 - A1 E) folds into A2 and A3, the data are still explained to the noise
    assert res.fit_error_pct < 1.3 * float(fit_errors(data, MEDIUM_TUBE)[0].max())


def test_long_loops_are_strided() -> None:
    plan = calibration_plan((100.0, 250.0, 400.0), (0.1, 1.0, 4.0), n_loops=2)
    s = synth_session(MEDIUM_TUBE, plan, samples_per_loop=4096, noise_um=0.005, seed=4)
    exps = split_experiments(s.recording)
    data = prepare(exps, max_samples_per_loop=1024)
    assert data.counts.tolist() == [2 * 1024 + 1] * 9
    full = prepare(exps, max_samples_per_loop=None)
    assert full.counts.tolist() == [2 * 4096 + 1] * 9
    # striding keeps the per-sample noise: the fit errors stay comparable with the full data
    a, b = fit(data), fit(full)
    assert a.fit_error_pct == pytest.approx(b.fit_error_pct, rel=0.05)
    for k in PARAM_NAMES:
        assert abs(getattr(a.params, k) - getattr(MEDIUM_TUBE, k)) < 4 * a.stderr[k], k


def test_user_fixed_parameters_are_held_at_the_start() -> None:
    _, data = _frame(8, n_exp=8, spl=256)
    res = fit(data, fix=["tau_s"])
    assert res.fixed == ("tau_s",) and res.stderr["tau_s"] == 0.0
    assert res.params.tau_s == auto_start(data).tau_s
    res = fit(data, start=MEDIUM_TUBE, fix=["tau_s", "a2_per_v"])
    assert (res.params.tau_s, res.params.a2_per_v) == (MEDIUM_TUBE.tau_s, MEDIUM_TUBE.a2_per_v)
    assert res.free == ("alpha_per_v", "b_um_per_v", "u_um_per_v", "a1", "a3")
    assert res.correlations.shape == (5, 5)


def test_frames_that_cannot_determine_the_model() -> None:
    one_range = synth_session(MEDIUM_TUBE, calibration_plan((200.0,), (0.1, 1.0, 3.0)), samples_per_loop=256)
    with pytest.raises(CalibrationError, match="1 distinct voltage range"):
        calibrate(split_experiments(one_range.recording))
    _, data = _frame(1, n_exp=6, spl=128)
    with pytest.raises(CalibrationError, match="unknown loss"):
        fit(data, loss="l3")
    with pytest.raises(CalibrationError, match="unknown parameter"):
        fit(data, fix=["gamma"])
    with pytest.raises(CalibrationError, match="no experiments"):
        prepare([])


def test_non_scan_experiment_is_rejected_with_its_line() -> None:
    t = np.linspace(0, 3, 301)
    sine = Experiment(
        "sine", "x", t, 100 * np.sin(2 * np.pi * t), t, path="s.csv", line_numbers=np.arange(301) + 7
    )
    with pytest.raises(RecordingError, match=r"^s\.csv:7: experiment 'sine' \(axis x\): the voltage is not"):
        prepare([sine])


def test_skip_loops_drops_transients() -> None:
    plan = [
        PlannedExperiment(f"r{r:g}_f{f:g}", -r / 2 + o, r / 2 + o, f, n_loops=4, settle_loops=0)
        for r, o in ((300.0, 20.0), (360.0, -20.0), (400.0, 0.0))
        for f in (0.1, 0.5, 2.0)
    ]
    s = synth_session(MEDIUM_TUBE, plan, samples_per_loop=256, noise_um=0.005, model="ode", seed=2)
    exps = split_experiments(s.recording)
    with_transients = calibrate(exps)
    settled = calibrate(exps, skip_loops=2)
    assert settled.experiments[0].n == 2 * 256 + 1
    assert settled.fit_error_pct < 0.5 * with_transients.fit_error_pct
    with pytest.raises(CalibrationError, match="cannot skip 4"):
        calibrate(exps, skip_loops=4)


def test_calibrated_config_without_and_with_base(tmp_path: os.PathLike[str]) -> None:
    _, data = _frame(2, n_exp=8, spl=256)
    res = fit(data)
    cfg = calibrated_config(res, inputs=["a.csv"], voltage_span_v=(-180.4, 220.2))
    p = f"{tmp_path}/cal.yaml"
    dump_config(cfg, p)
    back = load_config(p)
    assert back.axes["x"].thesis.params() == res.params
    assert (back.axes["x"].voltage_min_v, back.axes["x"].voltage_max_v) == (-181.0, 221.0)
    assert back.calibration is not None and back.calibration["recordings"] == ["a.csv"]
    assert back.calibration["fit_error_pct"] == pytest.approx(res.fit_error_pct, rel=1e-4)

    other = ThesisModelConfig(**{k: getattr(MEDIUM_TUBE, k) for k in PARAM_NAMES})
    base = ScannerConfig(
        name="stage",
        axes={
            "x": AxisConfig(voltage_min_v=-250, voltage_max_v=250, slew_rate_v_per_s=900, thesis=other),
            "y": AxisConfig(voltage_min_v=-100, voltage_max_v=100, thesis=other),
        },
    )
    cfg = calibrated_config(res, axis="y", base=base)
    assert cfg.axes["y"].thesis.params() == res.params
    assert cfg.axes["y"].voltage_max_v == 100 and cfg.axes["x"] == base.axes["x"]
    assert cfg.name == "stage" and cfg.calibration is not None and cfg.calibration["axis"] == "y"
    with pytest.raises(CalibrationError, match="needs --config"):
        calibrated_config(res, axis="y", voltage_span_v=(0.0, 1.0))
    with pytest.raises(CalibrationError, match="no axis 'z'"):
        calibrated_config(res, axis="z", base=base)


def test_result_json_has_the_contract_keys() -> None:
    _, data = _frame(3, n_exp=6, spl=256)
    doc = result_json(fit(data), inputs=["f.csv"])
    assert set(doc["params"]) == set(PARAM_NAMES) == set(doc["stderr"])
    assert doc["fit_error_pct"] == max(e["fit_error_pct"] for e in doc["experiments"])
    for key in ("label", "range_v", "offset_v", "frequency_hz", "range_um", "fit_error_pct", "n"):
        assert key in doc["experiments"][0]
    assert doc["correlations"]["b_um_per_v"]["b_um_per_v"] == pytest.approx(1.0)


@pytest.mark.slow
@pytest.mark.parametrize(("n_exp", "seed"), [(30, 11), (35, 12), (35, 13)])
def test_full_frame_recovery_and_time(n_exp: int, seed: int) -> None:
    """30-35 experiments x 2048 samples, 80-400 V p-p, 0.02-5 Hz, offsets, 5 nm noise."""
    truth, data = _frame(seed, n_exp=n_exp, spl=2048)
    cpu0 = time.process_time()
    res = fit(data)
    cpu = time.process_time() - cpu0
    _check_recovery(truth, data, res)
    floor = float(fit_errors(data, truth)[0].max())
    print(
        f"\n{n_exp} x 2048: fit {res.seconds:.2f} s wall, {cpu:.2f} s CPU, {res.nfev} evaluations; "
        f"worst fit error {res.fit_error_pct:.5f} % vs noise floor {floor:.5f} % "
        f"(ratio {res.fit_error_pct / floor:.4f}); condition {res.condition_number:.3g}"
    )
    for k in PARAM_NAMES:
        z = (getattr(res.params, k) - getattr(truth, k)) / res.stderr[k]
        print(
            f"  {k:<12} truth {getattr(truth, k):<11.5g} fit {getattr(res.params, k):<11.5g} ({z:+.2f} sigma)"
        )
