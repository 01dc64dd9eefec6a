"""Simulated stages of other physics: Prandtl-Ishlinskii loops, power-law voltage creep, curvature, lag."""

from __future__ import annotations

import itertools
import subprocess
import sys
from typing import Any

import numpy as np
import pytest

from hil_sim.creep import CreepBank
from hil_sim.errors import SimConfigError
from hil_sim.hysteresis import (
    BoucWenParams,
    CHParams,
    PIParams,
    PreisachParams,
    boucwen_rest_state,
    boucwen_step,
    ch_rest_state,
    ch_step,
    pi_rest_state,
    pi_step,
    preisach_position,
    preisach_rest_state,
    preisach_step,
)
from hil_sim.stage import Stage, StageConfig, preset_names, resolve_stage


def _stage(axis: dict[str, Any], creep: dict[str, Any] | None = None, **extra: Any) -> Stage:
    data: dict[str, Any] = {"axes": {"x": axis}, "sensor_noise_nm_rms": 0.0, **extra}
    if creep is not None:
        data["creep"] = creep
    return Stage(StageConfig.model_validate(data))


PI_AXIS = {
    "law": "prandtl-ishlinskii",
    "b_um_per_v": 0.1,
    "pi_rho0": 0.4,
    "pi_span_v": 300.0,
    "pi_decay_v": 150.0,
    "creep_pct_per_decade": 0.0,
}
CH_AXIS = {"alpha_per_v": 3e-3, "b_um_per_v": 0.115, "u_um_per_v": 0.072, "creep_pct_per_decade": 0.0}


def _minor_cycles(center: float, amp: float, cycles: int, n: int = 200) -> np.ndarray:
    phase = np.linspace(0.0, 2.0 * np.pi * cycles, cycles * n + 1)[1:]
    return center + amp * np.sin(phase)


def test_pi_minor_loops_close_and_ch_loops_do_not() -> None:
    """After a big excursion, a repeated minor loop returns to the same point every period (PI only)."""
    lead = np.concatenate([np.linspace(0, 200, 400), np.linspace(200, 50, 300)])
    loops = _minor_cycles(50.0, 30.0, 10)
    v = np.concatenate([lead, loops])
    pi = PIParams.from_shape(0.1, 0.4, 300.0, 16, 150.0)
    x_pi, _ = pi_step(pi, v, pi_rest_state(pi))
    ch = CHParams(3e-3, 0.115, 0.072)
    x_ch, _ = ch_step(ch, v, ch_rest_state(ch))
    ends = len(lead) + 200 * np.arange(1, 11) - 1
    drift_pi = np.ptp(x_pi[ends[1:]])
    drift_ch = np.ptp(x_ch[ends[1:]])
    assert drift_pi < 1e-12
    assert drift_ch > 1e-3, "the Coleman-Hodgdon minor loop drifts (it is the contrast, not a PI property)"
    # the loop is a real loop: the two branches differ at the centre
    period = x_pi[ends[-2] + 1 : ends[-1] + 1]
    assert np.ptp(period) > 0.9 * 0.1 * 60.0 * 0.4


def test_pi_is_exact_across_block_splits_and_wipes_out() -> None:
    pi = PIParams.from_shape(0.1, 0.35, 250.0, 12, None)
    rng = np.random.default_rng(1)
    v = np.cumsum(rng.normal(0, 4, 3000))
    whole, end = pi_step(pi, v, pi_rest_state(pi))
    parts, state = [], pi_rest_state(pi)
    for chunk in np.array_split(v, [1, 7, 700, 701, 2500]):
        x, state = pi_step(pi, chunk, state)
        parts.append(x)
    np.testing.assert_array_equal(np.concatenate(parts), whole)
    np.testing.assert_array_equal(state.plays_v, end.plays_v)
    # wiping out: a large excursion erases the memory of everything smaller before it
    a, _ = pi_step(pi, np.array([300.0, -300.0, 0.0]), pi_step(pi, v[:500], pi_rest_state(pi))[1])
    b, _ = pi_step(pi, np.array([300.0, -300.0, 0.0]), pi_rest_state(pi))
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_pi_branch_slope_rises_from_rho0_to_b() -> None:
    pi = PIParams.from_shape(0.1, 0.4, 200.0, 20, None)
    v = np.concatenate([np.linspace(0, 300, 3001), np.linspace(300, -300, 6001)[1:]])
    x, _ = pi_step(pi, v, pi_rest_state(pi))
    slope = np.diff(x) / np.diff(v)
    after = slope[3000:3005]
    assert after == pytest.approx(0.1 * 0.4, rel=1e-9)
    assert slope[-5:] == pytest.approx(0.1, rel=1e-9)


