"""docs/model-family.md: each results table names the command that regenerates it, in that tool's format."""

from __future__ import annotations

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "model-family.md").read_text(encoding="utf-8")


def _section(title: str) -> str:
    start = DOC.index(title)
    end = DOC.find("\n### ", start + len(title))
    return DOC[start : end if end > 0 else None]


def test_each_results_section_names_its_command() -> None:
    for title, command in [
        ("### 6.1", "python tools/model_family_verify.py --stage pi-stage"),
        ("### 6.2", "python tools/model_family_verify.py --stage preisach-stage"),
        ("### 6.3", "python tools/model_family_p885.py"),
    ]:
        assert command in _section(title), (title, command)


def _tool() -> Any:
    spec = importlib.util.spec_from_file_location("mfv", ROOT / "tools" / "model_family_verify.py")
    assert spec is not None and spec.loader is not None
    mfv = importlib.util.module_from_spec(spec)
    # registered first, as importlib's recipe does: its dataclasses look their module up by name
    sys.modules[spec.name] = mfv
    try:
        spec.loader.exec_module(mfv)
    finally:
        del sys.modules[spec.name]
    return mfv


def test_verification_tables_have_the_tool_format_and_the_held_out_stage_is_labelled() -> None:
    mfv = _tool()
    result = {
        "choice": {
            "chosen": "a",
            "heldout_rms_um": {"a": 0.005, "b": 0.1},
            "train_rms_um": {"a": 0.004, "b": 0.1},
        },
        "rows": [
            {
                "model": "family",
                "why": "inside: small range",
                "range_um": 13.3,
                "frequency_hz": 0.63,
                "offset_um": 0.0,
                "nonlinearity_pct": 0.038,
                "length_error_pct": -0.015,
            }
        ],
        "summary": {"family/inside": {"max_nonlinearity_pct": 0.038, "max_abs_length_error_pct": 0.015}},
    }
    text = mfv.markdown(result)
    header = text.splitlines()[0]
    assert header in _section("### 6.1") and header in _section("### 6.2")
    assert "| family | inside: small range | 13.3 | 0.63 | +0.00 | 0.038 | -0.015 |" in text
    for title in ("### 6.1", "### 6.2"):
        assert re.search(
            r"\| \*\*family\*\* \| \*\*max inside\*\* \|( \|){3} \*\*\d\.\d{3}\*\* \| \*\*\d\.\d{3}\*\* \|",
            _section(title),
        )
    assert "Held-out physics" in _section("### 6.2") and "boucwen-stage" in _section("### 6.2")
    assert "developed against" in _section("### 6.2")


def test_the_true_position_is_the_stage_without_its_sensor() -> None:
    """``--truth`` steps the stage without its sensor noise and sensor-side delay and lag: the same
    position, free of what lies between it and the readback."""
    import numpy as np

    from hil_sim.stage import Stage, StageConfig

    mfv = _tool()
    cfg = StageConfig.from_file(ROOT / "configs" / "sim-thorn33-holdout-stage.yaml")
    assert cfg.sensor_noise_nm_rms > 0 and cfg.effects.delay is not None and cfg.effects.delay.at == "sensor"
    truth = mfv.truth_config(cfg)
    assert truth.sensor_noise_nm_rms == 0.0 and truth.effects.delay is None
    assert (truth.creep, truth.axes, truth.amplifier_lag_s) == (cfg.creep, cfg.axes, cfg.amplifier_lag_s)
    v = 10.0 * np.sin(np.linspace(0.0, 2.0 * np.pi, 4000))
    quiet = cfg.model_copy(update={"sensor_noise_nm_rms": 0.0})
    x_true = Stage(truth, axes=("x",)).step(v, 2.5e-4)
    x_lagged = Stage(quiet, axes=("x",)).step(v, 2.5e-4)
    assert 0.0 < float(np.max(np.abs(x_true - x_lagged))) < 0.05 * float(np.ptp(x_true))


@pytest.mark.slow
def test_full_frame_calibrate_and_verify_on_pi_stage_meets_the_targets(tmp_path: Path) -> None:
    """The #9 targets on the other-physics stage, full frame, in process (~5-20 min)."""
    out = tmp_path / "verify.json"
    tool = str(ROOT / "tools" / "model_family_verify.py")
    subprocess.run(
        [sys.executable, tool, "--stage", "pi-stage", "--skip-dynamic", "--json", str(out)],
        check=True,
        cwd=ROOT,
    )
    summary = json.loads(out.read_text())["summary"]
    inside, outside = summary["family/inside"], summary["family/outside"]
    assert inside["max_nonlinearity_pct"] <= 0.05
    assert inside["max_abs_length_error_pct"] <= 0.1
    assert outside["max_abs_length_error_pct"] <= 1.0
