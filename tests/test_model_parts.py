"""Runtime parts around an axis model (piezod.model.parts): exact inverses, config, agreement with hil_sim."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezod.calibrate_family import family_model_config
from piezod.config import AxisConfig, ThesisModelConfig
from piezod.errors import ModelError
from piezod.model.axis_model import DynamicAxisModel, FamilyAxisModel
from piezod.model.dynamic import DynamicParams
from piezod.model.family import CreepSpectrum, FamilyParams
from piezod.model.parts import PART_EFFECTS, Parts, PartsAxisModel, with_parts
from piezod.model.play import PlayParams
from piezod.model.registry import REGISTRY
from piezod.service.axes import AxisDriver, axis_model

W = np.exp(-np.arange(16) / 6.0)
PI = PlayParams.uniform(0.11, 0.45, 320.0, 16, 0.55 * W / W.sum())
SPEC = CreepSpectrum.log_spaced(1e-4, 1e5, 2, 0.015 / 2)
ALL = Parts(
    negative_sensitivity_pct=-7.0,
    rate_pct_per_hour=2.0,
    sensitivity_pct_per_um=0.1,
    x_sat_um=90.0,
    rate_nm_per_s=1.5,
)
THESIS = ThesisModelConfig(
    alpha_per_v=3e-3, b_um_per_v=0.09, u_um_per_v=0.05, tau_s=2.666, a1=0.081, a2_per_v=0.0, a3=0.6
)


def _targets(n: int, dt: float) -> np.ndarray:
    t = np.arange(n) * dt
    return 15.0 * (1.0 - 4.0 * np.abs((t * 5.0) % 1.0 - 0.5)) + 2.0


@pytest.mark.parametrize(
    "inner",
    [
        FamilyAxisModel(FamilyParams(PI, SPEC, 2e-4, 0.05, "voltage")),
        FamilyAxisModel(FamilyParams(PI, SPEC, 2e-4, 0.05, "position")),
        DynamicAxisModel(DynamicParams(3e-3, 0.115, 0.072, 1.5)),
    ],
    ids=["family-voltage-creep", "family-position-creep", "dynamic"],
)
def test_every_part_inverts_exactly_over_blocks_split_anywhere(inner: object) -> None:
    assert isinstance(inner, FamilyAxisModel | DynamicAxisModel)
    model = PartsAxisModel(inner, ALL)
    dt = 1e-5
    x = _targets(20_000, dt)  # crosses 0 V (polarity) on the way down
    s0 = model.rest(-5.0)
    x = x - x[0] + model.position(s0)
    v, s1 = model.inverse(x, dt, s0)
    assert v.min() < 0.0 < v.max()
    back, s2 = model.forward(v, dt, s0)
    np.testing.assert_allclose(back, x, rtol=0, atol=1e-9)
    assert model.position(s1) == pytest.approx(model.position(s2), abs=1e-9)
    parts, s = [], s0
    for chunk in np.array_split(x, [1, 2, 777, 13_000]):
        vb, s = model.inverse(chunk, dt, s)
        parts.append(vb)
    np.testing.assert_allclose(np.concatenate(parts), v, rtol=0, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    polarity=st.floats(-10.0, 10.0),
    stiffness=st.floats(-0.15, 0.15),
    x_sat=st.floats(60.0, 150.0),
    drift=st.floats(-2.0, 2.0),
    cut=st.integers(1, 299),
)
def test_random_walks_round_trip_through_the_parts(
    seed: int, polarity: float, stiffness: float, x_sat: float, drift: float, cut: int
) -> None:
    rng = np.random.default_rng(seed)
    parts = Parts(polarity, 1.0, stiffness, x_sat, drift)
    model = PartsAxisModel(FamilyAxisModel(FamilyParams(PI, SPEC, 1e-4, -0.05, "voltage")), parts)
    v = np.cumsum(rng.normal(0, 15.0, 300))
    s0 = model.rest(0.0)
    x, end = model.forward(v, 1e-4, s0)
    va, s1 = model.inverse(x[:cut], 1e-4, s0)
    vb, s2 = model.inverse(x[cut:], 1e-4, s1)
    np.testing.assert_allclose(np.concatenate([va, vb]), v, rtol=0, atol=1e-9 * max(1.0, float(np.ptp(v))))
    assert model.position(s2) == pytest.approx(model.position(end), abs=1e-9)


def test_hold_and_adopt_carry_time_and_the_maps() -> None:
    model = PartsAxisModel(FamilyAxisModel(FamilyParams(PI, SPEC, 0.0, 0.0, "voltage")), ALL)
    s = model.adopt(-20.0, -3.0)
    assert model.position(s) == pytest.approx(-3.0, abs=1e-9) and model.voltage(s) == pytest.approx(-20.0)
    held = model.hold(100_000, 1e-5, s)
    assert held.time_s == pytest.approx(1.0)
    # the drift moves the held position by 1.5 nm/s (plus the thermal scale and the creep)
    assert model.position(held) != model.position(s)
    assert with_parts(model.inner, Parts()) is model.inner
    assert model.kind == "family" and model.with_plan(0.0, 0.0) == model


def test_parts_refuse_what_is_not_physical_or_not_a_part() -> None:
    with pytest.raises(ModelError, match=r"stiffness\.sensitivity_pct_per_um"):
        Parts(sensitivity_pct_per_um=3.0)
    with pytest.raises(ModelError, match="no runtime part"):
        Parts.from_effects({"resonance": {"f0_hz": 800.0}})
    with pytest.raises(ModelError, match="no runtime parameter"):
        Parts.from_effects({"drift": {"rate_um_per_s": 1.0}})
    assert Parts.from_effects(ALL.effects()) == ALL
    for effect, names in PART_EFFECTS.items():
        assert set(names) <= set(REGISTRY[effect].names)


def test_the_axis_config_wraps_its_model_in_the_parts() -> None:
    family = family_model_config(FamilyParams(PI, SPEC, creep_driver="voltage"))
    base = {
        "voltage_min_v": -230.0,
        "voltage_max_v": 230.0,
        "thesis": THESIS,
        "model": "family",
        "family": family,
    }
    ax = AxisConfig(**base, extensions={"stiffness": {"sensitivity_pct_per_um": -0.08}})
    model = axis_model(ax)
    assert isinstance(model, PartsAxisModel) and model.parts.sensitivity_pct_per_um == -0.08
    assert isinstance(axis_model(AxisConfig(**base)), FamilyAxisModel)
    with pytest.raises(ValueError, match=r"extensions: .*saturation\.x_sat_um"):
        AxisConfig(**base, extensions={"saturation": {"x_sat_um": 0.5}})
    # the engine's axis driver streams it without knowing (blocks, hold, adopt into another model)
    full = AxisConfig(**{**base, "slew_rate_v_per_s": 1e6}, extensions=ALL.effects())
    d = AxisDriver("x", full, 100_000.0)
    targets = _targets(3000, 1e-5) + d.position_um - _targets(1, 1e-5)[0]
    volts = np.concatenate([d.corrected(b).voltage_v for b in np.array_split(targets, 4)])
    x, _ = d.model.forward(volts, 1e-5, d.model.rest(full.safe_voltage_v))
    np.testing.assert_allclose(x, targets, rtol=0, atol=1e-9)
    d.hold(500)
    plain = AxisDriver("x", AxisConfig(**base), 100_000.0)
    plain.adopt_state(d)
    assert plain.voltage_v == pytest.approx(d.voltage_v)


def test_the_parts_apply_the_same_laws_as_the_simulated_stage() -> None:
    """hil_sim may not import piezod: its own implementation of every part agrees with the runtime's."""
    from hil_sim.stage import StageConfig, StageModel, resolve_stage, rest_state, stage_step

    path = resolve_stage("stage")
    assert path is not None
    base = StageConfig.from_file(path).without_effects()
    specs = [
        "polarity=-7",
        "thermal=2",
        "stiffness=0.1",
        "saturation=90",
        "drift=1.5",
    ]
    dt = 1e-4
    t = np.arange(4000) * dt
    v = 150.0 * np.sin(2 * np.pi * 2.0 * t)[None, :].repeat(StageModel.from_config(base).channels, axis=0)
    plain_model = StageModel.from_config(base)
    with_fx = StageModel.from_config(base.with_effects(*specs))
    x0, _ = stage_step(plain_model, ALL.voltage_in(v), dt, rest_state(plain_model))
    x1, _ = stage_step(with_fx, v, dt, rest_state(with_fx))
    expected = ALL.position_out(x0, t + dt)
    np.testing.assert_allclose(x1, expected, rtol=0, atol=1e-9)
    assert not math.isclose(float(np.max(np.abs(x1 - x0))), 0.0)


