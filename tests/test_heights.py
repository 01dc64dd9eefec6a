"""Heights from the z voltage (thesis chapter 5): forward model vs linear conversion, on simulated steps.

Self-consistency: the z model here carries the simulated z piezo's own parameters (the simulator's
``simulation:`` section), so the figure checks the conversion and the recording path, not a
calibration of z. ``python -m pytest -s tests/test_heights.py`` prints both figures.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from hil_sim.server import spawn_sim
from piezod.config import DynamicModelConfig, MicroscopeSection, config_dir, load_config
from piezod.heights import compare_heights, plot_height_profiles
from piezod.image import forward_heights, raster_samples
from piezod.imagecal import read_truth_log
from piezod.recording import read_recording
from piezod.service.engine import Engine
from piezod.service.schemas import ScanRequest


def _true_z_axis_model(path: Path) -> DynamicModelConfig:
    sim = load_config(path).simulation
    assert sim is not None
    z, creep = sim["axes"]["z"], sim.get("creep", {})
    return DynamicModelConfig(
        alpha_per_v=z["alpha_per_v"],
        b_um_per_v=z["b_um_per_v"],
        u_um_per_v=z["u_um_per_v"],
        creep_pct_per_decade=z["creep_pct_per_decade"],
        creep_tau_min_s=creep.get("tau_min_s", 1e-3),
        creep_tau_max_s=creep.get("tau_max_s", 1e5),
        creep_per_decade=creep.get("per_decade", 3),
    )


def test_forward_model_heights_remove_the_overshoots_of_the_linear_conversion(tmp_path: Path) -> None:
    cfg_path = config_dir() / "sim-stage-calibrated.yaml"
    base = load_config(cfg_path)
    z_axis = base.axes["z"].model_copy(update={"model": "dynamic", "dynamic": _true_z_axis_model(cfg_path)})
    config = base.model_copy(update={"microscope": MicroscopeSection()})
    truth = tmp_path / "truth.f64"
    rec_path = tmp_path / "steps.csv"
    extra = ("--sample", "steps-100nm", "--truth-log", str(truth))
    with spawn_sim(cfg_path, extra_args=extra) as sim:
        engine = Engine(config, sim.path, recording_dir=tmp_path)
        engine.open()
        try:
            request = ScanRequest(range_um=20.0, line_rate_hz=2.0, lines=4, pixels=256, name="steps")
            engine.start_scan(request, path=rec_path)
            limit = time.monotonic() + 120.0
            while engine.status().state == "scanning" and time.monotonic() < limit:
                time.sleep(0.1)
            assert engine.wait_idle(timeout_s=30.0) == "idle"
            engine.wait_recorded()
        finally:
            engine.close()
    rec = read_recording(rec_path)
    rs = raster_samples(rec)
    assert rs.z_voltage_v is not None
    rate = base.sample_rate_hz
    model = forward_heights(z_axis, rs.z_voltage_v, 1.0 / rate)
    idx, z_true = read_truth_log(truth, "z_um")
    k = np.rint(rs.t_s * rate).astype(np.int64)
    pos = np.searchsorted(idx, k)
    pos = np.clip(pos, 0, idx.size - 1)
    true_um = np.where(idx[pos] == k, z_true[pos], np.nan)
    cmp, e_m, e_l = compare_heights(rs, model, true_um)
    print(
        f"\n100 nm steps (step {cmp.step_um * 1e3:.1f} nm, {cmp.samples} samples): forward model max "
        f"{cmp.model_max_pct:.2f} % (rms {cmp.model_rms_pct:.2f} %) of the step; linear conversion "
        f"({cmp.sensitivity_um_per_v:.4f} um/V) max {cmp.linear_max_pct:.2f} % "
        f"(rms {cmp.linear_rms_pct:.2f} %)"
    )
    plot_height_profiles(rs, true_um, e_m, e_l, tmp_path / "heights.png", "100 nm steps")
    assert cmp.step_um == pytest.approx(0.1, rel=0.05)
    assert cmp.model_max_pct <= 1.0
    assert cmp.linear_max_pct > 3.0 * cmp.model_max_pct  # the overshoots the linear conversion shows
