"""``piezod calibrate`` and ``piezod linearity`` end to end on files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from piezod.cli import main
from piezod.config import AxisConfig, ScannerConfig, ThesisModelConfig, dump_config, load_config
from piezod.recording import Recording, write_recording
from piezod.synth import MEDIUM_TUBE, random_plan, synth_session

PARAMS = ("alpha_per_v", "b_um_per_v", "u_um_per_v", "tau_s", "a1", "a2_per_v", "a3")


@pytest.fixture(scope="module")
def frame(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 10-experiment frame split over two files."""
    d = tmp_path_factory.mktemp("frame")
    s = synth_session(MEDIUM_TUBE, random_plan(6, 10, offset_v=(-20.0, 20.0)), samples_per_loop=512, seed=6)
    rec = s.recording
    half = int(np.flatnonzero(rec.experiment == s.plan[5].label)[0])
    parts = []
    for name, sl in (("a.csv", slice(0, half)), ("b.csv", slice(half, None))):
        part = Recording(
            t_s=rec.t_s[sl],
            voltage_v=rec.voltage_v[sl],
            position_um=rec.position_um[sl],
            axis=rec.axis[sl] if rec.axis is not None else None,
            experiment=rec.experiment[sl] if rec.experiment is not None else None,
        )
        write_recording(d / name, part)
        parts.append(d / name)
    return parts[0], parts[1]


def _one_line_error(capsys: pytest.CaptureFixture[str], prefix: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    assert err.startswith(prefix), err
    return err


def test_calibrate_writes_config_and_json(frame: tuple[Path, Path], tmp_path: Path) -> None:
    out, js = tmp_path / "cal.yaml", tmp_path / "cal.json"
    rc = main(["calibrate", str(frame[0]), str(frame[1]), "--out", str(out), "--json", str(js)])
    assert rc == 0
    doc = json.loads(js.read_text())
    assert {"params", "stderr", "fit_error_pct", "experiments", "correlations"} <= set(doc)
    assert set(doc["params"]) == set(PARAMS)
    assert len(doc["experiments"]) == 10
    assert doc["experiments"][0]["label"].startswith("a.csv:")
    for key in ("label", "range_v", "offset_v", "frequency_hz", "range_um", "fit_error_pct", "n"):
        assert key in doc["experiments"][0]
    assert doc["fit_error_pct"] < 0.5
    # the stage follows (3.8) itself: refitted on the training experiments it predicts the held-out
    # ones better than any member of the family, so it is written
    family = doc["family"]
    best = min(m["heldout_rms_um"] for m in family["members"] if m["heldout_rms_um"] is not None)
    assert family["others"]["thesis (3.8)"] < best
    assert "the thesis (3.8) model is written" in doc["model_reason"]
    cfg = load_config(out)
    assert cfg.axes["x"].thesis.params().alpha_per_v == pytest.approx(doc["params"]["alpha_per_v"])
    assert cfg.calibration is not None and cfg.calibration["n_experiments"] == 10
    # the tracker learns only from lines as long as the recordings' shortest (symmetric triangles)
    fastest = max(e["frequency_hz"] for e in doc["experiments"])
    assert cfg.axes["x"].tracking_min_line_s == pytest.approx(0.5 / fastest, rel=1e-3)
    # the files do not say when they were measured: no recorded_utc (the daemon takes the age as unknown)
    assert "recorded_utc" not in cfg.calibration


def test_an_offline_calibration_says_when_its_recordings_were_measured(
    frame: tuple[Path, Path], tmp_path: Path
) -> None:
    """With ``started_utc`` in the headers (piezod's recordings) the written config carries
    ``calibration.recorded_utc``: the sample-weighted middle of the experiments on the wall clock."""
    import calendar
    import time

    from piezod.calibrate_any import recorded_mid_unix_s
    from piezod.config import recorded_age_s
    from piezod.recording import read_experiments, read_recording

    stamped = []
    for k, path in enumerate(frame):
        rec = read_recording(path)
        dest = tmp_path / path.name
        write_recording(dest, rec, metadata={"started_utc": f"2026-11-0{k + 1}T10:00:00Z"})
        stamped.append(dest)
    exps = read_experiments(stamped)
    mid = recorded_mid_unix_s(exps)
    day1 = calendar.timegm(time.strptime("2026-11-01T10:00:00Z", "%Y-%m-%dT%H:%M:%SZ"))
    assert day1 < mid < day1 + 2 * 86400
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(stamped[0]), str(stamped[1]), "--out", str(out)]) == 0
    age = recorded_age_s(load_config(out), mid)
    assert age is not None and age == pytest.approx(0.0, abs=1.0)