def test_time_parts_hold_after_their_horizon_and_still_invert_exactly() -> None:
    """A trend found over a session is followed for a horizon, then held (not extrapolated for
    ever); forward and inverse stay exact across the horizon, and the YAML round-trips it."""
    parts = Parts.from_effects(
        {
            "thermal": {"rate_pct_per_hour": 2.0, "horizon_s": 10.0},
            "drift": {"rate_nm_per_s": 10.0, "horizon_s": 5.0},
        }
    )
    assert parts.effects()["drift"] == {"rate_nm_per_s": 10.0, "horizon_s": 5.0}
    assert Parts.from_effects(parts.effects()) == parts
    t = np.array([0.0, 2.5, 5.0, 50.0, 3600.0])
    x = parts.position_out(np.full(t.size, 10.0), t)
    drift = x - 10.0 * (1.0 + 2.0 * np.minimum(t, 10.0) / 360000.0)
    np.testing.assert_allclose(drift, [0.0, 0.025, 0.05, 0.05, 0.05], atol=1e-12)
    np.testing.assert_allclose(parts.position_in(x, t), 10.0, atol=1e-12)
    short = Parts(rate_pct_per_hour=2.0, thermal_horizon_s=0.1, rate_nm_per_s=10.0, drift_horizon_s=0.05)
    model = PartsAxisModel(FamilyAxisModel(FamilyParams(PI, SPEC, 0.0, 0.0, "voltage")), short)
    dt = 1e-4
    s0 = model.rest(0.0)
    target = _targets(2000, dt) - _targets(1, dt)[0] + model.position(s0)  # 0.2 s: across both horizons
    v, _ = model.inverse(target, dt, s0)
    xf, _ = model.forward(v, dt, s0)
    np.testing.assert_allclose(xf, target, rtol=0, atol=1e-9)
    with pytest.raises(ModelError, match="no runtime parameter 'horizon_s'"):
        Parts.from_effects({"stiffness": {"sensitivity_pct_per_um": 0.1, "horizon_s": 10.0}})
    with pytest.raises(ModelError, match="horizon_s"):
        Parts.from_effects({"drift": {"rate_nm_per_s": 1.0, "horizon_s": 0.0}})


