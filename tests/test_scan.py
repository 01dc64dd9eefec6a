"""Raster scan generation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezod.errors import SafetyError
from piezod.scan import RasterGenerator, RasterParams, move_profile, slew_limit

FS = 10_000.0


def _all(gen: RasterGenerator, block: int = 777) -> dict[str, np.ndarray]:
    out: dict[str, list[np.ndarray]] = {}
    while not gen.done:
        b = gen.next_block(block)
        for name in ("fast_um", "slow_um", "x_um", "y_um", "fast_direction", "line", "frame"):
            out.setdefault(name, []).append(getattr(b, name))
    return {k: np.concatenate(v) for k, v in out.items()}


def test_fast_axis_is_a_triangle_with_trace_and_retrace() -> None:
    p = RasterParams(range_um=10.0, line_rate_hz=10.0, lines=4)
    gen = RasterGenerator(p, FS)
    assert gen.total_samples() == 4000
    s = _all(gen)
    assert s["fast_um"].size == 4000
    assert s["fast_um"].min() == pytest.approx(-5.0) and s["fast_um"].max() == pytest.approx(5.0, abs=0.02)
    trace = s["fast_direction"] == 1
    assert np.all(np.diff(s["fast_um"][:500]) > 0) and np.all(np.diff(s["fast_um"][500:1000]) < 0)
    assert trace.sum() == 2000
    assert np.array_equal(np.unique(s["line"]), np.arange(4))


def test_block_size_does_not_change_the_trajectory() -> None:
    p = RasterParams(range_um=7.0, line_rate_hz=3.3, lines=5, rotation_deg=17.0, slow_mode="ramp")
    a = _all(RasterGenerator(p, FS), block=1000)
    b = _all(RasterGenerator(p, FS), block=313)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def test_slow_axis_steps_are_slew_limited_not_jumps() -> None:
    p = RasterParams(range_um=10.0, line_rate_hz=10.0, lines=11, slow_step_fraction=0.05)
    s = _all(RasterGenerator(p, FS))
    step = 10.0 / 10
    max_jump = np.max(np.abs(np.diff(s["slow_um"])))
    assert max_jump < step / 20  # spread over >= 50 samples
    # Each line sits on its row outside the step window.
    assert s["slow_um"][400] == pytest.approx(-5.0) and s["slow_um"][-1] == pytest.approx(5.0)


def test_rotation_and_offset_map_the_image_frame_onto_the_axes() -> None:
    p = RasterParams(
        range_um=4.0, line_rate_hz=10.0, lines=3, rotation_deg=90.0, offset_x_um=1.0, offset_y_um=-2.0
    )
    s = _all(RasterGenerator(p, FS))
    np.testing.assert_allclose(s["x_um"], 1.0 - s["slow_um"], atol=1e-12)
    np.testing.assert_allclose(s["y_um"], -2.0 + s["fast_um"], atol=1e-12)
    (x0, x1), (y0, y1) = p.extent_um()
    assert (y0, y1) == pytest.approx((-4.0, 0.0))
    assert (x0, x1) == pytest.approx((-1.0, 3.0))


def test_change_applies_at_the_next_line_boundary() -> None:
    p = RasterParams(range_um=10.0, line_rate_hz=10.0, lines=100, frames=0)
    gen = RasterGenerator(p, FS)
    gen.next_block(1500)  # mid line 1
    gen.change(range_um=4.0)
    b = gen.next_block(1000)
    # samples 1500..1999 still belong to the old line (range 10), 2000.. to the new one.
    assert np.max(np.abs(b.fast_um[:500])) > 4.5
    assert np.max(np.abs(b.fast_um[500:])) <= 2.0 + 1e-12
    assert b.line[500] == 2


def test_overscan_extends_travel_but_not_the_image() -> None:
    p = RasterParams(range_um=10.0, line_rate_hz=10.0, lines=2, overscan=0.1)
    b = RasterGenerator(p, FS).next_block(1000)
    assert b.fast_um.max() == pytest.approx(6.0, abs=0.03)
    assert np.all(np.abs(b.fast_um[b.in_image]) <= 5.0)


def test_invalid_parameters_are_refused() -> None:
    with pytest.raises(SafetyError, match="range_um"):
        RasterParams(range_um=-1.0, line_rate_hz=1.0)
    with pytest.raises(SafetyError, match="samples per line"):
        RasterGenerator(RasterParams(range_um=1.0, line_rate_hz=5000.0), FS)


def test_move_profile_respects_the_speed_limit_and_arrives() -> None:
    path = move_profile(np.array([0.0, 5.0]), np.array([10.0, 5.0]), 100.0, FS)
    assert path.shape[0] == 2
    speed = np.abs(np.diff(path, axis=1)) * FS
    assert speed.max() <= 100.0 * 1.001
    np.testing.assert_allclose(path[:, -1], [10.0, 5.0])
    assert np.all(path[1] == 5.0)


def test_slew_limit_clamps_only_when_needed() -> None:
    v = np.array([0.0, 0.1, 0.2])
    out, changed = slew_limit(v, 0.0, 0.5)
    assert changed == 0 and np.array_equal(out, v)
    out, changed = slew_limit(np.array([0.0, 3.0, 3.0]), 0.0, 1.0)
    assert changed == 2 and np.array_equal(out, [0.0, 1.0, 2.0])


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-50, 50), min_size=1, max_size=60),
    st.floats(-50, 50),
    st.floats(0.05, 5.0),
    st.booleans(),
)
def test_slew_limited_samples_keep_the_limit_and_stay_between_the_values(
    values: list[float], previous: float, step: float, centred: bool
) -> None:
    v = np.asarray(values)
    out, changed = slew_limit(v, previous, step, centred=centred)
    assert np.all(np.abs(np.diff(out, prepend=previous)) <= step * (1 + 1e-9))
    lo, hi = min(v.min(), previous), max(v.max(), previous)
    assert np.all((out >= lo - 1e-12) & (out <= hi + 1e-12))
    assert changed == np.count_nonzero(out != v)
    if not np.any(np.abs(np.diff(v, prepend=previous)) > step * (1 + 1e-9)):
        assert changed == 0


def test_a_centred_slew_limit_ramps_around_the_step() -> None:
    v = np.r_[np.zeros(10), np.full(10, 5.0)]
    out, _ = slew_limit(v, 0.0, 1.0, centred=True)
    moving = np.flatnonzero((out > 0) & (out < 5))
    # as many samples of the ramp before the step (index 10) as after it
    assert moving.min() < 10 and 10 - moving.min() == moving.max() - 9
    assert np.sum(out - v) == pytest.approx(0.0)


def test_non_integer_samples_per_line_terminate() -> None:
    """Regression: 20 kS/s at 0.63 Hz (31746.03 samples/line) looped forever at the end of the scan."""
    gen = RasterGenerator(
        RasterParams(range_um=17.0, line_rate_hz=0.63, lines=4, slow_range_um=0.0), 20_000.0
    )
    total = gen.total_samples()
    assert total == round(4 * 20_000.0 / 0.63)
    s = _all(gen, block=400)
    assert s["fast_um"].size == total
    assert np.array_equal(np.unique(s["line"]), np.arange(4))


@given(
    st.floats(1_000.0, 100_000.0),
    st.floats(0.01, 20.0),
    st.integers(1, 5),
    st.integers(1, 3),
    st.integers(64, 5000),
)
def test_scans_end_with_whole_lines_for_any_rates(
    fs: float, f: float, lines: int, frames: int, block: int
) -> None:
    if fs / f < 8 or fs / f * lines * frames > 60_000:
        return
    gen = RasterGenerator(RasterParams(range_um=10.0, line_rate_hz=f, lines=lines, frames=frames), fs)
    total = gen.total_samples()
    s = _all(gen, block=block)
    assert s["fast_um"].size == total
    counts = np.bincount(s["line"])
    spl = fs / f
    expected = np.diff(np.round(np.arange(lines * frames + 1) * spl))
    assert np.array_equal(counts, expected)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    assert np.allclose(s["fast_um"][starts], -5.0)  # every line starts at the start of its trace
