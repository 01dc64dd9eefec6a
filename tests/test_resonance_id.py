"""The resonance identified on a calibrated model's residual (piezod.resonance_id) and adopted."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from piezod.audit.dynamics import resonance
from piezod.config import AxisConfig, ThesisModelConfig, default_sim_config_path, dump_config, load_config
from piezod.errors import ConfigError
from piezod.model.resonance import ResonancePart
from piezod.recording import Experiment
from piezod.resonance_id import MIN_GAIN, adopt_resonance, identify_resonance
from piezod.service.axes import axis_model

RATE = 10_000.0
THESIS = ThesisModelConfig(
    alpha_per_v=3e-3, b_um_per_v=0.09, u_um_per_v=0.05, tau_s=2.666, a1=0.081, a2_per_v=0.0, a3=0.6
)
CONFIG = AxisConfig(voltage_min_v=-30.0, voltage_max_v=150.0, thesis=THESIS)


def _frame(f0: float | None, q: float, noise_um: float = 0.002, delay_s: float = 0.0) -> list[Experiment]:
    """Triangles over 3 ranges x 3 rates (3 loops each) through the axis's own model, then through a
    resonance (exact, from rest) when ``f0`` is given, read ``delay_s`` late, plus sensor noise."""
    rng = np.random.default_rng(3)
    model = axis_model(CONFIG)
    out = []
    for range_v in (40.0, 80.0, 120.0):
        for f in (0.5, 1.0, 2.0):
            per = round(RATE / f)
            phase = (np.arange(3 * per + 1) % per) / per
            v = range_v * np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
            x, _ = model.forward(v, 1.0 / RATE, model.rest(0.0))
            y = x if f0 is None else resonance(x, 1.0 / RATE, f0, q, 0)
            t = np.arange(v.size) / RATE
            y = np.interp(t - delay_s, t, y) + rng.normal(0.0, noise_um, y.size)
            out.append(Experiment(f"R{range_v:g}_f{f:g}", "x", t, v, y))
    return out


def test_a_ringing_stage_is_found_and_adopted() -> None:
    found = identify_resonance(_frame(350.0, 15.0), CONFIG)
    assert found is not None and found.adopted, found
    assert found.f0_hz == pytest.approx(350.0, rel=0.02)
    assert found.q == pytest.approx(15.0, rel=0.1)
    assert found.heldout_rms_um[1] <= (1.0 - MIN_GAIN) * found.heldout_rms_um[0]
    assert "adopted" in found.note and found.effect == {"f0_hz": found.f0_hz, "q": found.q}


def test_a_mode_is_judged_against_the_noise_the_aligned_readback_carries() -> None:
    """A readback 2.5 samples late is aligned by interpolating halfway between samples, which halves
    the noise's variance: against the raw readback's floor the residual had no excess to lower, and
    a mode that rings was refused (rowan49, docs/model-family.md 6.2bl)."""
    late = 2.5 / RATE
    delay = {"delay_s": late, "lag_time_constant_s": 0.0}
    config = CONFIG.model_copy(update={"extensions": {"delay": delay}})
    found = identify_resonance(_frame(350.0, 8.0, noise_um=0.008, delay_s=late), config)
    assert found is not None and found.adopted, found
    assert found.f0_hz == pytest.approx(350.0, rel=0.02)
    assert found.heldout_rms_um[0] < 0.008  # below the raw readback's noise
    none = identify_resonance(_frame(None, 1.0, noise_um=0.008, delay_s=late), config)
    assert none is None or not none.adopted


def test_a_stage_without_a_mode_gets_none() -> None:
    found = identify_resonance(_frame(None, 1.0), CONFIG)
    assert found is None or not found.adopted
    if found is not None:
        assert "not adopted" in found.note
        assert found.heldout_rms_um[1] > (1.0 - MIN_GAIN) * found.heldout_rms_um[0] or found.q < 1.0


def test_the_adopted_resonance_is_written_into_the_scanner_yaml(tmp_path: Path) -> None:
    config = load_config(default_sim_config_path())
    config = config.model_copy(update={"axes": {**config.axes, "x": CONFIG}})
    extended, found = adopt_resonance(_frame(350.0, 15.0), "x", config)
    assert found is not None and found.adopted
    path = tmp_path / "s.yaml"
    dump_config(extended, path)
    back = load_config(path).axes["x"]
    assert back.resonance() == ResonancePart(found.f0_hz, found.q)
    assert back.thesis == CONFIG.thesis
    same, none = adopt_resonance(_frame(None, 1.0), "x", config)
    assert same is config and (none is None or not none.adopted)
    with pytest.raises(ConfigError, match="no axis 'q'"):
        adopt_resonance(_frame(None, 1.0), "q", config)


def test_a_fit_that_fails_leaves_the_model_without_the_mode_and_says_why(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import piezod.resonance_id as rid
    from piezod.errors import ModelError
    from piezod.stagecal import ThesisFit, _with_resonance

    def broken(*_: object) -> None:
        raise ModelError("voltage_v contains non-finite samples")

    monkeypatch.setattr(rid, "adopt_resonance", broken)
    config = load_config(default_sim_config_path())
    fit = ThesisFit({"text": "held-out RMS 5 nm", "skipped": []}, config, 0.005)
    out = _with_resonance(_frame(None, 1.0), "x", fit)
    assert out.config is config and out.fit_error_pct == 0.005
    assert out.report["skipped"] == ["resonance: not fitted (voltage_v contains non-finite samples)"]
    assert out.report["text"].endswith("resonance: not fitted (voltage_v contains non-finite samples)")
