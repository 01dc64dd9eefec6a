"""The model family: exact per-sample inverse of every part, state across blocks and holds, the driver."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezod.calibrate_family import family_model_config
from piezod.config import AxisConfig, FamilyModelConfig, ThesisModelConfig
from piezod.errors import ModelError, RangeUnreachableError
from piezod.model.axis_model import FamilyAxisModel, ThesisAxisModel
from piezod.model.family import (
    CreepSpectrum,
    FamilyParams,
    family_adopt_state,
    family_forward,
    family_hold,
    family_inverse,
    family_rest_state,
)
from piezod.model.params import HysteresisParams
from piezod.model.play import PlayParams, play_forward, play_inverse, play_rest_state
from piezod.service.axes import AxisDriver, AxisOutput

W = np.exp(-np.arange(16) / 6.0)
PI = PlayParams.uniform(0.11, 0.45, 320.0, 16, 0.55 * W / W.sum())
CH = HysteresisParams(3e-3, 0.115, 0.072)
SPEC = CreepSpectrum.log_spaced(1e-4, 1e5, 3, 0.015 / 3)
THESIS = ThesisModelConfig(
    alpha_per_v=3e-3, b_um_per_v=0.09, u_um_per_v=0.05, tau_s=2.666, a1=0.081, a2_per_v=0.0, a3=0.6
)


def _pi_section(**extra: float) -> FamilyModelConfig:
    """The ``family:`` section of the Prandtl-Ishlinskii law ``PI`` with the creep ``SPEC``."""
    return family_model_config(FamilyParams(PI, SPEC, **extra))


def _smooth_targets(n: int, dt: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    tri = 12.0 * np.abs((t * 7.0) % 1.0 - 0.5) * 2.0 - 4.0
    ramp_in = np.minimum(1.0, t / 0.05)
    return tri * ramp_in + 0.01 * np.cumsum(rng.normal(0, 0.02, n))


@pytest.mark.parametrize("driver", ["position", "voltage"])
@pytest.mark.parametrize("law", [PI, CH], ids=["prandtl-ishlinskii", "coleman-hodgdon"])
@pytest.mark.parametrize("lag", [0.0, 2e-4])
def test_inverse_is_exact_and_block_invariant(
    law: PlayParams | HysteresisParams, lag: float, driver: str
) -> None:
    p = FamilyParams(law, SPEC, lag, 0.05, creep_driver=driver)
    dt = 5e-5
    x = _smooth_targets(8000, dt, 1)
    s0 = family_rest_state(p, 3.0)
    x = x + s0.position_um
    v, s1 = family_inverse(p, x, dt, s0)
    xf, s2 = family_forward(p, v, dt, s0)
    np.testing.assert_allclose(xf, x, atol=1e-9)
    assert s1.position_um == pytest.approx(s2.position_um, abs=1e-9)
    np.testing.assert_allclose(s1.creep_um, s2.creep_um, atol=1e-9)
    parts, s = [], s0
    for chunk in np.array_split(x, [1, 2, 333, 5000]):
        vb, s = family_inverse(p, chunk, dt, s)
        parts.append(vb)
    np.testing.assert_allclose(np.concatenate(parts), v, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.1, 60.0))
def test_play_inverse_reaches_any_targets(seed: int, scale: float) -> None:
    rng = np.random.default_rng(seed)
    v = np.cumsum(rng.normal(0, scale, 300))
    x, end = play_forward(PI, v, play_rest_state(PI))
    vi, end_i = play_inverse(PI, x, play_rest_state(PI))
    np.testing.assert_allclose(vi, v, atol=1e-8 * max(1.0, float(np.max(np.abs(v)))))
    np.testing.assert_allclose(end_i.plays_v, end.plays_v, atol=1e-8 * max(1.0, float(np.max(np.abs(v)))))


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    scale=st.floats(0.05, 40.0),
    ch=st.booleans(),
    creep=st.floats(0.0, 0.08),
    cut=st.integers(1, 399),
)
def test_voltage_creep_inverse_round_trips_any_voltages(
    seed: int, scale: float, ch: bool, creep: float, cut: int
) -> None:
    """Random walks (reversals anywhere, holds, jumps) through forward then inverse, split anywhere."""
    rng = np.random.default_rng(seed)
    v = 20.0 + np.cumsum(rng.normal(0, scale, 400) * (rng.random(400) < 0.8))
    p = FamilyParams(
        CH if ch else PI, CreepSpectrum.log_spaced(1e-4, 1e2, 2, creep / 13), 1e-4, -0.1, "voltage"
    )
    dt = 1e-4
    s0 = family_rest_state(p, -5.0)
    x, end = family_forward(p, v, dt, s0)
    va, s1 = family_inverse(p, x[:cut], dt, s0)
    vb, s2 = family_inverse(p, x[cut:], dt, s1)
    span = max(1.0, float(np.ptp(v)))
    np.testing.assert_allclose(np.concatenate([va, vb]), v, atol=1e-9 * span)
    assert s2.position_um == pytest.approx(end.position_um, abs=1e-9 * max(1.0, float(np.ptp(x))))
    np.testing.assert_allclose(s2.creep_um, end.creep_um, atol=1e-9 * span)


def test_voltage_and_position_creep_differ_by_the_loop_share() -> None:
    """At rest both drivers agree; on a loop the voltage-driven creep ignores the loop's lag."""
    pos = FamilyParams(PI, SPEC, 0.0, 0.0, "position")
    vol = FamilyParams(PI, SPEC, 0.0, 0.0, "voltage")
    for v in (-40.0, 0.0, 75.0):
        assert family_rest_state(pos, v).position_um == pytest.approx(family_rest_state(vol, v).position_um)
    dt = 1e-3
    volts = 100.0 * np.sin(2 * np.pi * np.arange(4000) * dt)
    xp, _ = family_forward(pos, volts, dt, family_rest_state(pos))
    xv, _ = family_forward(vol, volts, dt, family_rest_state(vol))
    assert 0.0 < float(np.max(np.abs(xp - xv))) < 0.2 * float(np.ptp(xp))


