"""Input as instruments write it: one-period triangles are scans, ``calibrate`` fits any waveform.

A one-period triangle (``0 -> +V -> 0 -> -V -> 0``, one loop per block, as many instruments
export) is a triangular scan for ``calibrate`` and ``linearity``; a sine is fitted by the
dynamic model and refused by ``linearity`` with the reason; ``calibrate`` says which model.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from piezod.calibrate_any import calibrate_any, choose_model
from piezod.errors import CalibrationError, RecordingError
from piezod.linearity import experiment_linearity
from piezod.model.ode import hysteresis_step, relaxed_state
from piezod.model.params import HysteresisParams
from piezod.recording import Experiment
from piezod.scan_inference import infer_scan

P = HysteresisParams(alpha_per_v=5e-3, b_um_per_v=0.05, u_um_per_v=0.035)


def _one_period(f: float, v_half: float, *, n: int = 800, t0: float = 0.0, lead: float = 0.25) -> Experiment:
    """One steady triangle period (after a settling one), from ``lead`` of a period after a lower turn."""
    t = np.arange(2 * n + 1) / (n * f)
    ph = (t * f + lead) % 1.0
    v = -v_half + 2.0 * v_half * np.where(ph < 0.5, 2.0 * ph, 2.0 - 2.0 * ph)
    x, _ = hysteresis_step(P, v, relaxed_state(P, float(v[0])))
    t, v, x = t[n:] - t[n], v[n:], x[n:]
    return Experiment(f"r{2 * v_half:g}_f{f:g}", None, t + t0, v, x + 2e-4 * np.sin(7.0 * t))


@pytest.mark.parametrize("lead", [0.25, 0.75, 0.1])
@pytest.mark.parametrize("noise", [0.0, 0.5])
def test_a_one_period_triangle_is_a_scan(lead: float, noise: float) -> None:
    e = _one_period(0.5, 100.0, lead=lead)
    v = e.voltage_v + np.random.default_rng(1).normal(0.0, noise, e.voltage_v.size)
    info = infer_scan(e.t_s, v)
    assert info.is_scan and info.wraps and info.n_loops == 1, info.reason
    assert info.frequency_hz == pytest.approx(0.5, rel=0.01)
    assert info.v_max - info.v_min == pytest.approx(200.0, rel=0.02)
    assert info.duty == pytest.approx(0.5, abs=0.02)


@pytest.mark.parametrize(
    ("times", "volts", "why"),
    [
        ([0, 1, 3, 3.5], [0, 100, -100, -50], "not one whole period"),  # stops half way up
        ([0, 0.5, 3, 4], [0, 100, -100, 0], "not one straight half period"),  # rising slopes differ
    ],
)
def test_two_turning_points_that_are_not_a_period_are_not_a_scan(
    times: list[float], volts: list[float], why: str
) -> None:
    t = np.linspace(0.0, times[-1], 2001)
    info = infer_scan(t, np.interp(t, times, volts))
    assert not info.is_scan and not info.wraps
    assert why in info.reason


def test_linearity_of_a_one_period_triangle_equals_that_of_many_periods() -> None:
    def exp(periods: int) -> Experiment:
        t = np.linspace(0.0, 2.0 * periods, 1000 * periods + 1)
        v = np.interp(t % 2.0, [0, 0.5, 1.5, 2.0], [0, 100, -100, 0])
        x = 0.1 * v + 2e-4 * v**2
        return Experiment("a", None, t, v, x, target_um=0.1 * v)

    one, many = experiment_linearity(exp(1)), experiment_linearity(exp(3))
    for a, b in ((one.trace, many.trace), (one.retrace, many.retrace)):
        assert a.nonlinearity_pct == pytest.approx(b.nonlinearity_pct, rel=0.02)
        assert a.length_error_pct == pytest.approx(b.length_error_pct, abs=0.05)
    assert one.trace.nonlinearity_pct > 1.0  # the quadratic is measured, not cut away


def test_linearity_refuses_a_sine_with_the_reason() -> None:
    t = np.linspace(0.0, 4.0, 2001)
    v = 100.0 * np.sin(2 * np.pi * t)
    with pytest.raises(RecordingError, match="sine, not a linear"):
        experiment_linearity(Experiment("s", None, t, v, 0.1 * v, metadata={"range_um": "20"}))


def test_one_period_triangles_of_several_ranges_are_fitted_by_the_thesis_model() -> None:
    exps = [
        _one_period(f, vh, t0=10.0 * k)
        for k, (f, vh) in enumerate([(0.5, 50.0), (0.5, 100.0), (0.1, 75.0), (0.1, 100.0)])
    ]
    choice = choose_model(exps)
    assert choice.model == "thesis" and "triangular" in choice.reason
    res = calibrate_any(exps)
    assert res.thesis is not None and res.dynamic is None
    assert res.thesis.params.alpha_per_v == pytest.approx(P.alpha_per_v, rel=0.3)


def test_a_sine_is_fitted_by_the_dynamic_model_and_thesis_refused_with_the_reason() -> None:
    t = np.arange(0.0, 8.0, 0.005)
    v = 100.0 * np.sin(2 * np.pi * 0.5 * t) * np.minimum(1.0, 0.3 + t / 4.0)
    x, _ = hysteresis_step(P, v, relaxed_state(P, 0.0))
    e = Experiment("sine", None, t, v, x)
    choice = choose_model([e])
    assert choice.model == "dynamic" and "sine" in choice.reason
    res = calibrate_any([e])
    assert res.dynamic is not None and res.thesis is None
    assert res.dynamic.params.b_um_per_v == pytest.approx(P.b_um_per_v, rel=0.1)
    with pytest.raises(RecordingError, match="not a periodic triangular scan"):
        choose_model([e], "thesis")
    with pytest.raises(CalibrationError, match="options of the thesis model"):
        calibrate_any([e], skip_loops=1)


def _write(path: Path, e: Experiment) -> None:
    rows = "\n".join(
        f"{a:.6f},{b:.6f},{c:.6f}" for a, b, c in zip(e.t_s, e.voltage_v, e.position_um, strict=True)
    )
    path.write_text("t,voltage,position\n" + rows + "\n", encoding="utf-8")


def test_cli_says_which_model_and_writes_it(tmp_path: Path) -> None:
    t = np.arange(0.0, 6.0, 0.01)
    v = 80.0 * np.sin(2 * np.pi * 0.5 * t)
    x, _ = hysteresis_step(P, v, relaxed_state(P, 0.0))
    _write(tmp_path / "sine.csv", Experiment("s", None, t, v, x))
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "piezod",
            "calibrate",
            str(tmp_path / "sine.csv"),
            "--json",
            str(tmp_path / "c.json"),
            "--out",
            str(tmp_path / "c.yaml"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "model: dynamic" in proc.stdout
    doc = json.loads((tmp_path / "c.json").read_text())
    assert doc["model"] == "dynamic" and "sine" in doc["model_reason"]
    assert "model: dynamic" in (tmp_path / "c.yaml").read_text()
    # the stage follows the dynamic model's own law: no member of the family predicts it better
    assert "dynamic" in doc["family"]["others"] and "the dynamic model is written" in doc["model_reason"]