def test_time_parts_go_on_from_the_session_they_were_measured_in(tmp_path: Path) -> None:
    """The calibration's sensitivity is the one at its session's start: a thermal part adopted ten
    minutes later starts ten minutes into its trend (and its horizon counts from the session), on
    the wall clock the daemon reads when it builds the model; without ``since_unix_s`` the clock
    starts at the adoption as before."""
    import time as _time

    from piezod.extensions import adopt_findings, session_origin_unix_s

    since = 1_800_000_000.0
    parts = Parts.from_effects(
        {"thermal": {"rate_pct_per_hour": 1.0, "horizon_s": 1800.0, "since_unix_s": since}}
    )
    assert Parts.from_effects(parts.effects()) == parts
    assert parts.effects()["thermal"]["since_unix_s"] == since
    now = parts.anchored(since + 600.0)
    assert now.thermal_t0_s == 600.0 and parts.thermal_t0_s == 0.0
    x = now.position_out(np.full(3, 10.0), np.array([0.0, 600.0, 3600.0]))
    np.testing.assert_allclose(x, 10.0 * (1.0 + np.array([600.0, 1200.0, 1800.0]) / 360000.0), rtol=1e-12)
    np.testing.assert_allclose(now.position_in(x, np.array([0.0, 600.0, 3600.0])), 10.0, rtol=1e-12)
    assert Parts(rate_pct_per_hour=1.0).anchored(since + 600.0) == Parts(rate_pct_per_hour=1.0)
    with pytest.raises(ModelError, match="since_unix_s"):
        Parts.from_effects({"drift": {"rate_nm_per_s": 1.0, "since_unix_s": -5.0}})
    # the daemon anchors at its wall clock when it builds the axis model
    ax = AxisConfig(
        voltage_min_v=-200.0,
        voltage_max_v=200.0,
        model="thesis",
        thesis=THESIS,
        extensions={"thermal": {"rate_pct_per_hour": 1.0, "since_unix_s": _time.time() - 600.0}},
    )
    model = axis_model(ax)
    assert isinstance(model, PartsAxisModel) and model.parts.thermal_t0_s == pytest.approx(600.0, abs=60.0)
    # a recording's clock origin: its header's started_utc minus its first t
    rec = tmp_path / "frame.csv"
    rec.write_text(
        "# scanner: s\n# started_utc: 2027-01-15T08:00:10Z\nt,voltage,position\n12.5,0,0\n13,0,0\n"
    )
    assert session_origin_unix_s(rec) == 1_800_000_010.0 - 12.5
    (tmp_path / "old.csv").write_text("t,voltage,position\n0,0,0\n")
    assert math.isnan(session_origin_unix_s(tmp_path / "old.csv"))
    found = adopt_findings(
        [{"effect": "drift", "params": {"rate_nm_per_s": 0.5}}], horizon_s=900.0, since_unix_s=since
    )
    assert found.effects["drift"] == {"rate_nm_per_s": 0.5, "horizon_s": 900.0, "since_unix_s": since}