def test_voltage_driven_power_law_creep() -> None:
    """Creep per decade ~ pct at 1 s and rising like t^beta; driven by b V, not by the hysteretic position."""
    bank = CreepBank.from_law(1.5, 1e-5, 1e5, 4, spectrum_exponent=0.03)
    t = np.array([0.1, 1.0, 10.0, 100.0, 1000.0])
    r = bank.step_response(t)[0]
    per_decade = np.diff(r) * 100
    assert per_decade[1] == pytest.approx(1.5 * 10**0.015, rel=0.05)  # decade 1-10 s, centred at ~3 s
    assert np.all(np.diff(per_decade) > 0), "power-law creep grows faster than log creep"
    flat = CreepBank.from_law(1.5, 1e-5, 1e5, 4).step_response(t)[0]
    assert np.diff(flat) * 100 == pytest.approx(1.5, rel=0.02)
    # voltage drive: creep after a step is proportional to b dV for PI and CH alike
    fs = 1000.0
    v = np.concatenate([np.linspace(0, 100, 50), np.full(5000, 100.0)])
    for axis in (PI_AXIS, CH_AXIS):
        stage = _stage(
            {**axis, "creep_pct_per_decade": 1.5},
            {"tau_min_s": 1e-5, "tau_max_s": 1e5, "drive": "voltage", "spectrum_exponent": 0.0},
        )
        x = stage.step(v[None, :], 1 / fs)[0]
        b = float(axis["b_um_per_v"])
        i_05, i_5 = 50 + int(0.5 * fs), 50 + int(5 * fs) - 1
        assert (x[i_5] - x[i_05]) / (b * 100.0) * 100 == pytest.approx(1.5, rel=0.05)


def test_asymmetric_curvature_changes_the_local_sensitivity() -> None:
    stage = _stage({**PI_AXIS, "pi_rho0": 1.0, "asymmetry_pct": 0.5, "asymmetry_range_v": 200.0})
    v = np.array([[-201.0, -199.0, 199.0, 201.0]])
    x = stage.step(v, 1e-3)[0]
    low, high = (x[1] - x[0]) / 2.0 / 0.1, (x[3] - x[2]) / 2.0 / 0.1
    assert low == pytest.approx(0.995, abs=1e-9)
    assert high == pytest.approx(1.005, abs=1e-9)


