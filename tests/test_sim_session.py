"""Offline sessions on the simulated stage."""

from __future__ import annotations

import numpy as np
import pytest

from hil_sim.errors import SimConfigError as ConfigError
from hil_sim.errors import SimSafetyError as SafetyError
from hil_sim.session import (
    Hold,
    MinorLoops,
    PlanItem,
    Ramp,
    Sine,
    Step,
    Triangle,
    Waypoints,
    calibration_plan,
    run_scanner_session,
    run_session,
)
from hil_sim.stage import StageConfig
from piezod.config import default_sim_config_path, load_config
from piezod.simulator import session_experiments, session_recording

FS = 2000.0


@pytest.fixture(scope="module")
def stage_cfg() -> StageConfig:
    """The default simulated stage (2 nm sensor noise)."""
    return StageConfig.from_file(default_sim_config_path())


def test_calibration_plan_grid_and_references() -> None:
    plan = calibration_plan(
        [200.0, 400.0], [0.5, 1.0, 2.0], [-20.0, 20.0], reference=Triangle(300.0, 1.0), reference_every=4
    )
    labels = [p.name() for p in plan]
    refs = [lab for lab in labels if lab.startswith("reference_")]
    assert refs == ["reference_01", "reference_02", "reference_03", "reference_04"]
    assert len(plan) == 12 + 4 and len(set(labels)) == len(labels)
    assert labels[0] == "reference_01" and labels[-1] == "reference_04"
    grid = [p for p in plan if not p.name().startswith("reference")]
    assert [p.params()["offset_v"] for p in grid] == [-20.0] * 6 + [20.0] * 6
    assert grid[0].name() == "tri_r200V_f0.5Hz_o-20V"


def test_session_records_continuous_time_and_the_planned_waveforms(stage_cfg: StageConfig) -> None:
    plan: list[PlanItem] = [
        Triangle(300.0, 2.0, offset_v=10.0, cycles=3, settle_cycles=2, record_settle=True),
        Sine(200.0, 5.0, cycles=2, settle_cycles=1),
        Ramp(-50.0, 80.0, 0.25),
        Step(0.0, 60.0, after_s=0.2, before_s=0.05),
        Hold(-40.0, 0.1),
        MinorLoops(0.0, (150.0, 100.0, 50.0), rate_v_per_s=1000.0, repeats=2),
        Waypoints((0.0, 100.0, -20.0), rate_v_per_s=400.0, label="path"),
    ]
    res = run_session(stage_cfg, plan, sample_rate_hz=FS, seed=1)
    assert res.labels() == [
        "tri_r300V_f2Hz_o10V_settle",
        "tri_r300V_f2Hz_o10V",
        "sin_r200V_f5Hz_o0V",
        "ramp_-50V_to_80V_0.25s",
        "step_0V_to_60V",
        "hold_-40V_0.1s",
        "minor_3loops_c0V",
        "path",
    ]
    t_all = np.concatenate([r.t_s for r in res.experiments])
    assert np.all(np.diff(t_all) > 0)
    steps = np.diff(t_all) * FS
    assert np.allclose(steps, np.round(steps), rtol=0, atol=1e-6)  # gaps: unrecorded moves, whole samples
    assert np.count_nonzero(np.round(steps) > 1) == 6
    tri = res["tri_r300V_f2Hz_o10V"]
    assert len(tri) == 3 * FS / 2.0 and len(res["tri_r300V_f2Hz_o10V_settle"]) == 2 * FS / 2.0
    assert tri.kind == "triangle" and res["tri_r300V_f2Hz_o10V_settle"].kind == "settle"
    assert tri.voltage_v.min() == pytest.approx(-140.0) and tri.voltage_v.max() == pytest.approx(160.0)
    assert tri.params == {"range_v": 300.0, "frequency_hz": 2.0, "offset_v": 10.0}
    sine = res["sin_r200V_f5Hz_o0V"]
    t_rel = sine.t_s - (sine.t_s[0] - 1 / FS - 0.2)  # after one settle cycle
    np.testing.assert_allclose(sine.voltage_v, -100.0 * np.cos(2 * np.pi * 5.0 * t_rel), atol=1e-9)
    step = res["step_0V_to_60V"]
    assert np.count_nonzero(step.voltage_v == 0.0) == 100 and step.voltage_v[-1] == 60.0
    assert np.all(res["hold_-40V_0.1s"].voltage_v == -40.0)
    minor = res["minor_3loops_c0V"].voltage_v
    assert minor.max() == pytest.approx(150.0) and minor[-1] == pytest.approx(-50.0)
    assert len(res["path"]) == round((100 + 120) / 400 * FS)
    noise = np.concatenate([r.position_um - r.true_position_um for r in res.experiments])
    assert np.std(noise) == pytest.approx(2e-3, rel=0.05)


