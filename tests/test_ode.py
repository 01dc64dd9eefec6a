"""The exact per-sample solution of the hysteresis ODE (2.21)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezod.model import HysteresisParams, HysteresisState, hysteresis_step, relaxed_state

LONG_TUBE = HysteresisParams(alpha_per_v=3.44e-3, b_um_per_v=0.64, u_um_per_v=0.38)


def _naive(p: HysteresisParams, v: np.ndarray, st0: HysteresisState) -> np.ndarray:
    y = st0.position_um - p.b_um_per_v * st0.voltage_v
    prev = st0.voltage_v
    out = []
    for vv in v:
        a = np.exp(-p.alpha_per_v * abs(vv - prev))
        y = a * y + np.sign(vv - prev) * p.delta_um * (a - 1.0)
        out.append(y + p.b_um_per_v * vv)
        prev = vv
    return np.array(out)


@given(
    st.lists(st.floats(-300, 300), min_size=1, max_size=200),
    st.floats(-300, 300),
    st.floats(-50, 50),
)
def test_matches_sample_by_sample_recurrence(volts: list[float], v0: float, dy: float) -> None:
    v = np.array(volts)
    st0 = HysteresisState(v0, LONG_TUBE.b_um_per_v * v0 + dy)
    x, _ = hysteresis_step(LONG_TUBE, v, st0)
    np.testing.assert_allclose(x, _naive(LONG_TUBE, v, st0), atol=1e-9, rtol=1e-12)


def test_blocks_compose() -> None:
    rng = np.random.default_rng(1)
    v = np.cumsum(rng.normal(0, 20, 5000))
    s0 = relaxed_state(LONG_TUBE)
    whole, end = hysteresis_step(LONG_TUBE, v, s0)
    a, mid = hysteresis_step(LONG_TUBE, v[:1234], s0)
    b, end2 = hysteresis_step(LONG_TUBE, v[1234:], mid)
    np.testing.assert_allclose(np.concatenate([a, b]), whole, atol=1e-9)
    assert end2.position_um == pytest.approx(end.position_um, abs=1e-9)


def test_steady_loop_is_the_closed_solution_2_24() -> None:
    vm, vM = -150.0, 250.0
    up = np.linspace(vm, vM, 2001)[1:]
    down = np.linspace(vM, vm, 2001)[1:]
    v = np.concatenate([np.linspace(0, vM, 500), *([down, up] * 8)])
    x, _ = hysteresis_step(LONG_TUBE, v, relaxed_state(LONG_TUBE))
    a, b, d = LONG_TUBE.alpha_per_v, LONG_TUBE.b_um_per_v, LONG_TUBE.delta_um
    c_t = 2.0 / (np.exp(-a * vm) + np.exp(-a * vM))
    x_t = b * up - d * (1.0 - c_t * np.exp(-a * up))
    np.testing.assert_allclose(x[-up.size :], x_t, atol=1e-7)
