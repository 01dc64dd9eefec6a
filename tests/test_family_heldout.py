"""The model family scored on held-out data of recordings (piezod.family_heldout); the audit uses it."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from piezod.audit.standins import preset_session
from piezod.calibrate_family import fit_family, session_positions, settled_rows
from piezod.cli import main
from piezod.config import load_config
from piezod.errors import CalibrationError, RecordingError
from piezod.family_heldout import (
    FamilyComparison,
    MemberScore,
    PartGain,
    best_model,
    check_findings,
    compare_family,
    heldout_mask,
    prediction_error,
    session,
    time_blocks,
)
from piezod.model.family import CreepSpectrum, FamilyParams
from piezod.model.play import PlayParams
from piezod.readback import align_known_delay
from piezod.recording import Recording, read_experiments, write_recording

P885 = Path(__file__).resolve().parents[1] / "piezod" / "data" / "real" / "pi-p885"


@pytest.fixture(scope="module")
def p885() -> tuple[list, list]:  # type: ignore[type-arg]
    return read_experiments([P885 / "identification.csv"]), read_experiments([P885 / "validation.csv"])


def test_the_play_law_predicts_the_real_validation_run_and_the_ode_law_does_worse(
    p885: tuple[list, list],
) -> None:  # type: ignore[type-arg]
    ident, val = p885
    c = compare_family(ident, val, laws=["prandtl-ishlinskii", "coleman-hodgdon"])
    assert c.method.startswith("validation recordings")
    assert [m.name for m in c.members] == [
        "family/prandtl-ishlinskii",
        "family/prandtl-ishlinskii/voltage-creep",
        "family/coleman-hodgdon",
        "family/coleman-hodgdon/voltage-creep",
    ]
    best = c.best
    assert best is not None and best.law == "prandtl-ishlinskii"
    ch = min(m.heldout_rms_um for m in c.members if m.law == "coleman-hodgdon")
    assert best.heldout_rms_um < 0.7 * ch
    # real data: the noise floor of the validation run (third differences) and a ratio above it
    assert 0.06 < c.noise_floor_um < 0.09
    assert 1.2 < best.heldout_rms_um / c.noise_floor_um < 4.0
    # one sensor gain for the separate validation session, close to the training one
    (gain,) = c.gains.values()
    assert abs(gain - 1.0) < 0.02
    # what the best member's parts are worth on the held-out run: its static map and its creep
    # spectrum are material, its drive lag (fitted 0) is not
    material = {p.effect: p.material for p in c.parts}
    assert material == {"stiffness": True, "creep": True, "delay": False}
    stiffness = c.part("stiffness")
    assert stiffness is not None and stiffness.gain > 1.2
    doc = c.to_json()
    assert doc["best"] == best.name and len(doc["members"]) == 4 and len(doc["parts"]) == 3
    assert "<- best" in c.table()


def test_one_recording_is_cut_into_time_blocks_and_the_model_runs_through_them(
    p885: tuple[list, list],  # type: ignore[type-arg]
) -> None:
    ident, _ = p885
    blocks = time_blocks(ident[0], 5)
    assert [b.label for b in blocks][3] == f"{ident[0].label}[4/5]"
    assert np.array_equal(np.concatenate([b.position_um for b in blocks]), ident[0].position_um)
    whole, cut = session(ident), session(blocks)
    fit = fit_family(whole, "prandtl-ishlinskii", skip_s=1.0)
    np.testing.assert_allclose(
        session_positions(cut, fit.params), session_positions(whole, fit.params), atol=1e-9
    )
    c = compare_family(ident, laws=["prandtl-ishlinskii"], creep_drivers=["position"])
    assert c.heldout == (f"{ident[0].label}[4/5]",)
    assert c.method.startswith("blocked split in time")
    with pytest.raises(CalibrationError, match="held-out"):
        compare_family(ident, blocks=1, laws=["prandtl-ishlinskii"])


def test_heldout_mask_holds_out_every_fourth_and_at_least_one() -> None:
    assert heldout_mask(2).tolist() == [True, False]
    assert np.flatnonzero(~heldout_mask(8)).tolist() == [3, 7]
    with pytest.raises(CalibrationError):
        heldout_mask(1)


def test_a_documented_sensor_delay_aligns_the_readback(tmp_path: Path) -> None:
    rows = "\n".join(f"{0.005 * k:.3f},{np.sin(0.1 * k):.6f},{k:.1f}" for k in range(200))
    rec = tmp_path / "r.csv"
    rec.write_text(f"# sensor_delay_s: 0.005\nt,voltage,position\n{rows}\n")
    (e,) = read_experiments([rec])
    (a,), note = align_known_delay([e])
    assert note is not None and "r.csv 5 ms" in note
    # the position recorded one sample later is the stage's at the drive's time
    np.testing.assert_allclose(a.position_um, e.position_um[1:], atol=1e-9)
    assert len(a) == len(e) - 1
    # once aligned, the key is spent: aligning again changes nothing
    assert a.metadata.get("sensor_delay_aligned_s") == "0.005" and "sensor_delay_s" not in a.metadata
    (again,), note_again = align_known_delay([a])
    assert again is a and note_again is None
    plain = dataclasses.replace(e, metadata={})
    assert align_known_delay([plain]) == ([plain], None)
    bad = tmp_path / "bad.csv"
    bad.write_text(f"# sensor_delay_s: soon\nt,voltage,position\n{rows}\n")
    with pytest.raises(RecordingError, match=r"sensor_delay_s.*soon") as info:
        align_known_delay(read_experiments([bad]))
    assert info.value.path is not None and info.value.path.endswith("bad.csv")


def _member(rms: float, lag_s: float, stiffness: float = 0.0) -> MemberScore:
    law = PlayParams(b_um_per_v=1.0, rho0=1.0, thresholds_v=(0.5,), weights=(0.2,))
    params = FamilyParams(
        law, CreepSpectrum((1.0,), (0.01,)), lag_time_constant_s=lag_s, stiffness_pct_per_um=stiffness
    )
    return MemberScore("family/prandtl-ishlinskii", "prandtl-ishlinskii", "position", rms, rms, params)


def _parts(delay: bool, stiffness: bool = True) -> tuple[PartGain, ...]:
    return (
        PartGain("stiffness", 0.3, 2.5 if stiffness else 1.0, 0.08, stiffness),
        PartGain("creep", 0.2, 1.2, 0.02, True),
        PartGain("delay", 0.2, 1.3 if delay else 1.0, 0.05, delay),
    )


def test_findings_are_checked_against_a_better_predicting_member_only() -> None:
    finding = SimpleNamespace(effect="delay", params={"delay_s": 0.0, "lag_time_constant_s": 0.011})
    stiff = SimpleNamespace(effect="stiffness", params={"sensitivity_pct_per_um": -0.28})
    creep = SimpleNamespace(effect="creep", params={"creep_pct_per_decade": 8.8})
    other = SimpleNamespace(effect="drift", params={"rate_nm_per_s": 3.0})
    lagless = FamilyComparison("m", (_member(0.17, 0.0, -0.27),), 0.074, 1.0, (), parts=_parts(delay=False))
    checks = check_findings(lagless, [finding, stiff, creep, other], audit_heldout_rms_um=0.47)
    assert [c["effect"] for c in checks] == ["delay", "stiffness", "creep"]
    assert checks[0]["confirmed"] is False and "does not need it" in checks[0]["text"]
    assert checks[1]["confirmed"] is True and checks[2]["confirmed"] is True
    # a material lag of the member's own, of the finding's size, confirms it; a tenth of it does not
    lagged = FamilyComparison("m", (_member(0.17, 0.009),), 0.074, 1.0, (), parts=_parts(delay=True))
    assert check_findings(lagged, [finding], 0.47)[0]["confirmed"] is True
    small = FamilyComparison("m", (_member(0.17, 0.001),), 0.074, 1.0, (), parts=_parts(delay=True))
    assert "far less" in check_findings(small, [finding], 0.47)[0]["text"]
    # a part the member could not be refitted without checks nothing
    unmeasured = (PartGain("delay", math.nan, math.nan, math.nan, False, "no admissible law"),)
    failed = FamilyComparison("m", (_member(0.17, 0.0),), 0.074, 1.0, (), parts=unmeasured)
    assert check_findings(failed, [finding], 0.47) == []
    assert "not measured (no admissible law)" in failed.table()
    # a member that predicts worse than the audit's model checks nothing
    assert check_findings(lagless, [finding], audit_heldout_rms_um=0.1) == []
    best = best_model(lagless, "audit: hysteresis ODE (2.21) + delay", 0.47, 0.07)
    assert best["source"] == "family" and abs(best["ratio_to_noise_floor"] - 0.17 / 0.074) < 1e-9
    assert best_model(None, "audit: x", 0.47, 0.07)["source"] == "audit"


def test_audit_cli_reports_the_family_and_the_best_model(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "a.json"
    args = ["audit", str(P885 / "identification.csv"), "--validate", str(P885 / "validation.csv")]
    assert main([*args, "--effects", "delay", "--family-laws", "prandtl-ishlinskii", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "the model family on held-out data" in text and "best model on the held-out data:" in text
    assert "documented sensor delay" in text
    doc = json.loads(out.read_text())
    assert doc["best_model"]["source"] == "family"
    assert doc["family"]["best"] == doc["best_model"]["name"]
    assert doc["best_model"]["heldout_rms_um"] < doc["baseline"]["heldout_rms_um"]
    # the lag the ODE baseline needed is not a candidate: the play law, better, does not need it
    assert doc["rejected_candidates"] == ["delay"] and doc["cause"] != "delay"
    assert all(not c["confirmed"] for c in doc["finding_checks"] if c["effect"] == "delay")


def test_calibrate_model_family_writes_the_member_that_predicts_best(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, report = tmp_path / "p885.yaml", tmp_path / "c.json"
    args = ["calibrate", str(P885 / "identification.csv"), "--validate", str(P885 / "validation.csv")]
    laws = ["--family-laws", "prandtl-ishlinskii", "coleman-hodgdon"]
    assert main([*args, "--model", "family", *laws, "--out", str(out), "--json", str(report)]) == 0
    text = capsys.readouterr().out
    assert "model: family (family/prandtl-ishlinskii" in text and "documented sensor delay" in text
    doc = json.loads(report.read_text())
    assert doc["model"] == "family" and doc["chosen"].startswith("family/prandtl-ishlinskii")
    assert len(doc["family"]["members"]) == 4
    config = load_config(out)
    assert config.axes["x"].model == "family"
    family = config.axes["x"].family
    assert family is not None and family.law == "prandtl-ishlinskii"
    # the written model is the one scored: it predicts the validation run as the table says
    val, _ = align_known_delay(read_experiments([P885 / "validation.csv"]))
    data = session(val)
    rows = settled_rows(data, doc["family"]["skip_s"])
    resid, _ = prediction_error(data, family.params(), rows, np.zeros(len(val), dtype=np.intp))
    scored = {m["name"]: m["heldout_rms_um"] for m in doc["family"]["members"]}
    assert float(np.sqrt(np.mean(resid**2))) == pytest.approx(scored[doc["chosen"]], rel=1e-3)


def test_calibrate_auto_writes_the_family_member_when_it_predicts_the_held_out_data_better(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Real data, not triangular scans: the dynamic model (the ODE with log creep) and the family's
    members are scored on the validation run; the play law predicts it better and is written."""
    out, report = tmp_path / "auto.yaml", tmp_path / "auto.json"
    args = ["calibrate", str(P885 / "identification.csv"), "--validate", str(P885 / "validation.csv")]
    laws = ["--family-laws", "prandtl-ishlinskii"]
    assert main([*args, *laws, "--out", str(out), "--json", str(report)]) == 0
    text = capsys.readouterr().out
    assert "model: family (family/prandtl-ishlinskii" in text
    assert "auto: it predicts the held-out data better than the dynamic model" in text
    doc = json.loads(report.read_text())
    dynamic = doc["family"]["others"]["dynamic"]
    scored = {m["name"]: m["heldout_rms_um"] for m in doc["family"]["members"]}
    assert doc["model"] == "family" and scored[doc["chosen"]] < 0.98 * dynamic
    assert load_config(out).axes["x"].model == "family"


