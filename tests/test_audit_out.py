"""``piezod audit REC... --out F.yaml --config BASE``: findings reach the scanner YAML as runtime parts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_audit_decide import MID

from piezod.audit.synthetic import frame_plan, hidden_session
from piezod.cli import main
from piezod.config import default_sim_config_path, load_config
from piezod.extensions import adopt_findings
from piezod.model.parts import PartsAxisModel
from piezod.recording import write_recording
from piezod.service.axes import axis_model
from piezod.synth import random_params


def test_findings_map_to_parts_and_the_rest_is_named() -> None:
    adoption = adopt_findings(
        [
            {"effect": "stiffness", "params": {"sensitivity_pct_per_um": -0.16}},
            {"effect": "delay", "params": {"delay_s": 0.0158, "lag_time_constant_s": 0.0}},
            {"effect": "resonance", "params": {"f0_hz": 665.0, "q": 10.0}},
            {"effect": "saturation", "params": {"x_sat_um": 0.5}},  # outside the physical range
            {"effect": "drift", "params": {"rate_nm_per_s": None}},
        ]
    )
    assert adoption.effects == {
        "stiffness": {"sensitivity_pct_per_um": -0.16},
        "delay": {"delay_s": 0.0158, "lag_time_constant_s": 0.0},
        "resonance": {"f0_hz": 665.0, "q": 10.0},
    }
    text = adoption.summary()
    assert "adopted stiffness: sensitivity_pct_per_um = -0.16" in text
    assert "adopted delay: delay_s = 0.0158, lag_time_constant_s = 0 (sensor path" in text
    assert "adopted resonance: f0_hz = 665, q = 10" in text
    assert (
        "resonance.q = 500.0 outside"
        in adopt_findings([{"effect": "resonance", "params": {"f0_hz": 665.0, "q": 500.0}}]).summary()
    )
    assert "not adopted saturation" in text and "not adopted drift: no finite value" in text
    assert adopt_findings([]).summary().startswith("no material finding")


def test_audit_out_writes_a_scanner_yaml_the_daemon_loads(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rng = np.random.default_rng(5)
    plan = frame_plan(
        rng, ranges_v=(120.0, 260.0, 400.0), n_frequencies=3, frequency_hz=(0.05, 5.0), n_references=3
    )
    session = hidden_session(
        random_params(rng), plan, {"stiffness": MID["stiffness"]}, samples_per_loop=512, seed=rng
    )
    rec = tmp_path / "frame.csv"
    write_recording(rec, session.recording)
    out = tmp_path / "extended.yaml"
    base = default_sim_config_path()
    assert main(["audit", str(rec), "--config", str(base), "--out", str(out), "--no-family"]) == 0
    text = out.read_text()
    assert text.startswith("# Extended by piezod audit frame.csv")
    assert "# adopted stiffness: sensitivity_pct_per_um = " in text
    config = load_config(out)
    extensions = config.axes["x"].extensions
    assert extensions is not None
    k = extensions["stiffness"]["sensitivity_pct_per_um"]
    assert k == pytest.approx(MID["stiffness"]["sensitivity_pct_per_um"], rel=0.3)
    model = axis_model(config.axes["x"])
    assert isinstance(model, PartsAxisModel) and model.parts.sensitivity_pct_per_um == k
    assert "extended scanner YAML" in capsys.readouterr().out
    # everything else of the base config is kept
    assert config.axes["y"] == load_config(base).axes["y"]


def test_audit_out_needs_the_base_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "r.csv"
    rec.write_text("t,x\n")
    assert main(["audit", str(rec), "--out", str(tmp_path / "o.yaml")]) == 2
    assert "--out needs --config F" in capsys.readouterr().err