@pytest.mark.parametrize("driver", ["position", "voltage"])
def test_hold_and_adopt_with_either_creep_driver(driver: str) -> None:
    p = FamilyParams(PI, SPEC, 1e-3, 0.0, creep_driver=driver)
    dt = 1e-4
    s0 = family_rest_state(p)
    _, s = family_forward(p, np.linspace(0, 100, 500), dt, s0)
    held = family_hold(p, 50_000, dt, s)
    _, step = family_forward(p, np.full(50_000, s.voltage_v), dt, s)
    assert held.position_um == pytest.approx(step.position_um, abs=1e-6)
    adopted = family_adopt_state(p, 50.0, 5.0)
    assert adopted.position_um == pytest.approx(5.0, abs=1e-9)
    v, _ = family_inverse(p, np.full(10, 5.0), dt, adopted)
    np.testing.assert_allclose(v, 50.0, atol=1e-9)


@pytest.mark.parametrize("driver", ["position", "voltage"])
def test_the_sensor_offset_moves_every_position_and_nothing_else(driver: str) -> None:
    """``offset_um`` (where the sensor reads the model's zero, fitted by the calibration) is added
    after the static map: forward, rest and adopted positions move by it, the inverse takes it
    off, the voltages for the same motion do not change; the config carries it."""
    base = FamilyParams(PI, SPEC, 1e-3, 0.4, creep_driver=driver)
    off = FamilyParams(PI, SPEC, 1e-3, 0.4, creep_driver=driver, offset_um=-1.5)
    dt = 1e-4
    volts = np.linspace(0, 100, 500)
    x0, s0 = family_forward(base, volts, dt, family_rest_state(base))
    x1, s1 = family_forward(off, volts, dt, family_rest_state(off))
    np.testing.assert_allclose(x1, x0 - 1.5, atol=1e-12)
    assert family_rest_state(off).position_um == pytest.approx(family_rest_state(base).position_um - 1.5)
    v0, _ = family_inverse(base, x0[-1] + np.linspace(0, 2, 50), dt, s0)
    v1, _ = family_inverse(off, x1[-1] + np.linspace(0, 2, 50), dt, s1)
    np.testing.assert_allclose(v1, v0, atol=1e-9)
    adopted = family_adopt_state(off, 50.0, 5.0)
    assert adopted.position_um == pytest.approx(5.0, abs=1e-9)
    assert adopted.law.position_um == pytest.approx(family_adopt_state(base, 50.0, 6.5).law.position_um)
    assert family_model_config(off).params().offset_um == -1.5
    with pytest.raises(ModelError, match="offset_um"):
        FamilyParams(PI, SPEC, offset_um=float("nan"))


