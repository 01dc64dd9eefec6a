"""``piezod audit`` on the command line: report, JSON keys of docs/formats.md, plots, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from test_audit_decide import MID

from piezod.audit.synthetic import frame_plan, hidden_session
from piezod.cli import main
from piezod.recording import write_recording
from piezod.synth import random_params


@pytest.fixture(scope="module")
def delay_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(21)
    params = random_params(rng)
    plan = frame_plan(
        rng, ranges_v=(120.0, 260.0, 400.0), n_frequencies=3, frequency_hz=(0.05, 5.0), n_references=3
    )
    session = hidden_session(params, plan, {"delay": MID["delay"]}, samples_per_loop=512, seed=rng)
    path = tmp_path_factory.mktemp("audit") / "frame.csv"
    write_recording(path, session.recording)
    return path


def test_json_report_and_plots(delay_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "audit.json"
    plots = tmp_path / "plots"
    family = ["--family-laws", "prandtl-ishlinskii"]
    assert main(["audit", str(delay_csv), "--json", str(out), "--plots", str(plots), *family]) == 0
    doc = json.loads(out.read_text())
    assert doc["cause"] == "delay"
    f = doc["findings"][0]
    for key in (
        "effect",
        "evidence",
        "gain",
        "heldout_rms_before_um",
        "heldout_rms_after_um",
        "params",
        "bic_delta",
    ):
        assert key in f
    assert f["heldout_rms_after_um"] < f["heldout_rms_before_um"]
    assert f["gain"] == pytest.approx(f["heldout_rms_before_um"] / f["heldout_rms_after_um"])
    for key in ("rms_um", "heldout_rms_um", "noise_floor_um"):
        assert doc["baseline"][key] > 0
    assert [c["effect"] for c in doc["candidates"]] == [
        "drift",
        "thermal",
        "stiffness",
        "polarity",
        "resonance",
        "delay",
        "saturation",
        "creep",
    ]
    assert all("gain" in c and "heldout_rms_after_um" in c for c in doc["candidates"])
    # the stage follows the audit's own law: its model, not the play law, predicts best
    assert [m["name"] for m in doc["family"]["members"]] == [
        "family/prandtl-ishlinskii",
        "family/prandtl-ishlinskii/voltage-creep",
    ]
    assert doc["best_model"]["source"] == "audit" and doc["best_model"]["name"].endswith("+ delay")
    text = capsys.readouterr().out
    assert "cause: delay" in text and "finding 1: delay" in text
    assert sorted(p.name for p in plots.iterdir()) == [
        "gains.png",
        "loops.png",
        "prediction.png",
        "residuals.png",
        "structure.png",
        "summary.png",
    ]


def test_json_on_stdout_sends_the_report_to_stderr(
    delay_csv: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["audit", str(delay_csv), "--json", "-", "--effects", "delay", "drift", "--no-family"]) == 0
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    assert doc["cause"] == "delay"
    assert [c["effect"] for c in doc["candidates"]] == ["delay", "drift"]
    assert "cause: delay" in cap.err


def test_validate_recordings_are_the_held_out_data(delay_csv: Path, tmp_path: Path) -> None:
    out = tmp_path / "a.json"
    args = [
        "audit",
        str(delay_csv),
        "--validate",
        str(delay_csv),
        "--json",
        str(out),
        "--effects",
        "delay",
        "--no-family",
    ]
    assert main(args) == 0
    doc = json.loads(out.read_text())
    assert doc["heldout"]["method"].startswith("validation recordings")
    assert doc["validate"] == [str(delay_csv)]
    assert doc["cause"] == "delay"


def test_bad_input_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("t,voltage,position\n0,1,2\n0.1,x,3\n")
    assert main(["audit", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{bad}:3" in err[0] and "voltage" in err[0]


def test_too_few_samples_names_the_experiment(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    short = tmp_path / "short.csv"
    short.write_text("t,voltage,position\n" + "".join(f"{k * 0.1},{k},{k}\n" for k in range(5)))
    assert main(["audit", str(short)]) == 2
    err = capsys.readouterr().err
    assert "short.csv" in err and "at least" in err


def test_base_effects_are_fitted_into_the_baseline_never_named(capsys: pytest.CaptureFixture[str]) -> None:
    data = Path(__file__).resolve().parents[1] / "piezod" / "data" / "real" / "pi-p885"
    args = [
        "audit",
        str(data / "identification.csv"),
        "--validate",
        str(data / "validation.csv"),
        "--no-family",
    ]
    assert main([*args, "--base-effects", "creep", "--effects", "delay", "stiffness"]) == 0
    out = capsys.readouterr().out
    baseline = next(line for line in out.splitlines() if line.startswith("baseline parameters:"))
    assert "creep_pct_per_decade" in baseline and "(creep)" in baseline
    assert "note: baseline: + creep" in out
    assert not any(line.startswith("creep ") for line in out.splitlines())
