"""Fast creep identified from the frame's harmonics at its several rates (piezod.rate_id) and adopted.

The frames here are synthetic: triangles through a thesis-model axis and a known fast creep
(:mod:`piezod.model.fast_creep`), so the tests check that the identification recovers what was put
in, also when the calibrated model's hysteresis is not the data's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from piezod.config import (
    AxisConfig,
    FamilyModelConfig,
    ThesisModelConfig,
    default_sim_config_path,
    dump_config,
    load_config,
)
from piezod.errors import ConfigError
from piezod.model.family import CreepSpectrum
from piezod.model.fast_creep import FastCreep
from piezod.rate_id import MIN_GAIN, adopt_fast_creep, identify_fast_creep, member_creep_share
from piezod.recording import Experiment
from piezod.service.axes import axis_model

RATE = 5_000.0
THESIS = ThesisModelConfig(
    alpha_per_v=3e-3, b_um_per_v=0.09, u_um_per_v=0.05, tau_s=2.666, a1=0.081, a2_per_v=0.0, a3=0.6
)
CONFIG = AxisConfig(voltage_min_v=-30.0, voltage_max_v=150.0, thesis=THESIS)
TRUTH = FastCreep((0.003, 0.01), (0.015, 0.015))


def _frame(
    fast: FastCreep,
    thesis: ThesisModelConfig = THESIS,
    noise_um: float = 0.002,
    stage: AxisConfig | None = None,
) -> list[Experiment]:
    """Triangles over 2 ranges x 4 rates (one unrecorded loop, then 3 recorded) through a thesis-model
    axis (or ``stage``'s model) and then ``fast``, plus sensor noise."""
    rng = np.random.default_rng(5)
    model = axis_model(stage if stage is not None else CONFIG.model_copy(update={"thesis": thesis}))
    dt = 1.0 / RATE
    out = []
    for range_v in (60.0, 120.0):
        for f in (0.25, 0.5, 1.0, 2.0):
            per = round(RATE / f)
            phase = (np.arange(4 * per + 1) % per) / per
            v = range_v * np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
            x, _ = model.forward(v, dt, model.rest(0.0))
            if not fast.identity:
                x, _ = fast.forward(x, dt, np.full(len(fast.taus_s), x[0]))
            y = x[per:] + rng.normal(0.0, noise_um, x.size - per)
            t = np.arange(y.size, dtype=np.float64) * dt
            out.append(Experiment(f"R{range_v:g}_f{f:g}", "x", t, v[per:], y))
    return out


def _late_at(fast: FastCreep, f_hz: float) -> float:
    """How much less of the motion a sine at ``f_hz`` reaches than a slow one (fraction)."""
    return float(1.0 - abs(fast.response(np.array([f_hz]))[0]))


def test_fast_creep_is_found_and_adopted() -> None:
    found = identify_fast_creep(_frame(TRUTH), CONFIG)
    assert found is not None and found.adopted, found
    assert found.heldout_rms[1] <= (1.0 - MIN_GAIN) * found.heldout_rms[0]
    # what a fast line feels: the gain lost at 20 and 60 Hz, within a fifth of the truth
    for f in (20.0, 60.0):
        assert _late_at(found.fast, f) == pytest.approx(_late_at(TRUTH, f), rel=0.2)
    assert "adopted" in found.note


def test_it_is_found_through_a_hysteresis_the_model_does_not_fit() -> None:
    """The harmonic ratios cancel the hysteresis: a 30 % wider loop than the model's changes nothing."""
    other = THESIS.model_copy(update={"u_um_per_v": 0.065, "alpha_per_v": 2.2e-3})
    found = identify_fast_creep(_frame(TRUTH, other), CONFIG)
    assert found is not None and found.adopted, found
    for f in (20.0, 60.0):
        assert _late_at(found.fast, f) == pytest.approx(_late_at(TRUTH, f), rel=0.25)


def test_a_stage_without_fast_creep_gets_none_adopted() -> None:
    found = identify_fast_creep(_frame(FastCreep()), CONFIG)
    assert found is None or not found.adopted, found
    if found is not None:
        assert "not adopted" in found.note
        assert _late_at(found.fast, 20.0) < 0.25 * _late_at(TRUTH, 20.0)


def _member(fast_weight: float) -> AxisConfig:
    """A Prandtl-Ishlinskii member with position creep: 0.4 % per element from 0.1 ms to 100 s
    (2 per decade), ``fast_weight`` on each element at 1, 3.2 and 10 ms."""
    spec = CreepSpectrum.log_spaced(1e-4, 100.0, 2, 0.004)
    weights = [fast_weight if 9e-4 < t < 0.011 else w for t, w in zip(spec.taus, spec.w, strict=True)]
    law = FamilyModelConfig(
        law="prandtl-ishlinskii",
        b_um_per_v=0.09,
        pi_rho0=0.5,
        pi_thresholds_v=list(np.linspace(5.0, 100.0, 12)),
        pi_weights=list(np.full(12, 0.4 / 12)),
        creep_taus_s=list(spec.taus),
        creep_weights=weights,
    )
    return CONFIG.model_copy(update={"model": "family", "family": law})


def test_a_member_with_too_much_millisecond_creep_gets_it_taken_out() -> None:
    """The member's spectrum carries 3 % per element at 1-10 ms where the stage has 0.4 %
    (docs/model-family.md 6.2aw: the frame's loops do not resolve those times): the harmonics
    find negative weights there, no more negative than the member's own creep, and the corrected
    model's gain at 20 and 60 Hz is the stage's."""
    stage, member = _member(0.004), _member(0.03)
    found = identify_fast_creep(_frame(FastCreep(), stage=stage), member)
    assert found is not None and found.adopted, found
    assert found.fast.total < 0.0 and "too much" in found.note
    floor = member_creep_share(member, np.array(found.fast.taus_s))
    assert np.all(np.array(found.fast.weights) >= -floor - 1e-12)
    dt = 1.0 / RATE

    def gain(cfg: AxisConfig, fast: FastCreep, f: float) -> float:
        """Peak-to-peak of the settled response to a 20 V sine at ``f`` (um)."""
        t = np.arange(round(4.0 / f / dt)) * dt
        v = 50.0 + 20.0 * np.sin(2.0 * np.pi * f * t)
        model = axis_model(cfg)
        x, _ = model.forward(v, dt, model.rest(50.0))
        if not fast.identity:
            x, _ = fast.forward(x, dt, np.full(len(fast.taus_s), x[0]))
        return float(np.ptp(x[t >= 2.0 / f]))

    for f in (20.0, 60.0):
        # relative to a 1 Hz sine: the member's static gain is its own, the rate dependence is what counts
        truth = gain(stage, FastCreep(), f) / gain(stage, FastCreep(), 1.0)
        before = gain(member, FastCreep(), f) / gain(member, FastCreep(), 1.0)
        after = gain(member, found.fast, f) / gain(member, found.fast, 1.0)
        assert abs(after - truth) < 0.25 * abs(before - truth), (f, truth, before, after)


def test_a_model_without_a_creep_spectrum_gets_no_negative_weight() -> None:
    """The thesis model has no spectrum to take creep out of: the lower bound stays at zero."""
    assert not np.any(member_creep_share(CONFIG, np.geomspace(1e-4, 0.02, 10)))
    found = identify_fast_creep(_frame(FastCreep()), CONFIG)
    assert found is None or min(found.fast.weights, default=0.0) >= 0.0


def test_scans_that_are_not_periodic_give_no_finding() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(20000) / RATE
    v = 60.0 + np.cumsum(rng.normal(0.0, 0.2, t.size))
    assert identify_fast_creep([Experiment("walk", "x", t, v, 0.09 * v)], CONFIG) is None


def test_a_scan_ending_in_part_of_a_period_is_no_error() -> None:
    """A recording that ends part of a period after its last whole one (here 10 periods of a 1 Hz
    line and 7 samples: 5000.6 samples per period rounded up past the last sample, as on the
    P-885 recordings, where `piezod calibrate` raised) is judged, not an error; beside the frame's
    whole-period scans the fast creep is still found."""
    model = axis_model(CONFIG)
    per = round(RATE)
    phase = (np.arange(10 * per + 7) % per) / per
    v = 60.0 * np.where(phase < 0.5, 2.0 * phase, 2.0 - 2.0 * phase)
    x, _ = model.forward(v, 1.0 / RATE, model.rest(0.0))
    x, _ = TRUTH.forward(x, 1.0 / RATE, np.full(len(TRUTH.taus_s), x[0]))
    tail = Experiment("tail", "x", np.arange(v.size) / RATE, v, x)
    found = identify_fast_creep([*_frame(TRUTH), tail], CONFIG)
    assert found is not None and found.adopted, found


def test_the_adopted_fast_creep_is_written_into_the_scanner_yaml(tmp_path: Path) -> None:
    base = load_config(default_sim_config_path())
    config = base.model_copy(update={"axes": {**base.axes, "x": CONFIG}})
    new, found = adopt_fast_creep(_frame(TRUTH), "x", config)
    assert found is not None and found.adopted
    path = tmp_path / "cal.yaml"
    dump_config(new, path)
    back = load_config(path).axes["x"]
    assert back.fast_creep is not None
    assert back.fast_creep_part().total == pytest.approx(found.fast.total, rel=1e-6)
    kept = tuple(t for t, w in zip(found.fast.taus_s, found.fast.weights, strict=True) if w)
    assert back.fast_creep_part().taus_s == kept
    with pytest.raises(ConfigError, match="no axis"):
        adopt_fast_creep(_frame(TRUTH), "q", config)


def test_piezod_calibrate_reports_the_step_and_writes_the_part() -> None:
    """The calibration's step (piezod.stagecal) puts the finding into the report and the config."""
    from piezod.stagecal import ThesisFit, _with_fast_creep

    base = load_config(default_sim_config_path())
    config = base.model_copy(update={"axes": {**base.axes, "x": CONFIG}})
    fit = ThesisFit({"text": "held-out RMS 5 nm", "adopted": []}, config, 0.005)
    out = _with_fast_creep(_frame(TRUTH), "x", fit)
    assert out.fit_error_pct == 0.005
    assert out.config.axes["x"].fast_creep is not None
    doc = out.report["fast_creep"]
    assert doc["adopted"] and doc["total"] == pytest.approx(out.config.axes["x"].fast_creep_part().total)
    assert out.report["adopted"][-1].startswith("fast creep") and out.report["text"].endswith("adopted")
    none = _with_fast_creep(_frame(FastCreep()), "x", fit)
    assert none.config.axes["x"].fast_creep is None
    assert none.report["skipped"][-1].startswith("fast creep") and not none.report["fast_creep"]["adopted"]
