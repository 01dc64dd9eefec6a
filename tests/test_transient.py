"""Transients after an offset / range change (5.1)-(5.9), against the exact ODE."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezod.errors import ModelError
from piezod.model import HysteresisParams, HysteresisState, hysteresis_loop, hysteresis_step
from piezod.model.range_sensitivity import LONG_TUBE_TABLE_2_3
from piezod.model.thesis import MEDIUM_TUBE_TABLE_3_3
from piezod.model.transient import (
    convergence_ratio,
    first_retrace,
    first_trace,
    loops_to_settle,
    retrace_difference,
    retrace_end_position,
    steady_fraction,
    steady_state,
)

LONG = LONG_TUBE_TABLE_2_3.hysteresis


def _turning_points(
    p: HysteresisParams, start: HysteresisState, vm: float, vM: float, loops: int
) -> np.ndarray:
    """Exact ODE positions at the turning points V'_M, V'_m, V'_M, ... (linear ramps between them)."""
    v = np.tile([vM, vm], loops)
    x, _ = hysteresis_step(p, v, start)
    return x


def test_first_trace_and_retrace_are_the_ode() -> None:
    start = steady_state(LONG, -160.0, 0.0, -160.0, -1)
    up = np.linspace(-160.0, 80.0, 2001)[1:]
    down = np.linspace(80.0, -80.0, 1001)[1:]
    x, _ = hysteresis_step(LONG, np.concatenate([up, down]), start)
    np.testing.assert_allclose(first_trace(LONG, start, up), x[: up.size], atol=1e-10)
    np.testing.assert_allclose(first_retrace(LONG, start, 80.0, down), x[up.size :], atol=1e-10)


@given(
    st.floats(-200.0, 0.0),
    st.floats(10.0, 300.0),
    st.floats(-30.0, 30.0),
    st.floats(-250.0, 0.0),
)
def test_retrace_ends_5_4_match_the_ode(vm: float, v_range: float, dy: float, v0: float) -> None:
    vM = vm + v_range
    v0 = min(v0, vM)
    start = HysteresisState(v0, LONG.b_um_per_v * v0 + dy)
    x = _turning_points(LONG, start, vm, vM, 20)
    n = np.arange(1, 21)
    np.testing.assert_allclose(retrace_end_position(LONG, start, vm, vM, n), x[1::2], atol=1e-9)


def test_closed_loop_limit_and_5_6() -> None:
    vm, vM = -80.0, 80.0
    start = steady_state(LONG, -160.0, 0.0, -160.0, -1)
    x_inf = float(retrace_end_position(LONG, start, vm, vM, 10_000))
    assert x_inf == pytest.approx(float(hysteresis_loop(LONG, vm, -1, vm, vM)), abs=1e-12)
    a = LONG.alpha_per_v
    assert steady_fraction(LONG, vm, vM) == pytest.approx(
        1.0 - 2.0 * math.exp(a * vm) / (math.exp(a * vm) + math.exp(a * vM)), rel=1e-14
    )
    q = convergence_ratio(LONG, vm, vM)
    assert q == pytest.approx(math.exp(-2.0 * a * 160.0))
    assert steady_fraction(LONG, vm, vM) == pytest.approx((1.0 - math.sqrt(q)) ** 2 / (1.0 - q))


def test_successive_loops_shrink_by_q_5_7_5_8() -> None:
    vm, vM = -80.0, 80.0
    start = steady_state(LONG, -160.0, 0.0, -160.0, -1)
    up = np.linspace(-160.0, vM, 241)[1:]
    down = np.linspace(vM, vm, 161)[1:]
    up2 = np.linspace(vm, vM, 161)[1:]
    v = np.concatenate([up, down, *([up2, down] * 6)])
    x, _ = hysteresis_step(LONG, v, start)
    retraces = [x[up.size + k * 320 : up.size + k * 320 + 160] for k in range(7)]
    q = convergence_ratio(LONG, vm, vM)
    d1 = retraces[1] - retraces[0]
    for n in range(1, 6):
        dn = retraces[n] - retraces[n - 1]
        np.testing.assert_allclose(dn, q ** (n - 1) * d1, atol=1e-10)  # (5.7)
        np.testing.assert_allclose(retrace_difference(LONG, start, vm, vM, down, n), dn, atol=1e-10)
    assert (retraces[3] - retraces[2])[50] / d1[50] == pytest.approx(
        math.exp(-2 * LONG.alpha_per_v * 160 * 2)
    )


