"""Per-axis target -> voltage mapping with carried model state."""

from __future__ import annotations

import numpy as np
import pytest

from piezod.config import AxisConfig, ThesisModelConfig
from piezod.errors import RangeUnreachableError, SafetyError
from piezod.model.inverse import ThesisInverse
from piezod.model.ode import hysteresis_step
from piezod.service.axes import AxisDriver

FS = 10_000.0
MEDIUM = ThesisModelConfig(
    alpha_per_v=3.23e-3, b_um_per_v=0.081, u_um_per_v=0.016, tau_s=2.666, a1=0.081, a2_per_v=2.78e-3, a3=0.872
)


def _axis(slew: float = 1e6) -> AxisDriver:
    cfg = AxisConfig(voltage_min_v=-230, voltage_max_v=230, slew_rate_v_per_s=slew, thesis=MEDIUM)
    return AxisDriver("x", cfg, FS)


def _triangle(range_um: float, center_um: float, loops: int, n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    phase = (np.arange(loops * n) % n) / n
    tri = np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    return center_um + (tri - 0.5) * range_um, np.where(phase < 0.5, 1, -1)


def test_steady_corrected_scan_is_the_thesis_inverse() -> None:
    ax = _axis()
    plan = ax.plan(20.0, 5.0, 1.5)
    ax.use_plan(plan)
    targets, direction = _triangle(20.0, 1.5, loops=8)
    volts = np.concatenate([ax.corrected(blk).voltage_v for blk in np.array_split(targets, 13)])
    inv = ThesisInverse.for_voltages(ax.params, plan.v_min, plan.v_max, 5.0)
    np.testing.assert_allclose(
        volts[-2000:], inv.voltage(targets[-2000:] + 0.0, direction[-2000:]), atol=1e-4
    )
    assert ax.position_um == pytest.approx(targets[-1], abs=1e-9)


def test_offset_change_transient_is_carried_by_the_state() -> None:
    ax = _axis()
    ax.use_plan(ax.plan(10.0, 5.0, -3.0))
    first, _ = _triangle(10.0, -3.0, loops=6)
    ax.corrected(first)
    ax.use_plan(ax.plan(10.0, 5.0, 3.0))
    # a slew-free move to the new scan's start, then the scan
    move = np.linspace(first[-1], 3.0 - 5.0, 200)
    ax.corrected(move)
    second, _ = _triangle(10.0, 3.0, loops=6)
    start = ax.state
    volts = ax.corrected(second).voltage_v
    # The forward model (ODE + creep term) reaches every target, transient included.
    x_h, _ = hysteresis_step(ax.params.hysteresis, volts, start)
    plan = ax.plan(10.0, 5.0, 3.0)
    model = x_h + plan.kappa_um_per_v * (volts - plan.v_center)
    np.testing.assert_allclose(model, second, atol=1e-9)
    # ...and the first loop after the change needs other voltages than the steady loop.
    assert np.max(np.abs(volts[:2000] - volts[-2000:])) > 1e-3


def test_uncorrected_drive_is_linear_in_the_target() -> None:
    ax = _axis(slew=1e9)
    plan = ax.plan(20.0, 1.0, 0.0)
    targets, _ = _triangle(20.0, 0.0, loops=1)
    out = ax.linear(targets, plan)
    assert out.voltage_v.min() == pytest.approx(plan.v_min, rel=1e-3)
    assert out.voltage_v.max() == pytest.approx(plan.v_max, rel=1e-3)
    assert out.clamped == 0


def test_voltages_never_leave_the_limits_and_slew_is_limited() -> None:
    ax = _axis(slew=1000.0)
    out = ax.corrected(np.array([50.0, 50.0, 50.0]))  # far beyond +230 V
    assert out.clamped > 0 or out.slew_limited > 0
    assert np.all(np.abs(np.diff(out.voltage_v, prepend=0.0)) <= 1000.0 / FS + 1e-12)
    assert np.all(out.voltage_v <= 230.0)
    ax2 = _axis(slew=1e9)
    out2 = ax2.corrected(np.array([50.0]))
    assert out2.clamped == 1 and out2.voltage_v[0] == 230.0


def test_unreachable_scans_are_refused_with_the_reason() -> None:
    ax = _axis()
    with pytest.raises(RangeUnreachableError, match="largest reachable"):
        ax.plan(500.0, 1.0, 0.0)
    with pytest.raises(SafetyError, match="outside the voltage limits"):
        ax.plan(1.0, 1.0, 100.0)
