"""The closed-loop model: loop (2.24), tilt (2.29), creep (3.1)-(3.8), range dependence (2.30)-(2.34)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezod.errors import ModelError
from piezod.model import (
    HysteresisParams,
    ThesisParams,
    creep_factor,
    effective_sensitivity,
    hysteresis_loop,
    max_creep_um,
    thesis_loop,
    tilt,
)
from piezod.model.range_sensitivity import (
    LONG_TUBE_RANGES_V,
    LONG_TUBE_TABLE_2_3,
    MEDIUM_TUBE_TABLE_2_3,
    enhanced_loop,
    enhanced_scan_range_um,
    range_sensitivity_loop,
    sensitivity_exponential,
    sensitivity_log,
    sensitivity_quadratic,
    thesis_params_from_table_2_3,
)
from piezod.model.thesis import MEDIUM_TUBE_TABLE_3_3, scan_range_um

LONG = LONG_TUBE_TABLE_2_3.hysteresis


def test_loop_closes_at_both_turning_points_2_23() -> None:
    for vm, vM in ((-220.0, 220.0), (-160.0, 0.0), (30.0, 90.0)):
        ends = np.array([vm, vM])
        np.testing.assert_allclose(
            hysteresis_loop(LONG, ends, 1, vm, vM), hysteresis_loop(LONG, ends, -1, vm, vM)
        )


def test_loop_is_the_literal_2_24() -> None:
    a, b, d = LONG.alpha_per_v, LONG.b_um_per_v, LONG.delta_um
    vm, vM = -100.0, 150.0
    v = np.linspace(vm, vM, 101)
    for s in (1, -1):
        lit = b * v - s * d * (1 - 2 / (np.exp(-s * a * vm) + np.exp(-s * a * vM)) * np.exp(-s * a * v))
        np.testing.assert_allclose(hysteresis_loop(LONG, v, s, vm, vM), lit, atol=1e-12)


def test_tilt_2_29_limits_u_small_range_b_large_range() -> None:
    assert float(tilt(LONG, 0.0)) == pytest.approx(LONG.u_um_per_v, rel=1e-12)
    assert float(tilt(LONG, 1e-3)) == pytest.approx(LONG.u_um_per_v, rel=1e-6)
    big = 1e6  # tanh -> 1: s = b - (b - u) / (alpha V_M) -> b
    assert float(tilt(LONG, big)) == pytest.approx(LONG.b_um_per_v - LONG.delta_um / big, rel=1e-14)
    assert float(tilt(LONG, 1e12)) == pytest.approx(LONG.b_um_per_v, rel=1e-9)
    vm = np.linspace(0.5, 2000.0, 400)
    s = tilt(LONG, vm)
    assert np.all(np.diff(s) > 0)  # monotone transition u -> b
    assert np.all((s > LONG.u_um_per_v) & (s < LONG.b_um_per_v))


@given(st.floats(1.0, 500.0))
def test_tilt_is_the_slope_between_turning_points(v_half: float) -> None:
    ends = hysteresis_loop(LONG, np.array([-v_half, v_half]), 1, -v_half, v_half)
    assert float(tilt(LONG, v_half)) == pytest.approx((ends[1] - ends[0]) / (2 * v_half), rel=1e-10)


def test_max_creep_3_1_is_distance_to_b_v() -> None:
    for vm, vM in ((-100.0, 100.0), (-20.0, 180.0)):
        x_top = float(hysteresis_loop(LONG, vM, 1, vm, vM))
        vc = 0.5 * (vm + vM)
        # offset scans: the distance is measured from the loop centre (b V_C, point symmetry)
        assert max_creep_um(LONG, vm, vM) == pytest.approx(
            LONG.b_um_per_v * (vM - vc) - (x_top - LONG.b_um_per_v * vc)
        )


def test_creep_model_3_5_to_3_8_symmetric_scan_is_the_literal_formula() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    f, vM = 0.6, 150.0
    k = (1 - p.a1 * np.exp(-1 / (f * p.tau_s))) * (p.a2_per_v * vM + p.a3)
    assert creep_factor(p, f, vM) == pytest.approx(k)
    d = max_creep_um(p.hysteresis, -vM, vM)
    b_hat = p.b_um_per_v + k * d / vM
    assert effective_sensitivity(p, f, -vM, vM) == pytest.approx(b_hat)
    v = np.linspace(-vM, vM, 51)
    a, delta = p.alpha_per_v, p.hysteresis.delta_um
    for s in (1, -1):
        c = 2 / (np.exp(s * a * vM) + np.exp(-s * a * vM))
        lit = b_hat * v - s * delta * (1 - c * np.exp(-s * a * v))
        np.testing.assert_allclose(thesis_loop(p, v, s, -vM, vM, f), lit, atol=1e-12)


@given(st.floats(-150.0, 150.0), st.floats(5.0, 80.0), st.floats(0.05, 5.0))
def test_offset_scan_is_a_translated_symmetric_scan(center: float, v_half: float, f: float) -> None:
    """Section 3.3: the loop shape does not depend on the offset; its centre is (V_C, b V_C)."""
    p = MEDIUM_TUBE_TABLE_3_3
    u = np.linspace(-v_half, v_half, 21)
    for s in (1, -1):
        off = thesis_loop(p, center + u, s, center - v_half, center + v_half, f)
        sym = thesis_loop(p, u, s, -v_half, v_half, f)
        np.testing.assert_allclose(off - p.b_um_per_v * center, sym, atol=1e-9)


def test_loop_is_point_symmetric_about_its_centre() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    vm, vM, f = -40.0, 160.0, 1.0
    vc, u = 60.0, np.linspace(0, 100.0, 11)
    xc = p.b_um_per_v * vc
    t = thesis_loop(p, vc + u, 1, vm, vM, f) - xc
    r = thesis_loop(p, vc - u, -1, vm, vM, f) - xc
    np.testing.assert_allclose(t, -r, atol=1e-12)


def test_scan_range_is_the_forward_range_4_12() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    for vm, vM, f in ((-86.25, 86.25, 0.2), (-30.0, 170.0, 1.4), (0.0, 1.0, 0.1)):
        x = thesis_loop(p, np.array([vm, vM]), 1, vm, vM, f)
        assert float(scan_range_um(p, f, 0.5 * (vM - vm))) == pytest.approx(x[1] - x[0], rel=1e-12)
    with pytest.raises(ModelError, match="frequency"):
        scan_range_um(p, 0.0, 10.0)
    with pytest.raises(ModelError, match="frequency"):
        creep_factor(p, -1.0, 10.0)


def test_creep_raises_sensitivity_more_at_low_frequency() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    b_slow = effective_sensitivity(p, 0.1, -100.0, 100.0)
    b_fast = effective_sensitivity(p, 1.4, -100.0, 100.0)
    assert b_slow > b_fast > p.b_um_per_v


def test_sensitivity_laws_2_30_to_2_32() -> None:
    vr = np.array([10.0, 100.0, 400.0])
    np.testing.assert_allclose(sensitivity_quadratic(0.5, 1e-4, 1e-7, vr), 0.5 + 1e-4 * vr + 1e-7 * vr**2)
    np.testing.assert_allclose(sensitivity_log(0.5, 0.01, 2.0, vr), 0.5 + 0.01 * np.log(vr - 2.0))
    np.testing.assert_allclose(
        sensitivity_exponential(0.64, 0.18, 3.04e-3, vr), 0.64 - 0.18 * np.exp(-3.04e-3 * vr)
    )
    with pytest.raises(ModelError, match="a_4"):
        sensitivity_log(0.5, 0.01, 20.0, vr)


def test_enhanced_model_2_34_long_tube_spans_the_thesis_ranges() -> None:
    """Table 2.3: 5-440 V p-p correspond to about 1-160 um."""
    r = enhanced_scan_range_um(LONG_TUBE_TABLE_2_3, np.array([5.0, 50.0, 440.0]))
    assert r[0] == pytest.approx(1.0, abs=0.1)
    assert r[1] == pytest.approx(11.3, abs=0.1)  # "12 um"
    assert r[2] == pytest.approx(164.2, abs=0.1)  # "160 um"
    v = np.linspace(-220.0, 220.0, 41)
    loop = enhanced_loop(LONG_TUBE_TABLE_2_3, v, 1, -220.0, 220.0)
    b3 = float(LONG_TUBE_TABLE_2_3.sensitivity(440.0))
    np.testing.assert_allclose(loop, range_sensitivity_loop(LONG, b3, v, 1, -220.0, 220.0))
    assert loop[-1] - loop[0] == pytest.approx(r[2])
    assert MEDIUM_TUBE_TABLE_2_3.hysteresis.b_um_per_v == 0.18


def test_7_parameter_approximation_of_2_34_for_the_long_tube() -> None:
    approx = thesis_params_from_table_2_3(LONG_TUBE_TABLE_2_3)
    p = approx.params
    assert p.a1 == 0.0 and (p.alpha_per_v, p.b_um_per_v, p.u_um_per_v) == (3.44e-3, 0.64, 0.38)
    assert 0.030 < approx.max_error_rel < 0.034
    vr = np.array(LONG_TUBE_RANGES_V)
    dev = (scan_range_um(p, 0.1, vr / 2) - enhanced_scan_range_um(LONG_TUBE_TABLE_2_3, vr)) / 2
    rel = dev / enhanced_scan_range_um(LONG_TUBE_TABLE_2_3, vr)
    assert float(np.max(np.abs(rel))) == pytest.approx(approx.max_error_rel, rel=1e-9)
    # the plain loop (a2 = a3 = 0) would be far worse
    plain = ThesisParams(3.44e-3, 0.64, 0.38, 1.0, 0.0, 0.0, 0.0)
    dev0 = (scan_range_um(plain, 0.1, vr / 2) - enhanced_scan_range_um(LONG_TUBE_TABLE_2_3, vr)) / 2
    rel0 = np.abs(dev0 / enhanced_scan_range_um(LONG_TUBE_TABLE_2_3, vr))
    assert rel0[0] == pytest.approx(0.44, abs=0.01) and rel0[-1] == pytest.approx(0.063, abs=0.001)


def test_range_sensitivity_params_validate() -> None:
    with pytest.raises(ModelError):
        type(LONG_TUBE_TABLE_2_3)(3e-3, -0.1, 0.3, 0.1, 1e-3)
    with pytest.raises(ModelError):
        type(LONG_TUBE_TABLE_2_3)(3e-3, 0.6, 0.3, float("nan"), 1e-3)
    assert isinstance(LONG_TUBE_TABLE_2_3.hysteresis, HysteresisParams)