def _assert_settles_first_at(
    p: HysteresisParams, start: HysteresisState, vm: float, vM: float, pixel: float, lines: int, n: int
) -> None:
    """Brute force with the exact ODE: loop n is the first whose next ``lines`` loops stay within a pixel."""
    x = _turning_points(p, start, vm, vM, n + lines + 1)
    top = x[0::2]  # V'_M: the worst point of each loop
    assert abs(top[n - 1 + lines] - top[n - 1]) < pixel * (1 + 1e-9)
    if n > 1:
        assert abs(top[n - 2 + lines] - top[n - 2]) >= pixel * (1 - 1e-9)


@given(st.floats(20.0, 200.0), st.floats(-0.9, 1.0), st.sampled_from([1, 16, 512]))
def test_loops_to_settle_5_9_matches_brute_force(v_range: float, shift_rel: float, lines: int) -> None:
    shift = shift_rel * v_range
    vm_old, vM_old = -0.5 * v_range, 0.5 * v_range
    vm, vM = vm_old + shift, vM_old + shift
    start = steady_state(LONG, vm_old, vM_old, vm_old, -1)
    r = float(hysteresis_loop(LONG, vM, 1, vm, vM) - hysteresis_loop(LONG, vm, 1, vm, vM))
    pixel = r / 512
    n = loops_to_settle(LONG, vm, vM, start=start, pixel_um=pixel, lines=lines)
    _assert_settles_first_at(LONG, start, vm, vM, pixel, lines, n)


def test_retrace_start_is_the_mirrored_problem() -> None:
    start = steady_state(LONG, -50.0, 50.0, 50.0, 1)  # left at the top, moving down
    vm, vM = 20.0, 120.0
    mirrored = HysteresisState(-start.voltage_v, -start.position_um)
    r = float(hysteresis_loop(LONG, vM, 1, vm, vM) - hysteresis_loop(LONG, vm, 1, vm, vM))
    n = loops_to_settle(LONG, vm, vM, start=start, pixel_um=r / 512, direction=-1)
    assert n > 1
    _assert_settles_first_at(LONG, mirrored, -vM, -vm, r / 512, 512, n)


def test_thesis_offset_change_example() -> None:
    """Section 5.1: offset -80 V -> 0 V on the long tube, left at the lower turning point.

    The scan range is not stated; for the range of figure 5.2 (160 V p-p) (5.9) gives 6 loops
    (5 measured at V'_m as in (5.4)); the thesis's "9 loops" corresponds to a 100 V p-p scan.
    """
    for v_half, expected_worst, expected_low in ((80.0, 6, 5), (50.0, 9, 9)):
        vm, vM = -v_half, v_half
        start = steady_state(LONG, vm - 80.0, vM - 80.0, vm - 80.0, -1)
        r = float(hysteresis_loop(LONG, vM, 1, vm, vM) - hysteresis_loop(LONG, vm, 1, vm, vM))
        assert loops_to_settle(LONG, vm, vM, start=start, pixel_um=r / 512) == expected_worst
        assert loops_to_settle(LONG, vm, vM, start=start, pixel_um=r / 512, voltage_v=vm) == expected_low


def test_thesis_params_are_accepted_and_creep_ignored() -> None:
    start = HysteresisState(-100.0, -5.0)
    n1 = loops_to_settle(MEDIUM_TUBE_TABLE_3_3, -50.0, 50.0, start=start, pixel_um=0.01)
    n2 = loops_to_settle(MEDIUM_TUBE_TABLE_3_3.hysteresis, -50.0, 50.0, start=start, pixel_um=0.01)
    assert n1 == n2 > 1


def test_invalid_inputs_raise() -> None:
    start = HysteresisState(100.0, 0.0)
    with pytest.raises(ModelError, match="above the new upper turning point"):
        retrace_end_position(LONG, start, -50.0, 50.0, 1)
    with pytest.raises(ModelError, match="pixel"):
        loops_to_settle(LONG, -50.0, 50.0, start=HysteresisState(0.0, 0.0), pixel_um=0.0)
    with pytest.raises(ModelError, match="v_max > v_min"):
        convergence_ratio(LONG, 10.0, -10.0)
    with pytest.raises(ModelError, match=">= 1"):
        retrace_end_position(LONG, HysteresisState(0.0, 0.0), -50.0, 50.0, 0)
    with pytest.raises(ModelError, match="direction"):
        loops_to_settle(LONG, -50.0, 50.0, start=HysteresisState(0.0, 0.0), pixel_um=0.1, direction=0)