def test_amplifier_pole_lags_a_sine_by_atan() -> None:
    tau, f, fs = 2e-4, 200.0, 50_000.0
    stage = _stage(
        {**PI_AXIS, "pi_rho0": 1.0}, effects={"delay": {"lag_time_constant_s": tau, "at": "drive"}}
    )
    t = np.arange(int(0.1 * fs)) / fs
    v = 10.0 * np.sin(2 * np.pi * f * t)
    x = stage.step(v[None, :], 1 / fs)[0]
    tail = slice(len(t) // 2, None)
    z = np.sum(x[tail] * np.exp(-2j * np.pi * f * t[tail])) / np.sum(
        v[tail] * np.exp(-2j * np.pi * f * t[tail])
    )
    assert -np.angle(z) == pytest.approx(np.arctan(2 * np.pi * f * tau), rel=0.02)
    assert abs(z) / 0.1 == pytest.approx(1 / np.hypot(1, 2 * np.pi * f * tau), rel=0.01)


PREISACH = PreisachParams(0.1, 0.4, 90.0, 0.3, 300.0)


def test_preisach_minor_loops_close_branches_increase_and_blocks_split_anywhere() -> None:
    rest = preisach_rest_state(PREISACH)
    assert preisach_position(PREISACH, 0.0, rest) == pytest.approx(0.0, abs=1e-12)
    lead = np.concatenate([np.linspace(0, 200, 400), np.linspace(200, 50, 300)])
    v = np.concatenate([lead, _minor_cycles(50.0, 30.0, 10), np.linspace(50, -230, 700)])
    x, _ = preisach_step(PREISACH, v, rest)
    ends = len(lead) + 200 * np.arange(1, 11) - 1
    assert np.ptp(x[ends[1:]]) < 1e-9
    dv, dx = np.diff(v), np.diff(x)
    moving = np.abs(dv) > 1e-9
    slope = dx[moving] / dv[moving] / PREISACH.b_um_per_v
    assert slope.min() >= PREISACH.rho0 - 1e-9
    for cut in (1, 401, 777, v.size - 1):
        xa, mid = preisach_step(PREISACH, v[:cut], rest)
        xb, _ = preisach_step(PREISACH, v[cut:], mid)
        np.testing.assert_allclose(np.concatenate([xa, xb]), x, rtol=0, atol=1e-12)
    # wiping out: a larger excursion erases the minor loops; the same major branch as without them
    x_plain, _ = preisach_step(PREISACH, np.concatenate([lead, np.linspace(50, 230, 300)]), rest)
    x_loops, _ = preisach_step(
        PREISACH, np.concatenate([lead, _minor_cycles(50.0, 30.0, 3), np.linspace(50, 230, 300)]), rest
    )
    assert x_loops[-1] == pytest.approx(x_plain[-1], abs=1e-10)


def test_preisach_minor_loops_are_not_congruent() -> None:
    """The relay density depends on the relay centre: the same loop is taller at +100 V than at -100 V."""
    rest = preisach_rest_state(PREISACH)
    heights = []
    for offset in (-100.0, 100.0):
        v = np.concatenate([np.linspace(0, offset + 30, 200), _minor_cycles(offset, 30.0, 2)])
        x, _ = preisach_step(PREISACH, v, rest)
        heights.append(np.ptp(x[-200:]))
    assert heights[1] / heights[0] > 1.03


BOUC_WEN = BoucWenParams(0.1, 0.45, 0.012, 0.004)
BOUC_WEN_2 = BoucWenParams(0.1, 0.4, 3.2e-4, 1.2e-4, exponent=2)


@pytest.mark.parametrize("params", [BOUC_WEN, BOUC_WEN_2], ids=["n1", "n2"])
def test_bouc_wen_matches_its_ode_increases_and_blocks_split_anywhere(params: BoucWenParams) -> None:
    rest = boucwen_rest_state(params)
    v = np.concatenate(
        [
            np.linspace(0, 180, 500),
            np.linspace(180, -60, 600),
            _minor_cycles(-60.0, 25.0, 3),
            np.linspace(-60, 120, 400),
        ]
    )
    x, end = boucwen_step(params, v, rest)
    # the closed form against dh = A dV - beta |dV| |h|^(n-1) h - gamma dV |h|^n in fine steps
    a, beta, gamma, n = params.a, params.beta_per_v, params.gamma_per_v, params.exponent

    def dh(hh: float, dv: float) -> float:
        return a * dv - beta * abs(dv) * abs(hh) ** (n - 1) * hh - gamma * dv * abs(hh) ** n

    h, hs = 0.0, [0.0]
    for v0, v1 in itertools.pairwise(v):
        step = (v1 - v0) / 50
        for _ in range(50):
            k1 = dh(h, step)
            k2 = dh(h + 0.5 * k1, step)
            k3 = dh(h + 0.5 * k2, step)
            k4 = dh(h + k3, step)
            h += (k1 + 2 * k2 + 2 * k3 + k4) / 6.0
        hs.append(h)
    np.testing.assert_allclose(x, params.b_um_per_v * (v - np.array(hs)), rtol=0, atol=1e-6)
    dv, dx = np.diff(v), np.diff(x)
    moving = np.abs(dv) > 1e-9
    assert np.all(dx[moving] / dv[moving] > 0)
    for cut in (1, 333, 1100, v.size - 1):
        xa, mid = boucwen_step(params, v[:cut], rest)
        xb, last = boucwen_step(params, v[cut:], mid)
        np.testing.assert_allclose(np.concatenate([xa, xb]), x, rtol=0, atol=1e-12)
        assert last.h_v == pytest.approx(end.h_v, abs=1e-12)
    # not a play law: repeated minor loops do not close exactly (no wiping-out memory)
    ends = 1100 + 200 * np.arange(1, 4) - 1
    assert np.ptp(x[ends]) > 1e-6


def test_presets_load_and_are_other_physics() -> None:
    names = preset_names()
    assert {"stage", "pi-stage", "p885-stage", "preisach-stage", "boucwen-stage"} <= set(names)
    second = StageConfig.from_file(resolve_stage("boucwen-stage") or "")
    assert all(a.law == "bouc-wen" for a in second.axes.values())
    Stage(second).step(np.linspace(0, 50, 30).repeat(3).reshape(30, 3).T, 1e-4)
    knee = StageConfig.from_file(resolve_stage("knee-holdout-stage") or "")
    assert all(a.law == "bouc-wen" and a.bw_exponent == 2 for a in knee.axes.values())
    held_out = StageConfig.from_file(resolve_stage("preisach-stage") or "")
    assert all(a.law == "preisach" for a in held_out.axes.values())
    assert held_out.amplifier_lag_s > 0 and held_out.effects.delay is not None
    Stage(held_out).step(np.zeros((3, 10)), 1e-4)
    for name in ("pi-stage", "p885-stage"):
        path = resolve_stage(name)
        assert path is not None
        cfg = StageConfig.from_file(path)
        assert all(a.law == "prandtl-ishlinskii" for a in cfg.axes.values())
        assert cfg.creep.drive == "voltage"
        Stage(cfg).step(np.zeros((3, 10)), 1e-4)
    with pytest.raises(SimConfigError, match="no such preset"):
        resolve_stage("no-such-stage")


def test_law_fields_are_checked() -> None:
    with pytest.raises(ValueError, match="pi_rho0 and pi_span_v"):
        StageConfig.model_validate({"axes": {"x": {"law": "prandtl-ishlinskii", "b_um_per_v": 0.1}}})
    with pytest.raises(ValueError, match="alpha_per_v and u_um_per_v"):
        StageConfig.model_validate({"axes": {"x": {"b_um_per_v": 0.1}}})


def test_hil_sim_stage_does_not_import_piezod() -> None:
    code = (
        "import sys; import hil_sim.stage, hil_sim.creep, hil_sim.effects, hil_sim.hysteresis;"
        "bad = sorted(m for m in sys.modules if m == 'piezod' or m.startswith('piezod.'));"
        "print(bad); sys.exit(1 if bad else 0)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_a_resonance_steps_through_an_idle_hold_longer_than_its_period() -> None:
    """The board steps the stage through an idle hold in one step of ~0.1 s; a resonance of 1.1 kHz
    used to refuse it ("needs a sample rate above 2442 Hz"), so `piezod sim` died at start-up on a
    preset with a resonance. Long steps are sub-stepped: the same as the input played finely."""
    from hil_sim.effects import ResonanceEffect, resonance_rest_state, resonance_step

    fx = ResonanceEffect(f0_hz=1100.0, q=12.0)
    x = np.array([[0.0, 3.0, 3.0, -1.0]])
    coarse, after = resonance_step(fx, x, 0.1, resonance_rest_state(np.array([0.0])))
    k = 2000
    fine_in = np.concatenate(
        [np.linspace(a, b, k + 1)[1:] for a, b in zip([0.0, *x[0, :-1]], x[0], strict=True)]
    )[None, :]
    fine, fine_after = resonance_step(fx, fine_in, 0.1 / k, resonance_rest_state(np.array([0.0])))
    np.testing.assert_allclose(coarse[0], fine[0, k - 1 :: k], atol=1e-9)
    np.testing.assert_allclose(after.position_um, fine_after.position_um, atol=1e-9)
    np.testing.assert_allclose(after.velocity_um_per_s, fine_after.velocity_um_per_s, atol=1e-6)