def test_sessions_are_deterministic_given_a_seed(stage_cfg: StageConfig) -> None:
    plan = [Triangle(200.0, 2.0, cycles=2), Triangle(100.0, 4.0, offset_v=50.0, cycles=2)]
    a = run_session(stage_cfg, plan, sample_rate_hz=FS, seed=7)
    b = run_session(stage_cfg, plan, sample_rate_hz=FS, seed=7, block_samples=333)
    c = run_session(stage_cfg, plan, sample_rate_hz=FS, seed=8)
    for ra, rb, rc in zip(a.experiments, b.experiments, c.experiments, strict=True):
        np.testing.assert_allclose(ra.true_position_um, rb.true_position_um, rtol=0, atol=1e-9)
        np.testing.assert_allclose(
            ra.position_um - ra.true_position_um, rb.position_um - rb.true_position_um, atol=1e-12
        )
        np.testing.assert_array_equal(ra.true_position_um, rc.true_position_um)
        assert np.abs(ra.position_um - rc.position_um).max() > 0


def test_limits_and_bad_plans_are_refused(stage_cfg: StageConfig) -> None:
    with pytest.raises(SafetyError, match=r"experiment 'tri_r500V_f1Hz_o0V': voltage -250\.\.250 V"):
        run_session(stage_cfg, [Triangle(500.0, 1.0)], sample_rate_hz=FS, voltage_limits_v=(-230, 230))
    with pytest.raises(ConfigError, match="repeated experiment label"):
        run_session(stage_cfg, [Triangle(100.0, 1.0), Triangle(100.0, 1.0)], sample_rate_hz=FS)
    with pytest.raises(ConfigError, match="frequency_hz"):
        Triangle(100.0, 0.0)
    with pytest.raises(ConfigError, match="must not increase"):
        MinorLoops(0.0, (50.0, 100.0), rate_v_per_s=100.0)
    with pytest.raises(ConfigError, match="sample_rate_hz"):
        run_session(stage_cfg, [Hold(0.0, 1.0)], sample_rate_hz=-1.0)


def test_scanner_session_uses_the_scanner_limits_and_hidden_effects() -> None:
    scanner = load_config(default_sim_config_path())
    plan = calibration_plan([300.0], [2.0, 4.0], reference=Triangle(300.0, 2.0, cycles=2), reference_every=1)
    res = run_scanner_session(scanner, plan, sample_rate_hz=FS, effects=["drift=2.0"], seed=0)
    clean = run_scanner_session(scanner, plan, sample_rate_hz=FS, seed=0)
    ref1, ref3 = res["reference_01"], res["reference_03"]
    diff = (res["reference_03"].true_position_um - clean["reference_03"].true_position_um).mean()
    assert diff == pytest.approx(2e-3 * ref3.t_s.mean(), rel=1e-6)
    assert ref3.t_s[0] > ref1.t_s[-1]
    with pytest.raises(SafetyError):
        run_scanner_session(scanner, [Triangle(470.0, 1.0)], sample_rate_hz=FS)
    with pytest.raises(ValueError, match="unknown effect"):
        run_scanner_session(scanner, plan, sample_rate_hz=FS, effects=["wobble=1"])


def test_session_converts_to_the_recording_format(stage_cfg: StageConfig) -> None:
    recording = pytest.importorskip("piezod.recording")
    plan = [Triangle(300.0, 2.0, cycles=3), Triangle(200.0, 5.0, offset_v=30.0, cycles=3)]
    res = run_session(stage_cfg.with_effects("delay=1e-4"), plan, sample_rate_hz=FS, seed=0)
    rec = session_recording(res)
    assert rec.columns == ("t", "voltage", "position", "axis", "experiment")
    assert rec.metadata["effects"] == "delay"
    exps = session_experiments(res)
    assert [e.label for e in exps] == res.labels()
    info = recording.infer_scan(exps[1].t_s, exps[1].voltage_v)
    assert info.frequency_hz == pytest.approx(5.0, rel=1e-3)
    assert info.offset_v == pytest.approx(30.0, abs=1.0)
