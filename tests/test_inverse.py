"""Inverse (4.2)-(4.12) of the closed-loop model (3.8)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezod.errors import ModelError, RangeUnreachableError
from piezod.model.inverse import ThesisInverse, solve_half_range
from piezod.model.params import ThesisParams
from piezod.model.range_sensitivity import (
    LONG_TUBE_TABLE_2_3,
    MEDIUM_TUBE_TABLE_2_3,
    thesis_params_from_table_2_3,
)
from piezod.model.thesis import MEDIUM_TUBE_TABLE_3_3, loop_constant, scan_range_um, thesis_loop

MEDIUM_TEXT_A3 = ThesisParams(3.23e-3, 0.081, 0.016, 2.666, 0.081, 2.78e-3, 0.681)
LONG_TUBE = thesis_params_from_table_2_3(LONG_TUBE_TABLE_2_3).params
MEDIUM_2_3 = thesis_params_from_table_2_3(MEDIUM_TUBE_TABLE_2_3, np.arange(140.0, 461.0, 20.0)).params
#: A hypothetical stage with b < u (delta < 0): positive Lambert W arguments.
SOFT = ThesisParams(2e-3, 0.05, 0.08, 1.0, 0.05, 1e-3, 0.5)
#: Large alpha V: c2 of (4.4) overflows float64 at these voltages.
STIFF = ThesisParams(0.8, 0.05, 0.04, 1.0, 0.0, 0.0, 0.0)

SETS = {
    "medium_3_3": (MEDIUM_TUBE_TABLE_3_3, (-230.0, 230.0)),
    "medium_text_a3": (MEDIUM_TEXT_A3, (-230.0, 230.0)),
    "long_tube": (LONG_TUBE, (-220.0, 220.0)),
    "medium_2_3": (MEDIUM_2_3, (-230.0, 230.0)),
    "soft": (SOFT, (-300.0, 300.0)),
    "stiff": (STIFF, (-1000.0, 1000.0)),
}


def _max_range(params: ThesisParams, limits: tuple[float, float], f: float, center: float) -> float:
    vh = min(limits[1] - center, center - limits[0])
    return float(scan_range_um(params, f, vh))


@given(
    st.sampled_from(sorted(SETS)),
    st.floats(0.01, 1.0),
    st.floats(math.log(0.01), math.log(10.0)),
    st.floats(-0.8, 0.8),
    st.sampled_from([1, -1]),
)
def test_round_trip_all_sets_ranges_frequencies_offsets(
    name: str, fraction: float, log_f: float, offset: float, direction: int
) -> None:
    params, limits = SETS[name]
    f = math.exp(log_f)
    center = offset * 0.5 * (limits[1] - limits[0]) * 0.5
    range_um = fraction * _max_range(params, limits, f, center)
    inv = ThesisInverse.for_scan(params, range_um, f, v_limits=limits, center_v=center)
    assert inv.range_um == pytest.approx(range_um, rel=1e-12)
    x = inv.to_absolute(np.linspace(0.0, inv.range_um, 501))
    v = inv.voltage(x, direction)
    assert np.all(np.isfinite(v))
    assert inv.v_min <= v.min() and v.max() <= inv.v_max
    assert np.all(np.diff(v) > 0.0)
    err = np.max(np.abs(inv.position(v, direction) - x))
    assert err <= 1e-9 * inv.range_um


def test_forward_is_the_thesis_loop() -> None:
    inv = ThesisInverse.for_voltages(MEDIUM_TUBE_TABLE_3_3, -60.0, 140.0, 0.7)
    v = np.linspace(-60.0, 140.0, 301)
    for d in (1, -1):
        np.testing.assert_allclose(
            inv.position(v, d), thesis_loop(MEDIUM_TUBE_TABLE_3_3, v, d, -60.0, 140.0, 0.7), atol=1e-12
        )


def test_constants_are_the_thesis_constants() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    inv = ThesisInverse.for_voltages(p, -100.0, 100.0, 0.5)
    delta = p.hysteresis.delta_um
    for br, s in ((inv.trace, 1), (inv.retrace, -1)):
        assert br.c1 == pytest.approx(inv.b_hat)
        assert br.c2 == pytest.approx(s * delta * loop_constant(p.alpha_per_v, -100.0, 100.0, s), rel=1e-12)
        assert br.c3 == -s * p.alpha_per_v
        assert br.c4 == pytest.approx(-s * delta)  # symmetric scan: no creep offset
        v = np.linspace(-100.0, 100.0, 11)
        np.testing.assert_allclose(br.position(v), br.c1 * v + br.c2 * np.exp(br.c3 * v) + br.c4, atol=1e-12)


def test_literal_4_11_agrees_where_it_does_not_overflow() -> None:
    from scipy.special import lambertw

    inv = ThesisInverse.for_scan(MEDIUM_TUBE_TABLE_3_3, 25.0, 0.4, v_limits=(-230.0, 230.0), center_v=30.0)
    x = inv.to_absolute(np.linspace(0.0, inv.range_um, 101))
    for d in (1, -1):
        br = inv.branch(d)
        u = (x - br.c4) / br.c1
        v_411 = u - lambertw(br.c2 * br.c3 / br.c1 * np.exp(br.c3 * u)).real / br.c3
        np.testing.assert_allclose(inv.voltage(x, d), v_411, atol=1e-9)


def test_offset_scan_is_centred_on_b_times_centre() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    inv = ThesisInverse.for_scan(p, 20.0, 1.0, v_limits=(-230.0, 230.0), center_v=-50.0)
    assert inv.center_v == pytest.approx(-50.0)
    assert 0.5 * (inv.x_min + inv.x_max) == pytest.approx(p.b_um_per_v * -50.0, abs=1e-12)
    sym = ThesisInverse.for_scan(p, 20.0, 1.0, v_limits=(-230.0, 230.0))
    assert inv.v_half == pytest.approx(sym.v_half, rel=1e-14)  # (4.12) does not depend on the offset
    c = inv.to_absolute(0.0, centred=True)
    assert float(inv.voltage(c, 1)) == pytest.approx(float(sym.voltage(0.0, 1)) - 50.0, abs=1e-9)


def test_range_solve_matches_forward_range_and_starts_like_the_thesis() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    for r in (1.0, 15.0, 35.0):
        vh = solve_half_range(p, r, 0.2, v_limits=(-230.0, 230.0))
        x_t = thesis_loop(p, np.array([-vh, vh]), 1, -vh, vh, 0.2)
        assert x_t[1] - x_t[0] == pytest.approx(r, rel=1e-12)  # h_R of (4.12) is zero


def test_unreachable_range_names_the_numbers() -> None:
    p = MEDIUM_TUBE_TABLE_3_3
    r_max = _max_range(p, (-230.0, 230.0), 1.0, 0.0)
    with pytest.raises(RangeUnreachableError, match=r"largest reachable range there is 4[0-9.]+ um"):
        ThesisInverse.for_scan(p, r_max * 1.01, 1.0, v_limits=(-230.0, 230.0))
    # an offset eats into the reachable range
    ThesisInverse.for_scan(p, 0.9 * r_max, 1.0, v_limits=(-230.0, 230.0))
    with pytest.raises(RangeUnreachableError, match=r"±180 V around 50 V"):
        ThesisInverse.for_scan(p, 0.9 * r_max, 1.0, v_limits=(-230.0, 230.0), center_v=50.0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"range_um": 0.0}, "scan range"),
        ({"range_um": math.nan}, "scan range"),
        ({"frequency_hz": 0.0}, "frequency"),
        ({"center_v": 300.0}, "centre"),
        ({"v_limits": (10.0, -10.0)}, "limits"),
    ],
)
def test_invalid_scan_requests(kwargs: dict[str, object], match: str) -> None:
    args: dict[str, object] = {"range_um": 10.0, "frequency_hz": 1.0, "v_limits": (-230.0, 230.0)}
    args.update(kwargs)
    with pytest.raises(ModelError, match=match):
        ThesisInverse.for_scan(MEDIUM_TUBE_TABLE_3_3, **args)  # type: ignore[arg-type]


def test_targets_outside_the_branch_raise_never_nan() -> None:
    inv = ThesisInverse.for_scan(MEDIUM_TUBE_TABLE_3_3, 10.0, 1.0, v_limits=(-230.0, 230.0))
    for bad in (inv.x_max + 1e-3, inv.x_min - 1e-3, math.nan, math.inf):
        with pytest.raises(ModelError, match="outside the scan branch"):
            inv.voltage(np.array([inv.x_min, bad]), 1)
    with pytest.raises(ModelError, match="direction"):
        inv.voltage(np.array([inv.x_min]), 0)
    with pytest.raises(ModelError, match="direction"):
        inv.voltage(np.array([inv.x_min, inv.x_max]), np.array([1, 2]))
    with pytest.raises(ModelError, match="outside the scan"):
        inv.position(np.array([inv.v_max + 1.0]), 1)
    # rounding-level excursions are accepted and clipped into the voltage range
    v = inv.voltage(np.array([inv.x_min - 1e-12, inv.x_max + 1e-12]), 1)
    assert inv.v_min <= v[0] <= v[1] <= inv.v_max


def test_non_monotone_branch_is_detected_and_can_be_allowed() -> None:
    # creep-free medium tube hysteresis: b > 2 u, so dx/dV < 0 at the start of large loops
    p = ThesisParams(3.23e-3, 0.081, 0.016, 1.0, 0.0, 0.0, 0.0)
    with pytest.raises(ModelError, match=r"trace branch .* is not monotone: dx/dV = -0\.0"):
        ThesisInverse.for_voltages(p, -200.0, 200.0, 1.0)
    inv = ThesisInverse.for_voltages(p, -200.0, 200.0, 1.0, allow_nonmonotone=True)
    assert not inv.trace.monotone and not inv.retrace.monotone
    x = np.linspace(inv.x_min, inv.x_max, 201)
    for d in (1, -1):
        v = inv.voltage(x, d)
        np.testing.assert_allclose(inv.position(v, d), x, atol=1e-9 * inv.range_um)
    # the rising part is reached by jumping over the dip at the branch start
    v_t = inv.voltage(x, 1)
    assert v_t[0] - inv.v_min > 50.0
    assert ThesisInverse.for_voltages(p, -20.0, 20.0, 1.0).trace.monotone


def test_per_sample_directions_match_the_scalar_paths() -> None:
    inv = ThesisInverse.for_scan(MEDIUM_TUBE_TABLE_3_3, 30.0, 1.0, v_limits=(-230.0, 230.0))
    rng = np.random.default_rng(5)
    x = inv.to_absolute(rng.uniform(0.0, inv.range_um, 400))
    v_t, v_r = inv.voltage(x, 1), inv.voltage(x, -1)
    few = np.where(np.arange(400) < 150, 1, -1)
    many = rng.choice([1, -1], 400)
    for d in (few, many, np.ones(400, dtype=np.int8)):
        np.testing.assert_array_equal(inv.voltage(x, d), np.where(d > 0, v_t, v_r))
        np.testing.assert_allclose(inv.position(inv.voltage(x, d), d), x, atol=1e-12)
    assert inv.voltage(x.reshape(20, 20), 1).shape == (20, 20)
    assert inv.voltage(np.empty(0), 1).shape == (0,)


def test_parameters_whose_4_4_constant_overflows() -> None:
    inv = ThesisInverse.for_scan(STIFF, 20.0, 1.0, v_limits=(-3000.0, 3000.0), center_v=1500.0)
    assert math.isinf(inv.trace.c2)  # the literal (4.4) constant overflows ...
    x = inv.to_absolute(np.linspace(0.0, inv.range_um, 201))
    for d in (1, -1):  # ... the relative form does not
        v = inv.voltage(x, d)
        np.testing.assert_allclose(inv.position(v, d), x, atol=1e-9 * inv.range_um)
