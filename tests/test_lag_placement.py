"""The lag placement experiment: where a lag sits, from the branch a short spike leaves."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from piezod.config import ScannerConfig, load_config
from piezod.errors import CalibrationError
from piezod.lag_placement import (
    PLACEMENT_LABEL,
    jumps_um,
    movable_s,
    moved_config,
    place_lag,
    placement_program,
    predicted_readback,
    program_for,
)
from piezod.recording import Experiment

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "sim-pi-microscope-calibrated.yaml"


def _with_lags(base: ScannerConfig, drive_s: float, sensor_s: float, delay_s: float = 0.0) -> ScannerConfig:
    ax = base.axes["x"]
    assert ax.family is not None
    family = ax.family.model_copy(update={"lag_time_constant_s": drive_s})
    ext = {"delay": {"delay_s": delay_s, "lag_time_constant_s": sensor_s}} if sensor_s or delay_s else None
    return base.with_axis("x", family=family, extensions=ext)


def _recorded(truth: ScannerConfig, seed: int = 1) -> tuple[Experiment, object]:
    """The program played on a 'stage' that is ``truth``'s own model, read with 2 nm of noise."""
    program = program_for(truth, "x", truth.sample_rate_hz)
    t = np.arange(program.volts.size) / program.rate_hz
    blank = Experiment(PLACEMENT_LABEL, "x", t, program.volts, np.zeros_like(t))
    y = predicted_readback(blank, truth, "x") + np.random.default_rng(seed).normal(0.0, 0.002, t.size)
    return Experiment(PLACEMENT_LABEL, "x", t, program.volts, y), program


def test_the_program_stays_inside_the_limits_and_the_slew_limit() -> None:
    prog = placement_program(-10.0, 120.0, 2000.0, 10000.0)
    assert prog.volts.min() >= -10.0 + 1.3 - 1e-9 and prog.volts.max() <= 120.0 - 1.3 + 1e-9
    assert np.max(np.abs(np.diff(prog.volts))) * prog.rate_hz <= 0.5 * 2000.0 * 1.001
    assert len(prog.marks_s) == 2 * len(prog.signs)
    assert 10.0 < prog.duration_s < 40.0


def test_a_drive_pole_the_model_puts_at_the_sensor_is_moved_to_the_drive() -> None:
    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, drive_s=1.0e-3, sensor_s=0.0, delay_s=1.5e-4))
    written = _with_lags(base, drive_s=0.0, sensor_s=1.0e-3, delay_s=1.5e-4)
    found = place_lag(exp, program, written, "x")  # type: ignore[arg-type]
    assert found is not None and found.adopted
    assert found.moved_s == pytest.approx(1.0e-3, rel=0.1)
    assert np.sqrt(np.mean(np.square(found.jumps_moved_um))) < 0.2 * np.sqrt(
        np.mean(np.square(found.jumps_um))
    )
    # the spikes leave the stage on a lower branch than the written model says: J < 0
    assert all(j < 0 for j in found.jumps_um)


def test_a_sensor_lag_stays_at_the_sensor() -> None:
    base = load_config(CONFIG)
    truth = _with_lags(base, drive_s=0.0, sensor_s=1.0e-3, delay_s=1.5e-4)
    exp, program = _recorded(truth)
    found = place_lag(exp, program, truth, "x")  # type: ignore[arg-type]
    assert found is not None and not found.adopted
    assert found.moved_s < 1.0e-4
    assert "left at the sensor" in found.note


def test_a_drive_lag_the_frame_left_short_is_reported_not_added() -> None:
    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, drive_s=7e-4, sensor_s=0.0))
    for written_s in (0.0, 4e-4):
        found = place_lag(exp, program, _with_lags(base, written_s, 0.0), "x")  # type: ignore[arg-type]
        assert found is not None and not found.adopted and found.movable_s == 0.0 and found.moved_s == 0.0
        assert written_s + found.placed_s == pytest.approx(7e-4, rel=0.1)
        assert "ms more drive lag than written" in found.note and "no sensor path" in found.note


def test_beyond_the_sensor_path_the_whole_path_moves_and_the_rest_is_reported() -> None:
    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, drive_s=9e-4, sensor_s=0.0))
    found = place_lag(exp, program, _with_lags(base, 0.0, 5e-4), "x")  # type: ignore[arg-type]
    assert found is not None and found.adopted and found.moved_s == pytest.approx(5e-4)
    assert found.placed_s == pytest.approx(9e-4, rel=0.1)
    assert "moved to the drive" in found.note and "more drive lag than written" in found.note


def test_nothing_to_place_on_a_model_without_a_drive_lag() -> None:
    config = load_config(Path(__file__).resolve().parents[1] / "configs" / "sim-stage-calibrated.yaml")
    assert config.axes["x"].model != "family"
    program = program_for(config, "x", config.sample_rate_hz)
    t = np.arange(program.volts.size) / program.rate_hz
    exp = Experiment(PLACEMENT_LABEL, "x", t, program.volts, np.zeros_like(t))
    assert place_lag(exp, program, config, "x") is None


