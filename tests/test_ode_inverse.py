"""Per-sample inverse of the exact hysteresis ODE step."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezod.errors import ModelError
from piezod.model import HysteresisParams, HysteresisState, hysteresis_step, relaxed_state
from piezod.model.inverse import ThesisInverse
from piezod.model.ode import hysteresis_inverse_step
from piezod.model.params import ThesisParams

LONG_TUBE = HysteresisParams(alpha_per_v=3.44e-3, b_um_per_v=0.64, u_um_per_v=0.38)
#: b > 2 u: branches dip backwards after a reversal.
NON_MONOTONE = HysteresisParams(alpha_per_v=3.23e-3, b_um_per_v=0.081, u_um_per_v=0.016)
#: b < u: delta < 0, positive Lambert W arguments.
SOFT = HysteresisParams(alpha_per_v=2e-3, b_um_per_v=0.05, u_um_per_v=0.08)
STIFF = HysteresisParams(alpha_per_v=0.8, b_um_per_v=0.05, u_um_per_v=0.04)
ALL = [LONG_TUBE, NON_MONOTONE, SOFT, STIFF]


def _round_trip_error(p: HysteresisParams, targets: np.ndarray, state: HysteresisState) -> float:
    v, _ = hysteresis_inverse_step(p, targets, state)
    assert np.all(np.isfinite(v))
    x, _ = hysteresis_step(p, v, state)
    return float(np.max(np.abs(x - targets)))


@given(
    st.sampled_from(ALL),
    st.lists(st.floats(-5.0, 5.0), min_size=1, max_size=300),
    st.floats(-200.0, 200.0),
    st.floats(-20.0, 20.0),
)
def test_forward_of_inverse_reaches_every_target(
    p: HysteresisParams, steps: list[float], v0: float, dy: float
) -> None:
    state = HysteresisState(v0, p.b_um_per_v * v0 + dy)
    targets = state.position_um + np.cumsum(steps)
    scale = max(float(np.ptp(np.append(targets, state.position_um))), 1.0)
    assert _round_trip_error(p, targets, state) <= 1e-9 * scale


@pytest.mark.parametrize("p", ALL)
def test_triangular_targets_many_periods(p: HysteresisParams) -> None:
    up = np.linspace(-10.0, 10.0, 401)[1:]
    tri = np.concatenate([np.linspace(0.0, 10.0, 201), *([up[::-1], up] * 6)])
    assert _round_trip_error(p, tri, relaxed_state(p)) <= 1e-9 * 20.0


def test_inverse_of_forward_recovers_voltages_and_matches_closed_loop_inverse() -> None:
    p = LONG_TUBE
    v_line = np.concatenate([np.linspace(-100.0, 100.0, 501)[1:], np.linspace(100.0, -100.0, 501)[1:]])
    x, _ = hysteresis_step(p, np.tile(v_line, 24), relaxed_state(p, -100.0))
    v, _ = hysteresis_inverse_step(p, x, relaxed_state(p, -100.0))
    np.testing.assert_allclose(v, np.tile(v_line, 24), atol=1e-9)
    # after 24 loops (q = 0.25 per loop) the ODE inverse is the closed-loop inverse (4.11)
    creep_free = ThesisParams(p.alpha_per_v, p.b_um_per_v, p.u_um_per_v, 1.0, 0.0, 0.0, 0.0)
    inv = ThesisInverse.for_voltages(creep_free, -100.0, 100.0, 1.0)
    last = x[-v_line.size :]
    direction = np.where(np.arange(v_line.size) < 500, 1, -1)
    np.testing.assert_allclose(inv.voltage(np.clip(last, inv.x_min, inv.x_max), direction), v_line, atol=1e-8)


@pytest.mark.parametrize("cut", [1, 17, 600, 999])
def test_state_carries_across_blocks(cut: int) -> None:
    rng = np.random.default_rng(cut)
    targets = np.cumsum(rng.normal(0.0, 0.5, 1000))
    s0 = relaxed_state(NON_MONOTONE, 20.0)
    whole, end = hysteresis_inverse_step(NON_MONOTONE, targets, s0)
    a, mid = hysteresis_inverse_step(NON_MONOTONE, targets[:cut], s0)
    b, end2 = hysteresis_inverse_step(NON_MONOTONE, targets[cut:], mid)
    np.testing.assert_allclose(np.concatenate([a, b]), whole, atol=1e-9)
    assert end2.voltage_v == pytest.approx(end.voltage_v, abs=1e-9)


def test_many_runs_and_few_runs_paths_agree() -> None:
    rng = np.random.default_rng(9)
    targets = np.cumsum(rng.normal(0.0, 1.0, 300))  # ~150 runs: the repeat path
    s0 = relaxed_state(LONG_TUBE)
    whole, _ = hysteresis_inverse_step(LONG_TUBE, targets, s0)
    pieces, state = [], s0
    for i in range(0, 300, 5):  # <= 5 runs per call: the sliced path
        v, state = hysteresis_inverse_step(LONG_TUBE, targets[i : i + 5], state)
        pieces.append(v)
    np.testing.assert_allclose(np.concatenate(pieces), whole, atol=1e-9)


def test_held_targets_hold_the_voltage() -> None:
    s0 = HysteresisState(12.0, 5.0)
    v, end = hysteresis_inverse_step(NON_MONOTONE, np.array([5.0, 5.0, 5.0]), s0)
    np.testing.assert_array_equal(v, [12.0, 12.0, 12.0])
    assert end == HysteresisState(12.0, 5.0)
    v, _ = hysteresis_inverse_step(LONG_TUBE, np.array([5.0, 6.0, 6.0, 6.0, 7.0]), s0)
    assert v[0] == 12.0 and v[2] == v[1] == v[3] and v[4] > v[3]


def test_non_monotone_reversal_jumps_over_the_dip() -> None:
    p = NON_MONOTONE
    # a long run down leaves the state near the upper asymptote: B > 1 for the next run up
    v_down = np.linspace(200.0, -200.0, 2001)
    _, s = hysteresis_step(p, v_down, relaxed_state(p, 200.0))
    eta = s.position_um - p.b_um_per_v * s.voltage_v
    big_b = p.alpha_per_v * (eta + p.delta_um) / p.b_um_per_v
    assert big_b > 1.0
    dip = p.b_um_per_v / p.alpha_per_v * (big_b - 1.0 - np.log(big_b))
    targets = s.position_um + np.array([1e-6, 0.1, 0.2])
    v, _ = hysteresis_inverse_step(p, targets, s)
    # the first target, 1 pm above the state, needs a finite voltage step past the dip ...
    assert v[0] - s.voltage_v > 10.0
    # ... through which the stage moves backwards by the predicted dip
    v_path = np.linspace(s.voltage_v, v[0], 20001)
    x_path, _ = hysteresis_step(p, v_path, s)
    assert s.position_um - x_path.min() == pytest.approx(dip, rel=1e-3)
    x, _ = hysteresis_step(p, v, s)
    np.testing.assert_allclose(x, targets, atol=1e-12)


def test_state_outside_the_major_loop_uses_positive_arguments() -> None:
    s0 = HysteresisState(0.0, 100.0)  # far above the asymptotes: B < 0 going down
    targets = np.linspace(99.0, 0.0, 50)
    assert _round_trip_error(LONG_TUBE, targets, s0) <= 1e-9 * 100.0


def test_non_finite_targets_raise() -> None:
    with pytest.raises(ModelError, match="not finite"):
        hysteresis_inverse_step(LONG_TUBE, np.array([1.0, np.nan]), relaxed_state(LONG_TUBE))
    with pytest.raises(ValueError, match="1-D"):
        hysteresis_inverse_step(LONG_TUBE, np.zeros((2, 2)), relaxed_state(LONG_TUBE))
    v, s = hysteresis_inverse_step(LONG_TUBE, np.empty(0), relaxed_state(LONG_TUBE, 3.0))
    assert v.size == 0 and s == relaxed_state(LONG_TUBE, 3.0)


def test_creep_term_inverse_is_the_thesis_inverse_in_steady_state() -> None:
    """With kappa = b_hat - b the per-sample inverse converges to the closed-form (3.8) inverse."""
    from piezod.model import ThesisParams, hysteresis_step, relaxed_state
    from piezod.model.inverse import ThesisInverse

    p = ThesisParams(3.23e-3, 0.081, 0.016, 2.666, 0.081, 2.78e-3, 0.872)
    inv = ThesisInverse.for_scan(p, 20.0, 1.0, v_limits=(-230.0, 230.0), center_v=20.0)
    kappa = inv.b_hat - p.b_um_per_v
    n = 2000
    phase = (np.arange(8 * n) % n) / n
    tri = np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    direction = np.where(phase < 0.5, 1, -1)
    x_abs = p.b_um_per_v * inv.center_v + (tri - 0.5) * 20.0
    start = relaxed_state(p.hysteresis, inv.v_min)
    v, _ = hysteresis_inverse_step(p.hysteresis, x_abs + kappa * inv.center_v, start, kappa_um_per_v=kappa)
    np.testing.assert_allclose(v[-n:], inv.voltage(x_abs[-n:], direction[-n:]), atol=1e-4)
    x_h, _ = hysteresis_step(p.hysteresis, v, start)
    np.testing.assert_allclose(x_h + kappa * v, x_abs + kappa * inv.center_v, atol=1e-9)


def test_creep_term_must_keep_the_branch_invertible() -> None:
    from piezod.errors import ModelError
    from piezod.model import relaxed_state

    p = HysteresisParams(3e-3, 0.1, 0.06)
    with pytest.raises(ModelError, match="b \\+ kappa"):
        hysteresis_inverse_step(p, np.array([1.0]), relaxed_state(p), kappa_um_per_v=-0.2)