def test_adoption_gives_the_time_parts_a_horizon_of_three_sessions() -> None:
    from piezod.extensions import TREND_HORIZON_FACTOR, adopt_findings, trend_horizon_s
    from piezod.recording import Experiment

    t = np.linspace(10.0, 70.0, 11)
    exps = [Experiment("a", "x", t, t, t), Experiment("b", "x", t + 60.0, t, t)]
    assert trend_horizon_s(exps) == pytest.approx(TREND_HORIZON_FACTOR * 120.0)
    findings = [
        {"effect": "drift", "params": {"rate_nm_per_s": 0.5}},
        {"effect": "stiffness", "params": {"sensitivity_pct_per_um": 0.05}},
    ]
    adoption = adopt_findings(findings, horizon_s=360.0)
    assert adoption.effects == {
        "drift": {"rate_nm_per_s": 0.5, "horizon_s": 360.0},
        "stiffness": {"sensitivity_pct_per_um": 0.05},
    }
    assert "horizon_s" not in adopt_findings(findings).effects["drift"]


def test_a_part_found_after_the_sensor_path_is_adopted() -> None:
    """The sensor path is not a runtime part: a finding after it was checked together with it and
    skipped as "effect 'delay' has no runtime part" (a held-out stage's -4 % polarity, found by the
    audit after the readback delay, was not adopted)."""
    from piezod.extensions import adopt_findings

    findings = [
        {"effect": "stiffness", "params": {"sensitivity_pct_per_um": 0.05}},
        {"effect": "delay", "params": {"delay_s": 5e-4, "lag_time_constant_s": 1e-5}},
        {"effect": "polarity", "params": {"negative_sensitivity_pct": -4.0}},
    ]
    adoption = adopt_findings(findings)
    assert list(adoption.effects) == ["stiffness", "delay", "polarity"], adoption.skipped
    assert adoption.skipped == ()
    assert adoption.effects["polarity"] == {"negative_sensitivity_pct": -4.0}