def test_a_drive_lag_the_member_has_too_much_of_moves_to_the_sensor() -> None:
    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, drive_s=2.0e-4, sensor_s=4.0e-4))
    written = _with_lags(base, drive_s=6.0e-4, sensor_s=0.0)
    found = place_lag(exp, program, written, "x")  # type: ignore[arg-type]
    assert found is not None and found.adopted
    assert found.drive_lag_s == pytest.approx(6.0e-4)
    assert found.moved_s == found.placed_s == pytest.approx(-4.0e-4, rel=0.15)
    assert all(j > 0 for j in found.jumps_um)
    rms = [float(np.sqrt(np.mean(np.square(j)))) for j in (found.jumps_um, found.jumps_moved_um)]
    assert rms[1] < 0.2 * rms[0], rms
    assert "of the member's 0.600 ms drive lag at the sensor" in found.note
    assert "moved to the sensor" in found.note
    assert "reported, not made" not in found.note
    placed = moved_config(written, "x", found.moved_s).axes["x"]
    assert placed.family is not None
    assert placed.family.lag_time_constant_s == pytest.approx(2.0e-4, rel=0.3)
    assert placed.family.lag_time_constant_s + placed.sensor_path().lag_time_constant_s == pytest.approx(
        6.0e-4
    )


def test_a_drive_lag_that_is_right_stays_at_the_drive() -> None:
    base = load_config(CONFIG)
    truth = _with_lags(base, drive_s=5.0e-4, sensor_s=0.0)
    exp, program = _recorded(truth)
    found = place_lag(exp, program, truth, "x")  # type: ignore[arg-type]
    assert found is not None and not found.adopted
    assert abs(found.moved_s) < 1.0e-4


def test_the_lag_moves_first_then_the_delay() -> None:
    base = _with_lags(load_config(CONFIG), drive_s=1e-4, sensor_s=3e-4, delay_s=2e-4)
    assert movable_s(base, "x") == pytest.approx(5e-4)
    moved = moved_config(base, "x", 4e-4).axes["x"]
    assert moved.family is not None and moved.family.lag_time_constant_s == pytest.approx(5e-4)
    path = moved.sensor_path()
    assert path.lag_time_constant_s == pytest.approx(0.0) and path.delay_s == pytest.approx(1e-4)
    whole = moved_config(base, "x", 5e-4).axes["x"]
    assert whole.sensor_path().identity
    more = moved_config(base, "x", 6e-4).axes["x"]
    assert more.sensor_path().identity
    assert more.family is not None and more.family.lag_time_constant_s == pytest.approx(7e-4)
    back = moved_config(base, "x", -1e-4).axes["x"]
    assert back.family is not None and back.family.lag_time_constant_s == pytest.approx(0.0)
    assert back.sensor_path().lag_time_constant_s == pytest.approx(4e-4)
    assert back.sensor_path().delay_s == pytest.approx(2e-4)
    with pytest.raises(CalibrationError, match="of its drive lag to the sensor"):
        moved_config(base, "x", -2e-4)


def test_a_recording_of_another_program_is_refused() -> None:
    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, 0.0, 1e-3))
    short = Experiment(exp.label, "x", exp.t_s[:1000], exp.voltage_v[:1000], exp.position_um[:1000])
    with pytest.raises(CalibrationError, match="not the placement program"):
        place_lag(short, program, _with_lags(base, 0.0, 1e-3), "x")  # type: ignore[arg-type]


def test_a_pattern_beyond_the_sensors_range_is_left_out() -> None:
    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, 0.0, 1e-3))
    y = exp.position_um.copy()
    t = exp.t_s - exp.t_s[0]
    first = program.marks_s[0]  # type: ignore[attr-defined]
    y[(t > first - 0.1) & (t < first)] = np.nan
    j = jumps_um(Experiment(exp.label, "x", exp.t_s, exp.voltage_v, y), program, y * 0.0)  # type: ignore[arg-type]
    assert np.isnan(j[0]) and np.all(np.isfinite(j[1:]))


def test_the_calibration_step_moves_the_lag_and_says_so() -> None:
    from piezod.stagecal import ThesisFit, with_lag_placed

    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, drive_s=8e-4, sensor_s=0.0))
    written = _with_lags(base, drive_s=0.0, sensor_s=8e-4)
    fit = with_lag_placed((exp, program), "x", ThesisFit({"adopted": ["delay: ..."]}, written, 0.01))  # type: ignore[arg-type]
    placed = fit.config.axes["x"]
    assert placed.family is not None and placed.family.lag_time_constant_s == pytest.approx(8e-4, rel=0.1)
    assert fit.report["lag_placement"]["adopted"] is True
    assert (
        fit.report["adopted"][-1].startswith("lag placement:")
        and "moved to the drive" in fit.report["adopted"][-1]
    )
    assert with_lag_placed(None, "x", fit) is fit


def test_the_calibration_step_moves_a_drive_lag_to_the_sensor_and_says_so() -> None:
    from piezod.stagecal import ThesisFit, with_lag_placed

    base = load_config(CONFIG)
    exp, program = _recorded(_with_lags(base, drive_s=1e-4, sensor_s=7e-4))
    written = _with_lags(base, drive_s=8e-4, sensor_s=0.0)
    fit = with_lag_placed((exp, program), "x", ThesisFit({"adopted": []}, written, 0.01))  # type: ignore[arg-type]
    placed = fit.config.axes["x"]
    assert placed.family is not None and placed.family.lag_time_constant_s == pytest.approx(1e-4, abs=1e-4)
    assert placed.sensor_path().lag_time_constant_s == pytest.approx(7e-4, rel=0.15)
    assert fit.report["lag_placement"]["adopted"] is True and fit.report["lag_placement"]["moved_s"] < 0.0
    note = fit.report["adopted"][-1]
    assert note.startswith("lag placement:") and "moved to the sensor" in note