def test_calibrate_validate_needs_a_model_it_scores(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["calibrate", str(P885 / "identification.csv"), "--validate", str(P885 / "validation.csv")]
    assert main([*args, "--model", "dynamic"]) == 2
    assert "--model auto or family" in capsys.readouterr().err


def test_calibrate_auto_on_triangular_scans_writes_what_predicts_held_out_scans_best(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Triangular scans of a stage of other physics (play hysteresis, voltage-driven creep): the
    thesis model (3.8), refitted on the training experiments, and the family's members are scored
    on the same held-out scans; the play law predicts them far better and is written, not (3.8)."""
    exps = preset_session("pi-stage")
    path = tmp_path / "frame.csv"
    write_recording(path, Recording.of_experiments(exps))
    out, report = tmp_path / "tri.yaml", tmp_path / "tri.json"
    laws = ["--family-laws", "prandtl-ishlinskii", "coleman-hodgdon"]
    assert main(["calibrate", str(path), *laws, "--out", str(out), "--json", str(report)]) == 0
    text = capsys.readouterr().out
    assert "better than the thesis (3.8) model" in text and "(fitted on the training part)" in text
    doc = json.loads(report.read_text())
    thesis = doc["family"]["others"]["thesis (3.8)"]
    assert doc["family"]["others_fitted_on"]["thesis (3.8)"] == "the training part"
    scored = {m["name"]: m["heldout_rms_um"] for m in doc["family"]["members"]}
    assert doc["model"] == "family" and doc["chosen"].startswith("family/prandtl-ishlinskii")
    assert scored[doc["chosen"]] < 0.5 * thesis
    config = load_config(out)
    assert config.axes["x"].model == "family" and config.axes["x"].thesis is not None