def test_hold_relaxes_creep_and_settles_the_lag() -> None:
    p = FamilyParams(PI, SPEC, 1e-3, 0.0)
    dt = 1e-4
    s0 = family_rest_state(p)
    _, s = family_forward(p, np.linspace(0, 100, 500), dt, s0)
    held = family_hold(p, 200_000, dt, s)
    _, step = family_forward(p, np.full(200_000, s.voltage_v), dt, s)
    assert held.position_um == pytest.approx(step.position_um, abs=1e-6)
    assert held.drive_v == pytest.approx(100.0, abs=1e-6)
    assert held.position_um > s.position_um  # it crept on


def test_driver_runs_a_family_axis_without_model_branches() -> None:
    section = _pi_section(lag_time_constant_s=2e-4)
    cfg = AxisConfig(
        voltage_min_v=-230,
        voltage_max_v=230,
        slew_rate_v_per_s=1e6,
        thesis=THESIS,
        model="family",
        family=section,
    )
    d = AxisDriver("x", cfg, 20_000.0)
    assert isinstance(d.model, FamilyAxisModel)
    targets = _smooth_targets(4000, 5e-5, 2)
    out = np.concatenate([d.corrected(b).voltage_v for b in np.array_split(targets, 5)])
    x, _ = family_forward(section.params(), out, 5e-5, family_rest_state(section.params()))
    np.testing.assert_allclose(x, targets, atol=1e-9)
    d.hold(1000)
    thesis = AxisDriver("x", AxisConfig(voltage_min_v=-230, voltage_max_v=230, thesis=THESIS), 20_000.0)
    assert isinstance(thesis.model, ThesisAxisModel)
    thesis.adopt_state(d)
    assert thesis.position_um == pytest.approx(d.position_um, abs=1e-12)
    assert thesis.voltage_v == d.voltage_v


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ModelError):
        CreepSpectrum((1.0, 0.5), (0.1, 0.1))
    with pytest.raises(ModelError):
        CreepSpectrum((1.0, 10.0), (0.5, 0.5))
    with pytest.raises(ModelError):
        PlayParams(0.1, 0.5, (2.0, 1.0), (0.1, 0.1))
    with pytest.raises(ModelError):
        FamilyParams(PI, SPEC, -1.0)
    with pytest.raises(ValueError, match="pi_rho0"):
        FamilyModelConfig(law="prandtl-ishlinskii", b_um_per_v=0.1, creep_taus_s=[1, 2], creep_weights=[0, 0])


def test_a_fitted_spectrum_with_zero_weights_is_pruned_and_inverts() -> None:
    spectrum = CreepSpectrum((1e-3, 1e-2, 1e-1, 1.0, 10.0), (0.01, 0.0, 0.0, 0.02, 0.0))
    p = FamilyParams(PI, spectrum)
    assert p.creep.taus == (1e-3, 1.0)
    dt = 1e-4
    x = _smooth_targets(3000, dt, 4)
    s0 = family_rest_state(p)
    v, _ = family_inverse(p, x, dt, s0)
    xf, _ = family_forward(p, v, dt, s0)
    np.testing.assert_allclose(xf, x, atol=1e-9)
    assert FamilyParams(PI, CreepSpectrum((1.0, 2.0), (0.0, 0.0))).creep.total_creep == 0.0


