"""The resonance part (piezod.model.resonance): targets shaped ahead so the stage's mode does not ring."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import lsim

from piezod.config import AxisConfig, ThesisModelConfig
from piezod.errors import ModelError
from piezod.model.resonance import MAX_HALF_WIDTH, ResonancePart
from piezod.service.axes import AxisDriver

RATE = 14000.0
DT = 1.0 / RATE
THESIS = ThesisModelConfig(
    alpha_per_v=3e-3, b_um_per_v=0.09, u_um_per_v=0.05, tau_s=2.666, a1=0.081, a2_per_v=0.0, a3=0.6
)


def _triangle(range_um: float, frequency_hz: float, periods: int) -> np.ndarray:
    per = round(RATE / frequency_hz)
    phase = (np.arange(per * periods) % per) / per
    return range_um * np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)


def _resonator(u: np.ndarray, f0: float, q: float) -> np.ndarray:
    """The continuous resonator on ``u`` linear between samples (scipy, not piezod's or hil_sim's
    discretisation), from rest at ``u[0]``."""
    w0 = 2.0 * math.pi * f0
    t = np.arange(u.size) * DT
    _, y, _ = lsim(([w0 * w0], [1.0, w0 / q, w0 * w0]), u - u[0], t)
    out: np.ndarray = np.asarray(y, dtype=np.float64) + u[0]
    return out


def _away_from_turns(n: int, per: int, margin: int) -> np.ndarray:
    keep = np.ones(n, dtype=bool)
    keep[: 2 * per // 2] = False  # the start from rest
    for c in range(0, n + per, per // 2):
        keep[max(0, c - margin) : c + margin + 1] = False
    return keep


@pytest.mark.parametrize(("f0", "q"), [(290.0, 28.0), (665.0, 8.0), (120.0, 3.0)])
def test_shaped_targets_bring_a_resonant_stage_onto_the_line(f0: float, q: float) -> None:
    """A 40 um, 2 Hz triangle through a resonator: raw, it rings at every turning point; shaped,
    what is left away from the turns is < 2 % of that; the turns leave the apex by at most the
    kernel's mean ``|j|`` times ``v dt`` (about ``2 v dt K / 9``; plus 10 %), with a deviation of
    zero area (the line's regression slope kept) where a triangular kernel's would be
    ``-v dt ((K + 1)^2 - 1) / 6`` um x samples (5 % allowed: the ringing left)."""
    x = _triangle(40.0, 2.0, 3)
    part = ResonancePart(f0, q)
    u = part.shape(x, [], [], DT)
    per = round(RATE / 2.0)
    k = part.half_width(DT)
    keep = _away_from_turns(x.size, per, 2 * k + 2)
    ringing = np.max(np.abs(_resonator(x, f0, q) - x)[keep])
    stage = _resonator(u, f0, q)
    left = np.max(np.abs(stage - x)[keep])
    assert ringing > 0.02
    assert left < 0.02 * ringing
    v = 160.0  # 2 x 40 um x 2 Hz
    near = ~keep
    near[:per] = False
    w1, w2, a = k + 1, 2 * k + 1, 4.0 * (k + 1) / (3.0 * k + 2.0)
    mean_j = a * (w1 * w1 - 1) / (3.0 * w1) + (1.0 - a) * (w2 * w2 - 1) / (3.0 * w2)
    assert np.max(np.abs(stage - x)[near]) < 1.1 * v * DT * mean_j + 0.02 * ringing
    apex = per + per // 2
    area = float(np.sum((stage - x)[apex - 3 * k : apex + 3 * k + 1]))
    triangular = v * DT * ((k + 1) ** 2 - 1) / 6.0
    assert abs(area) < 0.05 * triangular


@settings(max_examples=25, deadline=None)
@given(
    cuts=st.lists(st.integers(min_value=1, max_value=2999), min_size=1, max_size=6, unique=True),
    f0=st.floats(min_value=80.0, max_value=2000.0),
    q=st.floats(min_value=0.5, max_value=100.0),
)
def test_blocks_split_anywhere_with_the_targets_ahead_shape_alike(
    cuts: list[int], f0: float, q: float
) -> None:
    x = np.cumsum(np.random.default_rng(len(cuts)).normal(0.0, 0.01, 3000))
    part = ResonancePart(f0, q)
    m = part.lookahead(DT)
    whole = part.shape(x, [], [], DT)
    edges = [0, *sorted(cuts), x.size]
    pieces = [
        part.shape(x[a:b], x[max(0, a - m) : a], x[b : b + m], DT) for a, b in itertools.pairwise(edges)
    ]
    np.testing.assert_allclose(np.concatenate(pieces), whole, rtol=0, atol=1e-9)


def test_straight_stretches_keep_their_targets_plus_the_lead() -> None:
    """A line maps onto itself (the kernel is symmetric) plus the resonator's lag undone ahead."""
    part = ResonancePart(400.0, 12.0)
    v = 250.0
    x = 3.0 + v * DT * np.arange(500)
    u = part.shape(x[100:400], x[:100], x[400:], DT)
    np.testing.assert_allclose(u, x[100:400] + v / (12.0 * 2.0 * math.pi * 400.0), rtol=0, atol=1e-9)


def test_cubics_pass_the_smoothing_unchanged() -> None:
    """The kernel's second moment is 0: a cubic leaves it as it came, so the shaped target is the
    resonator's exact inverse of the target itself (the lead's centred difference aside)."""
    f0, q = 300.0, 20.0
    part = ResonancePart(f0, q)
    w0 = 2.0 * math.pi * f0
    t = np.arange(-300, 300) * DT
    x = 1e6 * t**3 - 2e3 * t**2 + 40.0 * t + 3.0
    d1, d2, d3 = 3e6 * t**2 - 4e3 * t + 40.0, 6e6 * t - 4e3, 6e6
    want = x + (d1 + d3 * DT * DT / 6.0) / (q * w0) + d2 / (w0 * w0)
    u = part.shape(x[100:500], x[:100], x[500:], DT)
    np.testing.assert_allclose(u, want[100:500], rtol=0, atol=1e-9)


def test_off_and_bounds() -> None:
    assert ResonancePart().off and ResonancePart().lookahead(DT) == 0
    x = np.linspace(0.0, 1.0, 7)
    np.testing.assert_array_equal(ResonancePart().shape(x, [], [], DT), x)
    assert ResonancePart(1.0e5, 10.0).half_width(DT) == 1
    assert ResonancePart(50.0, 10.0).half_width(1e-6) == MAX_HALF_WIDTH
    with pytest.raises(ModelError, match=r"resonance.f0_hz = 20.0 outside"):
        ResonancePart(20.0, 10.0)
    with pytest.raises(ModelError, match="no parameter 'damping'"):
        ResonancePart.from_effects({"resonance": {"f0_hz": 300.0, "damping": 0.1}})
    with pytest.raises(ModelError, match="needs f0_hz"):
        ResonancePart.from_effects({"resonance": {"q": 5.0}})


def _axis(resonance: dict[str, float] | None) -> AxisConfig:
    return AxisConfig(
        voltage_min_v=-30.0,
        voltage_max_v=150.0,
        slew_rate_v_per_s=1e5,
        thesis=THESIS,
        extensions=None if resonance is None else {"resonance": resonance},
    )


def test_the_axis_config_refuses_an_unphysical_resonance() -> None:
    with pytest.raises(ValueError, match=r"extensions: resonance.q = 500.0 outside"):
        _axis({"f0_hz": 300.0, "q": 500.0})


def test_the_driver_shapes_ahead_and_keeps_its_window_across_blocks() -> None:
    """The driver with the targets ahead gives, block by block, the voltages of one whole call; a
    hold (the drive not corrected) starts the window again."""
    x = 2.0 + _triangle(4.0, 5.0, 2)
    one = AxisDriver("x", _axis({"f0_hz": 300.0, "q": 20.0}), RATE)
    assert one.lookahead == ResonancePart(300.0, 20.0).lookahead(DT) > 0
    out = one.corrected(x)
    assert out.clamped == 0
    whole = out.voltage_v
    split = AxisDriver("x", _axis({"f0_hz": 300.0, "q": 20.0}), RATE)
    volts = []
    for i in range(0, x.size, 97):
        volts.append(split.corrected(x[i : i + 97], x[i + 97 : i + 97 + split.lookahead]).voltage_v)
    np.testing.assert_allclose(np.concatenate(volts), whole, rtol=0, atol=1e-9)
    plain = AxisDriver("x", _axis(None), RATE)
    assert plain.lookahead == 0
    assert not np.allclose(plain.corrected(x).voltage_v, whole)
    split.hold(10)
    assert split._before is None
