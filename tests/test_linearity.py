"""Linearity metrics (4.14)-(4.16)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from piezod.errors import RecordingError
from piezod.linearity import experiment_linearity, linearity, noise_pct
from piezod.recording import Experiment

R_UM = 20.0


def _scan(
    lines: int = 8,
    spl: int = 2000,
    f: float = 1.0,
    overscan: float = 0.0,
    phase: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Time, voltage, target (um, linear triangle incl. overscan) and direction of a scan."""
    k = np.arange(lines * spl // 2 + 1) + phase * spl
    ph = (k / spl) % 1.0
    tri = np.where(ph < 0.5, 2 * ph, 2 - 2 * ph)
    travel = R_UM * (1 + 2 * overscan)
    target = -travel / 2 + travel * tri
    direction = np.where(ph < 0.5, 1, -1)
    # a corrected scan: the voltage is a smooth monotone map of the target (not a triangle)
    voltage = 10.0 * target + 0.02 * target**2 + 40.0
    return k / (f * spl), voltage, target, direction


def _exp(t: np.ndarray, v: np.ndarray, x: np.ndarray, target: np.ndarray | None, **meta: str) -> Experiment:
    return Experiment(
        label="e",
        axis="x",
        t_s=t,
        voltage_v=v,
        position_um=x,
        target_um=target,
        metadata=meta,
        path="mem.csv",
    )


def test_perfectly_linear_scan_gives_zero() -> None:
    t, v, target, _ = _scan()
    res = experiment_linearity(_exp(t, v, 1.0 * target + 3.0, target))
    assert res.reference == "target"
    assert res.nonlinearity_pct < 1e-9
    assert abs(res.length_error_pct) < 1e-9
    assert res.range_um == pytest.approx(R_UM)
    assert res.frequency_hz == pytest.approx(1.0, rel=1e-9)
    assert res.offset_v == pytest.approx(40.0 + 0.02 * R_UM**2 / 4, rel=1e-9)
    assert res.trace.lines == 4 and res.retrace.lines == 4


def test_known_length_error_and_quadratic_nonlinearity() -> None:
    t, v, target, _ = _scan(spl=4000)
    a = 2e-3  # 1/um
    x = 1.01 * target + a * target**2
    res = experiment_linearity(_exp(t, v, x, target))
    # the centred quadratic a (xi - c)^2 over a uniform range R has residual std a R^2 / (6 sqrt 5)
    sigma = a * R_UM**2 / (6 * math.sqrt(5))
    assert res.trace.sigma_um == pytest.approx(sigma, rel=2e-3)
    assert res.nonlinearity_pct == pytest.approx(100 * sigma / (1.01 * R_UM), rel=2e-3)
    assert res.length_error_pct == pytest.approx(1.0, abs=1e-6)


def test_pixel_mode_uses_the_nominal_range() -> None:
    t, v, target, _ = _scan()
    x = 0.98 * target - 5.0
    exp = _exp(t, v, x, None, range_um=str(R_UM))
    res = experiment_linearity(exp)
    assert res.reference == "pixel"
    assert res.length_error_pct == pytest.approx(-2.0, abs=1e-6)
    assert res.nonlinearity_pct < 1e-9
    # --range-um overrides the metadata
    res = experiment_linearity(exp, range_um=2 * R_UM)
    assert res.length_error_pct == pytest.approx(100 * (0.98 * R_UM - 2 * R_UM) / (2 * R_UM), abs=1e-6)


def test_worse_branch_is_reported() -> None:
    t, v, target, direction = _scan(spl=4000)
    a = 1e-3  # the retrace bulges (continuous at the turning points), the trace is straight
    x = target + np.where(direction < 0, a * (target**2 - R_UM**2 / 4), 0.0) + 0.01 * t
    res = experiment_linearity(_exp(t, v, x, target))
    assert res.trace.nonlinearity_pct < 1e-9 and res.retrace.nonlinearity_pct > 0.01
    assert res.nonlinearity_pct == res.retrace.nonlinearity_pct
    assert res.trace.length_error_pct > 0 > res.retrace.length_error_pct
    assert res.length_error_pct == max(res.trace.length_error_pct, res.retrace.length_error_pct, key=abs)


def test_drift_is_a_length_error_not_nonlinearity() -> None:
    t, v, target, _ = _scan(lines=10)
    drift = 0.04  # um/s; one line lasts 0.5 s
    res = experiment_linearity(_exp(t, v, target + drift * t, target))
    assert res.nonlinearity_pct < 1e-9
    assert res.trace.length_error_pct == pytest.approx(100 * drift * 0.5 / R_UM, rel=1e-6)
    assert res.retrace.length_error_pct == pytest.approx(-100 * drift * 0.5 / R_UM, rel=1e-6)


def test_overscan_declared_in_the_recording_is_excluded() -> None:
    o = 0.1
    t, v, target, _ = _scan(overscan=o, spl=4000)
    # the stage misbehaves only in the overscan (turnaround), linear inside the image
    outside = np.abs(target) > R_UM / 2
    x = target + np.where(outside, 0.3 * (np.abs(target) - R_UM / 2) ** 2, 0.0)
    plain = experiment_linearity(_exp(t, v, x, target))
    assert plain.nonlinearity_pct > 0.05 and plain.range_um == pytest.approx(R_UM * 1.2)
    res = experiment_linearity(_exp(t, v, x, target, overscan=str(o)))
    assert res.range_um == pytest.approx(R_UM)
    assert res.nonlinearity_pct < 1e-9 and abs(res.length_error_pct) < 1e-9
    # without a target, the overscan is the first and last o / (1 + 2 o) of each line
    res = experiment_linearity(_exp(t, v, x, None, overscan=str(o), range_um=str(R_UM)))
    assert res.nonlinearity_pct < 1e-9 and abs(res.length_error_pct) < 1e-9


def test_noise_gives_the_noise_over_range() -> None:
    t, v, target, _ = _scan(lines=20, spl=2000)
    noise = 0.004
    x = target + np.random.default_rng(2).normal(0, noise, t.size)
    res = experiment_linearity(_exp(t, v, x, target))
    assert res.nonlinearity_pct == pytest.approx(100 * noise / R_UM, rel=0.05)


def test_errors() -> None:
    t, v, target, _ = _scan()
    with pytest.raises(RecordingError, match="no nominal scan range"):
        experiment_linearity(_exp(t, v, target, None))
    with pytest.raises(RecordingError, match="not a periodic back-and-forth scan"):
        experiment_linearity(_exp(t, t * 3, t, None), range_um=1.0)
    with pytest.raises(RecordingError, match="overscan must be"):
        experiment_linearity(_exp(t, v, target, target), overscan=0.7)
    with pytest.raises(RecordingError, match="metadata 'range_um': not a number"):
        experiment_linearity(_exp(t, v, target, None, range_um="wide"))
    with pytest.raises(RecordingError, match="no experiments"):
        linearity([])


def test_report_maxima() -> None:
    t, v, target, _ = _scan()
    rep = linearity([_exp(t, v, 1.02 * target, target), _exp(t, v, 0.97 * target, target)])
    assert rep.max_abs_length_error_pct == pytest.approx(3.0, abs=1e-6)
    doc = rep.to_json()
    assert set(doc) >= {"experiments", "max_nonlinearity_pct", "max_abs_length_error_pct"}
    assert doc["skipped"] == []
    for key in ("range_um", "frequency_hz", "offset_v", "nonlinearity_pct", "length_error_pct"):
        assert key in doc["experiments"][0]


def test_non_scans_are_skipped_only_when_asked() -> None:
    t, v, target, _ = _scan()
    slow = _exp(t, v, np.linspace(0.0, 1.0, t.size), np.linspace(0.0, 1.0, t.size))
    good = _exp(t, v, 1.01 * target, target)
    with pytest.raises(RecordingError, match="not a periodic"):
        linearity([good, slow])
    rep = linearity([good, slow], skip_non_scans=True)
    assert len(rep.experiments) == 1 and len(rep.skipped) == 1
    with pytest.raises(RecordingError, match="not a periodic"):
        linearity([slow], skip_non_scans=True)


def test_a_sine_is_refused_with_the_reason_not_compared_with_a_ramp() -> None:
    t = np.arange(4000) / 1000.0
    v = 50.0 * np.sin(2 * np.pi * 1.0 * t)
    exp = Experiment("sine", None, t, v, 0.2 * v)
    with pytest.raises(RecordingError, match="sine, not a linear") as info:
        experiment_linearity(exp, range_um=20.0)
    assert "target" in str(info.value)
    # A corrected scan: its voltage is no triangle, but its target is; that one is measured.
    target = 10.0 * (2.0 * np.abs(((t * 1.0) % 1.0) - 0.5) * 2.0 - 1.0)
    corrected = Experiment("corrected", None, t, v, target + 0.001, target_um=target)
    assert experiment_linearity(corrected).nonlinearity_pct < 0.1


def test_the_sensors_noise_as_a_nonlinearity() -> None:
    """3 nm of white noise on a 0.6 um line reads as 0.5 % of (4.16) (the buzzer-disc stage of
    docs/model-family.md 6.2ao): noise_pct says how much of the figure that is, with or without a
    bow of the scan under it."""
    t, v, target, _ = _scan(spl=4000)
    line = 0.6 / R_UM * target
    noise = np.random.default_rng(3).normal(0.0, 0.003, t.size)
    for bow in (0.0, 0.002):
        x = line + bow * (line / 0.3) ** 2 + noise
        res = experiment_linearity(_exp(t, v, x, line))
        measured = 0.6 * (1.0 + res.length_error_pct / 100.0)
        assert res.nonlinearity_pct > 0.45
        assert noise_pct(x, measured) == pytest.approx(100.0 * 0.003 / measured, rel=0.05)
    assert math.isnan(noise_pct(np.zeros(3), 0.6))


def test_the_verification_table_names_the_noise_when_it_is_most_of_the_figure() -> None:
    from piezod.stagecal import format_table

    row = {"model": "family", "range_um": 0.6, "frequency_hz": 0.63, "offset_um": 0.1, "inside_frame": True}
    noisy = {**row, "what": "inside: small range", "nonlinearity_pct": 0.522, "length_error_pct": 0.069}
    quiet = {**row, "what": "inside: mid range", "nonlinearity_pct": 0.014, "length_error_pct": -0.015}
    table = format_table([{**noisy, "noise_pct": 0.506}, {**quiet, "noise_pct": 0.004}]).splitlines()
    assert table[2].endswith("inside: small range (the sensor's noise alone: 0.506 %)")
    assert table[3].endswith("inside: mid range")


def test_the_line_averaged_profile_at_the_pixels_reads_below_the_sensors_noise() -> None:
    """3 nm of noise on a 0.6 um line is 0.5 % of (4.16) whatever the scan; averaged over the
    samples of each of 256 pixels and over the lines, it is noise / sqrt(samples behind a pixel),
    which the pixel figure says, and a bow of the scan under it comes back in quadrature."""
    for lines, bow in ((8, 0.0), (8, 0.002), (40, 0.002), (2, 0.002)):
        t, v, target, _ = _scan(lines=lines, spl=4000)
        line = 0.6 / R_UM * target
        shape = bow * (line / 0.3) ** 2
        noise = np.random.default_rng(3).normal(0.0, 0.003, t.size)
        clean = experiment_linearity(_exp(t, v, line + shape, line))
        res = experiment_linearity(_exp(t, v, line + shape + noise, line))
        assert res.nonlinearity_pct > 0.45
        # a smooth bow is the same at the pixels and on the samples
        assert clean.pixel_nonlinearity_pct == pytest.approx(clean.nonlinearity_pct, rel=0.01, abs=1e-9)
        assert clean.pixel_noise_pct < 1e-3
        behind = 2000 / 256 * max(1, lines // 2)
        assert res.pixel_noise_pct == pytest.approx(100 * 0.003 / 0.6 / math.sqrt(behind), rel=0.15)
        excess = math.sqrt(max(res.pixel_nonlinearity_pct**2 - res.pixel_noise_pct**2, 0.0))
        assert excess == pytest.approx(clean.nonlinearity_pct, abs=0.5 * res.pixel_noise_pct)
    assert res.trace.pixels == 256
    assert res.to_json()["pixel_nonlinearity_pct"] == res.pixel_nonlinearity_pct
    fewer = experiment_linearity(_exp(t, v, line + shape + noise, line, pixels="32"))
    assert fewer.trace.pixels == 32 and fewer.pixel_noise_pct < res.pixel_noise_pct
    with pytest.raises(RecordingError, match="pixels must be >= 1"):
        experiment_linearity(_exp(t, v, line, line), pixels=0)


def test_the_verification_table_shows_the_pixel_figure_beside_the_noisy_one() -> None:
    from piezod.stagecal import format_table, summary

    row = {"model": "family", "range_um": 0.6, "frequency_hz": 0.63, "offset_um": 0.1, "inside_frame": True}
    noisy = {
        **row,
        "what": "inside: small range",
        "nonlinearity_pct": 0.522,
        "length_error_pct": 0.069,
        "noise_pct": 0.506,
        "pixel_nonlinearity_pct": 0.041,
        "pixel_noise_pct": 0.03,
    }
    table = format_table([noisy]).splitlines()
    assert "nonlin %  pixels %  length %" in table[0]
    assert "0.522     0.041" in table[2]
    assert table[2].endswith("(the sensor's noise alone: 0.506 %; at the pixels 0.030 %)")
    assert summary([noisy])["family_inside"]["max_pixel_nonlinearity_pct"] == 0.041