def test_calibrate_keeps_the_base_config(frame: tuple[Path, Path], tmp_path: Path) -> None:
    base = ScannerConfig(
        name="medium-tube",
        axes={
            "x": AxisConfig(
                voltage_min_v=-300,
                voltage_max_v=300,
                thesis=ThesisModelConfig(**{k: getattr(MEDIUM_TUBE, k) for k in PARAMS}),
            )
        },
    )
    dump_config(base, tmp_path / "base.yaml")
    out = tmp_path / "new.yaml"
    rc = main(
        [
            "calibrate",
            str(frame[0]),
            str(frame[1]),
            "--config",
            str(tmp_path / "base.yaml"),
            "--model",
            "thesis",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    cfg = load_config(out)
    assert cfg.name == "medium-tube" and cfg.axes["x"].voltage_max_v == 300
    assert cfg.axes["x"].thesis.alpha_per_v == pytest.approx(MEDIUM_TUBE.alpha_per_v, rel=0.01)


def test_json_to_stdout_moves_the_table_to_stderr(
    frame: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["calibrate", str(frame[0]), str(frame[1]), "--model", "thesis", "--json", "-"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["params"]
    assert "worst fit error" in cap.err


def test_on_stage_calibration_arguments_are_checked(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # (the on-stage run itself is tested in tests/test_stagecal.py)
    assert main(["calibrate", "--sim"]) == 2
    assert "--out F.yaml is required" in _one_line_error(capsys, "piezod calibrate: error:")
    assert main(["calibrate", "--sim", "--out", "x.yaml", "missing.csv"]) == 2
    assert "missing.csv: No such file" in _one_line_error(capsys, "piezod calibrate: error:")
    rec = tmp_path / "rec.csv"
    rec.write_text("t,voltage,position\n")
    assert main(["calibrate", "--sim", "--out", "x.yaml", str(rec)]) == 2
    assert "not both" in _one_line_error(capsys, "piezod calibrate: error:")
    assert main(["calibrate", "--port", "/dev/ttyUSB0", "--out", "x.yaml"]) == 2
    assert "--config F is required" in _one_line_error(capsys, "piezod calibrate: error:")
    assert main(["calibrate"]) == 2
    assert "no recordings" in _one_line_error(capsys, "piezod calibrate: error:")
    # the frame played again after the fits is on by default; one or the other
    assert main(["calibrate", "--sim", "--out", "x.yaml", "--refresh-after", "5", "--no-refresh"]) == 2
    assert "--no-refresh: not allowed with" in _one_line_error(capsys, "piezod calibrate: error:")


@pytest.mark.parametrize("command", ["calibrate", "linearity"])
def test_corrupt_csv_exits_2_with_file_and_line(
    frame: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    lines = frame[0].read_text().splitlines(keepends=True)
    lines[40] = lines[40].replace(",", ";", 1)
    bad = tmp_path / "bad.csv"
    bad.write_text("".join(lines))
    assert main([command, str(bad)]) == 2
    err = _one_line_error(capsys, f"piezod {command}: error: {bad}:41: ")
    assert "wrong number of cells" in err


def test_several_axes_need_a_choice(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "xy.csv"
    p.write_text("t,voltage,position,axis\n0,0,0,x\n0,0,0,y\n")
    assert main(["calibrate", str(p)]) == 2
    assert "choose one with --axis" in _one_line_error(capsys, "piezod calibrate: error:")


def _scan_file(path: Path, gain: float) -> None:
    spl, lines = 1000, 8
    k = np.arange(lines * spl // 2 + 1)
    ph = (k / spl) % 1.0
    target = -10 + 20 * np.where(ph < 0.5, 2 * ph, 2 - 2 * ph)
    rec = Recording(
        t_s=k / (2.0 * spl),
        voltage_v=8.0 * target + 0.01 * target**2,
        position_um=gain * target + 0.3,
        target_um=target,
        experiment=np.full(k.size, f"g{gain:g}"),
    )
    write_recording(path, rec, metadata={"range_um": 20})


def test_linearity_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _scan_file(tmp_path / "a.csv", 1.002)
    _scan_file(tmp_path / "b.csv", 0.995)
    js = tmp_path / "lin.json"
    assert main(["linearity", str(tmp_path / "a.csv"), str(tmp_path / "b.csv"), "--json", str(js)]) == 0
    doc = json.loads(js.read_text())
    assert doc["max_abs_length_error_pct"] == pytest.approx(0.5, abs=1e-6)
    assert doc["max_nonlinearity_pct"] < 1e-6
    a, b = doc["experiments"]
    assert b["length_error_pct"] == pytest.approx(-0.5, abs=1e-6)
    for key in ("range_um", "frequency_hz", "offset_v", "nonlinearity_pct", "length_error_pct"):
        assert key in a
    assert a["length_error_pct"] == pytest.approx(0.2, abs=1e-6) and a["frequency_hz"] == pytest.approx(2.0)
    assert "max non-linearity" in capsys.readouterr().out
    assert main(["linearity", str(tmp_path / "a.csv"), "--json", "-"]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["experiments"][0]["label"] == "g1.002"
    assert "max non-linearity" in cap.err


def _ringing_frame(path: Path) -> None:
    """Eight ranges at 1 Hz (3 loops each, 10 kS/s; every 4th experiment is held out) from the
    thesis model through a 350 Hz mode of Q 15 (exact, from rest, about each experiment's first
    position), 2 nm of noise, one file."""
    from piezod.audit.dynamics import resonance
    from piezod.synth import calibration_plan

    plan = calibration_plan(tuple(np.linspace(100.0, 380.0, 8)), (1.0,), n_loops=3)
    s = synth_session(MEDIUM_TUBE, plan, samples_per_loop=10_000, noise_um=0.0, seed=4)
    rec = s.recording
    assert rec.experiment is not None
    pos = rec.position_um.copy()
    for exp in plan:
        rows = rec.experiment == exp.label
        x = pos[rows]
        pos[rows] = x[0] + resonance(x - x[0], 1e-4, 350.0, 15.0, 0)
    pos += np.random.default_rng(4).normal(0.0, 0.002, pos.size)
    write_recording(
        path,
        Recording(
            t_s=rec.t_s, voltage_v=rec.voltage_v, position_um=pos, axis=rec.axis, experiment=rec.experiment
        ),
    )


def test_an_offline_calibration_fits_the_stages_mode_as_on_the_stage(tmp_path: Path) -> None:
    """``piezod calibrate FRAME.csv --out F.yaml`` runs the mode and fast-creep steps of the
    calibration on the stage on the written model's residual: a ringing stage's mode is adopted
    into the YAML and reported (``resonance`` in the JSON, a line on the output);
    ``--no-dynamics`` leaves them out."""
    frame = tmp_path / "frame.csv"
    _ringing_frame(frame)
    out, js = tmp_path / "cal.yaml", tmp_path / "cal.json"
    args = ["calibrate", str(frame), "--model", "thesis"]
    assert main([*args, "--out", str(out), "--json", str(js)]) == 0
    doc = json.loads(js.read_text())
    assert doc["resonance"]["adopted"], doc["resonance"]
    assert doc["resonance"]["f0_hz"] == pytest.approx(350.0, rel=0.03)
    assert any(line.startswith("resonance f0") for line in doc["dynamics"])
    written = load_config(out).axes["x"]
    assert written.resonance().f0_hz == doc["resonance"]["f0_hz"]
    assert "resonance f0" in out.read_text()  # the YAML's header says what was adopted
    bare, bare_js = tmp_path / "bare.yaml", tmp_path / "bare.json"
    assert main([*args, "--no-dynamics", "--out", str(bare), "--json", str(bare_js)]) == 0
    assert "resonance" not in (load_config(bare).axes["x"].extensions or {})
    assert "resonance" not in json.loads(bare_js.read_text())