def test_the_planner_places_a_scan_by_the_model_in_use() -> None:
    """On a unipolar stack whose fitted law is not the thesis law, a scan centred on ``c`` um is
    planned between the turning voltages of the family model's own loop, not around ``c / b`` of
    the thesis parameters (those put the centre of a large scan below the amplifier's range and
    the planner refused it); the driver then runs the scan inside the planned voltages."""
    section = _pi_section()
    thesis = THESIS.model_copy(update={"b_um_per_v": 0.2})
    cfg = AxisConfig(
        voltage_min_v=-30,
        voltage_max_v=150,
        slew_rate_v_per_s=1e6,
        thesis=thesis,
        model="family",
        family=section,
    )
    rate = 10_000.0
    d = AxisDriver("x", cfg, rate)
    ramp = np.linspace(0.0, 60.0, 4001)[1:]
    rest = family_rest_state(section.params())
    centre_um = float(family_forward(section.params(), ramp, 1.0 / rate, rest)[0][-1])
    assert centre_um / 0.2 < 30.0  # the thesis b would centre it far below 60 V
    plan = d.plan(8.0, 1.0, centre_um)
    assert -30.0 <= plan.v_min < plan.v_max <= 150.0
    assert plan.v_center > centre_um / 0.2 + 15.0  # not where the thesis b puts it
    lo = centre_um - 4.0
    phase = (np.arange(1, 2 * 10_000 + 1) % 10_000) / 10_000
    tri = lo + 8.0 * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    targets = np.concatenate([np.linspace(d.position_um, lo, 2001)[1:], tri])
    volts = np.concatenate([d.corrected(b).voltage_v for b in np.array_split(targets, 10)])[-10_000:]
    assert float(volts.min()) == pytest.approx(plan.v_min, abs=0.5)
    assert float(volts.max()) == pytest.approx(plan.v_max, abs=0.5)
    with pytest.raises(RangeUnreachableError, match="largest reachable"):
        d.plan(16.0, 1.0, centre_um)


class _CausalSlew(AxisDriver):
    """The driver as it was: a step the slew limit cuts is ramped after the step only."""

    def corrected(self, targets_um: np.ndarray) -> AxisOutput:
        volts, state = self.model.inverse(targets_um, self._dt_s, self._state)
        return self._finish(volts, state)


def test_a_step_the_slew_limit_cuts_is_spread_around_the_turning_point() -> None:
    """The inverse of a drive lag steps the voltage at every turning point of a fast scan; under
    the slew limit the ramp is centred on the turning point, and the stage (the model itself
    here) follows the scan closer there than with the ramp started at the turning point."""
    section = _pi_section(lag_time_constant_s=5e-4)
    rate, n = 20_000.0, 500  # a 40 Hz scan
    phase = (np.arange(4 * n) % n) / n
    targets = 6.0 * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase) - 3.0
    blocks = np.array_split(targets, 4)

    def drive(cls: type[AxisDriver], slew: float) -> tuple[np.ndarray, Any]:
        cfg = AxisConfig(
            voltage_min_v=-230,
            voltage_max_v=230,
            slew_rate_v_per_s=slew,
            thesis=THESIS,
            model="family",
            family=section,
        )
        d = cls("x", cfg, rate)
        start = d.state
        return np.concatenate([d.corrected(b).voltage_v for b in blocks]), start

    turn = int(1.5 * n)  # a turning point inside a block (the top of the second loop)
    free = np.abs(np.diff(drive(AxisDriver, 1e9)[0]))[n:]
    ramp, step = float(np.median(free)), float(free[turn - n - 2 : turn - n + 2].max())
    assert step > 4 * ramp  # the lag's step at the turning points
    slew = 2 * ramp * rate
    (centred, s0), (causal, _) = drive(AxisDriver, slew), drive(_CausalSlew, slew)
    for v in (centred, causal):
        assert np.abs(np.diff(v)).max() <= slew / rate * (1 + 1e-9)
    assert centred[turn - 3] < causal[turn - 3] - 0.1 * step  # moving towards the step before it
    p = section.params()
    errs = []
    for v in (centred, causal):
        x, _ = family_forward(p, v, 1 / rate, s0)
        errs.append(float(np.abs(x - targets)[turn - 20 : turn + 40].max()))
    assert errs[0] < 0.7 * errs[1]
